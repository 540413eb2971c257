"""bench/facing.py: recall and precision split by which way the ground-truth surface faces; and the stool scene's
mesh, the case it was written for, is one closed surface (no faces inside the solid to count as missed)."""
import numpy as np
import pytest
import trimesh

from bench.facing import facing_fscore
from tests.conftest import ROOT


def test_a_mesh_without_the_underside_misses_only_the_downward_faces():
    gt = trimesh.creation.box((1.0, 1.0, 1.0))
    open_box = gt.copy()
    open_box.update_faces(open_box.face_normals[:, 2] > -0.5)  # the bottom face gone
    r = facing_fscore(open_box, gt, np.array([0.0, 0.0, 2.0]))
    assert r["down"]["share"] == pytest.approx(1 / 6, abs=0.02)
    assert r["down"]["recall"] < 0.1  # only the points along the bottom's rim lie near the sides
    assert min(r["up"]["recall"], r["side"]["recall"]) > 0.99  # missing only where the samples are sparse
    assert min(r[k]["precision"] for k in ("up", "side")) > 0.99
    whole = facing_fscore(gt, gt, np.array([0.0, 0.0, 1.0]))
    assert all(whole[k]["recall"] > 0.99 for k in ("up", "down", "side"))


def test_facing_follows_the_up_direction():
    gt = trimesh.creation.box((1.0, 1.0, 1.0))
    open_box = gt.copy()
    open_box.update_faces(open_box.face_normals[:, 0] < 0.5)  # the +x face gone: "up" when up is +x
    r = facing_fscore(open_box, gt, np.array([1.0, 0.0, 0.0]))
    assert r["up"]["recall"] < 0.1 and r["down"]["recall"] > 0.99


def test_the_stool_scene_mesh_is_one_closed_solid():
    from configs.scenes.meshes.stool import LEGS, SEAT, boxes_surface

    mesh = trimesh.load(ROOT / "configs" / "scenes" / "meshes" / "stool.obj")
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.body_count == 1
    seat_w, seat_d, seat_h = (hi - lo for lo, hi in SEAT)
    leg_w, leg_d, leg_h = (hi - lo for lo, hi in LEGS[0])
    assert mesh.volume == pytest.approx(seat_w * seat_d * seat_h + 4 * leg_w * leg_d * leg_h)
    # the boxes' areas less the legs' tops and the seat's underside where they join
    def box_area(w, d, h):
        return 2 * (w * d + w * h + d * h)

    boxes = box_area(seat_w, seat_d, seat_h) + 4 * box_area(leg_w, leg_d, leg_h)
    assert mesh.area == pytest.approx(boxes - 2 * 4 * leg_w * leg_d)
    v, f = boxes_surface([SEAT, *LEGS])
    assert trimesh.Trimesh(v, f).area == pytest.approx(mesh.area)  # the committed file is the generator's
