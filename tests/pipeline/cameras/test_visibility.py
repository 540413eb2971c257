"""The visibility check of an SfM model: conflicts where a point lies in front of one a view observes, the misjoined
group they point to, the pairs that joined it, and the ladder's choice between the model and its regrouped map."""

import json
import sqlite3
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml

from pipeline.cameras import mapping
from pipeline.cameras.config import CamerasConfig
from pipeline.cameras.pose_sanity import View, model_views, rotation_disagreement
from pipeline.cameras.sfm import Rung
from pipeline.cameras.visibility import (
    conflicted_views,
    count_conflicts,
    database_without,
    joining_pairs,
    misjoined_group,
    occlusion_conflicts,
    sampson_px,
    split_off,
    unexplained,
    unexplained_matches,
)
from pipeline.cli import main
from pipeline.colmaplib import PAIR_ID_BASE, pycolmap
from synth import scene_from_dict, write_scene
from tests.conftest import ROOT

K = np.array([[100.0, 0, 100], [0, 100.0, 100], [0, 0, 1]])


def _look_at(centre: np.ndarray, target: np.ndarray, name: str) -> View:
    """A 200×200 view at ``centre`` looking at ``target``, its image up along +z."""
    z = (target - centre) / np.linalg.norm(target - centre)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return View(name, R, -R @ centre, K, 200, 200)


def test_a_point_in_front_of_an_observed_one_conflicts_and_only_that():
    """One view at the origin looking along +z observes a point 10 away on its axis. Points it does not observe:
    on the same pixel at 5 (it would hide the observed one: a conflict), at 9.5 (within the depth margin), at 12
    (hidden behind it), 20 px beside it at 5 (nothing observed there) and behind the camera: only the first."""
    view = View("v", np.eye(3), np.zeros(3), K, 200, 200)
    points = np.array([[0, 0, 10], [0, 0, 5], [0, 0, 9.5], [0, 0, 12], [1.0, 0, 5], [0, 0, -5]])
    observers = [np.array([0])] + [np.array([], int)] * 5
    assert occlusion_conflicts([view], points, observers) == [(0, 1)]
    assert occlusion_conflicts([view], points, observers, depth_margin=0.01) == [(0, 1), (0, 2)]


def test_bad_points_are_refused():
    view = View("v", np.eye(3), np.zeros(3), K, 200, 200)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        occlusion_conflicts([view], np.zeros((4, 2)), [np.array([0])] * 4)
    with pytest.raises(ValueError, match="one observer list each"):
        occlusion_conflicts([view], np.zeros((4, 3)), [np.array([0])] * 3)


def _sphere_capture(shift: float):
    """12 views on a ring 4 from the origin, 30° above it, and 600 points of the unit sphere, each observed by the
    views that face it. ``shift``: views 0–2 and their points are moved by it along x, as a mapper that joined
    them at the wrong place would have them (their points are their own: the others do not observe them)."""
    angles = np.radians(np.arange(12) * 30.0)
    centres = 4 * np.stack([np.cos(angles) * np.cos(np.radians(30)), np.sin(angles) * np.cos(np.radians(30)),
                            np.full(12, np.sin(np.radians(30)))], 1)
    k = np.arange(600) + 0.5
    phi, theta = np.arccos(1 - 2 * k / 600), np.pi * (1 + 5 ** 0.5) * k
    sphere = np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], 1)
    group = [0, 1, 2]
    points, observers = [], []
    for part, views in ((0, group), (1, [v for v in range(12) if v not in group])):
        for p in sphere:
            facing = [v for v in views if (centres[v] - p) @ p > 0.3 * np.linalg.norm(centres[v] - p)]
            if len(facing) >= 2:
                points.append(p + (np.array([shift, 0, 0]) if part == 0 else 0))
                observers.append(np.array(facing))
    offset = np.array([[shift, 0, 0]]) * np.isin(np.arange(12), group)[:, None]
    views = [_look_at(c + o, o, f"v{i}") for i, (c, o) in enumerate(zip(centres, offset))]
    return views, np.array(points), observers


def test_a_group_joined_at_the_wrong_place_conflicts_and_a_right_model_does_not():
    """The ring of views round a sphere: as it is, no view sees a point in front of one it observes. With views 0–2
    and their points 0.6 off, the others' points lie in front of theirs and theirs in front of the others'."""
    views, points, observers = _sphere_capture(0.0)
    assert occlusion_conflicts(views, points, observers) == []
    views, points, observers = _sphere_capture(0.6)
    counts = np.bincount([v for v, _ in occlusion_conflicts(views, points, observers)], minlength=12)
    assert (counts >= 5).sum() >= 2, counts


def test_the_misjoined_group_is_the_one_the_conflicts_part_from_the_others():
    """Views 0–2 hold together by 300 explained matches a pair, as do neighbours 3–11; 40 false matches join 2 to
    3, and 11 to 0. The conflicts lie between 0–2 and the others: the group is 0–2, and the pairs that joined it are
    those the model explains (1–5's matches it does not). One conflicted view alone is no group."""
    explained = {(i, i + 1): 300 for i in range(11) if i != 2}
    explained |= {(2, 3): 40, (0, 11): 40, (1, 5): 2}
    totals = dict(explained) | {(1, 5): 50}
    observers = [np.array([3, 4]), np.array([0, 1]), np.array([9, 10])]
    conflicts = [(0, 0)] * 3 + [(1, 0)] * 3 + [(5, 1)] * 6 + [(2, 2)] * 2
    group = misjoined_group(12, explained, conflicts, observers, {0, 1, 5})
    assert group == {0, 1, 2}
    assert sorted(joining_pairs(explained, totals, group)) == [(0, 11), (2, 3)]
    assert misjoined_group(12, explained, conflicts, observers, {5}) is None  # one view alone


def test_a_pair_the_model_does_not_explain_splits_off_the_group_it_was_joined_to_falsely():
    """Views 0–5 hold together by 300 explained matches a pair, as do 6–11; false matches join 2 to 8 and 4 to 10
    (40 each, explained), while the 400 true matches of 5 with 6 are not. The pair 5–6 sets the groups 0–5 and 6–11
    apart; of two as large, the one with the first view stands for the model, and 6–11 is the group. The pairs that
    joined it are the false ones."""
    explained = {(i, i + 1): 300 for i in range(11) if i != 5}
    explained |= {(2, 8): 40, (4, 10): 40, (5, 6): 10}
    totals = dict(explained) | {(5, 6): 400}
    doubtful = unexplained(explained, totals)
    assert doubtful == [(5, 6)]
    group = split_off(12, explained, doubtful)
    assert group == {6, 7, 8, 9, 10, 11}
    assert sorted(joining_pairs(explained, totals, group)) == [(2, 8), (4, 10)]
    assert split_off(12, explained, []) is None
    assert unexplained_matches([("a", "b", 400, 10), ("c", "d", 120, 50)]) == 460


def test_of_two_groups_the_pairs_touch_as_often_the_smaller_is_split_off():
    """Views 0, 2, 4, 6 hold together, as do 1, 3, 5; view 7 is joined to each view by 10 explained matches, and its
    pairs with 1 and 3 are in doubt. Apart, the group 1–5 and view 7 each hold one end of both pairs: the smaller,
    view 7, is the group."""
    explained = {(0, 2): 300, (2, 4): 300, (4, 6): 300, (1, 3): 300, (3, 5): 300}
    explained |= {(v, 7): 10 for v in range(7)}
    assert split_off(8, explained, [(1, 7), (3, 7)], share=1.0) == {7}


@pytest.mark.parametrize("registered, left, kept", [
    (16, [], "rejoined"), (16, [("a.png", "f.png", 300, 110)], "rejoined"), (15, [], "first"),
    (16, [("a.png", "f.png", 300, 100)], "first")])
def test_the_rejoined_model_is_kept_only_with_as_many_photos_and_under_half_the_unexplained_matches(
        tmp_path, monkeypatch, capsys, registered, left, kept):
    """The first model leaves 399 of a pair's 409 matches unexplained. Mapped again without the pairs that joined
    the group, it is kept with as many photos and under half those matches unexplained (190 of another pair: kept;
    200: not), with a warning that part of the group can still be off."""
    first = mapping._Kept(16, 0.4, "first model", Rung("default"), tmp_path / "m.db")
    doubtful = [("a.png", "b.png", 409, 10)]
    monkeypatch.setattr(mapping, "misjoined", lambda rec, db: None)
    monkeypatch.setattr(mapping, "doubts", lambda rec, db: (doubtful, (["a.png", "c.png"], [("a.png", "d.png")])))
    monkeypatch.setattr(mapping, "database_without", lambda db, cut, out: out)
    monkeypatch.setattr(mapping, "run_rung", lambda *a, **k: ("rejoined model", None, {}, None))
    monkeypatch.setattr(mapping, "_judge", lambda rec, *a: ({"registered": registered,
                                                              "mean_reprojection_error": 0.4}, []))
    monkeypatch.setattr(mapping, "unexplained_pairs", lambda rec, db: left)
    best, pairs = mapping._regrouped(first, tmp_path, tmp_path, [], CamerasConfig(), ["x"] * 16, 100.0, [])
    assert best.model == f"{kept} model" and pairs == (left if kept == "rejoined" else doubtful)
    assert (best.rung.name, best.database.name) == (("default-rejoined", "rejoined.db") if kept == "rejoined"
                                                    else ("default", "m.db"))
    out = capsys.readouterr()
    assert "does not explain the 409 verified matches of a with b" in out.out and "without the 1 pairs" in out.out
    assert ("part of them can still be off" in out.err) == (kept == "rejoined")
    off = mapping._regrouped(first, tmp_path, tmp_path, [], CamerasConfig(regroup=False), ["x"] * 16, 100.0, [])
    assert off == (first, doubtful)


def test_a_view_is_conflicted_by_few_conflicts_at_long_tracks_or_many_at_any():
    """One view looks along +z at a row of points 10 away, each observed by it and two others, and at 5 points in
    front of them that two other views observe: 5 conflicts among points three views observe make it conflicted,
    4 do not. The same with points two views observe: it takes 25."""
    def case(n_front: int, track: int, n_behind: int = 30):
        view = View("v", np.eye(3), np.zeros(3), K, 200, 200)
        xs = np.linspace(-0.8, 0.8, n_behind)
        behind = np.stack([xs * 10, np.zeros(n_behind), np.full(n_behind, 10.0)], 1)
        front = behind[:n_front] * 0.5
        others = np.arange(1, track)
        observers = [np.array([0, *others])] * n_behind + [np.array([7, 8, 9][:track])] * n_front
        far = [View(f"o{i}", np.eye(3), np.array([0, 0, -100.0]), K, 200, 200) for i in range(9)]
        return conflicted_views([view, *far], np.vstack([behind, front]), observers)
    conflicts, among_long, conflicted = case(5, 3)
    assert len(conflicts) == len(among_long) == 5 and conflicted == {0}
    assert [p for _, p in among_long] == [30, 31, 32, 33, 34]  # indices into all the points
    assert case(4, 3)[2] == set()
    assert case(24, 2)[2] == set() and case(25, 2)[2] == {0}


def test_sampson_distance_is_zero_on_the_epipolar_line_and_the_offset_beside_it():
    """Two views 1 apart along x see the same points: matched pixels lie on their epipolar lines (0 px). A match
    moved 3 px across its (horizontal) epipolar line in one view is 3/√2 px off: the distance shares it between the
    two."""
    X = np.array([[0.2, -0.3, 5.0], [-0.5, 0.4, 7.0], [0.1, 0.1, 4.0]])
    R, t = np.eye(3), np.array([-1.0, 0, 0])
    xa, xb = X[:, :2] / X[:, 2:], (X + t)[:, :2] / (X + t)[:, 2:]
    assert np.allclose(sampson_px(xa, xb, R, t, 100.0), 0, atol=1e-9)
    moved = xb + np.array([0, 0.03])
    assert np.allclose(sampson_px(xa, moved, R, t, 100.0), 3.0 / np.sqrt(2), atol=0.01)


def test_the_copy_without_the_pairs_loses_their_matches_and_the_original_is_untouched(tmp_path):
    db = tmp_path / "matches.db"
    with sqlite3.connect(db) as con:
        con.execute("create table images (image_id integer primary key, name text)")
        con.execute("create table two_view_geometries (pair_id integer primary key, rows integer, data blob, "
                    "config integer)")
        con.executemany("insert into images values (?, ?)", [(1, "a.png"), (2, "b.png"), (3, "c.png")])
        con.executemany("insert into two_view_geometries values (?, 40, x'00', 3)",
                        [(1 * PAIR_ID_BASE + 2,), (1 * PAIR_ID_BASE + 3,), (2 * PAIR_ID_BASE + 3,)])
    out = database_without(db, [("c.png", "a.png")], tmp_path / "regrouped.db")

    def rows(path):
        with sqlite3.connect(path) as con:
            return dict(con.execute("select pair_id, rows from two_view_geometries"))
    assert rows(out) == {PAIR_ID_BASE + 2: 40, PAIR_ID_BASE + 3: 0, 2 * PAIR_ID_BASE + 3: 40}
    assert set(rows(db).values()) == {40}


@pytest.mark.parametrize("registered, after, kept", [(24, (14, 9), "regrouped"), (23, (0, 0), "first"),
                                                     (24, (15, 0), "first"), (24, (0, 10), "first")])
def test_the_regrouped_model_is_kept_only_with_as_many_photos_and_half_the_conflicts(
        tmp_path, monkeypatch, capsys, registered, after, kept):
    """The first model has 28 conflicts, 10 of them at points three or more views observe. Mapped again, it is
    kept with as many photos, at most 14 conflicts and fewer than 10 of the latter."""
    first = mapping._Kept(24, 0.4, "first model", Rung("default"), tmp_path / "m.db")
    monkeypatch.setattr(mapping, "misjoined", lambda rec, db: (["a.png", "b.png"], [("a.png", "c.png")], (28, 10)))
    monkeypatch.setattr(mapping, "database_without", lambda db, cut, out: out)
    monkeypatch.setattr(mapping, "run_rung", lambda *a, **k: ("regrouped model", None, {}, None))
    monkeypatch.setattr(mapping, "_judge", lambda rec, *a: ({"registered": registered,
                                                              "mean_reprojection_error": 0.4}, []))
    monkeypatch.setattr(mapping, "count_conflicts", lambda rec: after)
    monkeypatch.setattr(mapping, "doubts", lambda rec, db: ([], None))
    best, doubtful = mapping._regrouped(first, tmp_path, tmp_path, [], CamerasConfig(), ["x"] * 24, 100.0, [])
    assert best.model == f"{kept} model" and doubtful == []
    assert (best.rung.name == "default-regrouped") == (kept == "regrouped")
    assert "mapping again without the 1 pairs" in capsys.readouterr().out
    off, _ = mapping._regrouped(first, tmp_path, tmp_path, [], CamerasConfig(regroup=False), ["x"] * 24, 100.0, [])
    assert off is first


def test_a_model_without_conflicts_is_not_mapped_again(tmp_path, monkeypatch):
    first = mapping._Kept(24, 0.4, SimpleNamespace(), Rung("default"), tmp_path / "m.db")
    monkeypatch.setattr(mapping, "misjoined", lambda rec, db: None)
    monkeypatch.setattr(mapping, "doubts", lambda rec, db: ([], None))
    monkeypatch.setattr(mapping, "run_rung", lambda *a, **k: pytest.fail("mapped again"))
    assert mapping._regrouped(first, tmp_path, tmp_path, [], CamerasConfig(), [], 100.0, []) == (first, [])


def test_a_pair_with_many_matches_the_model_does_not_explain_is_in_doubt():
    """120 matches of which 50 explained: in doubt; 60 of 120 explained, or 99 matches none explained: not."""
    totals = {(0, 1): 120, (1, 2): 120, (2, 3): 99, (3, 4): 400}
    explained = {(0, 1): 50, (1, 2): 60, (2, 3): 0, (3, 4): 10}
    assert unexplained(explained, totals) == [(3, 4), (0, 1)]


def test_the_cameras_stage_warns_of_a_pair_its_model_cannot_hold(tmp_path, monkeypatch, capsys):
    """The ladder's model leaves 545 of a pair's matches unexplained: one warning line naming the two photos, and
    the pair in the stage's record."""
    rec = SimpleNamespace(reg_image_ids=lambda: [])
    monkeypatch.setattr(mapping, "map_photos", lambda ws, photos, cfg: (rec, tmp_path, tmp_path / "m.db", "default",
                                                                         [], [("59F0.png", "CEAC.png", 545, 41)]))
    monkeypatch.setattr(mapping, "verified_matches", lambda db, reg: {})
    monkeypatch.setattr(mapping, "finish_model", lambda ws, rec, db, inp, cfg, rung: (rec, [], None))
    _, _, info = mapping.run_sfm(SimpleNamespace(root=tmp_path), [], CamerasConfig())
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "does not explain the 545 verified matches of 59F0 with CEAC" in err
    assert info["unexplained_pairs"] == [["59F0", "CEAC", 545, 41]] and info["rejoined"] is False
    monkeypatch.setattr(mapping, "map_photos", lambda ws, photos, cfg: (rec, tmp_path, tmp_path / "m.db",
                                                                         "merge-rejoined", [], []))
    _, _, info = mapping.run_sfm(SimpleNamespace(root=tmp_path), [], CamerasConfig())
    assert info["rejoined"] is True and info["unexplained_pairs"] == [] and capsys.readouterr().err == ""


def _torus_with_a_group_moved(tmp_path: Path, group: tuple[int, ...] = (0, 1, 2)):
    """16 photos of the textured torus posed by the cameras stage, and the same model with its views ``group`` (their
    places in the order of image ids) moved 0.6 of the object's radius sideways, as a misjoined model would hold
    them: (workspace, matches database, the right model, the moved one, its image ids)."""
    spec = yaml.safe_load((ROOT / "configs" / "scenes" / "torus_backdrop.yaml").read_text())
    spec["cameras"].update(n_views=16, heldout=0)
    write_scene(scene_from_dict(spec, ROOT / "configs" / "scenes"), tmp_path / "syn")
    ws = tmp_path / "ws"
    assert main(["cameras", str(ws), "--images", str(tmp_path / "syn" / "images"), "--cameras.no-board"]) == 0
    ladder = ws / "sfm" / "ladder"
    database = Path(json.loads((ladder / "default" / "result.json").read_text())["database"])
    right = pycolmap.Reconstruction(ladder / "default" / "model")
    moved = pycolmap.Reconstruction(right)
    ids = sorted(moved.reg_image_ids())
    points = np.array([p.xyz for p in moved.points3D.values()])
    shift = np.array([0.6 * np.median(np.linalg.norm(points - np.median(points, 0), axis=1)), 0, 0])
    for i in (ids[k] for k in group):
        frame = moved.frame(moved.image(i).frame_id)
        R, t = frame.rig_from_world.rotation.matrix(), frame.rig_from_world.translation
        frame.rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(R), t - R @ shift)
    return ws, database, right, moved, ids


@pytest.mark.slow
@pytest.mark.long
def test_a_group_moved_off_its_place_is_mapped_again_by_colmap_and_put_back(tmp_path, monkeypatch, capsys):
    """Three views of the torus moved off their place see points in front of what they observe. The ladder's
    regrouping maps the same matches again (COLMAP, in its child process, on a copy of the database without the
    pairs of the three with a fourth view) and keeps the new model, whose rotations agree with the stage's own within
    1° and which has fewer conflicts."""
    ws, database, right, moved, ids = _torus_with_a_group_moved(tmp_path)
    before = count_conflicts(moved)
    assert before[1] > count_conflicts(right)[1]
    group = [moved.image(i).name for i in ids[:3]]
    cut = [(n, moved.image(ids[3]).name) for n in group]
    monkeypatch.setattr(mapping, "misjoined", lambda rec, db: (group, cut, before))
    names = [moved.image(i).name.rsplit(".", 1)[0] for i in ids]
    first = mapping._Kept(16, 0.5, moved, Rung("default"), database)
    kept, doubtful = mapping._regrouped(first, ws / "sfm" / "ladder", ws / "sfm" / "input",
                                        [sorted(moved.image(i).name for i in ids)], CamerasConfig(), names, 100.0, [])
    assert kept.rung.name == "default-regrouped" and kept.registered == 16, capsys.readouterr().out
    assert doubtful == []  # the model kept explains its pairs' matches
    after = count_conflicts(kept.model)
    assert after[0] <= before[0] / 2 and after[1] < before[1]
    angles = rotation_disagreement(model_views(kept.model), model_views(right))
    assert max(angles.values()) < 1.0, angles


@pytest.mark.slow
@pytest.mark.long
def test_a_group_whose_pairs_the_model_cannot_hold_is_mapped_again_by_colmap_and_put_back(tmp_path, monkeypatch,
                                                                                           capsys):
    """Three neighbouring views of the torus's lower ring moved off their place, the conflicts left unread: the pairs
    of photos whose many matches the moved model does not explain set the group apart
    (:func:`pipeline.cameras.visibility.doubts`), COLMAP maps the matches again without the pairs that join it, and
    the model kept agrees with the stage's own within 1° and leaves no pair in doubt, with the warning."""
    ws, database, right, moved, ids = _torus_with_a_group_moved(tmp_path, (1, 3, 5))
    assert mapping.doubts(moved, database)[1][0] == ["000001.png", "000003.png", "000005.png"]
    monkeypatch.setattr(mapping, "misjoined", lambda rec, db: None)
    names = [moved.image(i).name.rsplit(".", 1)[0] for i in ids]
    first = mapping._Kept(16, 0.5, moved, Rung("default"), database)
    kept, doubtful = mapping._regrouped(first, ws / "sfm" / "ladder", ws / "sfm" / "input",
                                        [sorted(moved.image(i).name for i in ids)], CamerasConfig(), names, 100.0, [])
    out = capsys.readouterr()
    assert kept.rung.name == "default-rejoined" and kept.registered == 16, out.out
    assert doubtful == [] and "part of them can still be off" in out.err
    angles = rotation_disagreement(model_views(kept.model), model_views(right))
    assert max(angles.values()) < 1.0, angles
