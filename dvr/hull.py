"""Visual hull from masks: which points some view sees outside its mask (or no view sees at all).

Used twice: to initialise the occupancy (a smooth signed-distance-like logit volume of the hull), and as
3-D carving supervision during training (random points of the unit sphere that are outside the hull are
pushed to free space). Points are projected into all masks at once.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from scipy import ndimage

from dvr.cameras import in_contact_band, plane_height, project
from dvr.fields import evaluate_in_chunks


def mask_lookup(points: torch.Tensor, P: torch.Tensor, masks: torch.Tensor, sizes: torch.Tensor | None = None):
    """Mask value of every point in every view: (N, M) values in [0, 1] and (N, M) 'seen' flags.

    ``masks`` is (N, H, W) float, or (N, C, H, W) for C maps per view read at one projection (values (N, C, M)); a
    point is seen by a view when it is in front of the camera and projects inside the image — inside its own (width,
    height) of ``sizes`` (N, 2) when the views differ in size and the masks are padded to a common canvas (top-left
    aligned). Bilinear lookup with pixel centres at +0.5 (``align_corners=False``).
    """
    N, H, W = masks.shape[0], masks.shape[-2], masks.shape[-1]
    uv, z = project(points.to(P.dtype), P)
    w_v = torch.full((N, 1), float(W), device=P.device) if sizes is None else sizes[:, :1].to(uv.dtype)
    h_v = torch.full((N, 1), float(H), device=P.device) if sizes is None else sizes[:, 1:].to(uv.dtype)
    seen = (z > 0) & (uv[..., 0] >= 0) & (uv[..., 0] <= w_v) & (uv[..., 1] >= 0) & (uv[..., 1] <= h_v)
    g = torch.stack([uv[..., 0] / W * 2 - 1, uv[..., 1] / H * 2 - 1], dim=-1).to(masks.dtype)
    g = torch.nan_to_num(g, nan=-2.0, posinf=-2.0, neginf=-2.0).clamp(-2, 2)
    maps = masks[:, None] if masks.ndim == 3 else masks
    vals = F.grid_sample(maps, g[:, :, None, :], mode="bilinear", align_corners=False, padding_mode="zeros")
    return (vals[:, 0, :, 0] if masks.ndim == 3 else vals[..., 0]), seen


def view_votes(points: torch.Tensor, P: torch.Tensor, masks: torch.Tensor, sizes: torch.Tensor | None = None):
    """For each point, how many views see it outside their mask (mask value < 0.5) and how many see it at all: two
    (N,) counts (:func:`mask_lookup`); with (V, C, H, W) ``masks`` the first is (C, N), one count per map."""
    vals, seen = mask_lookup(points, P, masks, sizes)
    if masks.ndim == 4:
        return ((vals < 0.5) & seen[:, None]).sum(0), seen.sum(0)
    return ((vals < 0.5) & seen).sum(0), seen.sum(0)


def cut_by_frame(masks: torch.Tensor, sizes: torch.Tensor | None = None, share: float = 0.01) -> torch.Tensor:
    """(V,) bool: the views whose mask (V, H, W) reaches the image's edge along more than ``share`` of its border
    pixels (the object leaves the frame there). ``sizes`` (V, 2) width, height of each view on a common canvas
    (top-left aligned, as :func:`mask_lookup`'s); None: every view fills the canvas."""
    if masks.ndim != 3:
        raise ValueError(f"cut_by_frame: masks must be (V, H, W), got {tuple(masks.shape)}")
    V, H, W = masks.shape
    size = [(W, H)] * V if sizes is None else [(int(w), int(h)) for w, h in sizes.tolist()]
    cut = []
    for m, (w, h) in zip(masks, size):
        obj = m[:h, :w] >= 0.5
        border = torch.cat([obj[0], obj[-1], obj[1:-1, 0], obj[1:-1, -1]])
        cut.append(border.float().mean() > share)
    return torch.stack(cut) if cut else torch.zeros(0, dtype=torch.bool)


def background_distance(masks: torch.Tensor) -> np.ndarray:
    """(V, H, W) float64: each pixel's distance in pixels to its mask's nearest object pixel (mask ≥ 0.5; 0 on the
    object, inf in a mask without object pixels)."""
    background = (masks < 0.5).cpu().numpy()
    return np.stack([ndimage.distance_transform_edt(b) if not b.all() else np.full(b.shape, np.inf)
                     for b in background])


def near_object(masks: torch.Tensor, px) -> torch.Tensor:
    """(V, H, W) float on ``masks``' device: 1 where a pixel lies less than ``px`` pixels from its mask's nearest
    object pixel (:func:`background_distance`; the object pixels themselves included), 0 farther into the background.
    ``px``: one distance, or one per view."""
    dist = np.broadcast_to(np.asarray(px, dtype=float), (masks.shape[0],)) if masks.ndim == 3 else np.zeros(0)
    if masks.ndim != 3 or not (dist > 0).all():
        raise ValueError(f"near_object: masks must be (V, H, W) and px > 0, got {tuple(masks.shape)} and {px}")
    near = background_distance(masks) < dist[:, None, None]
    return torch.from_numpy(near).to(device=masks.device, dtype=masks.dtype)


def outside_hull(points: torch.Tensor, P: torch.Tensor, masks: torch.Tensor, min_views: int = 1,
                 chunk: int = 65536, ground: np.ndarray | None = None, sizes: torch.Tensor | None = None,
                 contact_band: float = 0.0, sparse_views: int = 0, near: torch.Tensor | None = None,
                 min_framing: int = 1, min_fraction: float = 0.0, fraction_near: torch.Tensor | None = None
                 ) -> torch.Tensor:
    """True for points that ≥ ``min_views`` views, and ≥ ``min_fraction`` of the views that see them, see outside their
    mask (never more than all of those; a fraction lets a capture of many views outvote a few wrong masks; with
    ``fraction_near``, a :func:`near_object` map of the masks, ≥ ``min_views`` views that see them outside that map, far
    from their mask, are enough: the fraction holds near a mask's edge, where a view that lost a thin part votes),
    that fewer than ``min_framing`` views see (project inside their image; 1: that no view sees), or that lie below the
    support plane ``ground`` (4,) when the object stands on one. Where fewer than ``sparse_views`` views see a point
    (the edge of the working sphere, which only a few photos frame), one view outside is enough: a vote of two
    needs enough voters (and no more than all the views that see it are ever asked). Within ``contact_band`` above
    that plane (where the object meets its support and automatic masks are least sure) a point needs ≥
    max(``min_views``, 2) views to be outside. ``near`` (:func:`near_object` of the masks): one view carves, wherever
    the point lies, when it projects where that view is 0 (far inside its background). ``sizes``: see
    :func:`mask_lookup`."""
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"outside_hull: points must have shape (N, 3), got {tuple(points.shape)}")
    if P.ndim != 3 or P.shape[1:] != (3, 4) or masks.ndim != 3 or masks.shape[0] != P.shape[0]:
        raise ValueError(f"outside_hull: P must be (V, 3, 4) and masks (V, H, W), got {tuple(P.shape)} and "
                         f"{tuple(masks.shape)}")
    if min_framing < 1:
        raise ValueError(f"outside_hull: min_framing must be ≥ 1, got {min_framing}")
    if not 0.0 <= min_fraction <= 1.0:
        raise ValueError(f"outside_hull: min_fraction must lie in [0, 1], got {min_fraction}")

    maps = [m for m in (near, fraction_near) if m is not None]

    def outside(p: torch.Tensor) -> torch.Tensor:
        """The test above for one chunk of points."""
        if not maps:
            n_out, n_seen = view_votes(p, P, masks, sizes)
        else:  # the masks and their distance maps read at one projection
            votes, n_seen = view_votes(p, P, torch.stack([masks, *maps], dim=1), sizes)
            n_out = votes[0]
            n_far = votes[1] if near is not None else None  # views far inside their background
            n_beyond = votes[-1] if fraction_near is not None else None  # views beyond the fraction's reach
        need = torch.ceil(min_fraction * n_seen - 1e-6).long().clamp(min=min_views)  # 1e-6: 0.1 × 30 is 3, not 4
        need = torch.minimum(need, n_seen).clamp(min=1)
        if fraction_near is not None:  # far from the masks, min_views views carve whatever the fraction
            plain = torch.minimum(torch.full_like(n_seen, min_views), n_seen).clamp(min=1)
            need = torch.where(n_beyond >= plain, torch.ones_like(need), need)
        need = torch.where(n_seen < sparse_views, torch.ones_like(need), need)
        if ground is not None:
            hgt = plane_height(ground, p)
            if contact_band > 0:
                need = torch.where(in_contact_band(hgt, contact_band), torch.clamp(need, min=2), need)
        free = (n_out >= need) | (n_seen < min_framing)
        if near is not None:
            free |= n_far > 0
        if ground is not None:
            free |= hgt < 0
        return free

    return evaluate_in_chunks(outside, points, chunk, dtype=torch.bool)


def grid_points(res: int, device=None, dtype=torch.float32) -> torch.Tensor:
    """(res+1)³ lattice points over [-1, 1]³, indexed [x, y, z] and flattened in that order."""
    lin = torch.linspace(-1.0, 1.0, res + 1, device=device, dtype=dtype)
    x, y, z = torch.meshgrid(lin, lin, lin, indexing="ij")
    return torch.stack([x, y, z], dim=-1).view(-1, 3)


def lattice_corners(points: np.ndarray, res: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Index arrays into a (res+1)³ lattice over [-1, 1]³ (:func:`grid_points`) of the 8 corners of the cell holding
    each of ``points`` (M, 3) inside the cube."""
    cell = np.floor((points + 1.0) * (res / 2.0)).astype(int)
    cell = cell[((cell >= 0) & (cell < res)).all(1)]
    corners = np.concatenate([cell + np.array(o) for o in np.ndindex(2, 2, 2)])
    return corners[:, 0], corners[:, 1], corners[:, 2]


def hull_inside(P: torch.Tensor, masks: torch.Tensor, res: int = 96, **rules) -> np.ndarray:
    """(res+1)³ bool lattice [x, y, z] over [-1, 1]³: inside the visual hull (:func:`outside_hull` with the carving
    ``rules``, its keyword arguments) and the unit sphere. Only the lattice points inside the sphere are projected
    (about half of them)."""
    pts = grid_points(res, device=masks.device)
    in_sphere = pts.norm(dim=-1) <= 1.0
    inside = torch.zeros(pts.shape[0], dtype=torch.bool, device=pts.device)
    inside[in_sphere] = ~outside_hull(pts[in_sphere], P, masks, **rules)
    return inside.view(res + 1, res + 1, res + 1).cpu().numpy()


def inside_logits(inside: np.ndarray, slope_cells: float = 1.0, clamp: float = 10.0,
                  device=None) -> torch.Tensor:
    """Logit volume of a bool lattice: ≈ signed distance (in cells) × 2/slope_cells, positive inside, within
    ±``clamp``; float32 on ``device``."""
    if not inside.any():
        return torch.full(inside.shape, -clamp, device=device)
    d_in = ndimage.distance_transform_edt(inside)
    d_out = ndimage.distance_transform_edt(~inside)
    sdf = np.where(inside, d_in - 0.5, -(d_out - 0.5))
    logit = np.clip(sdf * (2.0 / slope_cells), -clamp, clamp)
    return torch.from_numpy(logit.astype(np.float32)).to(device)


def coarse_points(lattice: np.ndarray, res: int) -> np.ndarray:
    """The (res+1)³ lattice's values read from ``lattice``, an (R+1)³ one over the same cube (finer, as a rule), at
    its nearest points (exact when R is a multiple of ``res``: the coarse points are fine points)."""
    R = lattice.shape[0] - 1
    if lattice.ndim != 3 or len(set(lattice.shape)) != 1 or R < 1 or res < 1:
        raise ValueError(f"coarse_points: need a cubic lattice and res ≥ 1, got {lattice.shape} and {res}")
    sel = np.rint(np.arange(res + 1) * (R / res)).astype(int)
    return lattice[np.ix_(sel, sel, sel)]


def settled_onto_plane(inside: np.ndarray, ground: np.ndarray, height: float) -> np.ndarray:
    """The bool lattice ``inside`` ((res+1)³ over [-1, 1]³, :func:`grid_points`) with the space under each of its
    points less than ``height`` above the plane ``ground`` filled down to the plane, along the plane's normal: an
    object resting on a support reaches it. (Masks lose a shiny object's lowest band, which mirrors the floor, and
    the hull then floats it a little above its support.) A point higher up keeps the space under it free: the floor
    under a table's top or between a cow's legs."""
    res = inside.shape[0] - 1
    pts = grid_points(res, dtype=torch.float64).numpy()
    h = plane_height(ground, pts)
    low = inside.reshape(-1) & (h > 0) & (h < height)
    p, hp = pts[low], h[low]
    normal = np.asarray(ground[:3], float)
    step = 1.0 / res  # half a lattice spacing: every lattice point on the way down is met
    out = inside.copy()
    for k in range(1, int(np.ceil(height / step)) + 1):
        q = p - normal * np.minimum(k * step, hp)[:, None]
        idx = np.rint((q + 1.0) * (res / 2.0)).astype(int)
        ok = ((idx >= 0) & (idx <= res)).all(1)
        out[idx[ok, 0], idx[ok, 1], idx[ok, 2]] = True
    return out


def hull_lattice(P: torch.Tensor, masks: torch.Tensor, res: int = 96, keep: np.ndarray | None = None,
                 settle: float = 0.0, **rules) -> np.ndarray:
    """(res+1)³ bool lattice [x, y, z] of the visual hull (:func:`hull_inside`; ``rules``: :func:`outside_hull`'s
    keyword arguments); points outside the unit sphere (or below the support plane ``ground``) are free, except the
    cells holding the points ``keep`` (M, 3), which stay inside whatever the masks say (:func:`lattice_corners`);
    with a ``ground`` plane and ``settle`` > 0, the hull's parts lower than that rest on it
    (:func:`settled_onto_plane`)."""
    inside = hull_inside(P, masks, res, **rules)
    if settle > 0 and rules.get("ground") is not None:
        inside = settled_onto_plane(inside, rules["ground"], settle)
    if keep is not None and len(keep):
        inside[lattice_corners(keep, res)] = True
    return inside


def hull_logits(P: torch.Tensor, masks: torch.Tensor, res: int = 96, slope_cells: float = 1.0, clamp: float = 10.0,
                keep: np.ndarray | None = None, settle: float = 0.0, **rules) -> torch.Tensor:
    """Logit volume (res+1)³ [x, y, z] of the visual hull (:func:`inside_logits` of :func:`hull_lattice`, which
    takes ``keep``, ``settle`` and the carving ``rules``). Returns a float32 tensor on masks' device."""
    return inside_logits(hull_lattice(P, masks, res, keep, settle, **rules), slope_cells, clamp, device=masks.device)


def hull_bounding_sphere(P: torch.Tensor, masks: torch.Tensor, res: int = 64, margin: float = 1.1,
                         **rules) -> tuple[np.ndarray, float] | None:
    """Centre and radius (this frame) of a sphere around the visual hull of the masks (:func:`outside_hull` with the
    carving ``rules``; above the support plane ``ground`` when they name one), × ``margin`` plus one cell; ``None``
    when the hull is empty or already fills the unit sphere (no tighter frame to gain)."""
    pts = grid_points(res, device=masks.device)
    pts = pts[pts.norm(dim=-1) <= 1.0]
    inside = pts[~outside_hull(pts, P, masks, **rules)]
    if inside.shape[0] < 8:
        return None
    lo, hi = inside.min(0).values, inside.max(0).values
    c = 0.5 * (lo + hi)
    r = float((inside - c).norm(dim=-1).max()) * margin + 2.0 * 3 ** 0.5 / res
    if r >= 0.95:
        return None
    return c.double().cpu().numpy(), max(r, 4.0 / res)


def carve_along_rays(logits: torch.Tensor, origins: torch.Tensor, dirs: torch.Tensor, depth: torch.Tensor,
                     value: float = 10.0, chunk: int = 4096) -> torch.Tensor:
    """Set to −``value`` (free) the lattice points of a (R+1)³ logit volume [x, y, z] over [-1, 1]³ nearest to
    the rays' segments from the unit-sphere entry to ``depth`` minus half a cell diagonal (so no carved lattice
    point lies behind ``depth``). Rays of non-positive length change nothing."""
    from dvr.cameras import sphere_bounds

    out = logits.clone()
    R = logits.shape[0] - 1
    near, far, valid = sphere_bounds(origins, dirs)
    end = torch.minimum(depth - 3 ** 0.5 / R, far)  # half the diagonal of a cell of size 2 / R
    n = 2 * R  # two samples per cell along the longest chord
    t = torch.linspace(0.0, 1.0, n, device=logits.device)
    for s in range(0, origins.shape[0], chunk):
        ok = valid[s : s + chunk] & (end[s : s + chunk] > near[s : s + chunk])
        if not ok.any():
            continue
        o, d = origins[s : s + chunk][ok], dirs[s : s + chunk][ok]
        a, b = near[s : s + chunk][ok], end[s : s + chunk][ok]
        z = a[:, None] + (b - a)[:, None] * t[None]
        p = o[:, None] + z[..., None] * d[:, None]
        idx = ((p.reshape(-1, 3) + 1.0) * 0.5 * R).round().long().clamp(0, R)
        out[idx[:, 0], idx[:, 1], idx[:, 2]] = torch.minimum(out[idx[:, 0], idx[:, 1], idx[:, 2]], torch.tensor(-value))
    return out
