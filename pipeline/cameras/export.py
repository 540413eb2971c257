"""The posed photos written as the workspace's cameras: undistorted images/, cameras.npz with the object's sphere,
points.ply."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import cv2
import numpy as np

from dvr.atomic import atomic_path, check_room, short_write, write_bytes, write_image
from dvr.cameras import (
    project_points,
    save_cameras,
    sphere_frame,
    transform_points,
)
from pipeline.cameras.board import board_support, spec_from_config, use_board
from pipeline.cameras.board_poses import (
    BoardCameras,
    board_info,
    board_plane,
    write_board_json,
    write_board_views,
)
from pipeline.cameras.config import CamerasConfig
from pipeline.cameras.pose_sanity import axes_convergence
from pipeline.colmaplib import warnings_only
from pipeline.errors import StageError
from pipeline.inputs.photos import downscale
from pipeline.messages import names_or_count
from pipeline.scene.plain_support import find_plain_support
from pipeline.scene.support import SupportPlane, find_support
from pipeline.workspace import Workspace


def write_points(path: Path, pts: np.ndarray, cols: np.ndarray) -> None:
    """Binary PLY of coloured points (also valid when empty)."""
    head = ("ply\nformat binary_little_endian 1.0\nelement vertex %d\nproperty float x\nproperty float y\n"
            "property float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
    rec = np.zeros(len(pts), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1")])
    if len(pts):
        rec["x"], rec["y"], rec["z"] = pts.T
        rec["r"], rec["g"], rec["b"] = cols.T
    write_bytes(path, (head % len(pts)).encode() + rec.tobytes())


SPHERE_MIN_POINTS = 20
"""Fewer central points (:func:`central_points`) than this, and the object's sphere is fitted to every point above
the support plane instead, which the images' bound then caps (a cliff: the 16-view cow's sphere is 1.30 from
its central points, 2.15 from every point)."""


def central_points(points: np.ndarray, Ps: np.ndarray, sizes: np.ndarray, support: SupportPlane | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """(points above the ``support`` plane, those of them inside at least 75 % of the images): what the object's
    sphere is fitted to (:func:`normalization`)."""
    if support is not None:
        points = points[support.height(points) > 2 * support.tolerance]
    if not len(points):
        return points, points
    uv, z = project_points(Ps, points, blas=False)
    inside = (z > 0) & (uv[..., 0] >= 0) & (uv[..., 1] >= 0) & (uv[..., 0] < sizes[:, None, 0]) & \
             (uv[..., 1] < sizes[:, None, 1])
    return points, points[inside.mean(0) >= 0.75]


def model_points(rec, min_track_length: int) -> tuple[np.ndarray, np.ndarray]:
    """The COLMAP model's points seen in at least ``min_track_length`` images: xyz (M, 3) and colour (M, 3) uint8."""
    kept = [p for p in rec.points3D.values() if p.track.length() >= min_track_length]
    return (np.asarray([p.xyz for p in kept], np.float64).reshape(-1, 3),
            np.asarray([p.color for p in kept], np.uint8).reshape(-1, 3))


def normalization(points: np.ndarray, Ps: np.ndarray, sizes: np.ndarray, centers: np.ndarray, dirs: np.ndarray,
                  margin: float, focals: np.ndarray | None = None, support: SupportPlane | None = None) -> np.ndarray:
    """scale_mat (normalized → SfM) from sparse points seen inside most images, centred where the optical
    axes converge; the radius is a robust (97th percentile) extent of those points × margin, kept inside
    the cameras and, with ``focals``, inside what the images can show: at most 1.25 × the (median over views)
    sphere whose outline passes through the image corners. A weakly textured object in front of a textured
    background yields few points of its own (a white cow: 19 of 3900), and the background's would otherwise
    set the radius. With a ``support`` plane, its points (and any below it) are not the object: the sphere
    bounds what stands on it, and reaches down to it (radius ≥ 1.15 × the centre's height above it)."""
    c = axes_convergence(centers, dirs)
    dist = np.linalg.norm(centers - c, axis=1)
    points, central = central_points(points, Ps, sizes, support)
    if len(points):
        pts = central if len(central) >= SPHERE_MIN_POINTS else points
        r = np.percentile(np.linalg.norm(pts - c, axis=1), 97) * margin
    else:
        r = 0.5 * dist.min()
    if focals is not None:
        half_diag = np.arctan(0.5 * np.hypot(sizes[:, 0], sizes[:, 1]) / np.asarray(focals, float))
        r = min(r, 1.25 * float(np.median(dist * np.sin(half_diag))))
    if support is not None:
        r = max(r, 1.15 * float(support.height(c[None])[0]))
    return sphere_frame(c, min(r, 0.95 * dist.min()))


def report_sfm(rec, names: list[str], cfg: CamerasConfig, matches: dict[str, tuple[int, int]] | None = None) -> dict:
    """Print and return the model's summary (registered photos, reprojection error, track length, points); a
    StageError when fewer than ``min_registered_fraction`` of the photos registered."""
    reg = {rec.image(i).name.rsplit(".", 1)[0] for i in rec.reg_image_ids()}
    missing = [n for n in names if n not in reg]
    info = {"registered": len(reg), "total": len(names),
            "mean_reprojection_error": rec.compute_mean_reprojection_error(),
            "mean_track_length": rec.compute_mean_track_length(), "points": rec.num_points3D(), "unregistered": missing}
    print(f"cameras: registered {len(reg)}/{len(names)}, mean reprojection error "
          f"{info['mean_reprojection_error']:.3f} px, mean track length {info['mean_track_length']:.2f}, "
          f"{info['points']} points")
    if len(reg) < max(3, cfg.min_registered_fraction * len(names)):
        raise StageError(f"only {len(reg)}/{len(names)} photos registered (missing: {left_out(missing, matches)}); "
                         "likely too little overlap or texture, or motion blur — add photos between the missing ones")
    if missing:
        print(f"cameras: left out {len(missing)} photo(s) SfM could not pose: {left_out(missing, matches)}",
              file=sys.stderr)
    return info


def left_out(missing: list[str], matches: dict[str, tuple[int, int]] | None) -> str:
    """The photos SfM left out, and why when ``matches`` (per photo, its verified matches with the posed photos and
    with any photo) says."""
    if matches is None:
        return names_or_count(missing, look="the stamp .stages/cameras.json")
    posed, total = {}, {}
    for n in missing:
        posed[n], total[n] = matches.get(n, (0, 0))
    alone = [n for n in missing if not total[n]]
    apart = [n for n in missing if total[n] and not posed[n]]
    some = [n for n in missing if posed[n]]
    parts = [f"{names_or_count(alone)} (no verified match with any other photo: another scene, or blurred)"] \
        if alone else []
    if apart:
        parts.append(f"{names_or_count(apart)} (matched among themselves, not with the posed photos: SfM could not "
                     "join the two groups; photos between them help)")
    if some:
        parts.append(f"{names_or_count([f'{n} ({posed[n]} verified matches)' for n in some])} (too few to pose "
                     "them: a photo between each and its neighbours helps)")
    return "; ".join(parts)


def export_model(ws: Workspace, rec, image_dir: Path, cfg: CamerasConfig, names: list[str],
                 scale_mat: np.ndarray | None = None) -> dict:
    """Undistort the model to PINHOLE, write images/, cameras.npz and points.ply; ``scale_mat``: the object's sphere
    as given with the cameras (else found from the points)."""
    from pipeline.colmaplib import pycolmap

    warnings_only()  # an adjustment before turned COLMAP's info lines on: two per photo here
    und = ws.root / "sfm" / "undistorted"
    model_dir = ws.root / "sfm" / "sparse" / "best"
    with atomic_path(und, folder=True) as tmp:  # COLMAP's folder whole or absent (dvr.atomic)
        pycolmap.undistort_images(tmp, model_dir, image_dir, output_type="COLMAP")
        check_room(tmp)  # its writers say nothing when the disk fills
    urec = pycolmap.Reconstruction(und / "sparse")
    by_name = {urec.image(i).name.rsplit(".", 1)[0]: urec.image(i) for i in urec.reg_image_ids()}
    if ws.images.exists():
        shutil.rmtree(ws.images)
    ws.images.mkdir(parents=True)
    Ks, Rs, ts, sizes, kept, views = [], [], [], [], [], []
    for name in names:
        if name not in by_name:
            continue
        im = by_name[name]
        cam = urec.camera(im.camera_id)
        img = cv2.imread(str(und / "images" / im.name), cv2.IMREAD_COLOR)
        if img is None:  # COLMAP's image writer says nothing when the disk fills
            raise short_write(und / "images" / im.name)
        h, w = img.shape[:2]
        s = min(1.0, cfg.max_side / max(h, w))
        nw, nh = round(w * s), round(h * s)
        if s < 1.0:
            img = cv2.resize(img, (nw, nh), interpolation=cv2.INTER_AREA)
        write_image(ws.images / f"{name}.png", img)
        views.append(downscale(img, SWEEP_SIDE))
        K = cam.calibration_matrix().copy()
        K[0] *= nw / w  # corner-origin pixel coordinates scale exactly
        K[1] *= nh / h
        pose = im.cam_from_world()
        M = pose.matrix() if callable(getattr(pose, "matrix", None)) else np.asarray(pose.matrix)
        Ks.append(K), Rs.append(M[:3, :3]), ts.append(M[:3, 3]), sizes.append((nw, nh)), kept.append(name)
    Ks, Rs, ts, sizes = np.stack(Ks), np.stack(Rs), np.stack(ts), np.asarray(sizes, float)
    pts, cols = model_points(urec, cfg.min_track_length)
    Rs, ts, pts, fit = use_board(ws.root, und, [by_name[n].name for n in kept], Ks, Rs, ts, sizes, pts,
                                 cfg)  # a printed board: metres
    centers = -np.einsum("nji,nj->ni", Rs, ts)
    Ps = Ks @ np.concatenate([Rs, ts[:, :, None]], 2)
    target = axes_convergence(centers, Rs[:, 2, :])
    support = board_support(pts, centers, target) if fit is not None and cfg.support else None  # the board's plane
    support = support or (find_support(pts, centers, Rs, target) if cfg.support else None)
    if support is None and cfg.support and cfg.plain_support and fit is None:
        shrink = np.array([v.shape[1] / w for v, (w, _) in zip(views, sizes)])  # corner-origin pixels scale exactly
        support = find_plain_support(pts, centers, Rs, Ps * np.stack([shrink, shrink, np.ones_like(shrink)], 1)[
            :, :, None], target, views)
    if scale_mat is None:
        S = normalization(pts, Ps, sizes, centers, Rs[:, 2, :], cfg.radius_margin, focals=Ks[:, 0, 0],
                          support=support)
    else:  # the given sphere, moved with the cameras when a board put them in metres: still a sphere (its centre
        # mapped, its radius scaled), not rotated with the frame, as every stage's (x − c) / r expects
        S = scale_mat if fit is None else sphere_frame(transform_points(fit.matrix, scale_mat[:3, 3]),
                                                       fit.scale * scale_mat[0, 0])
    save_cameras(ws.cameras, Ks, Rs, ts, S, None if support is None else support.vector)
    write_points(ws.root / "points.ply", pts, cols)
    return {"views": kept, "radius": float(S[0, 0]), "center": S[:3, 3].tolist(), "support": support_info(support, S),
            **({"board": fit.info(len(names))} if fit is not None else {})}


SWEEP_SIDE = 400
"""The plain support's plane sweep reads the photos at most this large (px, longest side)."""


def support_info(support: SupportPlane | None, S: np.ndarray) -> dict | None:
    """What the stage reports of the support plane (heights in units of the object sphere's radius)."""
    if support is None:
        print("cameras: no support plane (the object is not standing on a textured surface the SfM points show)")
        return None
    centre_h = float(support.height(S[:3, 3][None])[0]) / S[0, 0]
    info = {"normal": np.round(support.normal, 4).tolist(), "offset": round(float(support.offset), 6),
            "inliers": support.inliers, "object_height": round(support.object_height / S[0, 0], 4),
            "sphere_centre_height": round(centre_h, 4)}
    info["kind"] = support.kind
    where = (f"{support.inliers} points on it" if support.kind != "base" else
             "a plain surface under the object's base, where the photos agree around it")
    print(f"cameras: support plane found: {where}, the object stands "
          f"{info['object_height']:.2f} high on it (unit sphere radii; the sphere centre {centre_h:.2f} above it)")
    return info


def export_board_cameras(ws: Workspace, photos: list[Path], cfg: CamerasConfig, cams: BoardCameras,
                         why_not_sfm: str) -> dict:
    """Cameras posed from the printed board (:mod:`pipeline.cameras.board_poses`): undistorted images/, cameras.npz in
    metres, the board's plane as the support plane, no SfM points."""
    for stale in ("undistorted", "sparse"):  # SfM's model with the wrong poses: later stages must not read it
        shutil.rmtree(ws.root / "sfm" / stale, ignore_errors=True)
    if ws.images.exists():
        shutil.rmtree(ws.images)
    ws.images.mkdir(parents=True)
    Ks, sizes = write_board_views(cams, photos, ws.images, cfg.max_side)
    centers = -np.einsum("nji,nj->ni", cams.R, cams.t)
    target = axes_convergence(centers, cams.R[:, 2, :])
    support = board_plane(cams, target) if cfg.support else None
    Ps = Ks @ np.concatenate([cams.R, cams.t[:, :, None]], 2)
    S = normalization(np.zeros((0, 3)), Ps, sizes, centers, cams.R[:, 2, :], cfg.radius_margin, focals=Ks[:, 0, 0],
                      support=support)
    save_cameras(ws.cameras, Ks, cams.R, cams.t, S, None if support is None else support.vector)
    write_points(ws.root / "points.ply", np.zeros((0, 3)), np.zeros((0, 3), np.uint8))
    info = board_info(cams, spec_from_config(cfg), len(photos), why_not_sfm)
    write_board_json(ws.root, info)
    print(f"cameras: SfM could not pose the photos; the printed board poses {len(cams.names)}/{len(photos)} "
          f"(its corners fit to {cams.rms_px:.2f} px, focal {cams.K[0, 0]:.0f} px) → cameras in metres, origin at "
          "the board's centre, z up")
    return {"views": cams.names, "rung": "board", "registered": f"{len(cams.names)}/{len(photos)}",
            "radius": float(S[0, 0]), "center": S[:3, 3].tolist(), "support": support_info(support, S), "board": info}
