"""Stage ``masks``: one binary mask per image (``masks/<stem>.png``), overlays and per-image confidence.

User masks (``--masks-dir DIR``) are matched by stem, validated (readable, binary-ish) and transformed like their
images (EXIF orientation applied, resized to the image size). Automatic masks use no learned model unless
``saliency`` is on (:mod:`pipeline.masks.saliency`: each view's salient pixels vote beside its mask,
:func:`with_salient`):

1. seeds from geometry: sparse SfM points inside the object's unit sphere are object, points the view
   observes far outside it are background (visibility from the COLMAP tracks in ``sfm/``), and everything
   outside the projected unit sphere is background (the object lies inside it by construction), and so is, on a
   support plane, every pixel that sees past the object's footprint (:func:`pipeline.scene.support.footprint_prism`:
   the table in front of the object, which GrabCut takes where it has the object's colours; with too few sparse
   points on the object, the footprint of the first masks' visual hull, :func:`hull_footprint`, seeds the vote
   rounds instead; with enough, beyond the points' prism is only probable background at first and the vote rounds
   take the union of both footprints, ``footprint_union``); plane-sweep
   stereo (:mod:`pipeline.masks.stereo`) adds object seeds where a pixel is photo-consistent only at depths
   inside the sphere and background seeds where only beyond it — what separates an object that has its
   backdrop's colours (and seeds GrabCut when given cameras come without SfM tracks); on the floor inside the
   object's sphere its background labels are only probable (:func:`support_in_sphere`);
2. GrabCut in every image, seeded by those;
3. multi-view consistency, ``vote_rounds`` times: the visual hull of all masks, carving a point only when
   ≥ ``carve_min_views`` views and ≥ ``carve_fraction`` of those that see it see it as background (never the cell of a
   sparse point on the object that ``keep_min_views`` views observe, :func:`kept_points`), is re-projected
   into every view as an upper bound, and GrabCut refines inside it to the image edges — a mistake in one view is
   outvoted by the others; with a support plane, up to ``floor_rounds`` more rounds that change only the pixels
   whose ray passes under the object (:func:`low_band`): the floor between an object's legs, in its shadow and seen
   only by the views along the legs, leaves the masks a little more each round, and the rounds stop where they grow
   instead (:func:`vote`);
4. confidence = IoU between a view's first GrabCut mask and the hull's silhouette.
"""

from __future__ import annotations

import os
import shutil
import sys
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from dvr.atomic import write_image, write_json
from dvr.cameras import Cameras, load_cameras, plane_height, project_points, sphere_bounds, to_normalized
from dvr.data import list_images, pad_stack, read_mask
from dvr.hull import grid_points, hull_lattice, mask_lookup, near_object
from pipeline.errors import StageError
from pipeline.masks.config import MasksConfig
from pipeline.masks.saliency import (
    SALIENT,
    beyond_share,
    evidence,
    first_labels,
    missing_model_message,
    model_installed,
    probe_views,
    saliency_maps,
    salient_pixels,
    vote_prior,
)
from pipeline.masks.stereo import BACKGROUND, BACKGROUND_RADIUS, OBJECT, stereo_seed_labels
from pipeline.messages import names_or_count
from pipeline.readers import read_stage_model
from pipeline.render.raycast import MeshCaster, pixel_center_rays
from pipeline.scene.exposure import even_out, read_exposure
from pipeline.scene.support import GROUND_BAND, footprint_prism, plane_basis
from pipeline.workspace import Done, Job, Workspace

FOOTPRINT_IN_FRAME = 0.75
"""Fraction of the views that must have a hull cell in frame for :func:`hull_footprint` to count it."""


# ----------------------------------------------------------------------------- user masks
def mask_files(names: list[str], mask_dir: Path) -> dict[str, Path]:
    """The user's mask file of each photo stem in ``names`` (``mask_dir``, matched by stem, any image extension);
    StageError naming the folder and the fix when it is no folder, holds two masks of one photo or lacks one. Also
    run on the photo folder before SfM (:func:`pipeline.stages.check_user_masks`), so a missing mask is said at once."""
    if not mask_dir.is_dir():
        raise StageError(f"{mask_dir}: not a folder; pass --masks-dir DIR with one mask per photo (same file name)")
    files = {}
    for p in list_images(mask_dir):  # image files only: a labelme .json beside its mask is not a mask
        if p.stem in files:
            raise StageError(f"{mask_dir}: {files[p.stem].name} and {p.name} are masks of one photo; keep one")
        files[p.stem] = p
    missing = [n for n in names if n not in files]
    if missing:
        raise StageError(f"{mask_dir}: no mask for {', '.join(missing[:5])}{'...' if len(missing) > 5 else ''}; "
                         "name each mask like its photo (any image extension)")
    return files


def read_user_masks(names: list[str], sizes: list[tuple[int, int]], mask_dir: Path, cfg: MasksConfig
                    ) -> dict[str, np.ndarray]:
    """Masks given by the user (``mask_dir``, matched by stem), every one checked to be binary and of the photo's
    aspect before any is kept: per name the mask resized to its image (``sizes``: (width, height) per name), bool."""
    files = mask_files(names, mask_dir)
    resized = {}
    for n, (w, h) in zip(names, sizes):
        m = cv2.imread(str(files[n]), cv2.IMREAD_GRAYSCALE)  # EXIF orientation applied, like the photos
        if m is None:
            raise StageError(f"{files[n]}: unreadable mask; save it as PNG (0 = background, 255 = object)")
        if m.max() == 1:  # numpy's and PIL's 0/1 masks: every pixel would be background
            raise StageError(f"{files[n]}: mask of 0 and 1; save the object as 255 (0 = background, 255 = object)")
        mid = ((m > 32) & (m < 223)).mean()
        if mid > 0.05:
            raise StageError(f"{files[n]}: {100 * mid:.0f} % of pixels are neither black nor white; save a binary mask")
        ar_m, ar_i = m.shape[1] / m.shape[0], w / h
        if abs(ar_m - ar_i) > 0.02 * ar_i:
            raise StageError(f"{files[n]}: mask is {m.shape[1]}x{m.shape[0]}, its photo's aspect is {w}x{h}; "
                             "make the mask the size of the photo")
        resized[n] = cv2.resize(m, (w, h), interpolation=cv2.INTER_AREA) > cfg.user_threshold
    return resized


# ----------------------------------------------------------------------------- automatic masks
def _tracks(ws: Workspace, names: list[str], max_error_ratio: float = 0.0):
    """Sparse points (SfM frame) and, per image, the ids of the points it observes (None without sfm/); with
    ``max_error_ratio`` > 0 only the observations that reproject within that multiple of the model's mean
    reprojection error (a wrong match lets a view "observe" a backdrop point that lies behind the object)."""
    model = ws.sfm_model
    if not model.exists():
        return None, None
    rec = read_stage_model(model)
    ids = list(rec.points3D.keys())
    index = {pid: k for k, pid in enumerate(ids)}
    xyz = np.array([rec.points3D[p].xyz for p in ids]).reshape(-1, 3)
    limit = max_error_ratio * rec.compute_mean_reprojection_error() if max_error_ratio > 0 else np.inf
    obs: dict[str, list[int]] = {n: [] for n in names}
    for iid in rec.reg_image_ids():
        im = rec.image(iid)
        stem = im.name.rsplit(".", 1)[0]
        if stem not in obs:
            continue
        seen = [p for p in im.points2D if p.has_point3D()]
        k = np.array([index[p.point3D_id] for p in seen], int)
        if len(k) and np.isfinite(limit):  # the undistorted model is a pinhole: K [R | t]
            P = rec.camera(im.camera_id).calibration_matrix() @ np.asarray(im.cam_from_world().matrix())
            uv, z = project_points(P, xyz[k])
            err = np.linalg.norm(uv - np.array([p.xy for p in seen]), axis=1)
            k = k[(z > 1e-12) & (err <= limit)]
        obs[stem] = k.tolist()
    return xyz, obs


def object_region(cams: Cameras, i: int, h: int, w: int, footprint=None, sphere: np.ndarray | None = None
                  ) -> np.ndarray:
    """(h, w) bool: pixels whose ray passes through the unit sphere ABOVE the support plane (all of the sphere
    without one; :func:`sphere_region`, or ``sphere`` when already computed) and, given the object's ``footprint``
    prism (:func:`pipeline.scene.support.footprint_prism`), through that. The object lies there by construction:
    every other pixel is background."""
    region = sphere_region(cams, i, h, w) if sphere is None else sphere
    if footprint is None:
        return region
    return region & MeshCaster(footprint).covered_pixels(cams.K[i], cams.R[i], cams.centers[i], w, h)


def sphere_region(cams: Cameras, i: int, h: int, w: int) -> np.ndarray:
    """(h, w) bool: pixels of view ``i`` whose ray passes through the unit sphere above the support plane (all of the
    sphere without one)."""
    o, d = pixel_center_rays(cams.K[i], cams.R[i], cams.centers[i], w, h)
    near, far, hit = (x.numpy() for x in sphere_bounds(torch.from_numpy(o.copy()), torch.from_numpy(d)))
    if cams.ground is not None:
        h0 = plane_height(cams.ground, o)  # camera height (the same for every ray)
        rate = d @ cams.ground[:3]  # height change per unit depth
        with np.errstate(divide="ignore", invalid="ignore"):
            t_cross = np.where(np.abs(rate) > 1e-12, -h0 / rate, np.inf)
        above_from = np.where((h0 < 0) & (rate > 0), t_cross, -np.inf)  # a camera below rises above at t_cross
        above_to = np.where((h0 >= 0) & (rate < 0), t_cross, np.inf)  # a camera above sinks below at t_cross
        near, far = np.maximum(near, above_from), np.minimum(far, above_to)
        hit &= (h0 >= 0) | (rate > 0)
    return (hit & (far > near)).reshape(h, w)


def support_in_sphere(cams: Cameras, i: int, h: int, w: int) -> np.ndarray:
    """(h, w) bool: pixels whose ray meets the support plane inside the unit sphere (the floor around and under the
    object; none without a plane). There the plane-sweep cannot tell the floor from the object's lowest
    ``GROUND_BAND`` (both lie within a fraction of a pixel's parallax of the plane), so its background evidence is
    only probable: GrabCut's colours decide (hard labels there cut the strip where the object meets the floor)."""
    if cams.ground is None:
        return np.zeros((h, w), bool)
    o, d = pixel_center_rays(cams.K[i], cams.R[i], cams.centers[i], w, h)
    rate = d @ cams.ground[:3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(rate < -1e-12, -plane_height(cams.ground, o) / rate, np.inf)
    x = o + np.where(np.isfinite(t), t, 0.0)[:, None] * d
    return (np.isfinite(t) & (t > 0) & (np.linalg.norm(x, axis=1) < 1.0)).reshape(h, w)


def remove_specks(mask: np.ndarray, fraction: float) -> np.ndarray:
    """Fill holes and drop islands smaller than ``fraction`` of the image (seed noise: a pin-hole in a mask carves a
    tunnel into the object, a speck grows a floater); larger holes (a handle, a torus) stay."""
    limit = fraction * mask.size
    out = mask.copy()
    for value in (False, True):  # holes (background components), then islands (object components)
        n, lab, stats, _ = cv2.connectedComponentsWithStats((out == value).astype(np.uint8), connectivity=4)
        small = np.nonzero(stats[1:, cv2.CC_STAT_AREA] < limit)[0] + 1
        if value is False:  # a background component touching the border is the outside, never a hole
            border = np.unique(np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]]))
            small = np.setdiff1d(small, border)
        out[np.isin(lab, small)] = not value
    return out


def uncertain_box(init: np.ndarray, margin: float, within: np.ndarray | None = None) -> tuple[slice, slice] | None:
    """The bounding box of the pixels of a GrabCut label image not fixed as background (``GC_BGD``; only those
    ``within`` a bool array, when given), widened by ``margin`` × the image's larger side and clipped to it; None
    when there are none."""
    ys, xs = np.nonzero((init != cv2.GC_BGD) if within is None else (init != cv2.GC_BGD) & within)
    if len(ys) == 0:
        return None
    pad = int(round(margin * max(init.shape)))
    return slice(max(0, ys.min() - pad), ys.max() + 1 + pad), slice(max(0, xs.min() - pad), xs.max() + 1 + pad)


def grabcut(img: np.ndarray, init: np.ndarray, iters: int, margin: float | None = None,
            box: tuple[slice, slice] | None = None) -> np.ndarray:
    """GrabCut from a label image (cv2.GC_*); returns a bool mask. Degenerate seeds fall back to the init. With
    ``margin`` ≥ 0 it runs on the bounding box of the pixels not fixed as background (``GC_BGD``, which stay
    background whatever GrabCut does), widened by that fraction of the image's larger side (1: the whole image): the
    same labels on fewer pixels, whose background colours are those near the object. ``box``: run on that box
    instead (outside it: background)."""
    has_fg = np.isin(init, (cv2.GC_FGD, cv2.GC_PR_FGD)).any()
    has_bg = np.isin(init, (cv2.GC_BGD, cv2.GC_PR_BGD)).any()
    if not (has_fg and has_bg):
        return np.isin(init, (cv2.GC_FGD, cv2.GC_PR_FGD))
    if box is None:
        box = (slice(None), slice(None)) if margin is None else uncertain_box(init, margin)
    m = init[box].copy()
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    cv2.setRNGSeed(0)  # GrabCut's k-means draws from this thread's RNG: same mask whatever thread runs it
    try:
        cv2.grabCut(np.ascontiguousarray(img[box]), m, None, bgd, fgd, iters, cv2.GC_INIT_WITH_MASK)
    except cv2.error:
        return np.isin(init, (cv2.GC_FGD, cv2.GC_PR_FGD))
    out = np.zeros(init.shape, bool)
    out[box] = np.isin(m, (cv2.GC_FGD, cv2.GC_PR_FGD))
    return out


def grabcut_all(imgs: list[np.ndarray], labels: list[np.ndarray], iters: int, margin: float | None = None,
                boxes: list[tuple[slice, slice]] | None = None) -> list[np.ndarray]:
    """:func:`grabcut` of every image (in ``boxes``, one per image, when given), on all CPU cores (OpenCV releases
    the GIL; results keep their order)."""
    boxes = boxes if boxes is not None else [None] * len(imgs)
    with ThreadPoolExecutor(max_workers=max(1, os.cpu_count() or 1)) as pool:
        return list(pool.map(lambda a: grabcut(a[0], a[1], iters, margin, a[2]), zip(imgs, labels, boxes)))


def seed_labels(cams: Cameras, i: int, h: int, w: int, pts_n: np.ndarray | None, vis: list[int] | None,
                r: int, footprint=None, sphere: np.ndarray | None = None) -> np.ndarray:
    """GrabCut labels of view ``i`` from geometry: outside the object region (:func:`object_region`) background;
    the sparse points it observes drawn as discs — object inside the sphere (radius < 0.9) and above the support,
    background beyond ``BACKGROUND_RADIUS`` or on (or below) the support plane."""
    lab = np.full((h, w), cv2.GC_PR_BGD, np.uint8)
    region = object_region(cams, i, h, w, footprint, sphere)
    lab[region] = cv2.GC_PR_FGD
    lab[~region] = cv2.GC_BGD
    if pts_n is not None and vis is not None and len(vis):
        p = pts_n[vis]
        uv, z = project_points(cams.P[i], p)
        ok = z > 1e-9
        uv = np.round(uv[ok] - 0.5).astype(int)
        rad = np.linalg.norm(p[ok], axis=1)
        on_support = plane_height(cams.ground, p[ok]) < GROUND_BAND if cams.ground is not None else \
            np.zeros(len(rad), bool)
        for (u, v), rr, flat in zip(uv, rad, on_support):
            if 0 <= u < w and 0 <= v < h:
                if flat or rr > BACKGROUND_RADIUS:
                    cv2.circle(lab, (int(u), int(v)), r, cv2.GC_BGD, -1)
                elif rr < 0.9:
                    cv2.circle(lab, (int(u), int(v)), r, cv2.GC_FGD, -1)
    return lab


def soften_beyond(lab: np.ndarray, cams: Cameras, i: int, footprint, sphere: np.ndarray | None = None) -> np.ndarray:
    """View ``i``'s GrabCut labels ``lab`` (h, w), in place: the pixels that were probably object but whose ray
    misses the points' ``footprint`` prism become probably background (``footprint_union``: GrabCut's colours decide
    there, so a plain part that overhangs the points, a cow's white ear, can stay object, and the table in front of
    the object starts on the background's side). Hard labels stay."""
    h, w = lab.shape
    lab[(lab == cv2.GC_PR_FGD) & ~object_region(cams, i, h, w, footprint, sphere)] = cv2.GC_PR_BGD
    return lab


def kept_points(pts_n: np.ndarray | None, obs: dict | None, cams: Cameras, min_views: int) -> np.ndarray | None:
    """(M, 3) the sparse points (normalized frame) no visual hull of the masks may carve: inside the object's sphere
    (radius < 0.9), above the support plane's ``GROUND_BAND``, observed by at least ``min_views`` views (``obs``,
    :func:`_tracks`). A point triangulated from several views lies on the object's surface: masks that miss it are
    wrong there (a white table under a cream rim), and a hull that carved it would cut it from every view. None
    without points or with ``min_views`` < 1."""
    if pts_n is None or obs is None or min_views < 1:
        return None
    views = np.bincount(np.concatenate([np.asarray(v, int) for v in obs.values()] + [np.zeros(0, int)]),
                        minlength=len(pts_n))
    keep = (views >= min_views) & (np.linalg.norm(pts_n, axis=1) < 0.9)
    if cams.ground is not None:
        keep &= plane_height(cams.ground, pts_n) > GROUND_BAND
    return pts_n[keep] if keep.any() else None


@torch.no_grad()
def visual_hull(masks: list[np.ndarray], cams: Cameras, res: int, min_views: int,
                min_fraction: float = 0.0, keep: np.ndarray | None = None, settle: float = 0.0,
                fraction_px: float = 0.0) -> torch.Tensor:
    """The visual hull of ``masks`` (one bool array per view, each its own size; carving with ``min_views`` and
    ``min_fraction``, the fraction only within ``fraction_px`` of a mask when > 0; nothing below the support plane) as
    a (res+1)³ float32 volume, 1 inside and -1 outside (:func:`dvr.hull.hull_lattice`); the cells holding the points
    ``keep`` (:func:`kept_points`) stay inside, and its parts lower than ``settle`` above the support plane rest on it
    (:func:`dvr.hull.settled_onto_plane`). Its zero level is that of :func:`dvr.hull.hull_logits`, whose lattice
    points on either side of the surface hold ±1 too, without the distance transforms."""
    canvas, sizes = (torch.from_numpy(a) for a in pad_stack([m.astype(np.float32) for m in masks]))
    near = near_object(canvas, fraction_px) if fraction_px > 0 and min_fraction > 0 else None
    inside = hull_lattice(torch.from_numpy(cams.P).float(), canvas, res=res, keep=keep, settle=settle,
                          min_views=min_views, min_fraction=min_fraction, ground=cams.ground, sizes=sizes,
                          fraction_near=near)
    return torch.from_numpy(np.where(inside, 1.0, -1.0).astype(np.float32))


def carved_hull(masks: list[np.ndarray], cams: Cameras, cfg: MasksConfig, keep: np.ndarray | None = None
                ) -> torch.Tensor:
    """:func:`visual_hull` of ``masks`` by the stage's carving rule (``carve_min_views``; ``carve_fraction`` within
    ``carve_fraction_px`` of a mask), holding the points ``keep``, resting on the support below ``settle_height``."""
    return visual_hull(masks, cams, cfg.hull_res, cfg.carve_min_views, cfg.carve_fraction, keep, cfg.settle_height,
                       cfg.carve_fraction_px)


@torch.no_grad()
def hull_silhouettes(masks: list[np.ndarray], cams: Cameras, volume: torch.Tensor) -> list[np.ndarray]:
    """Render a visual hull (its ``volume``, :func:`visual_hull`) into every view, each at its mask's size in
    ``masks``: one bool array per view.

    The volume's zero level becomes a mesh (marching cubes) and the ray of every pixel centre in the box of its
    projection is cast against it (:meth:`pipeline.render.raycast.MeshCaster.covered_pixels`), far faster than
    marching the volume along every ray.
    """
    import trimesh
    from skimage import measure

    vol = volume.cpu().numpy()
    if vol.max() <= 0 or vol.min() > 0:
        return [np.full(m.shape, vol.min() > 0) for m in masks]
    v, f, _, _ = measure.marching_cubes(vol, 0.0, spacing=(2.0 / (vol.shape[0] - 1),) * 3)
    hull = trimesh.Trimesh(v - 1.0, f, process=False)
    caster = MeshCaster(hull)
    return [caster.covered_pixels(cams.K[i], cams.R[i], cams.centers[i], W, H)
            for i, (H, W) in enumerate(m.shape for m in masks)]


def hull_footprint(masks: list[np.ndarray], cams: Cameras, cfg: MasksConfig, volume: torch.Tensor | None = None):
    """:func:`pipeline.scene.support.footprint_prism` of the visual hull of ``masks`` (carving with ``carve_min_views``;
    its :func:`visual_hull` ``volume`` when already built):
    the hull's grid cells more than ``footprint_hull_height`` above the support plane stand for the object's
    points, where at least :data:`FOOTPRINT_IN_FRAME` of the views have them in frame (elsewhere, near the
    sphere's edge, few views carve). A ring of table that every mask took lies flat on the plane, and the low
    views carve the space above it. The hull bounds the object already, so the prism is one hull cell wider than
    those cells and ends one cell above the hull's top (sparse points give no top): the floor behind the object,
    seen over it, is background too. None when no cell stands that high."""
    canvas, sizes = (torch.from_numpy(a) for a in pad_stack([m.astype(np.float32) for m in masks]))
    P = torch.from_numpy(cams.P)
    vol = visual_hull(masks, cams, cfg.hull_res, cfg.carve_min_views, cfg.carve_fraction,
                      fraction_px=cfg.carve_fraction_px) if volume is None else volume
    cells = grid_points(cfg.hull_res, dtype=torch.float64)[vol.reshape(-1).cpu() > 0]
    _, seen = mask_lookup(cells, P, canvas, sizes)  # in front of the camera and inside its own image
    # the hull is only carved where the views see
    cells = cells[seen.sum(0) >= FOOTPRINT_IN_FRAME * len(cams)].numpy()
    height = plane_height(cams.ground, cells)
    tall = height > cfg.footprint_hull_height
    if not tall.any():
        return None
    cell = 2.0 / cfg.hull_res  # the hull bounds the object already: a cell of margin, not the points' margin
    return footprint_prism(cells[tall], cams.ground, cell, 1, top=float(height.max()) + cell)


def united_footprint(points_prism, hull_prism):
    """The convex hull of two footprint prisms (:func:`pipeline.scene.support.footprint_prism`, either None): the space
    the object can fill by its sparse points or by the first masks' hull."""
    import trimesh

    prisms = [p for p in (points_prism, hull_prism) if p is not None]
    if len(prisms) < 2:
        return prisms[0] if prisms else None
    return trimesh.convex.convex_hull(np.concatenate([p.vertices for p in prisms]))


def background_depths(cams: Cameras, pts_n: np.ndarray | None, obs: dict | None, names: list[str]) -> np.ndarray:
    """Per view, the ray depth the stereo sweep reaches: 1.1 × the 95th percentile of the distances to the
    background points (beyond ``BACKGROUND_RADIUS``) the view observes; 3 × the distance to the sphere centre
    without."""
    far = 3.0 * np.linalg.norm(cams.centers, axis=1)
    if pts_n is None or obs is None:
        return far
    for i, n in enumerate(names):
        p = pts_n[obs.get(n, [])]
        bg = p[np.linalg.norm(p, axis=1) > BACKGROUND_RADIUS]
        if len(bg) >= 10:
            far[i] = 1.1 * np.percentile(np.linalg.norm(bg - cams.centers[i], axis=1), 95)
    return far


@dataclass
class Geometry:
    """What the automatic masks take from the cameras stage (:func:`geometry`), the same for every pass of a stage
    run: the cameras, the sparse points (normalized frame) and each photo's observations of them (:func:`_tracks`),
    the points no hull carves (:func:`kept_points`), each photo's stereo labels (None when off) and its pixels whose
    ray crosses the object's sphere (:func:`sphere_region`)."""

    cams: Cameras
    pts_n: np.ndarray | None
    obs: dict | None
    keep: np.ndarray | None
    stereo: list[np.ndarray] | None
    spheres: list[np.ndarray]


def geometry(ws: Workspace, names: list[str], imgs: list[np.ndarray], cfg: MasksConfig) -> Geometry:
    """The :class:`Geometry` of the BGR images ``imgs`` (the stereo's plane sweep is most of its time)."""
    cams = load_cameras(ws.cameras, n_views=len(names))
    xyz, obs = _tracks(ws, names, cfg.seed_max_error)
    pts_n = None
    if xyz is not None and len(xyz):
        pts_n = to_normalized(xyz, cams.scale_mat, uniform=True)
    stereo = None
    if cfg.stereo and len(names) >= 3:
        stereo = stereo_seed_labels(evened_out(ws, names, imgs) if cfg.even_exposure else imgs, cams,
                                    background_depths(cams, pts_n, obs, names), cfg.stereo_scale, cfg.stereo_depths,
                                    cfg.stereo_ratio)
    spheres = [sphere_region(cams, i, img.shape[0], img.shape[1]) for i, img in enumerate(imgs)]
    return Geometry(cams, pts_n, obs, kept_points(pts_n, obs, cams, cfg.keep_min_views), stereo, spheres)


def auto_masks(ws: Workspace, names: list[str], imgs: list[np.ndarray], cfg: MasksConfig,
               sal: list[np.ndarray] | None = None, geo: Geometry | None = None
               ) -> tuple[dict, str | bool | None, list[float]]:
    """Automatic masks of the BGR images ``imgs`` (module docstring: geometric and stereo seeds, GrabCut, multi-view
    votes) into masks/, from their :func:`geometry` (``geo`` when already computed); per name the confidence (IoU of
    the first GrabCut mask with the hull's silhouette), where
    the object's footprint that seeded the floor came from: "sparse points", "masks' hull", False (none could be
    built), None (no support plane, or the footprint off), and the fraction of the object's pixels each floor round
    changed (:func:`vote`; none without a support plane)."""
    geo = geo or geometry(ws, names, imgs, cfg)
    cams, pts_n, obs, keep, stereo, spheres = geo.cams, geo.pts_n, geo.obs, geo.keep, geo.stereo, geo.spheres
    footprint, used = None, None
    if cams.ground is not None and cfg.footprint_margin >= 0:
        if pts_n is not None:
            footprint = footprint_prism(pts_n, cams.ground, cfg.footprint_margin, cfg.footprint_min_points)
            if footprint is not None:
                print("masks: the support plane beyond the object's footprint is background")
            else:
                print(f"masks: fewer than {cfg.footprint_min_points} sparse points on the object: "
                      + ("the footprint comes from the first masks' hull" if cfg.footprint_hull_height > 0
                         else "no footprint"))
        used = footprint is not None and "sparse points"
    unite = bool(used) and cfg.footprint_union and cfg.footprint_hull_height > 0
    seeds = []
    for i, (n, img) in enumerate(zip(names, imgs)):
        h, w = img.shape[:2]
        lab = seed_labels(cams, i, h, w, pts_n, obs.get(n) if obs else None, cfg.seed_radius,
                          None if unite else footprint, spheres[i])
        if unite:
            soften_beyond(lab, cams, i, footprint, spheres[i])
        if stereo is not None:
            inside = lab != cv2.GC_BGD  # the projected sphere
            lab[inside & (stereo[i] == OBJECT)] = cv2.GC_FGD
            bg = inside & (stereo[i] == BACKGROUND)
            lab[bg] = cv2.GC_BGD
            lab[bg & support_in_sphere(cams, i, h, w)] = cv2.GC_PR_BGD
        seeds.append(lab)
    # saliency moves only the first pass' probable labels: the seeds the vote rounds keep are the geometry's
    starts = seeds if sal is None else [first_labels(lab.copy(), s) for lab, s in zip(seeds, sal)]
    first = [remove_specks(m, cfg.speck_fraction)
             for m in grabcut_all(imgs, starts, cfg.grabcut_iters, cfg.grabcut_margin)]
    first_hull = None  # built once when the footprint and the first vote both need it
    # the footprint of the first masks' hull: alone (too few points), or united with the points' prism
    if (used is False or unite) and cfg.footprint_hull_height > 0:
        first_hull = carved_hull(with_salient(first, salient_views(sal, seeds)), cams, cfg, keep)
        from_hull = hull_footprint(first, cams, cfg, first_hull)
        if unite:
            footprint, used = united_footprint(footprint, from_hull), "sparse points and masks' hull"
            print("masks: the support plane beyond the footprint of the points and the first masks' hull is "
                  "background")
        else:
            footprint, used = from_hull, from_hull is not None and "masks' hull"
            print("masks: " + ("the support plane beyond that footprint is background" if used
                               else "the first masks' hull stands nowhere above the plane: no footprint"))
        for i, img in enumerate(imgs if footprint is not None else []):  # hard background seeds for the vote rounds
            seeds[i][~object_region(cams, i, img.shape[0], img.shape[1], footprint, spheres[i])] = cv2.GC_BGD
    current, sil, _ = vote(imgs, seeds, first, cams, cfg, max(1, cfg.vote_rounds), first_hull=first_hull, sal=sal,
                           keep=keep)
    changed = []
    if cams.ground is not None and cfg.floor_rounds > 0:
        low = [low_band(cams, i, m.shape[0], m.shape[1], cfg.floor_band) for i, m in enumerate(current)]
        current, sil, changed = vote(imgs, seeds, current, cams, cfg, cfg.floor_rounds, cfg.floor_settle, low,
                                     sal=sal, keep=keep)
        print(f"masks: {len(changed)} floor rounds under the object; each changed "
              + ", ".join(f"{c:.2%}" for c in changed) + " of the object's pixels")
    conf = {}
    for i, n in enumerate(names):
        write_image(ws.masks / f"{n}.png", current[i].astype(np.uint8) * 255)
        inter = (first[i] & sil[i]).sum()
        union = (first[i] | sil[i]).sum()
        conf[n] = float(inter / union) if union else 0.0
    return conf, used, changed


def evened_out(ws: Workspace, names: list[str], imgs: list[np.ndarray]) -> list[np.ndarray]:
    """The photos as one exposure would have taken them, by the gains the cameras stage measured
    (``exposure.json``, :mod:`pipeline.scene.exposure`): the stereo compares colours across views, and an auto-exposed
    capture's differ by 10–30 % (the cow photographed at ±25 %: mask IoU 0.997 evened out, 0.976 as taken). As
    they are without it."""
    if not ws.exposure.exists():
        return imgs
    gains = read_exposure(ws.exposure, names).gains
    return [even_out(img, g) for img, g in zip(imgs, gains)]


def salient_views(sal: list[np.ndarray] | None, seeds: list[np.ndarray]) -> list[np.ndarray] | None:
    """Each view's salient pixels (:func:`pipeline.masks.saliency.salient_pixels` of its saliency map in ``sal`` and
    its ``seeds``); None without ``sal``."""
    return None if sal is None else [salient_pixels(s, seed) for s, seed in zip(sal, seeds)]


def with_salient(masks: list[np.ndarray], salient: list[np.ndarray] | None,
                 within: list[np.ndarray] | None = None) -> list[np.ndarray]:
    """Each view's mask joined by its ``salient`` pixels (:func:`salient_views`), only those ``within`` (one bool
    array per view) when given; the masks as they are without ``salient``. As the hull's voters, a point is carved
    only where views see it outside both their mask and their saliency: a thin part that most views' saliency sees
    stays though two or three views' GrabCut lost it (a shiny nozzle over a carpet that mirrors in it)."""
    if salient is None:
        return masks
    if within is None:
        return [m | s for m, s in zip(masks, salient)]
    return [m | (s & w) for m, s, w in zip(masks, salient, within)]


def vote_labels(seed: np.ndarray, sil: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """GrabCut labels of one view in a vote round: outside the hull's silhouette ``sil`` (widened by ``kernel``)
    background — an object seed there is outvoted by the views that carved that space; in the widened band
    probably background, inside probably object, and there the ``seed`` labels stay hard (GrabCut decides the
    rest, e.g. a hole the hull could not carve yet)."""
    s = sil.astype(np.uint8)
    near = cv2.dilate(s, kernel) > 0
    lab = np.full(s.shape, cv2.GC_BGD, np.uint8)
    lab[near] = cv2.GC_PR_BGD
    lab[s > 0] = cv2.GC_PR_FGD
    hard = ((seed == cv2.GC_FGD) & (s > 0)) | ((seed == cv2.GC_BGD) & near)
    lab[hard] = seed[hard]
    return lab


def vote(imgs: list[np.ndarray], seeds: list[np.ndarray], start: list[np.ndarray], cams: Cameras, cfg: MasksConfig,
         rounds: int, settle: float = 0.0, region: list[np.ndarray] | None = None,
         first_hull: torch.Tensor | None = None, sal: list[np.ndarray] | None = None, keep: np.ndarray | None = None
         ) -> tuple[list[np.ndarray], list[np.ndarray], list[float]]:
    """Multi-view vote rounds from the masks ``start``: the hull of the current masks (carving needs
    ``carve_min_views``; ``first_hull``: that of ``start`` when already built; the points ``keep`` never carved,
    :func:`kept_points`) is an upper bound in every view
    (:func:`vote_labels`) and GrabCut refines inside it, ``rounds`` times or until a round changes fewer than
    ``settle`` of the object's pixels; with ``region`` (a bool array per view) only those pixels change, and a round
    that changes more than the one before is undone and ends them (it eats into the object). With ``sal`` (each
    view's saliency map) a view's salient pixels vote in the hull and, inside its silhouette, join its mask
    (:func:`with_salient`). Returns (masks, the last round's hull silhouettes, the fraction each round changed)."""
    kernel = np.ones((2 * cfg.band_px + 1,) * 2, np.uint8)
    salient = salient_views(sal, seeds)  # the seeds do not change in the rounds
    current, sil, changed = start, [], []
    for rnd in range(rounds):
        hull = first_hull if rnd == 0 and first_hull is not None else carved_hull(with_salient(current, salient),
                                                                                  cams, cfg, keep)
        sil = hull_silhouettes(current, cams, hull)
        labs = [vote_labels(seeds[i], sil[i], kernel) for i in range(len(imgs))]
        if sal is not None:  # a probable start inside the hull's bound, never past it
            labs = [vote_prior(lab, s) for lab, s in zip(labs, sal)]
        if region is None:
            new = with_salient(grabcut_all(imgs, labs, cfg.round_iters, cfg.grabcut_margin), salient, sil)
        else:  # GrabCut on the box of the region's undecided pixels, the rest of that box fixed as it is
            labs = [np.where(r, lab, np.where(c, cv2.GC_FGD, cv2.GC_BGD)).astype(np.uint8)
                    for r, lab, c in zip(region, labs, current)]
            boxes = [uncertain_box(lab, cfg.grabcut_margin, r) for lab, r in zip(labs, region)]
            todo = [i for i, b in enumerate(boxes) if b is not None]
            cut = grabcut_all([imgs[i] for i in todo], [labs[i] for i in todo], cfg.round_iters,
                              boxes=[boxes[i] for i in todo])
            if salient is not None:
                cut = with_salient(cut, [salient[i] for i in todo], [sil[i] for i in todo])
            new = list(current)
            for i, m in zip(todo, cut):
                new[i] = np.where(region[i], m, current[i])
        new = [remove_specks(m, cfg.speck_fraction) for m in new]
        flips = sum(int((a != b).sum()) for a, b in zip(new, current))
        changed.append(flips / max(1, sum(int(m.sum()) for m in new)))
        if region is not None and len(changed) > 1 and changed[-1] > changed[-2]:
            break  # growing, not settling: the rounds eat into the object (one lying low on its floor); kept before
        current = new
        if changed[-1] < settle:
            break
    return current, sil, changed


def low_band(cams: Cameras, i: int, h: int, w: int, band: float) -> np.ndarray:
    """(h, w) bool: pixels of view ``i`` whose ray, where it passes closest to the vertical axis of the unit sphere
    (through its centre, along the support plane's normal), lies less than ``band`` above the plane: the floor
    between an object's legs and under it, and the object's lowest part; none without a support plane."""
    if cams.ground is None:
        return np.zeros((h, w), bool)
    n = np.asarray(cams.ground[:3], float)
    o, d = pixel_center_rays(cams.K[i], cams.R[i], cams.centers[i], w, h)
    w0 = o - (-float(cams.ground[3]) * n)  # from the axis' foot on the plane
    b = d @ n
    denom = 1.0 - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(denom > 1e-9, (b * (w0 @ n) - (w0 * d).sum(1)) / denom, np.nan)
    height = plane_height(cams.ground, o + np.nan_to_num(t)[:, None] * d)
    return ((t > 0) & (height < band)).reshape(h, w)


def support_outline(cams: Cameras, i: int, n: int = 180) -> np.ndarray | None:
    """Pixel polyline (k, 2) of the circle where the support plane cuts the unit sphere, as view ``i`` sees it
    (the part in front of the camera); None without a support plane or when the plane misses the sphere."""
    if cams.ground is None or abs(cams.ground[3]) >= 1.0:
        return None
    nrm, d = cams.ground[:3], cams.ground[3]
    e1, e2 = plane_basis(nrm)
    th = np.linspace(0, 2 * np.pi, n)
    pts = -d * nrm + np.sqrt(1 - d * d) * (np.cos(th)[:, None] * e1 + np.sin(th)[:, None] * e2)
    uv, z = project_points(cams.P[i], pts)
    ok = z > 1e-6
    return uv[ok] - 0.5 if ok.sum() > 1 else None


def write_overlays(ws: Workspace, names: list[str], imgs: list[np.ndarray], cams: Cameras | None = None) -> None:
    """Photo with the background darkened, the mask's outline (green) and, when the object stands on a support
    plane, where that plane cuts the object's sphere (orange)."""
    out = ws.masks / "overlays"
    out.mkdir(exist_ok=True)
    for i, (n, img) in enumerate(zip(names, imgs)):
        m = read_mask(ws.masks / f"{n}.png") > 0
        ov = img.copy()
        ov[~m] = (ov[~m] * 0.3).astype(np.uint8)
        cnt, _ = cv2.findContours(m.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(ov, cnt, -1, (0, 255, 0), 1)
        line = support_outline(cams, i) if cams is not None else None
        if line is not None:
            cv2.polylines(ov, [np.round(line * 16).astype(np.int32)], False, (0, 165, 255), 1, cv2.LINE_AA, shift=4)
        write_image(out / f"{n}.jpg", ov, [cv2.IMWRITE_JPEG_QUALITY, 90])


def lost_to_saliency(ws: Workspace, names: list[str], imgs: list[np.ndarray], cfg: MasksConfig, geo: Geometry
                     ) -> tuple[float, dict[int, np.ndarray]] | None:
    """How much of the object the geometry's masks (masks/) lose by the salient-object model: in the visual hull of
    :data:`~pipeline.masks.saliency.PROBES` photos' masks joined by their salient pixels, the part the views agree
    on, beyond the masks' outlines, as a share of their area (:func:`~pipeline.masks.saliency.beyond_share`) in three
    of four photos (a shiny nozzle over a carpet it mirrors). A printed board that some photos' saliency takes, or
    the floor between a stool's legs seen from one side, is carved by the photos that see it empty (the cameras and
    the sphere regions from the masks' :func:`geometry` ``geo``). Said on a line
    with what the stage does (more than ``cfg.saliency_check``: the masks again with the model's vote). Returns the
    share and the probe photos' saliency maps by index (the second pass reuses them); None without the model file
    (a warning)."""
    if not model_installed():
        print(f"masks: warning: {missing_model_message()}; the masks are not checked against it", file=sys.stderr)
        return None
    probes = probe_views(len(names))
    cams = geo.cams.subset(probes)
    masks = [read_mask(ws.masks / f"{names[i]}.png") > 0.5 for i in probes]
    sal = saliency_maps([imgs[i] for i in probes])
    salient = [(s >= SALIENT) & geo.spheres[i] for i, s in zip(probes, sal)]
    sil = hull_silhouettes(masks, cams, carved_hull(with_salient(masks, salient), cams, cfg))
    share = float(np.percentile([beyond_share(s, m, w) for s, m, w in zip(sal, masks, sil)], 25))
    print(f"masks: the salient-object model sees {share:.1%} of the masks' area beyond them in three of four of "
          f"{len(probes)} photos (masks.saliency-check {cfg.saliency_check:.0%})"
          + (": the masks again with its vote (masks.saliency)" if share > cfg.saliency_check else ""))
    return share, dict(zip(probes, sal))


def run(job: Job) -> Done:
    """Stage ``masks`` (called by :func:`pipeline.stages.run_stage`): the user's masks (``job.sources.masks_dir``)
    checked and resized, or automatic ones → masks/*.png, masks/overlays/, masks/confidence.json."""
    ws, cfg, masks = job.ws, job.cfg, job.sources.masks_dir
    paths = list_images(ws.images)
    names = [p.stem for p in paths]
    imgs = [cv2.imread(str(p), cv2.IMREAD_COLOR) for p in paths]
    # the user's masks are checked before the masks of before go: a wrong folder or one bad mask loses nothing
    user = None if masks is None else read_user_masks(names, [(im.shape[1], im.shape[0]) for im in imgs],
                                                      Path(masks), cfg)
    if ws.masks.exists():
        shutil.rmtree(ws.masks)
    ws.masks.mkdir(parents=True)
    footprint, sal, check = None, None, None
    if user is not None:
        for n, m in user.items():
            write_image(ws.masks / f"{n}.png", m.astype(np.uint8) * 255)
        conf, rounds = dict.fromkeys(user, 1.0), []
    else:
        sal = evidence(imgs) if cfg.saliency else None
        geo = geometry(ws, names, imgs, cfg)
        conf, footprint, rounds = auto_masks(ws, names, imgs, cfg, sal, geo)
        if sal is None and cfg.saliency_check > 0:
            check = lost_to_saliency(ws, names, imgs, cfg, geo)
        if check is not None and check[0] > cfg.saliency_check:
            sal = evidence(imgs, known=check[1])
            conf, footprint, rounds = auto_masks(ws, names, imgs, cfg, sal, geo)
    write_overlays(ws, names, imgs, load_cameras(ws.cameras, n_views=len(names)))
    write_json(ws.masks / "confidence.json", conf, indent=1)
    low = [n for n, c in conf.items() if c < 0.8]
    if low:
        print(f"masks: low confidence for {names_or_count(low, 'of the ' + str(len(names)) + ' photos')}; look at "
              f"{ws.masks / 'overlays'}", file=sys.stderr)
    print(f"masks: {len(names)} masks, mean confidence {np.mean(list(conf.values())):.3f} → {ws.masks}")
    return Done({"mean_confidence": float(np.mean(list(conf.values()))), "footprint": footprint,
                 "saliency": sal is not None, "salient_beyond": None if check is None else check[0],
                 "floor_rounds_changed": [round(c, 6) for c in rounds]})

