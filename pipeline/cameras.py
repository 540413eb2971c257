"""Stage ``cameras``: photos → ``sfm/`` (COLMAP database + sparse model), ``images/``, ``cameras.npz``, ``points.ply``.

SfM runs in-process with pycolmap: SIFT, matching chosen by image count, incremental (or global) mapping,
undistortion to PINHOLE. EXIF orientation: every photo is read with its EXIF orientation APPLIED
(OpenCV's default), and that upright copy is what SfM sees (``sfm/input/``) and what training sees
(``images/``) — COLMAP itself ignores the flag, so feeding it the originals would give it other pixels.
Inputs are never modified; everything is written inside the workspace.
"""

from __future__ import annotations

import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from dvr.cameras import (
    project_points,
    save_cameras,
    sphere_frame,
    transform_points,
)
from dvr.data import list_images

from .board import board_support, spec_from_config, use_board
from .board_poses import (
    BoardCameras,
    board_info,
    board_plane,
    require_board_cameras,
    write_board_json,
    write_board_views,
)
from .colmaplib import warnings_only
from .exposure import measure_exposure, write_exposure
from .photos import (
    PHOTO_EXTS,
    downscale,
    is_readable,
    read_photo,
)
from .pose_sanity import axes_convergence, model_views, pose_sanity
from .sfm import (
    RUNG_NAMES,
    ladder,
    model_stats,
    read_stage_model,
    refine_model,
    retriangulate,
    run_rung,
    shortfalls,
    verify_again,
    verify_at_poses,
)
from .support import SupportPlane, find_support
from .video import extract_frames, is_video
from .workspace import Done, Job, StageError, Workspace


@dataclass
class CamerasConfig:
    """Camera estimation (stage ``cameras``)."""

    max_side_sfm: int = 1600
    """Longest image side SfM works on (photos are downscaled to it, never upscaled)."""
    max_side: int = 400
    """Longest side of the training images written to images/."""
    video_frames: int = 48
    """Frames taken from a video given instead of a photo folder (``--images clip.mp4``): the sharpest of each of
    this many equal stretches of the clip, into frames/ (``pipeline/video.py``)."""
    matching: Literal["auto", "exhaustive", "sequential"] = "auto"
    """Pairs to match: 'auto' = exhaustive up to 80 images, sequential (with loop closure off) beyond."""
    start_rung: Literal["default", "guided", "dsp", "relaxed", "global", "merge"] = "default"
    """First rung of the SfM ladder: default SIFT → guided matching → DSP-SIFT + affine shape → relaxed mapper →
    global mapper → merge (the best model so far absorbs the photos it lacks). A rung runs only when the one before
    left the model short (a photo unregistered, a poor reprojection error or track length, too few points per
    view) or with poses that fail the sanity check."""
    last_rung: Literal["default", "guided", "dsp", "relaxed", "global", "merge"] = "merge"
    """Last rung of the SfM ladder ('default': one COLMAP run, as before the ladder)."""
    max_reprojection_error: float = 1.0
    """A model whose mean reprojection error (px) exceeds this is short: the ladder climbs."""
    max_bad_pose_fraction: float = 0.3
    """A model in which more than this fraction of the views fail the pose sanity check (axes that miss the
    object the others converge on, or two sides of a symmetric scene merged) is rejected as a whole; fewer such
    views are dropped from it (and listed as unregistered)."""
    seed: int = 0
    """Random seed of COLMAP's mapper, its geometric verification's RANSAC and the re-triangulation."""
    deterministic: bool = True
    """Run COLMAP (features, matching, mapping) on one thread: the same photos then give the same cameras, and the
    whole pipeline the same mesh. On all cores its runs differ (two runs of the cow's 40 photos: pose matrices
    1–3e-3 apart; over the bench's runs the floating cow scored 16.8–23 dB held-out, the jar 32.0–34.1); one
    thread costs the cow's cameras stage 14 → 21 s (1600×1200: 120 → 176 s). Off: all cores. The object matches'
    verification again (``object_verification`` "ransac") runs on all cores either way: its RANSAC is seeded per
    pair, and the result is the same on any number of threads."""
    triangulate_given: bool = True
    """With given cameras (--cameras FILE): match SIFT features and triangulate them at the given poses, so the
    later stages get sparse depth, the support plane and SfM tracks as after our own SfM (about 10 s for 36 photos
    of 400×300); off: the given cameras alone, no points."""
    camera_model: str = "SIMPLE_RADIAL"
    """COLMAP camera model estimated before undistortion."""
    pinhole_tolerance: float = 0.1
    """After SfM the pinhole model (distortion 0, focal length and poses re-adjusted) replaces the fitted lens
    distortion when its mean reprojection error is at most this fraction larger: on object-centric captures
    distortion and focal length trade off (a pinhole render came out with k = 0.11 and an 11 % long focal length
    at the same error). Negative: keep whatever SfM fits."""
    final_passes: int = 0
    """Passes of a final bundle adjustment after mapping (0: off, the model as mapped; 3 to use it): each drops the
    observations more than ``final_error_ratio`` × the mean reprojection error off and re-adjusts with a robust
    (Cauchy) loss. Where the camera model is exact it halves the pose error (a rendered cow: rotation 0.057° →
    0.030°). One SfM mapping each, with and without the passes (held-out PSNR, default preset; stop 27's saved
    mappings, then the bench's one-thread mappings of stop 28): the cow +0.4 / +0.54 dB (`balanced` +0.6 / +0.72),
    the floating cow +6.0 / +8.1, the jar −0.2 / −1.36, the book −0.4 / −0.74, DTU −1.05 (stop 28) (the passes
    take a quarter to half of the book's sparse depths with them; see ``final_retriangulate``). Degrees mislead:
    the jar's rotation error falls (0.070 → 0.051°) while its held-out views' picture of the object moves further
    from the truth (0.13 → 0.19 px, ``bench/object_px.py``), and held-out photos are rendered at the poses SfM gave
    them; with each held-out camera re-aimed onto its photo (``bench/reaim.py``, stop 42) the jar gains 0.17 dB
    and the cow 1.06, but the book loses 0.63 and DTU 0.64 in the mesh itself. On real photos the error tail is
    partly model misfit (DTU's principal point is off-centre). Off by default for a model from the ladder's first
    rung; a later rung's model gets ``climbed_passes``."""
    climbed_passes: int = 3
    """Passes of the final adjustment (as ``final_passes``, whichever is more) for a model that a later rung of the
    ladder gave: the first rung's model fell short, and the later rungs' features (16 k, guided matching, DSP-SIFT)
    fit looser (the cameras table: 0.7–0.85 px mean reprojection error against 0.33–0.6 px at the first rung). The
    four synthetic captures that climb, one SfM mapping each (stop 30), held-out PSNR (default preset) as mapped →
    passes → passes and points re-triangulated: the floating cow (dsp) 17.00 → 20.50 → 20.43 dB, the cow on a
    parquet (dsp) 21.99 → 22.61 → 18.61, the cow's 16 views (dsp) 24.05 → 16.70 → 24.97, the jar's 24 views of
    320×240 (dsp) 32.26 → 32.89 → 32.53 (``bench/pair.py``; ``climbed_retriangulate`` picks the column). The
    scenes that lose by the passes (jar, book, DTU: −0.7 to −1.4 dB) map at the first rung. 0: no passes but
    ``final_passes``."""
    climbed_retriangulate: bool = True
    """After the climbed passes (``climbed_passes``), triangulate the points afresh (as ``final_retriangulate``)
    where the passes take the object's sphere below the 20 points it is fitted to (points seen inside most views,
    ``SPHERE_MIN_POINTS``) and the model as mapped had them: the passes take points with the observations they
    drop, and where views are few the object's own go (the cow's 16 views: 22 → 7, the sphere falls back to the
    images' bound, about 1.7× larger; masks 0.984 → 0.954 IoU, held-out 24.05 → 16.70 dB; re-triangulated
    24.97). Elsewhere re-triangulating does harm: from every match, the parquet's regular planks bring wrong
    matches back (0.32 → 0.96 px), no support plane is found and the masks take the floor (IoU 0.99 → 0.48,
    held-out 22.61 → 18.61 dB); the floating cow and the jar's 24 views lose 0.07 and 0.36 dB (figures under
    ``climbed_passes``). Off: never after the climbed passes."""
    final_error_ratio: float = 2.5
    """Observations above this multiple of the model's mean reprojection error are dropped in each final pass."""
    final_retriangulate: bool = False
    """After the final passes, triangulate the points afresh from every match at the adjusted poses (COLMAP's point
    triangulator; poses unchanged). The passes drop a quarter to half of the object's sparse depths with the
    observations (the cow 212 → 110, the book 7768 → 5879); this brings them back (208, 7777) and the book's held-out
    PSNR with the passes 23.68 → 24.40 dB (24.09 without the passes). The observations it brings back include
    wrong matches, whose points the masks stage draws as hard background seeds: without masks.seed-max-error (now
    on by default) they cut a horn out of four of the floating cow's masks (IoU 0.9986 → 0.9874, 22.82 → 18.32
    dB; with it 22.53 dB). Off by default, as are the passes: the weakly textured jar loses by it (32.10 → 31.6 dB
    with the passes)."""
    max_features: int = 8192
    """SIFT features per image on the first rung (later rungs: at least 16 k)."""
    max_h_inlier_ratio: float = 0.8
    """Two-view verification (COLMAP's ``max_H_inlier_ratio``, its 0.8): a pair whose homography explains more than
    this fraction of its epipolar inliers is "planar", and keeps the homography's inliers when they outnumber them.
    1.0 everywhere broke the floating cow (its far backdrop's pairs, nearly a pure rotation, then count as general:
    mask IoU 0.987 → 0.938, 20.5 → 12.0 dB); ``object_matches`` uses it only where needed."""
    object_matches: bool = True
    """Photos twice the working size or larger (a phone's), and a model that leaves the object's sphere fewer than 20
    sparse points (:data:`SPHERE_MIN_POINTS`, :data:`LARGE_PHOTOS`): verify the stored matches again
    (``object_verification``) and triangulate the points again at the same poses. An object on a textured floor
    photographed larger than the working size: most of a pair's matches lie on the floor, the pair is "planar",
    and it keeps the homography's inliers — the floor's alone. The cow on its floor at 1200 × 900: 7 points on the
    object (28 verified object matches in all pairs; 346 again), so its sphere came from the floor's points (twice
    too large) and the masks lost its legs (IoU 0.955)."""
    object_verification: Literal["ransac", "poses"] = "ransac"
    """How ``object_matches`` verifies the stored matches again: "ransac" estimates each pair's geometry again with
    ``max_h_inlier_ratio`` 1.0 (33 s for the 190 pairs of 20 photos of 960 × 720); "poses" keeps each pair's matches
    within the epipolar error of the model's known relative pose (COLMAP's guided verifier, no RANSAC: 0.2 s there),
    faster and a little less accurate: the cow's 40 photos of 1200 × 900, cameras stage 318 → 184 s, held-out
    26.04 → 25.56 dB (as JPEGs 354 → 211 s, 24.96 → 24.63 dB); the ``fast`` preset uses it."""
    min_registered_fraction: float = 0.5
    """Fail when fewer images than this fraction register (the list of unregistered images is printed)."""
    radius_margin: float = 1.3
    """Unit sphere radius = margin × robust object radius from the sparse points (the points sample the object
    sparsely: at 1.1 the corners of a plate and the cow's hooves fell outside, and masks and hull cut them)."""
    min_track_length: int = 3
    """Sparse points used for normalisation need at least this many observations."""
    support: bool = True
    """Find the surface the object stands on (a robust plane fit of the SfM points: horizontal, under the cameras,
    under the point they converge on, around the object); every later stage then treats it as background and
    nothing below it as object. Without one (held, hung, plain backdrop), nothing changes."""
    board: bool = True
    """Look for a printed ChArUco board in the photos (``python -m pipeline board board.png`` prints one). When its
    corners are seen, the SfM frame becomes the board's: cameras.npz, points and meshes in metres (origin at the
    board's centre, z up), the board's plane is the support plane, and ``board.json`` says what was found. No
    board seen: nothing changes."""
    board_squares: tuple[int, int] = (5, 7)
    """Squares of the printed board (columns, rows)."""
    board_square_mm: float = 35.0
    """Side of one board square as printed (mm): measure it with a ruler; the metric scale is exactly as good."""
    board_marker_mm: float = 26.0
    """Side of one ArUco marker of the board as printed (mm), smaller than a square."""
    board_dictionary: str = "DICT_4X4_50"
    """ArUco dictionary of the board's markers (an OpenCV name, e.g. DICT_4X4_50, DICT_5X5_100)."""


# ----------------------------------------------------------------------------- inputs
def list_photos(folder: Path) -> tuple[list[Path], list[str]]:
    """Readable photos (sorted) and warnings about the files skipped; several photos with one stem (IMG_1.jpg and
    IMG_1.heic) are an error, since every later stage names its files by stem."""
    if not folder.is_dir():
        raise StageError(f"{folder}: not a folder of photos or a video; pass --images DIR (or a video file)")
    ok, skipped = [], []
    for p in sorted(folder.iterdir()):
        if not p.is_file() or p.name.startswith("."):
            continue
        if p.suffix.lower() not in PHOTO_EXTS:
            skipped.append(f"{p.name} (not an image file)")
            continue
        if not is_readable(p):
            skipped.append(f"{p.name} (unreadable)")
            continue
        ok.append(p)
    by_stem: dict[str, list[str]] = {}
    for p in ok:
        by_stem.setdefault(p.stem, []).append(p.name)
    dup = sorted(" and ".join(v) for v in by_stem.values() if len(v) > 1)
    if dup:
        raise StageError(f"{folder}: {'; '.join(dup[:3])}{' …' if len(dup) > 3 else ''} share a name with different "
                         "extensions (the same shot twice?); keep one of each or rename them")
    return ok, skipped


def write_points(path: Path, pts: np.ndarray, cols: np.ndarray) -> None:
    """Binary PLY of coloured points (also valid when empty)."""
    head = ("ply\nformat binary_little_endian 1.0\nelement vertex %d\nproperty float x\nproperty float y\n"
            "property float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
    rec = np.zeros(len(pts), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1")])
    if len(pts):
        rec["x"], rec["y"], rec["z"] = pts.T
        rec["r"], rec["g"], rec["b"] = cols.T
    path.write_bytes((head % len(pts)).encode() + rec.tobytes())


# ----------------------------------------------------------------------------- normalisation
SPHERE_MIN_POINTS = 20
"""Fewer central points (:func:`central_points`) than this, and the object's sphere is fitted to every point above
the support plane instead, which the images' bound then caps (a cliff: the 16-view cow's sphere 1.30 → 2.15)."""

LARGE_PHOTOS = 2.0
""":func:`keep_object_matches` runs when SfM saw the photos at least this many times the working size (a phone's): at
the working size it changed the bench's weakly textured jars and the mug for the worse (held-out 32.3 → 30.5,
32.2 → 28.2, 26.6 → 25.5 dB) and helped none of its eight scenes by more than their runs' spread."""


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


def sphere_points(rec, cfg: CamerasConfig) -> int:
    """How many of the COLMAP model's points the object's sphere would be fitted to (:func:`central_points`, with
    the support plane as the stage finds it; the model's pinhole intrinsics, distortion aside)."""
    pts = model_points(rec, cfg.min_track_length)[0]
    views = model_views(rec)
    Rs, centers = np.stack([v.R for v in views]), np.stack([v.center for v in views])
    support = find_support(pts, centers, Rs, axes_convergence(centers, Rs[:, 2, :])) if cfg.support else None
    Ps = np.stack([v.K @ np.concatenate([v.R, v.t[:, None]], 1) for v in views])
    sizes = np.array([(v.width, v.height) for v in views], float)
    return len(central_points(pts, Ps, sizes, support)[1])


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


# ----------------------------------------------------------------------------- SfM
def prepare_sfm_input(ws: Workspace, photos: list[Path], cfg: CamerasConfig
                      ) -> tuple[Path, list[list[str]], list[tuple[tuple[int, int], tuple[int, int]]]]:
    """Upright copies of the photos (longest side ≤ max_side_sfm) in ``sfm/input``, grouped by size; per photo the
    (height, width) of the upright photo and of its copy."""
    sfm = ws.root / "sfm"
    if sfm.exists():
        shutil.rmtree(sfm)
    inp = sfm / "input"
    inp.mkdir(parents=True)
    groups: dict[tuple[int, int], list[str]] = {}
    shapes = []
    for p in photos:
        full = read_photo(p)
        if full is None:
            raise StageError(f"{p}: unreadable image; remove it from the folder")
        img = downscale(full, cfg.max_side_sfm)
        cv2.imwrite(str(inp / f"{p.stem}.png"), img)
        groups.setdefault(img.shape[:2], []).append(f"{p.stem}.png")
        shapes.append((full.shape[:2], img.shape[:2]))
    return inp, list(groups.values()), shapes


def _drop_views(rec, names: set[str]) -> None:
    for i in list(rec.reg_image_ids()):
        if rec.image(i).name in names:
            rec.deregister_frame(rec.image(i).frame_id)


def run_sfm(ws: Workspace, photos: list[Path], cfg: CamerasConfig):
    """Climb the SfM ladder (:mod:`pipeline.sfm`) until a rung registers every photo with sane poses, then the
    final adjustment (:func:`finish_model`); returns (model, folder of the images SfM saw, summary of the rungs
    tried)."""
    rec, inp, database, rung, tried = map_photos(ws, photos, cfg)
    rec, final, object_note = finish_model(ws, rec, database, inp, cfg, rung)
    return rec, inp, {"rung": rung, "rungs": tried, "final_adjustment": final, "object_matches": object_note}


def final_adjustment(cfg: CamerasConfig, rung: str) -> tuple[int, str]:
    """The final adjustment for a model from the ladder's ``rung``: (passes, when to re-triangulate after them:
    "always", "when short" — when the passes take the object's sphere below ``SPHERE_MIN_POINTS`` points, which
    the model as mapped had — or "never"). ``cfg.final_passes`` and ``cfg.final_retriangulate``; past the first
    rung at least ``cfg.climbed_passes``, re-triangulated when short if ``cfg.climbed_retriangulate``."""
    climbed = rung != RUNG_NAMES[0] and cfg.climbed_passes > 0
    passes = max(cfg.final_passes, cfg.climbed_passes) if climbed else cfg.final_passes
    if cfg.final_retriangulate:
        return passes, "always"
    return passes, "when short" if climbed and cfg.climbed_retriangulate else "never"


def sfm_threads(cfg: CamerasConfig) -> int:
    """COLMAP's threads: 1 when ``cfg.deterministic``, else -1 (all cores)."""
    return 1 if cfg.deterministic else -1


def map_photos(ws: Workspace, photos: list[Path], cfg: CamerasConfig):
    """The SfM ladder: (model as mapped, folder of the images SfM saw, its COLMAP database, the rung's name,
    summary of the rungs tried)."""
    inp, groups, _ = prepare_sfm_input(ws, photos, cfg)
    names = [p.stem for p in photos]
    work = ws.root / "sfm" / "ladder"
    work.mkdir()
    tried, best, rejected = [], None, {}
    for rung in ladder(cfg.start_rung, cfg.last_rung, cfg.max_features, cfg.max_h_inlier_ratio):
        base = None
        if rung.mapper == "extend":  # continue from the best model so far: only when it lacks photos
            if best is None or best[1].num_reg_images() >= len(names):
                continue
            base = (work / "merge-base", best[3])
            shutil.rmtree(base[0], ignore_errors=True)
            base[0].mkdir()
            best[1].write(base[0])
        t0 = time.perf_counter()
        rec, database, secs, err = run_rung(work, inp, groups, rung, cfg.camera_model, cfg.matching, cfg.seed,
                                            base, sfm_threads(cfg))
        dt = time.perf_counter() - t0
        if rec is None or rec.num_reg_images() < 2:
            print(f"cameras: rung {rung.name}: {err or 'no model'} ({dt:.1f} s)")
            tried.append({"rung": rung.name, "seconds": round(dt, 1), "error": err or "no model"})
            continue
        bad = pose_sanity(rec, inp)
        n_reg = rec.num_reg_images()
        if len(bad) > cfg.max_bad_pose_fraction * n_reg:
            print(f"cameras: rung {rung.name}: {n_reg} registered but {len(bad)} poses are not credible, model "
                  f"rejected ({dt:.1f} s)")
            rejected.update(bad)
            tried.append({"rung": rung.name, "seconds": round(dt, 1), "registered": n_reg, "rejected": len(bad)})
            continue
        _drop_views(rec, set(bad))
        stats = model_stats(rec, names)
        short = shortfalls(stats, cfg.max_reprojection_error)
        dropped = f", dropped {len(bad)} views with wrong poses ({', '.join(sorted(bad)[:4])})" if bad else ""
        print(f"cameras: rung {rung.name}: registered {stats['registered']}/{len(names)}, "
              f"{stats['mean_reprojection_error']:.2f} px, track length {stats['mean_track_length']:.2f}"
              f"{dropped} in {dt:.1f} s → {'; '.join(short) if short else 'complete'}")
        tried.append({"rung": rung.name, "seconds": round(dt, 1), **{k: stats[k] for k in ("registered",
                      "mean_reprojection_error", "mean_track_length")}, "dropped": sorted(bad), "steps": secs})
        key = (stats["registered"], -stats["mean_reprojection_error"])
        if best is None or key > best[0]:
            best = (key, rec, rung.name, database)
        if not short:
            break
    _require_credible(None if best is None else best[1], rejected, inp, len(names), cfg.min_registered_fraction)
    return best[1], inp, best[3], best[2], tried


def finish_model(ws: Workspace, rec, database: Path, inp: Path, cfg: CamerasConfig, rung: str):
    """The model ``rec`` that the ladder's ``rung`` mapped, as the cameras stage keeps it: pinhole where the
    distortion is negligible, the final adjustment (:func:`final_adjustment`: passes, then re-triangulation);
    written to sfm/sparse/best with its ``database`` beside (sfm/database.db, where COLMAP puts it); the object's
    matches kept (:func:`keep_object_matches`). Returns (model, notes of the final adjustment, the object matches'
    note or None)."""
    threads = sfm_threads(cfg)
    rec, notes = prefer_pinhole(rec, cfg.pinhole_tolerance, threads)
    passes, again = final_adjustment(cfg, rung)
    adjusted, final = refine_model(rec, passes, cfg.final_error_ratio, threads=threads)
    if passes > cfg.final_passes:
        final = [f"{note} (the model came from the ladder's rung '{rung}': cameras.climbed-passes)" for note in final]
    if adjusted is not rec and again == "when short":
        before, left = sphere_points(rec, cfg), sphere_points(adjusted, cfg)
        again = "always" if left < SPHERE_MIN_POINTS <= before else "never"
        final.append(f"the passes left the object's sphere {left} of its {before} points (it needs "
                     f"{SPHERE_MIN_POINTS}): " + ("points re-triangulated" if again == "always" else
                                                  "points kept as adjusted"))
    if adjusted is not rec and again == "always":
        adjusted, note = retriangulate(adjusted, database, inp, ws.root / "sfm" / "ladder" / "final", cfg.seed,
                                       threads)
        final.append(note)
    object_note = None
    if cfg.object_matches:
        adjusted, database, object_note = keep_object_matches(ws, adjusted, database, inp, cfg)
    for note in notes + final + ([object_note] if object_note else []):
        print(f"cameras: {note}")
    best_dir = ws.root / "sfm" / "sparse" / "best"
    best_dir.mkdir(parents=True)
    adjusted.write(best_dir)
    shutil.copy(database, ws.root / "sfm" / "database.db")
    return adjusted, final, object_note


def keep_object_matches(ws: Workspace, rec, database: Path, inp: Path, cfg: CamerasConfig):
    """``rec`` with its points triangulated again, at the same poses, from its ``database``'s stored matches verified
    again (``object_verification``: against the model's poses, :func:`pipeline.sfm.verify_at_poses`, or by RANSAC
    keeping every pair's epipolar inliers, :func:`pipeline.sfm.verify_again`; either way a "planar" pair no longer
    keeps its floor's alone), when SfM saw the photos at :data:`LARGE_PHOTOS` × the working
    size or more, the model leaves the object's sphere fewer than :data:`SPHERE_MIN_POINTS` points, and that gives it
    more (``object_matches``). Returns (model, its database, a note or None)."""
    sfm_side = max(max(c.width, c.height) for c in rec.cameras.values())
    if sfm_side < LARGE_PHOTOS * cfg.max_side:
        return rec, database, None
    before = sphere_points(rec, cfg)
    if before >= SPHERE_MIN_POINTS:
        return rec, database, None
    work = ws.root / "sfm" / "ladder"
    work.mkdir(parents=True, exist_ok=True)  # bench/pair.py's saved mappings come without the ladder's folder
    threads = sfm_threads(cfg)
    if cfg.object_verification == "poses":
        db, how = work / f"{database.stem}-posed.db", "again at the model's poses"
        verify_at_poses(rec, database, db, threads)
    else:
        db, how = work / f"{database.stem}-h1.db", "keeping each pair's epipolar inliers"
        verify_again(database, db, 1.0, cfg.seed, -1)  # all cores even when deterministic: the same either way
    out, _ = retriangulate(rec, db, inp, work / "object", cfg.seed, threads)
    after = sphere_points(out, cfg)
    note = (f"{before} sparse points for the object's sphere (it needs {SPHERE_MIN_POINTS}); matches verified {how} "
            f"and points triangulated again at the same poses: {after}")
    return (out, db, note) if after > before else (rec, database, note + ", kept as mapped")


def _require_credible(rec, rejected: dict, inp: Path, n_photos: int, min_fraction: float) -> None:
    """The SfM ladder's failures as a StageError: no model at all (``rec`` None), or, when models were rejected for
    poses that cannot be (``rejected``), a kept model that registers fewer than ``min_fraction`` of the photos."""
    views = ", ".join(sorted(Path(n).stem for n in rejected)[:8])
    if rec is None:
        if rejected:
            raise StageError(f"{inp.parent.parent}: SfM poses are inconsistent for every setting tried (views {views}"
                             f"{' …' if len(rejected) > 8 else ''}): a symmetric or repetitive object or floor — "
                             "put a textured mat (a newspaper) under the object, or add texture around it")
        raise StageError(f"{inp}: SfM found no model (too few matches): photograph the object with more overlap "
                         "(≥ 60 % between neighbours), more texture, and sharp, well-lit images")
    if rejected and rec.num_reg_images() < max(3, min_fraction * n_photos):
        raise StageError(f"{inp.parent.parent}: SfM registered {rec.num_reg_images()}/{n_photos} photos with "
                         f"credible poses; other settings placed views {views}{' …' if len(rejected) > 8 else ''} "
                         "where they cannot be: a symmetric or repetitive object or floor — put a textured mat (a "
                         "newspaper) under the object, or add texture around it")


def prefer_pinhole(rec, tolerance: float, threads: int = -1):
    """Set the lens distortion to zero and re-adjust focal lengths and poses (bundle adjustment on ``threads``
    threads, -1: all cores); keep that pinhole model when its mean reprojection error grows by at most
    ``tolerance`` (relative, +0.01 px); returns (model, notes).

    Object-centric captures hardly constrain distortion against focal length: on a synthetic pinhole scene
    COLMAP fitted k = 0.11 with the focal length 11 % long, and the pinhole re-fit recovered the true focal
    length to 0.01 % at the same reprojection error; undistorting by the spurious model cost ~13 dB held-out
    PSNR. A real lens keeps its distortion because a pinhole explains its tracks clearly worse.
    """
    from .colmaplib import pycolmap

    if tolerance < 0:
        return rec, []
    trial = pycolmap.Reconstruction(rec)
    changed = []
    for cid, cam in trial.cameras.items():
        idx = list(cam.extra_params_idxs())
        if not idx or not np.any(cam.params[idx]):
            continue
        p = cam.params.copy()
        changed.append(f"camera {cid}: distortion {np.round(p[idx], 4).tolist()}, focal "
                       f"{np.round(p[list(cam.focal_length_idxs())], 1).tolist()}")
        p[idx] = 0.0
        cam.params = p
    if not changed:
        return rec, []
    opts = pycolmap.BundleAdjustmentOptions()
    opts.refine_extra_params = False
    opts.print_summary = False
    opts.ceres.solver_options.num_threads = threads
    pycolmap.bundle_adjustment(trial, opts)
    e0, e1 = rec.compute_mean_reprojection_error(), trial.compute_mean_reprojection_error()
    if e1 > (1 + tolerance) * e0 + 0.01:
        return rec, [f"lens distortion kept: as a pinhole the reprojection error grows from {e0:.3f} to {e1:.3f} px"]
    focal = [np.round(c.params[list(c.focal_length_idxs())], 1).tolist() for c in trial.cameras.values()]
    return trial, [f"{c} → pinhole" for c in changed] + [f"pinhole focal {focal}, mean reprojection error "
                                                         f"{e0:.3f} → {e1:.3f} px"]


def report_sfm(rec, names: list[str], cfg: CamerasConfig) -> dict:
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
    if missing:
        print(f"cameras: not registered: {', '.join(missing)}", file=sys.stderr)
    if len(reg) < max(3, cfg.min_registered_fraction * len(names)):
        raise StageError(f"only {len(reg)}/{len(names)} photos registered (missing: {', '.join(missing[:10])}"
                         f"{'...' if len(missing) > 10 else ''}); likely too little overlap or texture, or motion "
                         "blur — add photos between the missing ones")
    return info


def export_model(ws: Workspace, rec, image_dir: Path, cfg: CamerasConfig, names: list[str],
                 scale_mat: np.ndarray | None = None) -> dict:
    """Undistort the model to PINHOLE, write images/, cameras.npz and points.ply; ``scale_mat``: the object's sphere
    as given with the cameras (else found from the points)."""
    from .colmaplib import pycolmap

    warnings_only()  # an adjustment before turned COLMAP's info lines on: two per photo here
    und = ws.root / "sfm" / "undistorted"
    if und.exists():
        shutil.rmtree(und)
    model_dir = ws.root / "sfm" / "sparse" / "best"
    pycolmap.undistort_images(und, model_dir, image_dir, output_type="COLMAP")
    urec = pycolmap.Reconstruction(und / "sparse")
    by_name = {urec.image(i).name.rsplit(".", 1)[0]: urec.image(i) for i in urec.reg_image_ids()}
    if ws.images.exists():
        shutil.rmtree(ws.images)
    ws.images.mkdir(parents=True)
    Ks, Rs, ts, sizes, kept = [], [], [], [], []
    for name in names:
        if name not in by_name:
            continue
        im = by_name[name]
        cam = urec.camera(im.camera_id)
        img = cv2.imread(str(und / "images" / im.name), cv2.IMREAD_COLOR)
        h, w = img.shape[:2]
        s = min(1.0, cfg.max_side / max(h, w))
        nw, nh = round(w * s), round(h * s)
        if s < 1.0:
            img = cv2.resize(img, (nw, nh), interpolation=cv2.INTER_AREA)
        cv2.imwrite(str(ws.images / f"{name}.png"), img)
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


def support_info(support: SupportPlane | None, S: np.ndarray) -> dict | None:
    """What the stage reports of the support plane (heights in units of the object sphere's radius)."""
    if support is None:
        print("cameras: no support plane (the object is not standing on a textured surface the SfM points show)")
        return None
    centre_h = float(support.height(S[:3, 3][None])[0]) / S[0, 0]
    info = {"normal": np.round(support.normal, 4).tolist(), "offset": round(float(support.offset), 6),
            "inliers": support.inliers, "object_height": round(support.object_height / S[0, 0], 4),
            "sphere_centre_height": round(centre_h, 4)}
    print(f"cameras: support plane found: {support.inliers} points on it, the object stands "
          f"{info['object_height']:.2f} high on it (unit sphere radii; the sphere centre {centre_h:.2f} above it)")
    return info


def export_board_cameras(ws: Workspace, photos: list[Path], cfg: CamerasConfig, cams: BoardCameras,
                         why_not_sfm: str) -> dict:
    """Cameras posed from the printed board (:mod:`pipeline.board_poses`): undistorted images/, cameras.npz in
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


def run(job: Job) -> Done:
    """Stage ``cameras`` (called by :func:`pipeline.stages.run_stage`): the photos in ``job.sources.images`` posed by
    the SfM ladder, by given cameras (``job.sources.given_cameras``: a cameras.npz or a COLMAP model) or by a
    printed board → images/, cameras.npz, points.ply, sfm/."""
    ws, cfg, images, given = job.ws, job.cfg, job.sources.images, job.sources.given_cameras
    ws.root.mkdir(parents=True, exist_ok=True)
    video = None
    if is_video(images):
        clip, images = images, ws.root / "frames"
        record = extract_frames(clip, images, cfg.video_frames, cfg.max_side_sfm)
        video = {"clip": clip.name, "frames_in_clip": record["frames_in_clip"], "taken": len(record["chosen"])}
        print(f"cameras: {video['taken']} of the {video['frames_in_clip']} frames of {clip.name}, the sharpest of each "
              f"equal stretch → {images}")
    photos, skipped = list_photos(images)
    if video is not None:  # the frames' own record is no skipped photo
        skipped = [s for s in skipped if not s.startswith("frames.json ")]
    for s in skipped:
        print(f"warning: skipping {images / s.split(' (')[0]}: {s.split(' (', 1)[1][:-1]}", file=sys.stderr)
    if len(photos) < 3:
        raise StageError(f"{images}: {len(photos)} usable photo(s); at least 3 are needed (20–60 around the object is "
                         "typical)")
    info = pose_photos(ws, photos, images, given, cfg)
    print(f"cameras: {len(info['views'])} views → {ws.cameras}")
    if video is not None:
        info["video"] = video
    spread = record_exposure(ws)
    if spread is not None:
        info["exposure_spread"] = round(spread, 4)
    return Done({k: v for k, v in info.items() if k != "views"})


def pose_photos(ws: Workspace, photos: list[Path], images: Path, given: Path | None, cfg: CamerasConfig) -> dict:
    """The cameras of ``photos``: from a given COLMAP model folder or cameras.npz, else by the SfM ladder, else (SfM
    cannot pose them: a symmetric object) by a printed board in view. Returns the stage's record."""
    if given is not None:
        from .given_cameras import import_cameras, import_colmap_model  # they finish as SfM's model does, here

        return (import_colmap_model(ws, photos, images, given, cfg) if given.is_dir()
                else import_cameras(ws, photos, given, cfg))
    try:
        rec, inp, ladder_info = run_sfm(ws, photos, cfg)
        info = report_sfm(rec, [p.stem for p in photos], cfg)
        info.update(ladder_info)
        info.update(export_model(ws, rec, inp, cfg, [p.stem for p in photos]))
        return info
    except StageError as exc:  # SfM cannot pose them (a symmetric object): a printed board in view still can
        return export_board_cameras(ws, photos, cfg, require_board_cameras(photos, cfg, exc), str(exc))


def record_exposure(ws: Workspace) -> float | None:
    """The photos' per-view gains measured on the stage's SfM points → exposure.json (:mod:`pipeline.exposure`);
    their spread, or None (and no file) without an SfM model (cameras from a board, or given without points)."""
    ws.exposure.unlink(missing_ok=True)
    if not ws.sfm_model.exists():
        return None
    est = measure_exposure(read_stage_model(ws.sfm_model), list_images(ws.images))
    write_exposure(ws.exposure, est)
    spread = est.spread()
    print(f"cameras: the photos' exposure differs by {100 * spread:.1f} % (SfM points' colours, 90th "
          f"percentile of the photos against the average photo) → {ws.exposure}")
    return spread
