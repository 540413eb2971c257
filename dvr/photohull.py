"""Photo hull: carve from the visual hull the voxels that the views seeing them disagree on (space carving,
Kutulakos & Seitz 2000).

No silhouette removes a concavity (a cup's inside): the visual hull closes it with a lid at the rim, and DVR's
depth gradient moves a surface only locally along each ray, so training keeps the lid. On the lid the views
that see a point see different parts of the cup's inside, so their colours spread; on a true surface they
agree. Each sweep finds the hull's surface voxels, which views see them (a z-buffer of the surface voxels),
and carves those whose colours spread more than a threshold; the next sweep sees the layer below. The
threshold is relative to the first sweep's median spread (the noise, exposure and texture of this capture)
with an absolute floor, plus the photos' local contrast at the point (a lattice point stands for a surface up
to half a cell away: on texture that alone spreads its colours); a carve that would open a hole in any
silhouette is undone. Space no view sees stays (a cup's floor that no camera looks down onto).

All on a lattice at reduced image resolution (a lattice cell at most 2 pixels, so the z-buffer's 3×3 splats
close); the result is the initial occupancy of training (:class:`dvr.trainer.Trainer`, ``photo_hull``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from scipy import ndimage

from dvr.cameras import project
from dvr.hull import grid_points

NORMAL_SHIFTS = (-0.5, 0.5, 1.5, 2.5, 3.5)
"""Where else along the outward normal (in cells) a surface point's colours are read; its spread is the least.
Half a cell either way: the lattice point stands for a surface up to half a cell off. Up to 3.5 cells outward:
where a mask misses a bit of the object, the hull's surface lies inside the solid, its views read different
places of the true surface in front of it and disagree as over a cup's inside; read a few cells out they meet
that surface and agree, so the carving does not dig in."""


@dataclass
class PhotoCarveResult:
    """What :func:`photo_carve` did."""

    inside: np.ndarray
    """(R+1)³ bool lattice [x, y, z]: the photo hull."""
    carved: int
    """Lattice points carved (kept carved after the silhouette check)."""
    restored: int
    """Carves undone because they opened a silhouette."""
    shallow: int
    """Carved points put back because their carved region reached less than ``min_depth`` into the hull."""
    sweeps: int
    """Sweeps run."""
    threshold: float
    """Colour spread above which a surface point was carved."""
    pool: int
    """Image reduction factor the colours were read at."""


def _surface(inside: np.ndarray) -> np.ndarray:
    """Occupied lattice points with a free 6-neighbour (the lattice's border counts as free)."""
    return inside & ~ndimage.binary_erosion(inside, border_value=0)


def _outward_normals(inside: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """(M, 3) unit outward normals at lattice points ``idx`` (M, 3): the gradient of the smoothed occupancy."""
    smooth = ndimage.gaussian_filter(inside.astype(np.float32), 1.0)
    g = np.stack([np.gradient(smooth, axis=a)[tuple(idx.T)] for a in range(3)], 1)
    return -g / np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-8)


def _splats(uv: torch.Tensor, H: int, W: int):
    """For each of the 3×3 pixels around each projection uv (V, M, 2), centre fifth, row by row: its flat pixel
    index (V, M) and whether it lies inside the image (V, M). One offset at a time: nine (V, M, 2) offsets at once
    were most of the photo hull's time and memory."""
    base = torch.floor(uv).long()
    bx, by = base[..., 0], base[..., 1]
    for dy in (-1, 0, 1):
        y = by + dy
        row, ok_y = y.clamp(0, H - 1) * W, (y >= 0) & (y < H)
        for dx in (-1, 0, 1):
            x = bx + dx
            yield row + x.clamp(0, W - 1), ok_y & (x >= 0) & (x < W)


def _coverage(uv: torch.Tensor, z: torch.Tensor, H: int, W: int) -> torch.Tensor:
    """(V, H·W) bool: the pixels the points' 3×3 splats cover (points in front of the camera)."""
    front = z > 0
    cov = torch.zeros(uv.shape[0], H * W, dtype=torch.bool, device=uv.device)
    for idx, ok in _splats(uv, H, W):
        ok &= front
        cov.scatter_reduce_(1, idx, ok, reduce="amax")
    return cov


def _visible(uv: torch.Tensor, z: torch.Tensor, H: int, W: int, tol: torch.Tensor) -> torch.Tensor:
    """(V, M) bool: the point is within ``tol`` (V, 1) of the nearest of all the points' 3×3 splats at its
    pixel (a z-buffer of the surface points)."""
    front, far = z > 0, torch.full_like(z, float("inf"))
    zbuf = torch.full((uv.shape[0], H * W), float("inf"), device=uv.device)
    for k, (idx, ok) in enumerate(_splats(uv, H, W)):
        ok &= front
        zbuf.scatter_reduce_(1, idx, torch.where(ok, z, far), reduce="amin")
        if k == 4:
            centre, inside = idx, ok
    return inside & (z <= zbuf.gather(1, centre) + tol)


def _bilinear(img: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Sample (V, C, H, W) at pixel coordinates uv (V, M, 2) (centres at +0.5): (V, M, C)."""
    H, W = img.shape[-2:]
    g = torch.stack([uv[..., 0] / W * 2 - 1, uv[..., 1] / H * 2 - 1], -1).clamp(-2, 2)
    return F.grid_sample(img, g[:, :, None], align_corners=False, padding_mode="border")[..., 0].transpose(1, 2)


def _spread(colours: torch.Tensor, seen: torch.Tensor) -> torch.Tensor:
    """(M,) colour spread across the views that see each point: the mean absolute deviation from their median
    colour, averaged over the channels, the most deviant view left out when ≥ 4 see the point (a highlight or
    an occluder one view alone sees); NaN with no view."""
    c = torch.where(seen[..., None], colours, torch.full_like(colours, float("nan")))
    med = c.nanmedian(dim=0).values
    dev = (c - med).abs().mean(-1)  # (V, M), NaN where unseen
    n = seen.sum(0)
    total = torch.nan_to_num(dev, nan=0.0).sum(0)
    worst = torch.nan_to_num(dev, nan=0.0).max(0).values
    drop = n >= 4
    total = torch.where(drop, total - worst, total)
    count = torch.where(drop, n - 1, n).clamp(min=1)
    return torch.where(n > 0, total / count, torch.full_like(total, float("nan")))


def photo_carve(inside: np.ndarray, P: torch.Tensor, images: torch.Tensor, masks: torch.Tensor,
                sizes: torch.Tensor | None = None, min_views: int = 2, spread_floor: float = 0.01,
                spread_ratio: float = 6.0, max_sweeps: int = 96, min_cos: float = 0.2,
                pixels_per_cell: float = 2.0, contrast_weight: float = 1.0,
                min_depth: float = 0.1) -> PhotoCarveResult:
    """The photo hull of the (R+1)³ lattice ``inside`` [x, y, z] over [-1, 1]³ (the visual hull) from views
    with projections ``P`` (V, 3, 4), ``images`` (V, H, W, 3) in [0, 1] and ``masks`` (V, H, W).

    A surface point is carved when ≥ ``min_views`` views see it, unoccluded and at least ``min_cos`` head-on,
    inside their masks and photos, and their colours (each view's exposure and white balance divided out:
    :func:`_one_exposure`; read along the normal at :data:`NORMAL_SHIFTS` too, the least spread counting)
    spread (:func:`_spread`) more than max(``spread_floor``,
    ``spread_ratio`` × the first sweep's median spread) + ``contrast_weight`` × the photos' local contrast there
    (:func:`_local_contrast`). A carved region that reaches less than ``min_depth`` (lattice units: the working
    sphere's radius is 1) into the hull is put back: nibbles of a textured surface, not a concavity.
    ``sizes`` (V, 2): each view's own (width, height) on a padded canvas.
    """
    V, H, W = masks.shape
    if inside.ndim != 3 or len(set(inside.shape)) != 1:
        raise ValueError(f"photo_carve: inside must be a cubic (R+1)³ lattice, got shape {inside.shape}")
    if P.shape != (V, 3, 4) or images.shape != (V, H, W, 3):
        raise ValueError(f"photo_carve: P {tuple(P.shape)} and images {tuple(images.shape)} do not match masks "
                         f"{tuple(masks.shape)}")
    R = inside.shape[0] - 1
    dev = masks.device
    pts_all = grid_points(R, device=dev).view(R + 1, R + 1, R + 1, 3)
    start, inside = inside, inside.copy()
    cell = 2.0 / R

    surf_idx = np.argwhere(_surface(inside))
    if len(surf_idx) == 0:  # an empty hull
        return PhotoCarveResult(inside, 0, 0, 0, 0, float("nan"), 1)
    pool = _pool_factor(pts_all, surf_idx, P, cell, pixels_per_cell)
    scale = torch.tensor([1.0 / pool, 1.0 / pool, 1.0], device=dev)[None, :, None]
    P_low = P * scale
    img_low = F.avg_pool2d(images.permute(0, 3, 1, 2), pool, ceil_mode=True)
    mask_low = F.avg_pool2d(masks[:, None], pool, ceil_mode=True)[:, 0]
    if sizes is not None:  # the padding of a smaller view is outside it
        w_v = torch.div(sizes[:, 0], pool, rounding_mode="floor")
        h_v = torch.div(sizes[:, 1], pool, rounding_mode="floor")
        hh, ww = mask_low.shape[1:]
        in_view = (torch.arange(ww, device=dev)[None, None] < w_v[:, None, None]) \
            & (torch.arange(hh, device=dev)[None, :, None] < h_v[:, None, None])
        mask_low = mask_low * in_view
    # a point seen within a pixel of a silhouette reads colours mixed with the background
    mask_low = -F.max_pool2d(-mask_low[:, None], 3, stride=1, padding=1)[:, 0]
    h, w = mask_low.shape[1:]

    def project_idx(idx: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        p = pts_all[tuple(torch.from_numpy(idx).to(dev).T)]
        return project(p, P_low)

    silhouettes = _coverage(*project_idx(surf_idx), h, w)
    img_low = _one_exposure(inside, surf_idx, pts_all, P_low, img_low, mask_low, cell, min_cos)
    contrast = _local_contrast(img_low)
    threshold, carved_total, restored_total, sweeps = None, 0, 0, 0
    frozen = np.zeros_like(inside)  # carves once undone stay
    while sweeps < max_sweeps:
        sweeps += 1
        surf_idx = np.argwhere(_surface(inside))
        spread, texture = _surface_spread(inside, surf_idx, pts_all, P_low, img_low, contrast, mask_low, cell,
                                          min_views, min_cos)
        if threshold is None:
            finite = spread[torch.isfinite(spread)]
            if finite.numel() == 0:  # no surface point seen by enough views: nothing to judge
                return PhotoCarveResult(inside, 0, 0, 0, sweeps, float("nan"), pool)
            threshold = max(spread_floor, spread_ratio * float(finite.median()))
        over = torch.nan_to_num(spread - contrast_weight * texture, nan=0.0) > threshold
        over &= ~torch.from_numpy(frozen[tuple(surf_idx.T)]).to(over.device)
        cand = surf_idx[over.cpu().numpy()]
        if len(cand) == 0:
            break
        inside[tuple(cand.T)] = False
        undone = _reopened(inside, cand, spread[over], project_idx, silhouettes, h, w)
        inside[tuple(undone.T)] = True
        frozen[tuple(undone.T)] = True
        carved_total += len(cand) - len(undone)
        restored_total += len(undone)
        if len(undone) == len(cand):  # nothing changed: the next sweep would find the same
            break
    shallow = _shallow_carves(start, inside, min_depth / cell)
    inside |= shallow
    n_shallow = int(shallow.sum())
    return PhotoCarveResult(inside, carved_total - n_shallow, restored_total, n_shallow, sweeps, threshold, pool)


def _shallow_carves(hull: np.ndarray, carved_hull: np.ndarray, min_cells: float) -> np.ndarray:
    """The carved points (in ``hull``, not in ``carved_hull``) whose connected carved region reaches less than
    ``min_cells`` into the hull at its deepest (distance to the hull's outside): a textured surface's nibbles,
    not a concavity."""
    carved = hull & ~carved_hull
    if not carved.any():
        return carved
    depth = ndimage.distance_transform_edt(np.pad(hull, 1))[1:-1, 1:-1, 1:-1]
    labels, n = ndimage.label(carved)
    deepest = np.asarray(ndimage.maximum(depth, labels, index=np.arange(1, n + 1)))
    return carved & np.concatenate([[False], deepest < min_cells])[labels]


def _pool_factor(pts_all: torch.Tensor, surf_idx: np.ndarray, P: torch.Tensor, cell: float,
                 pixels_per_cell: float) -> int:
    """Image reduction factor at which a lattice cell spans at most ``pixels_per_cell`` pixels (95th percentile
    over the surface points and views): then the 3×3 splats of neighbouring points leave no gap in a z-buffer."""
    p = pts_all[tuple(torch.from_numpy(surf_idx[:: max(1, len(surf_idx) // 512)]).to(P.device).T)]
    uv0, z0 = project(p, P)
    uv1, _ = project(p + torch.tensor([cell, 0.0, 0.0], device=P.device), P)
    uv2, _ = project(p + torch.tensor([0.0, cell, 0.0], device=P.device), P)
    step = 0.5 * ((uv1 - uv0).norm(dim=-1) + (uv2 - uv0).norm(dim=-1))
    step = step[z0 > 0]
    if step.numel() == 0:
        return 1
    return max(1, math.ceil(float(torch.quantile(step, 0.95)) / pixels_per_cell))


def _surface_views(inside: np.ndarray, surf_idx: np.ndarray, pts_all: torch.Tensor, P: torch.Tensor,
                   masks: torch.Tensor, cell: float, min_cos: float) -> tuple[torch.Tensor, ...]:
    """The surface points ``surf_idx``: (M, 3) positions, (V, M, 2) their pixels, (V, M) whether each view sees
    them (unoccluded, at least ``min_cos`` head-on, inside its mask) and (M, 3) their outward normals."""
    dev = P.device
    pts = pts_all[tuple(torch.from_numpy(surf_idx).to(dev).T)]
    h, w = masks.shape[1:]
    uv, z = project(pts, P)
    seen = _visible(uv, z, h, w, tol=1.5 * cell * _depth_scale(P))
    normals = torch.from_numpy(_outward_normals(inside, surf_idx)).to(dev, torch.float32)
    centres = -torch.linalg.solve(P[:, :, :3], P[:, :, 3:])[..., 0]  # (V, 3)
    to_cam = centres[:, None] - pts[None]
    cos = (to_cam / to_cam.norm(dim=-1, keepdim=True) * normals[None]).sum(-1)
    in_mask = _bilinear(masks[:, None], uv)[..., 0] > 0.5
    return pts, uv, seen & (cos >= min_cos) & in_mask, normals


def _one_exposure(inside: np.ndarray, surf_idx: np.ndarray, pts_all: torch.Tensor, P: torch.Tensor,
                  images: torch.Tensor, masks: torch.Tensor, cell: float, min_cos: float) -> torch.Tensor:
    """The photos (V, 3, H, W) divided by their views' colour gains (:func:`_view_gains`, fitted on the hull's
    surface points), so that a view's exposure or white balance alone does not make colours disagree; as they are
    when that does not lower the surface points' median spread (a steady exposure: the fit's own error)."""
    _, uv, seen, _ = _surface_views(inside, surf_idx, pts_all, P, masks, cell, min_cos)
    colours = _bilinear(images, uv)
    gains = _view_gains(colours, seen)

    def median_spread(c: torch.Tensor) -> float:
        spread = _spread(c, seen)
        spread = spread[torch.isfinite(spread)]
        return float(spread.median()) if spread.numel() else math.inf

    if median_spread(colours / gains[:, None]) < median_spread(colours):
        return images / gains[:, :, None, None]
    return images


def _view_gains(colours: torch.Tensor, seen: torch.Tensor, rounds: int = 30, dark: float = 0.05) -> torch.Tensor:
    """(V, 3) each view's colour gains against the others (exposure, white balance), fitted with the points'
    colours: log colour = log gain of the view + log colour of the point, alternating means over the points seen
    by ≥ 2 views and brighter than ``dark``, each round on the better-agreeing half of them (not a lid's, whose
    views see different places). Means, not medians: views that share few points (one ring of a capture against
    another) are still tied together. 1 where a view sees no such point; their geometric mean is 1."""
    ok = seen[..., None] & (colours > dark) & (seen.sum(0) >= 2)[None, :, None]
    logc = torch.where(ok, colours.clamp(min=dark).log(), torch.zeros_like(colours))
    w = ok.to(colours.dtype)
    readings = w.sum((0, 2))  # (M,) how many colour values each point has
    fitted = readings > 0
    use = torch.ones(colours.shape[1], dtype=torch.bool, device=colours.device)
    log_g = torch.zeros(colours.shape[0], colours.shape[-1], dtype=colours.dtype, device=colours.device)
    for _ in range(rounds):
        wu = w * use[None, :, None]
        log_a = ((logc - log_g[:, None]) * wu).sum(0) / wu.sum(0).clamp(min=1)  # (M, 3) the points' colours
        log_g = ((logc - log_a[None]) * wu).sum(1) / wu.sum(1).clamp(min=1)  # (V, 3)
        log_g = log_g - log_g.mean(0)
        resid = ((logc - log_g[:, None] - log_a[None]).abs() * w).sum((0, 2)) / readings.clamp(min=1)  # (M,)
        use = fitted & (resid <= resid[fitted].median()) if fitted.any() else fitted
    return log_g.exp()


def _surface_spread(inside: np.ndarray, surf_idx: np.ndarray, pts_all: torch.Tensor, P: torch.Tensor,
                    images: torch.Tensor, contrast: torch.Tensor, masks: torch.Tensor, cell: float, min_views: int,
                    min_cos: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(M,) colour spread at the surface points ``surf_idx`` across the views that see them (NaN: fewer than
    ``min_views``), and (M,) the photos' local contrast there (:func:`_local_contrast`, median over those
    views)."""
    pts, uv, seen, normals = _surface_views(inside, surf_idx, pts_all, P, masks, cell, min_cos)
    spread = _spread(_bilinear(images, uv), seen)
    for shift in NORMAL_SHIFTS:  # the surface it stands for may lie off the lattice point (NORMAL_SHIFTS)
        uv_s, _ = project(pts + shift * cell * normals, P)
        spread = torch.fmin(spread, _spread(_bilinear(images, uv_s), seen))
    local = torch.where(seen, _bilinear(contrast, uv)[..., 0], torch.full_like(seen, float("nan"), dtype=uv.dtype))
    enough = seen.sum(0) >= min_views
    nan = torch.full_like(spread, float("nan"))
    return torch.where(enough, spread, nan), torch.where(enough, local.nanmedian(0).values, nan)


def _local_contrast(images: torch.Tensor) -> torch.Tensor:
    """(V, 1, H, W): the mean absolute deviation of each pixel's colour from its 3×3 mean, averaged over 3×3 and
    the channels: what a point's colour may change by when it is read a pixel off, on a textured surface."""
    dev = (images - F.avg_pool2d(images, 3, stride=1, padding=1, count_include_pad=False)).abs().mean(1, keepdim=True)
    return F.avg_pool2d(dev, 3, stride=1, padding=1, count_include_pad=False)


def _depth_scale(P: torch.Tensor) -> torch.Tensor:
    """(V, 1) factor from a distance to the projection's third coordinate (the norm of P's third row's 3-vector:
    z is depth × that)."""
    return P[:, 2, :3].norm(dim=-1, keepdim=True)


def _reopened(inside: np.ndarray, cand: np.ndarray, cand_spread: torch.Tensor, project_idx,
              silhouettes: torch.Tensor, h: int, w: int) -> np.ndarray:
    """The carved points ``cand`` to put back so that every view's silhouette stays covered: for each pixel the
    carved lattice leaves uncovered, of the carved points whose splat covered it the one whose colours agreed
    best (``cand_spread``)."""
    cov = _coverage(*project_idx(np.argwhere(_surface(inside))), h, w)
    lost = silhouettes & ~cov
    if not lost.any():
        return cand[:0]
    uv, z = project_idx(cand)
    front, offset = z > 0, torch.arange(uv.shape[0], device=uv.device)[:, None] * (h * w)
    spread = cand_spread.to(lost.device)[None, :].expand(uv.shape[0], -1)
    best = torch.full((lost.numel(),), float("inf"), device=lost.device)
    hits = []
    for idx, ok in _splats(uv, h, w):
        hit = ok & front & lost.gather(1, idx)
        best.scatter_reduce_(0, (idx + offset)[hit], spread[hit], reduce="amin")
        hits.append((idx + offset, hit))
    chosen = torch.zeros(len(cand), dtype=torch.bool, device=lost.device)
    for key, hit in hits:
        chosen |= (hit & (spread <= best[key])).any(0)
    return cand[chosen.cpu().numpy()]
