"""Isosurface extraction: hierarchical marching cubes of the occupancy logit at level τ.

A coarse lattice is evaluated everywhere; only coarse cells whose corners straddle the level (dilated by
one cell) are evaluated at the fine resolution, the rest is filled by trilinear upsampling of the coarse
values (far from the surface only the sign matters). Vertices can then be moved onto the level set with
a few Newton steps along ∇f, and get colours from the texture field.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from skimage import measure

from dvr.cameras import in_contact_band
from dvr.fields import Field, evaluate_in_chunks
from dvr.hull import grid_points
from dvr.march import LogitFn


def _logits_float32(logit_fn: LogitFn, pts: torch.Tensor, chunk: int) -> torch.Tensor:
    """``logit_fn`` at ``pts`` (M, 3) in chunks, as float32 (M,)."""
    return evaluate_in_chunks(lambda q: logit_fn(q).float(), pts, chunk)


@torch.no_grad()
def logit_volume(logit_fn: LogitFn, resolution: int = 256, coarse_factor: int = 4, device=None, chunk: int = 131072,
                 outside: float = -10.0) -> tuple[np.ndarray, int]:
    """(R+1)³ logit lattice over [-1, 1]³ [x, y, z], exact near the level set; returns (volume, fine evaluations)."""
    if resolution % coarse_factor:
        raise ValueError(f"resolution {resolution} must be a multiple of coarse_factor {coarse_factor}")
    rc = resolution // coarse_factor
    cp = grid_points(rc, device=device)
    cv = _logits_float32(logit_fn, cp, chunk).view(rc + 1, rc + 1, rc + 1)
    cv = torch.where(cp.norm(dim=-1).view_as(cv) > 1.0, torch.full_like(cv, outside), cv)
    # coarse cells straddling 0
    pos = (cv >= 0).float()[None, None]
    mx = F.max_pool3d(pos, 2, stride=1)[0, 0]
    mn = -F.max_pool3d(-pos, 2, stride=1)[0, 0]
    cells = (mx != mn).float()
    cells = F.max_pool3d(cells[None, None], 3, stride=1, padding=1)[0, 0] > 0  # dilate by one cell
    fine = F.interpolate(cv[None, None], size=(resolution + 1,) * 3, mode="trilinear", align_corners=True)[0, 0]
    # fine lattice points belonging to flagged cells
    flag = cells.repeat_interleave(coarse_factor, 0).repeat_interleave(coarse_factor, 1)
    flag = flag.repeat_interleave(coarse_factor, 2)
    flag = F.pad(flag[None, None].float(), (0, 1, 0, 1, 0, 1), mode="replicate")[0, 0] > 0
    # include the far faces of flagged cells
    flag = flag | F.pad(flag[:-1, :-1, :-1][None, None].float(), (1, 0, 1, 0, 1, 0))[0, 0].bool()
    idx = flag.nonzero()
    pts = idx.float() / resolution * 2 - 1
    vals = _logits_float32(logit_fn, pts, chunk)
    vals = torch.where(pts.norm(dim=-1) > 1.0, torch.full_like(vals, outside), vals)
    fine[idx[:, 0], idx[:, 1], idx[:, 2]] = vals
    return fine.cpu().numpy(), int(idx.shape[0])


def _newton_step(logit_fn: LogitFn, points: torch.Tensor, max_move: float, level: float) -> torch.Tensor:
    """One guarded Newton step of points (m, 3) towards the level set (see :func:`refine_vertices`)."""
    with torch.enable_grad():
        q = points.detach().requires_grad_(True)
        f = logit_fn(q) - level
        (g,) = torch.autograd.grad(f.sum(), q)
    gn2 = (g * g).sum(-1, keepdim=True)
    step = f.detach()[:, None] * g / gn2.clamp_min(1e-8)
    n = step.norm(dim=-1, keepdim=True)
    step = torch.where(n > max_move, step * (max_move / n.clamp_min(1e-12)), step)
    step = torch.where(gn2 > 1e-8, step, torch.zeros_like(step))
    return (q.detach() - step).to(points.dtype)


def refine_vertices(logit_fn: LogitFn, verts: torch.Tensor, steps: int, max_move: float,
                    level: float = 0.0) -> torch.Tensor:
    """Newton steps p ← p − (f − level)∇f/|∇f|², each clamped to ``max_move``; guarded for |∇f| → 0."""
    v = verts.clone()
    for _ in range(steps):
        v = evaluate_in_chunks(lambda q: _newton_step(logit_fn, q, max_move, level), v, 65536, (3,), v.dtype)
    return v


def footprint_occupancy(field: Field, height: float) -> LogitFn:
    """The field's occupancy logit with the band ``0 ≤ h < height`` above its support plane replaced by the vertical
    extrusion of the cross-section at ``height`` (the flat cap on the plane kept). An object standing on a floor
    meets it with the footprint of what stands just above, and there automatic masks are least sure (the contact
    shadow takes the object's lowest strip). ``field.occupancy`` itself without a support plane or for height 0."""
    if height <= 0 or field.support is None:
        return field.occupancy

    def occupancy(p: torch.Tensor) -> torch.Tensor:
        """The field's logits, points in the contact band read at the band's top (the footprint's extrusion)."""
        pl = field.support.to(device=p.device, dtype=p.dtype)
        h = p @ pl[:3] + pl[3]
        lift = torch.where(in_contact_band(h, height), height - h, torch.zeros_like(h))
        return field.clip_to_support(p, field.occupancy(p + lift[:, None] * pl[:3]))

    return occupancy


def extract_mesh(field: Field, resolution: int = 256, coarse_factor: int = 4, refine_steps: int = 2, level: float = 0.0,
                 device=None, footprint: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mesh of the level set in the normalized frame: vertices (V, 3) float64, faces (F, 3), colours (V, 3) uint8;
    ``footprint`` > 0: the lowest band above the support plane extruded (:func:`footprint_occupancy`).

    Returns empty arrays when the field has no surface.
    """
    device = device or next(field.parameters()).device
    occupancy = footprint_occupancy(field, footprint)
    vol, _ = logit_volume(occupancy, resolution, coarse_factor, device=device)
    vol = vol - level
    if not (vol.min() < 0 < vol.max()):
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 3), np.uint8)
    verts, faces, _, _ = measure.marching_cubes(vol, 0.0, spacing=(2.0 / resolution,) * 3)
    verts = verts - 1.0
    faces = faces[:, ::-1].copy()  # outward normals: occupancy > 0 inside
    vt = torch.from_numpy(verts).float().to(device)
    if refine_steps > 0:
        vt = refine_vertices(occupancy, vt, refine_steps, 0.5 * 2.0 / resolution, level)
    with torch.no_grad():
        cols = evaluate_in_chunks(field.texture, vt, 65536, (3,))
    colors = (cols.clamp(0, 1) * 255).round().byte().cpu().numpy()
    return vt.double().cpu().numpy(), faces.astype(np.int64), colors
