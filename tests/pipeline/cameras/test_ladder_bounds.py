"""The SfM ladder in bounded time: it stops at a model good enough to reconstruct from (the photos it lacks are
named, with why), later rungs extract fewer features for many photos, and its time budget ends it with one line."""

import json
import sqlite3
from dataclasses import replace

import cv2
import numpy as np
import yaml

from dvr.cameras import load_cameras
from dvr.data import list_images
from dvr.metrics import pose_errors
from pipeline.cameras.config import CamerasConfig
from pipeline.cameras.export import left_out
from pipeline.cameras.mapping import _judge, _upsampled_when_weak, matched_but_left_out
from pipeline.cameras.sfm import (
    GUIDED_COST,
    LADDER,
    UPSAMPLE_BELOW,
    UPSAMPLE_COST,
    _extract,
    ladder,
    median_features,
    number_by_name,
    refine_model,
    retriangulate,
    rung_seconds,
    shortfalls,
    verify_again,
    verify_at_poses,
)
from pipeline.cli import main
from pipeline.colmaplib import pycolmap
from synth import scene_from_dict, write_scene
from tests.conftest import ROOT


def _centres(c):
    return c.centers @ c.scale_mat[:3, :3].T + c.scale_mat[:3, 3]


def _torus_photos(tmp_path, n_views: int):
    spec = yaml.safe_load((ROOT / "configs" / "scenes" / "torus_backdrop.yaml").read_text())
    spec["cameras"].update(n_views=n_views, heldout=0)
    write_scene(scene_from_dict(spec, ROOT / "configs" / "scenes"), tmp_path / "syn")
    return tmp_path / "syn" / "images"


def test_the_ladder_does_not_climb_for_the_last_photo(tmp_path, capsys):
    """24 photos of the textured torus and one of something else: the first rung poses the 24, which is enough
    (cameras.enough-registered); no later rung runs for the 25th, and the stage says which photo it left out and
    that it shares no verified match with the others."""
    images = _torus_photos(tmp_path, 24)
    rng = np.random.default_rng(0)
    cv2.imwrite(str(images / "stray.png"), rng.integers(0, 256, (240, 320, 3), dtype=np.uint8))
    ws = tmp_path / "ws"
    assert main(["cameras", str(ws), "--images", str(images)]) == 0
    err = capsys.readouterr().err
    stamp = json.loads((ws / ".stages" / "cameras.json").read_text())
    assert [r["rung"] for r in stamp["rungs"]] == ["default"], stamp["rungs"]
    assert stamp["registered"] == 24 and stamp["unregistered"] == ["stray"]
    assert "left out 1 photo(s) SfM could not pose: stray (no verified match with any other photo" in err


def test_a_model_short_of_enough_photos_climbs():
    stats = {"registered": 22, "total": 23, "mean_reprojection_error": 0.5, "mean_track_length": 4.0,
             "median_points_per_view": 400}
    assert shortfalls(stats, enough_registered=0.9) == []
    assert shortfalls(stats, enough_registered=1.0) == ["22/23 registered"]
    assert shortfalls({**stats, "registered": 19}, enough_registered=0.9) == ["19/23 registered"]


def test_rungs_extract_fewer_features_for_many_photos():
    few, many = ladder("default", "merge", 8192, n_photos=20), ladder("default", "merge", 8192, n_photos=60)
    assert [r.max_features for r in few] == [8192] + [16384] * 5
    assert [r.max_features for r in many] == [4096] + [8192] * 5  # 8 k and 16 k × 30 / 60
    assert [r.max_features for r in ladder("default", "guided", 8192, n_photos=45)] == [5120, 11264]  # to 1 k
    assert [r.max_features for r in ladder("default", "guided", 8192, n_photos=200)] == [4096, 4096]  # floors
    assert ladder("default", "default", 2048, n_photos=200)[0].max_features == 2048  # never more than asked


def test_large_photos_are_not_upsampled_for_sift():
    assert all(r.upsample for r in ladder("default", "merge", sfm_side=UPSAMPLE_BELOW - 1))
    assert not any(r.upsample for r in ladder("default", "merge", sfm_side=1600))
    assert ladder("default", "default", sfm_side=1600)[0].features_key == "f8192-o0"


def _blob_photos(folder, n: int, blobs: int):
    """``n`` grey 400×300 photos with ``blobs`` soft dark spots each, as PNGs named like the SfM input's."""
    rng = np.random.default_rng(0)
    folder.mkdir()
    for i in range(n):
        img = np.full((300, 400), 200, np.uint8)
        for x, y in rng.integers((10, 10), (390, 290), (blobs, 2)):
            cv2.circle(img, (int(x), int(y)), int(rng.integers(2, 6)), int(rng.integers(40, 150)), -1)
        cv2.imwrite(str(folder / f"p{i:02d}.png"), cv2.GaussianBlur(img, (3, 3), 0))
    return [f"p{i:02d}" for i in range(n)]


def test_weakly_textured_photos_are_upsampled_for_sift(tmp_path, capsys):
    """SIFT finds few features in plain photos at their size: the ladder then upsamples them; photos with texture
    enough keep their size, and so does every rung when the probe is off."""
    rungs = ladder("default", "merge", sfm_side=1600)
    plain, busy = tmp_path / "plain", tmp_path / "busy"
    names_plain, names_busy = _blob_photos(plain, 10, 15), _blob_photos(busy, 10, 600)
    cfg = CamerasConfig(sift_upsample_features=100)
    assert median_features(tmp_path, plain, names_plain, rungs[0], 1) < 100 < median_features(
        tmp_path, busy, names_busy, rungs[0], 1)
    assert not (tmp_path / "probe.db").exists()
    assert all(r.upsample for r in _upsampled_when_weak(rungs, tmp_path, plain, names_plain, cfg))
    assert "upsampled for SIFT" in capsys.readouterr().out
    assert _upsampled_when_weak(rungs, tmp_path, busy, names_busy, cfg) == rungs
    assert _upsampled_when_weak(rungs, tmp_path, plain, names_plain, replace(cfg, sift_upsample_features=0)) == rungs


def test_a_rungs_cost_is_estimated_from_the_last_one():
    """A first rung of 67 photos (4096 features, not upsampled) that took 60 s for features, 35 s for matching and
    50 s for mapping: the guided rung's 7168 features take as long to find, (7168 / 4096)² × GUIDED_COST as long to
    match guided and 7168 / 4096 as long to map; the relaxed rung shares the dsp rung's features and matches and
    only maps; merging reuses the model's."""
    default, guided, dsp, relaxed, global_, merge = ladder("default", "merge", 8192, n_photos=67, sfm_side=1600)
    steps = {"features": 60.0, "matching": 35.0, "mapping": 50.0}
    more = 7168 / 4096
    assert rung_seconds(default, steps, guided) == 60.0 + 35.0 * more ** 2 * GUIDED_COST + 50.0 * more
    assert rung_seconds(guided, steps, relaxed) > rung_seconds(guided, steps, guided) == 50.0
    assert rung_seconds(dsp, steps, relaxed) == rung_seconds(dsp, steps, global_) == 50.0
    assert rung_seconds(default, steps, merge) == 0.0
    up = ladder("default", "default", 4096, n_photos=67)[0]  # small photos: upsampled
    assert rung_seconds(default, steps, up) == 60.0 * UPSAMPLE_COST + 35.0 + 50.0  # and its new features matched


def test_a_rung_that_would_not_finish_is_not_started(tmp_path, capsys, monkeypatch):
    """The 12 photos 30° apart again, with the time budget as it is and no global mapper: the first rung poses a
    few; every later rung estimated to take longer than the budget has left is not started (said, and in the
    stamp); merging, which makes no features, runs and poses all 12."""
    import pipeline.cameras.mapping as mapping

    monkeypatch.setattr(mapping, "rung_seconds", lambda done, steps, nxt: 0.0 if nxt.mapper == "extend" else 1e6)
    images = _torus_photos(tmp_path, 12)
    ws = tmp_path / "ws"
    assert main(["cameras", str(ws), "--images", str(images), "--cameras.no-board", "--cameras.no-global-mapper",
                 "--cameras.enough-registered", "1.01"]) == 0
    out = capsys.readouterr().out
    stamp = json.loads((ws / ".stages" / "cameras.json").read_text())
    skipped = [r["rung"] for r in stamp["rungs"] if "would take about 1000000 s" in r.get("skipped", "")]
    assert skipped == ["guided", "dsp", "relaxed", "global"], stamp["rungs"]
    assert [r["rung"] for r in stamp["rungs"] if "skipped" not in r] == ["default", "merge"]
    assert stamp["rungs"][0]["registered"] < 12 and stamp["registered"] == 12, stamp["rungs"]
    assert "cameras: rung guided not tried: its features, matches and mapping would take about 1000000 s" in out


def test_the_global_mapper_runs_at_the_first_rung_that_does_not_fit(tmp_path, capsys, monkeypatch):
    """The same 12 photos, every later rung estimated past the budget: at the first of them COLMAP's global mapper
    maps the first rung's matches and poses all 12, enough to end the ladder (the blowtorch: 19/67 from the first
    rung, 50/67 from the global mapper on its matches in 12 s, where the guided rung's matching ran past the budget's
    end without a model). Where that model is short too (``enough-registered`` above 1), the ladder goes on, and
    the global mapper does not map the same matches again when it ends."""
    import pipeline.cameras.mapping as mapping

    monkeypatch.setattr(mapping, "rung_seconds", lambda done, steps, nxt: 0.0 if nxt.mapper == "extend" else 1e6)
    images = _torus_photos(tmp_path, 12)
    ws = tmp_path / "ws"
    assert main(["cameras", str(ws), "--images", str(images), "--cameras.no-board"]) == 0
    stamp = json.loads((ws / ".stages" / "cameras.json").read_text())
    assert [r["rung"] for r in stamp["rungs"]] == ["default", "guided", "default-global"], stamp["rungs"]
    assert stamp["rungs"][0]["registered"] < 12 and stamp["registered"] == 12
    assert "would take about" in stamp["rungs"][1]["skipped"]

    ws = tmp_path / "short"
    assert main(["cameras", str(ws), "--images", str(images), "--cameras.no-board",
                 "--cameras.enough-registered", "1.01"]) == 0
    stamp = json.loads((ws / ".stages" / "cameras.json").read_text())
    assert [r["rung"] for r in stamp["rungs"] if "skipped" not in r] == ["default", "default-global"], stamp["rungs"]
    assert stamp["rungs"][1]["rung"] == "guided" and stamp["registered"] == 12


def test_the_time_budget_ends_the_climb(tmp_path, capsys):
    """12 photos 30° apart: the first rung poses a few of them and a later one would pose them all (the ladder's
    second rung does), but a budget spent before it starts ends the ladder: the first rung's model is all there is,
    too short here, and the stage stops with one line."""
    images = _torus_photos(tmp_path, 12)
    ws = tmp_path / "ws"
    rc = main(["cameras", str(ws), "--images", str(images), "--cameras.sfm-seconds", "0.001",
               "--cameras.sfm-seconds-per-photo", "0.001", "--cameras.no-board", "--cameras.no-global-mapper"])
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "photos registered" in err[0], err
    assert "is spent; rungs not tried: guided, dsp, relaxed, global, merge" in captured.out
    assert "rung guided:" not in captured.out and not (ws / "cameras.npz").exists()


def test_the_global_mapper_poses_what_the_incremental_one_left_out(tmp_path, capsys):
    """The same 12 photos: the incremental mapper poses two of them and the budget ends the ladder; COLMAP's global
    mapper, on the same matches, poses all 12 at their true poses, and the model is kept because its rotations
    agree with the incremental model's on the photos both posed. Against a model that turns some of those photos away
    (the phone's mouse through the global mapper: 32 of 59 photos over 5° off), the global model is rejected."""
    images = _torus_photos(tmp_path, 12)
    ws = tmp_path / "ws"
    assert main(["cameras", str(ws), "--images", str(images), "--cameras.sfm-seconds", "0.001",
                 "--cameras.sfm-seconds-per-photo", "0.001", "--cameras.no-board"]) == 0
    out = capsys.readouterr().out
    stamp = json.loads((ws / ".stages" / "cameras.json").read_text())
    assert [r["rung"] for r in stamp["rungs"] if "skipped" not in r] == ["default", "default-global"], stamp["rungs"]
    assert stamp["rungs"][0]["registered"] <= 6 and stamp["rung"] == "default-global" and stamp["registered"] == 12
    assert "rung default-global: registered 12/12" in out
    est, gt = load_cameras(ws / "cameras.npz"), load_cameras(tmp_path / "syn" / "cameras.npz")
    idx = [int(p.stem) for p in list_images(ws / "images")]
    err = pose_errors(_centres(est), est.R, _centres(gt)[idx], gt.R[idx])
    assert err["center_err_rel_max"] < 0.02 and err["rot_err_deg_max"] < 1.0, err

    ladder_dir = ws / "sfm" / "ladder"
    mapped = pycolmap.Reconstruction(ladder_dir / "default-global" / "model")
    turned = pycolmap.Reconstruction(mapped)
    for i in sorted(turned.reg_image_ids())[::2]:  # half the photos turned 40° about the vertical
        frame = turned.frame(turned.image(i).frame_id)
        R = frame.rig_from_world.rotation.matrix() @ cv2.Rodrigues(np.array([0, 0, np.radians(40)]))[0]
        frame.rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(R), frame.rig_from_world.translation)
    cfg, names = CamerasConfig(), [p.stem for p in images.iterdir()]
    judged = _judge(mapped, "default-global", 1.0, {}, None, ws / "sfm" / "input", names, cfg, None, [], [turned])
    assert judged is None and "6 rotations disagree with the incremental mapper's by over 5°" in capsys.readouterr().out
    judged = _judge(mapped, "default-global", 1.0, {}, None, ws / "sfm" / "input", names, cfg, None, [], [mapped])
    assert judged is not None and judged[0]["registered"] == 12


def test_the_global_mapper_runs_for_photos_left_out_of_a_model_enough_to_stop(tmp_path, capfd):
    """The same 12 photos, the ladder one rung long and any share of the photos enough (``enough-registered``
    0.1): the first rung poses a few, and the others match them; the global mapper on the same matches poses all 12
    (the floating cow: 39/40 and 0.15° rotation error from the first rung, 40/40 and 0.04° so)."""
    images = _torus_photos(tmp_path, 12)
    ws = tmp_path / "ws"
    assert main(["cameras", str(ws), "--images", str(images), "--cameras.enough-registered", "0.1",
                 "--cameras.last-rung", "default", "--cameras.no-board"]) == 0
    stamp = json.loads((ws / ".stages" / "cameras.json").read_text())
    assert [r["rung"] for r in stamp["rungs"]] == ["default", "default-global"], stamp["rungs"]
    assert stamp["rungs"][0]["registered"] < 12 and stamp["registered"] == 12

    capfd.readouterr()  # the final adjustment and the object matches keep COLMAP's info lines off the terminal
    rec, _ = refine_model(pycolmap.Reconstruction(ws / "sfm" / "sparse" / "best"), 1, 2.5)
    database = ws / "sfm" / "database.db"
    verify_again(database, tmp_path / "again.db", 1.0, 0)
    verify_at_poses(rec, database, tmp_path / "posed.db")
    again, note = retriangulate(rec, database, ws / "sfm" / "input", tmp_path / "tri")
    out, err = capfd.readouterr()
    assert again.num_points3D() > 0 and out + err == ""


def test_only_photos_with_matches_count_as_left_out_for_another_mapper(tmp_path):
    """matched_but_left_out: of the photos a model lacks, those sharing verified matches with some photo."""
    db = tmp_path / "m.db"
    with sqlite3.connect(db) as con:
        con.execute("create table images (image_id integer, name text)")
        con.execute("create table two_view_geometries (pair_id integer, rows integer)")
        con.executemany("insert into images values (?, ?)", [(1, "a.png"), (2, "b.png"), (3, "c.png"),
                                                              (4, "d.png"), (5, "e.png")])
        pair = 2147483647  # COLMAP's pair id: image_id1 * this + image_id2
        con.executemany("insert into two_view_geometries values (?, ?)",
                        [(1 * pair + 2, 100), (2 * pair + 3, 40), (4 * pair + 5, 0)])

    class Model:  # the part of a pycolmap.Reconstruction it reads: a and b posed
        def reg_image_ids(self):
            return [1, 2]

        def image(self, i):
            return type("Image", (), {"name": {1: "a.png", 2: "b.png"}[i]})

    assert matched_but_left_out(Model(), db) == ["c.png"]  # d and e matched nothing that verified


def test_photos_are_numbered_by_name_whatever_order_extraction_finished(tmp_path):
    """COLMAP numbers photos as its extraction threads finish them; the database's ids follow the names after
    :func:`number_by_name`, with each photo's keypoints, descriptors and frame kept with it."""
    images = _torus_photos(tmp_path, 4)
    names = sorted(p.name for p in images.iterdir())
    db = tmp_path / "f.db"
    _extract(db, images, [names], LADDER[0], "SIMPLE_RADIAL", threads=1)
    con = sqlite3.connect(db)

    def dump():
        return (con.execute("SELECT i.image_id, i.name, k.data, d.data FROM images i JOIN keypoints k USING (image_id) "
                            "JOIN descriptors d USING (image_id) ORDER BY i.image_id").fetchall(),
                sorted(con.execute("SELECT * FROM frame_data").fetchall()), sorted(con.execute("SELECT * FROM frames")))

    before = dump()
    assert [row[1] for row in before[0]] == names
    with con:  # the order two threads may leave: photos 1 and 3 swapped, frames with them
        for table, column in (("images", "image_id"), ("keypoints", "image_id"), ("descriptors", "image_id"),
                              ("frame_data", "data_id"), ("frame_data", "frame_id"), ("frames", "frame_id")):
            for old, new in ((1, 100), (3, 1), (100, 3)):
                con.execute(f"UPDATE {table} SET {column} = ? WHERE {column} = ?", (new, old))
    assert dump() != before
    number_by_name(db)
    assert dump() == before


def test_left_out_photos_are_grouped_by_why():
    """A photo that matches nothing, photos that match only each other, and one with a few matches with the posed
    photos: three reasons, three fixes."""
    text = left_out(["alone", "a1", "a2", "few"], {"a1": (0, 300), "a2": (0, 280), "few": (12, 40)})
    assert text.startswith("alone (no verified match with any other photo")
    assert "a1, a2 (matched among themselves, not with the posed photos" in text
    assert "few (12 verified matches) (too few to pose them" in text
    assert left_out(["x"], None) == "x"
