"""An object on a textured floor in photos larger than the working size: COLMAP's verification keeps the floor's
matches alone for "planar" pairs, and the cameras stage verifies again (``cameras.object_matches``; COLMAP runs). Its
own file so that the two test workers (``--dist loadfile``) can share the slow SfM tests."""

import json
import re
import sqlite3

import numpy as np
import pytest
import yaml

from pipeline.cameras.sfm import verify_again
from pipeline.cli import main
from synth import scene_from_dict, write_scene
from tests.conftest import ROOT

pytestmark = [pytest.mark.slow, pytest.mark.long]


def _object_matches(db, masks, scale: int) -> tuple[int, int]:
    """(verified matches in all pairs of a COLMAP database, those whose two features both lie on the object by the
    true ``masks``, which are ``scale`` times smaller than the photos)."""
    import cv2

    with sqlite3.connect(db) as con:
        names = dict(con.execute("select image_id, name from images"))
        on = {}
        for iid, rows, cols, data in con.execute("select image_id, rows, cols, data from keypoints"):
            xy = (np.frombuffer(data, np.float32).reshape(rows, cols)[:, :2] / scale).astype(int)
            m = cv2.imread(str(masks / names[iid]), cv2.IMREAD_GRAYSCALE) > 127
            on[iid] = m[np.clip(xy[:, 1], 0, m.shape[0] - 1), np.clip(xy[:, 0], 0, m.shape[1] - 1)]
        total = on_object = 0
        for pair, rows, data in con.execute("select pair_id, rows, data from two_view_geometries where rows > 0"):
            i2 = pair % 2147483647
            ij = np.frombuffer(data, np.uint32).reshape(rows, 2)
            total += rows
            on_object += int((on[(pair - i2) // 2147483647][ij[:, 0]] & on[i2][ij[:, 1]]).sum())
    return total, on_object


def test_an_object_on_a_textured_floor_keeps_its_matches_in_large_photos(tmp_path, capsys):
    """The cow on its textured floor in 20 photos of 960×720 (over twice the working size, as a phone's are): most of
    a pair's matches lie on the floor, so COLMAP's verification (``max_H_inlier_ratio`` 0.8) calls the pair planar
    and keeps the homography's inliers, the floor's alone, and the mapped model leaves the object's sphere next to
    no points (its sphere would come from the floor's). The stage verifies the stored matches again
    (``cameras.object_matches``): several times as many matches on the object, and points on it triangulated at
    the same poses, enough for its sphere. It runs here with the verification at the model's poses (the ``fast``
    preset's, 0.2 s: 309 matches where COLMAP's kept 15, 54 points where it had none); the default's RANSAC
    verification (240 matches, 50 points) then runs on the same database alone (33 s; the whole stage with it
    would make this test 162 s instead of 105). 12
    views 30° apart register 2 on the default rung."""
    spec = yaml.safe_load((ROOT / "configs" / "scenes" / "cow_floor.yaml").read_text())
    spec["cameras"].update(n_views=20, rings=1, elevation=[30, 30], heldout=0, width=320, height=240, photo_scale=3)
    write_scene(scene_from_dict(spec, ROOT / "configs" / "scenes"), tmp_path / "syn")
    ws = tmp_path / "ws"
    images = str(tmp_path / "syn" / "images")
    assert main(["cameras", str(ws), "--images", images, "--cameras.last-rung", "default",
                 "--cameras.object-verification", "poses"]) == 0
    note = [ln for ln in capsys.readouterr().out.splitlines() if "sparse points for the object's sphere" in ln]
    assert len(note) == 1, note
    before, after = (int(n) for n in re.search(r"(\d+) sparse points .*same poses: (\d+)", note[0]).groups())
    assert before < 20 <= after, note
    ladder = ws / "sfm" / "ladder"
    verify_again(ladder / "matches-f8192-h0.8.db", ladder / "matches-f8192-h0.8-h1.db", 1.0, seed=0)
    kept = {r: _object_matches(ladder / f"matches-f8192-h0.8{r}.db", tmp_path / "syn" / "gt" / "masks", 3)
            for r in ("", "-posed", "-h1") if (ladder / f"matches-f8192-h0.8{r}.db").exists()}
    assert len(kept) == 3, sorted(p.name for p in ladder.glob("*.db"))
    assert min(kept["-posed"][1], kept["-h1"][1]) >= 3 * max(1, kept[""][1]), kept
    stamp = json.loads((ws / ".stages" / "cameras.json").read_text())
    assert stamp["object_matches"] == note[0].removeprefix("cameras: "), stamp
