"""The printed ChArUco board: the page, detection in rendered photos, metric scale and board frame from cameras of an
arbitrary scale, no board → nothing changes, bad board definitions → one-line errors."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from dvr.cameras import project_points, transform_points
from pipeline.cameras.board import (
    board_spec,
    detect,
    locate,
    make_board,
    page_image,
    to_board_frame,
    use_board,
    write_page,
)
from pipeline.cameras.config import CamerasConfig
from pipeline.cli import main
from pipeline.errors import StageError
from pipeline.readers import mesh_units

ROOT = Path(__file__).resolve().parents[3]
SPEC = board_spec((5, 7), 35, 26, "DICT_4X4_50")


def _projections(cams, scale: float = 1.0, shift=(0.0, 0.0, 0.0)):
    """Projections of the GT cameras in a world scaled by ``scale`` and shifted (SfM's arbitrary frame)."""
    t = scale * cams.t - np.einsum("nij,j->ni", cams.R, np.asarray(shift))
    return [K @ np.concatenate([R, tt[:, None]], 1) for K, R, tt in zip(cams.K, cams.R, t)]


def test_detect_rendered_board(board_scene):
    """Corners are found in every view, where the board's true corners project (this project's pixel centres)."""
    out, images, cams, gt = board_scene
    from pipeline.cameras.board import board_points

    to_world = np.linalg.inv(np.asarray(gt["world_to_board"]))
    errs, counts = [], []
    for img, P in zip(images, _projections(cams)):
        ids, uv = detect(img, make_board(SPEC))
        counts.append(len(ids))
        errs.extend(np.linalg.norm(project_points(P, transform_points(to_world, board_points(SPEC, ids)))[0] - uv,
                                   axis=1))
    assert min(counts) >= 6, counts
    assert np.median(errs) < 0.5, np.median(errs)


def test_scale_and_frame_from_cameras_of_any_scale(board_scene):
    """Cameras in an arbitrary frame (× 3.7, shifted): metres per unit within 1 %, the board's plane z = 0, z up."""
    out, images, cams, gt = board_scene
    f, shift = 3.7, np.array([0.3, -1.2, 2.0])
    fit = locate(images, _projections(cams, f, shift), SPEC)
    truth = gt["metres_per_world_unit"] / f
    assert fit is not None and fit.corners >= 10 and fit.views == len(images)
    assert abs(fit.scale / truth - 1) < 0.01, (fit.scale, truth)
    assert fit.residual_mm < 2.0
    Rn, tn, _ = to_board_frame(fit, cams.R, f * cams.t - np.einsum("nij,j->ni", cams.R, shift), np.zeros((0, 3)))
    centers = -np.einsum("nji,nj->ni", Rn, tn)
    true_centers = transform_points(np.asarray(gt["world_to_board"]), cams.centers)
    assert np.abs(centers - true_centers).max() < 0.005  # metres: camera centres in the board frame within 5 mm
    assert (centers[:, 2] > 0).all()


def test_board_frame_keeps_the_pixels():
    """Moving cameras and points into the board frame changes no projection."""
    from pipeline.cameras.board import BoardFit

    rng = np.random.default_rng(0)
    R0 = cv2.Rodrigues(rng.normal(size=3))[0]
    fit = BoardFit(SPEC, 0.37, R0, rng.normal(size=3), 3, 10, 0.1)
    Rs = np.stack([cv2.Rodrigues(rng.normal(size=3))[0] for _ in range(3)])
    ts, pts = rng.normal(size=(3, 3)) + [0, 0, 5], rng.normal(size=(20, 3))
    Rn, tn, pn = to_board_frame(fit, Rs, ts, pts)
    for R, t, R2, t2 in zip(Rs, ts, Rn, tn):
        a, b = pts @ R.T + t, pn @ R2.T + t2
        np.testing.assert_allclose(a[:, :2] / a[:, 2:], b[:, :2] / b[:, 2:], atol=1e-9)


def test_no_board_changes_nothing(tmp_path):
    """Photos without a board: use_board hands back the very same arrays, writes nothing, and the mesh stays
    unitless."""
    und = tmp_path / "sfm" / "undistorted"
    (und / "images").mkdir(parents=True)
    rng = np.random.default_rng(1)
    names = ["a", "b", "c"]
    for n in names:
        cv2.imwrite(str(und / "images" / f"{n}.png"), cv2.GaussianBlur(rng.integers(0, 255, (300, 400), np.uint8),
                                                                       (0, 0), 2))
    Ks = np.stack([np.array([[300.0, 0, 200], [0, 300, 150], [0, 0, 1]])] * 3)
    Rs, ts, pts = np.stack([np.eye(3)] * 3), np.array([[0, 0, 3.0]] * 3), np.zeros((5, 3))
    sizes = np.array([[400, 300]] * 3, float)
    R2, t2, p2, fit = use_board(tmp_path, und, [f"{n}.png" for n in names], Ks, Rs, ts, sizes, pts, CamerasConfig())
    assert fit is None and R2 is Rs and t2 is ts and p2 is pts
    assert not (tmp_path / "board.json").exists() and mesh_units(tmp_path, "sfm") == {}
    assert locate([np.zeros((300, 400), np.uint8)] * 3, [np.eye(3, 4)] * 3, SPEC) is None


@pytest.mark.parametrize("args, words", [
    (((5, 7), 35, 40, "DICT_4X4_50"), "smaller than the square"),
    (((1, 7), 35, 26, "DICT_4X4_50"), "two counts"),
    (((5, 7), 35, 26, "DICT_9X9_1"), "unknown ArUco dictionary"),
    (((11, 11), 35, 26, "DICT_4X4_50"), "larger dictionary"),
])
def test_bad_board_definition(args, words):
    with pytest.raises(StageError, match=words) as e:
        board_spec(*args, where="--cameras.board-*")
    assert "\n" not in str(e.value) and str(e.value).startswith("--cameras.board-*")


def test_board_command(tmp_path, capsys):
    """`python -m pipeline board OUT.png`: an A4 page at 300 dpi the detector reads; bad sizes: one line, exit 2."""
    from PIL import Image

    assert main(["board", str(tmp_path / "board.png")]) == 0
    im = Image.open(tmp_path / "board.png")
    assert im.size == (2480, 3508) and round(im.info["dpi"][0]) == 300
    small = cv2.resize(np.asarray(im), None, fx=0.25, fy=0.25, interpolation=cv2.INTER_AREA)
    assert len(detect(small, make_board(SPEC))[0]) == 24
    assert main(["board", str(tmp_path / "b.png"), "--square-mm", "60"]) == 2  # 300 × 420 mm: not on A4
    err = capsys.readouterr().err
    assert err.startswith("error:") and err.count("\n") == 1 and "Traceback" not in err
    with pytest.raises(StageError, match="PNG"):
        write_page(tmp_path / "board.jpg", SPEC)
    assert page_image(SPEC, dpi=100).shape == (1169, 827)


def test_wrong_cameras_stop_with_one_line(board_scene):
    """The board seen in every view but the cameras swapped around (SfM's wrong poses on a symmetric object): a clear
    stop, not a wrong scale."""
    from pipeline.cameras.board import BoardMismatch

    out, images, cams, gt = board_scene
    Ps = _projections(cams)
    with pytest.raises(BoardMismatch, match="SfM poses are wrong") as e:
        locate(images, Ps[3:] + Ps[:3], SPEC)
    assert "\n" not in str(e.value)
