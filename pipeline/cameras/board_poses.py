"""Cameras from the printed board alone, for the captures SfM cannot pose (a symmetric or repetitive object: its
features match the wrong side, and COLMAP "registers" every photo at sub-pixel error with wrong poses).

The board is a known planar target, so its ChArUco corners give the camera directly (Zhang's calibration: one
focal length, radial distortion, and a pose per photo, in metres in the board's frame, z up). This is the cameras
stage's last resort, used only when the SfM ladder fails or its poses contradict the board.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from dvr.atomic import write_image, write_json
from pipeline.cameras.board import board_points, board_support, detect, make_board, spec_from_config
from pipeline.errors import StageError
from pipeline.inputs.photos import read_photo
from pipeline.scene.support import SupportPlane

MIN_CORNERS = 8
"""ChArUco corners a photo needs for its pose (fewer: too little of the board is seen to trust it)."""


@dataclass
class BoardCameras:
    """Photos posed from the board: full-resolution intrinsics and distortion, world → camera poses in the board's
    frame (metres, z up), the names posed, and the fit's quality."""

    K: np.ndarray
    dist: np.ndarray
    R: np.ndarray
    t: np.ndarray
    names: list[str]
    size: tuple[int, int]
    rms_px: float
    corners: int


def _reprojection_errors(obj, img, K, dist, rvecs, tvecs) -> list[np.ndarray]:
    out = []
    for o, x, r, t in zip(obj, img, rvecs, tvecs):
        proj, _ = cv2.projectPoints(o, r, t, K, dist)
        out.append(np.linalg.norm(proj.reshape(-1, 2) - x, axis=1))
    return out


def calibrate(views: dict[str, tuple[np.ndarray, np.ndarray]], size: tuple[int, int], spec, rounds: int = 3,
              ransac_px: float | None = 2.0) -> BoardCameras:
    """One camera (focal, principal point fixed at the centre, k1) and a pose per view from the corners ``views``
    (name → ids, pixel positions in this project's convention) seen in photos of ``size`` (w, h). A corner next to
    the object is sometimes interpolated from a marker the object half hides (5–6 px off): corners off their photo's
    board → image homography (RANSAC, ``ransac_px``) are dropped first, then those the fit puts over 3 × the
    median error (at least 1 px) away, and the fit repeated."""
    names = sorted(views)
    obj = [board_points(spec, views[n][0]).astype(np.float32) for n in names]
    img = [(views[n][1] - 0.5).astype(np.float32) for n in names]  # OpenCV: pixel centres at integers
    for k, (o, x) in enumerate(zip(obj, img) if ransac_px else ()):  # corners off their photo's homography
        _, inl = cv2.findHomography(o[:, :2], x, cv2.RANSAC, ransac_px)
        if inl is not None and inl.sum() >= 6:
            obj[k], img[k] = o[inl.ravel() > 0], x[inl.ravel() > 0]
    w, h = size
    K = np.array([[1.2 * max(w, h), 0, (w - 1) / 2], [0, 1.2 * max(w, h), (h - 1) / 2], [0, 0, 1]])
    flags = (cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_PRINCIPAL_POINT | cv2.CALIB_FIX_ASPECT_RATIO |
             cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3)
    for r in range(rounds):
        rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(obj, img, size, K, np.zeros(5), flags=flags)
        if r == rounds - 1:
            break
        errs = _reprojection_errors(obj, img, K, dist, rvecs, tvecs)
        limit = max(1.0, 3.0 * float(np.median(np.concatenate(errs))))
        keep = [e <= limit for e in errs]
        if all(k.all() for k in keep) or any(k.sum() < 6 for k in keep):
            break
        obj, img = [o[k] for o, k in zip(obj, keep)], [x[k] for x, k in zip(img, keep)]
    K = K.copy()
    K[:2, 2] += 0.5  # back to this project's pixel centres
    R = np.stack([cv2.Rodrigues(r)[0] for r in rvecs])
    return BoardCameras(K, dist.ravel(), R, np.stack([t.ravel() for t in tvecs]), names, size, float(rms),
                        int(sum(len(o) for o in obj)))


def board_cameras(photos: list[Path], cfg) -> tuple[BoardCameras | None, str]:
    """Pose the photos from the board; (None, why) when it cannot (no board, too few photos see it, photos of
    several sizes, a poor fit)."""
    spec = spec_from_config(cfg)
    board = make_board(spec)
    views, sizes = {}, set()
    for p in photos:
        img = read_photo(p)
        ids, uv = detect(img, board)
        sizes.add((img.shape[1], img.shape[0]))
        if len(ids) >= MIN_CORNERS:
            views[p.stem] = (ids, uv)
    if len(sizes) > 1:
        return None, "the photos have several sizes (one calibration needs one camera)"
    if len(views) < max(3, cfg.min_registered_fraction * len(photos)):
        return None, f"the board is seen in {len(views)}/{len(photos)} photos"
    cams = calibrate(views, sizes.pop(), spec)
    if cams.rms_px > cfg.max_reprojection_error:
        return None, f"the board's corners fit to {cams.rms_px:.2f} px only"
    return cams, ""


def write_board_views(cams: BoardCameras, photos: list[Path], out: Path, max_side: int):
    """Undistorted photos (longest side ≤ ``max_side``) into ``out`` and their intrinsics and sizes."""
    by_stem = {p.stem: p for p in photos}
    w, h = cams.size
    s = min(1.0, max_side / max(w, h))
    nw, nh = round(w * s), round(h * s)
    K = np.diag([nw / w, nh / h, 1.0]) @ cams.K
    K_cv = cams.K.copy()
    K_cv[:2, 2] -= 0.5
    for name in cams.names:
        img = cv2.undistort(read_photo(by_stem[name]), K_cv, cams.dist)
        if s < 1.0:
            img = cv2.resize(img, (nw, nh), interpolation=cv2.INTER_AREA)
        write_image(out / f"{name}.png", img)
    n = len(cams.names)
    return np.repeat(K[None], n, 0), np.tile(np.array([nw, nh], float), (n, 1))


def board_plane(cams: BoardCameras, target: np.ndarray) -> SupportPlane | None:
    """The board's plane as the support plane (:func:`pipeline.cameras.board.board_support`), its inliers the board's
    corners; with no SfM points the object's height is the fallback there: twice the height of the point the
    cameras aim at (an upper bound the masks and the hull refine)."""
    plane = board_support(np.zeros((0, 3)), -np.einsum("nji,nj->ni", cams.R, cams.t), target)
    return None if plane is None else replace(plane, inliers=cams.corners)


def board_info(cams: BoardCameras, spec, n_photos: int, why_not_sfm: str) -> dict:
    """What ``board.json`` and the stage's record say of cameras from the board."""
    return {**spec.info(), "views": len(cams.names), "photos": n_photos, "corners": cams.corners,
            "metres_per_sfm_unit": 1.0, "units": "metres", "poses_from": "board",
            "frame": "board: origin at its centre, z up, x along its rows of squares", "rms_px": round(cams.rms_px, 3),
            "focal_px": round(float(cams.K[0, 0]), 2), "distortion_k1_k2": np.round(cams.dist[:2], 5).tolist(),
            "sfm_failed": why_not_sfm}


def write_board_json(root: Path, info: dict) -> None:
    """Write ``info`` (:func:`board_info`) as ``board.json`` in the workspace ``root``."""
    write_json(root / "board.json", info, indent=1)


def require_board_cameras(photos: list[Path], cfg, sfm_error: StageError) -> BoardCameras:
    """Board poses, or the SfM error that sent us here (with why the board could not help) when there are none."""
    if not cfg.board:
        raise sfm_error
    cams, why = board_cameras(photos, cfg)
    if cams is None:
        raise StageError(f"{sfm_error} (the printed board cannot pose them either: {why})") from sfm_error
    return cams
