"""Surface finding without autograd: ray marching to the FIRST free→occupied change, then secant refinement.

Every ray gets a status:

* ``HIT``: a free → occupied change was found; ``depth`` is the refined root.
* ``MISS``: the ray never changes from free to occupied inside the unit sphere (or misses the sphere).
* ``INSIDE``: the first sample (the ray's entry into the unit sphere, or the camera when it is inside the
  sphere) is already occupied — the ray starts inside the object. It gets ``depth = near`` and is never
  reported as a hit; in particular no ray ever returns depth 0 at the camera as a "surface".

Memory does not grow with ``n_steps``: samples are evaluated in blocks of at most ``max_points`` points,
and rays that have found their crossing leave the work set.

Whole images of a trained field are rendered with it too (:func:`render_rays`, :func:`render_view`: the training's
previews, held-out views).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

import torch

from dvr.cameras import sphere_bounds

if TYPE_CHECKING:
    from dvr.data import SceneData
    from dvr.fields import Field

MISS, HIT, INSIDE = 0, 1, 2

LogitFn = Callable[[torch.Tensor], torch.Tensor]


@dataclass
class SurfaceResult:
    """What :func:`find_surface` returns per ray (B rays)."""

    depth: torch.Tensor  # (B,) refined depth for hits; near for INSIDE; far for MISS (finite everywhere)
    status: torch.Tensor  # (B,) int8 codes MISS / HIT / INSIDE
    near: torch.Tensor  # (B,) sphere entry
    far: torch.Tensor  # (B,) sphere exit
    max_depth: torch.Tensor  # (B,) depth of the sample with the largest logit (target for missed mask rays)

    @property
    def hit(self) -> torch.Tensor:
        """(B,) True for rays with status HIT."""
        return self.status == HIT


def _check_rays(origins: torch.Tensor, dirs: torch.Tensor) -> None:
    if origins.ndim != 2 or origins.shape[-1] != 3:
        raise ValueError(f"origins must be (B, 3), got {tuple(origins.shape)}")
    if dirs.shape != origins.shape:
        raise ValueError(f"dirs must match origins {tuple(origins.shape)}, got {tuple(dirs.shape)}")


def sample_fractions(n_rays: int, n_steps: int, jitter: bool, device: torch.device, dtype: torch.dtype,
                     generator=None) -> torch.Tensor:
    """(B, n_steps) positions along each ray's chord, 0 at near and 1 at far (both included); jitter moves interior
    samples within their cell (one uniform draw per sample)."""
    t = torch.linspace(0.0, 1.0, n_steps, device=device, dtype=dtype).expand(n_rays, n_steps)
    if jitter and n_steps > 2:
        noise = torch.rand(n_rays, n_steps, device=device, dtype=dtype, generator=generator) - 0.5
        noise[:, 0] = 0.0
        noise[:, -1] = 0.0
        t = t + noise / (n_steps - 1)
    return t


def depths_at(near: torch.Tensor, far: torch.Tensor, fractions: torch.Tensor) -> torch.Tensor:
    """(B, S) depths at the chord ``fractions`` (B, S) between near and far (B,)."""
    return near[:, None] + (far - near)[:, None] * fractions


def sample_depths(near: torch.Tensor, far: torch.Tensor, n_steps: int, jitter: bool, generator=None) -> torch.Tensor:
    """(B, n_steps) depths from near to far (both included); jitter moves interior samples within their cell."""
    return depths_at(near, far, sample_fractions(near.shape[0], n_steps, jitter, near.device, near.dtype, generator))


def _first_crossing(cross: torch.Tensor, vals: torch.Tensor, depths: torch.Tensor):
    """The bracket of each row's first free → occupied change: depths and logits − level at its two samples, from
    ``cross`` (B, S−1) (sample k free, k + 1 occupied), ``vals`` and ``depths`` (B, S). Rows without a change get the
    first two samples' (a bracket the caller does not use)."""
    k = cross.to(torch.int8).argmax(dim=1, keepdim=True)
    return (depths.gather(1, k)[:, 0], depths.gather(1, k + 1)[:, 0], vals.gather(1, k)[:, 0],
            vals.gather(1, k + 1)[:, 0])


@torch.no_grad()
def secant(
    logit_fn: LogitFn,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    d_lo: torch.Tensor,
    d_hi: torch.Tensor,
    f_lo: torch.Tensor,
    f_hi: torch.Tensor,
    n_iter: int,
    level: float = 0.0,
) -> torch.Tensor:
    """Refine roots bracketed by f_lo < level ≤ f_hi with the Illinois variant of the secant method: ``n_iter``
    field evaluations, each narrowing the bracket; the root returned is the secant of the last bracket (so the last
    evaluation counts too; ``n_iter`` 0: the secant of the given bracket).

    The bracket is kept, so the result never leaves [d_lo, d_hi]; f_hi − f_lo > 0 always (no division by 0).
    """
    f_lo = f_lo - level
    f_hi = f_hi - level
    side = torch.zeros_like(d_lo, dtype=torch.int8)
    for _ in range(n_iter):
        d = _secant_root(d_lo, d_hi, f_lo, f_hi)
        f = logit_fn(origins + d[:, None] * dirs).to(d.dtype) - level
        occ = f >= 0
        # Illinois: when the same end is kept twice, halve its value so the other end moves too
        keep_lo = occ & (side == 1)
        keep_hi = (~occ) & (side == -1)
        f_lo = torch.where(keep_lo, f_lo * 0.5, f_lo)
        f_hi = torch.where(keep_hi, f_hi * 0.5, f_hi)
        d_hi = torch.where(occ, d, d_hi)
        f_hi = torch.where(occ, f, f_hi)
        d_lo = torch.where(occ, d_lo, d)
        f_lo = torch.where(occ, f_lo, f)
        side = torch.where(occ, torch.ones_like(side), -torch.ones_like(side))
    return _secant_root(d_lo, d_hi, f_lo, f_hi)


def _secant_root(d_lo: torch.Tensor, d_hi: torch.Tensor, f_lo: torch.Tensor, f_hi: torch.Tensor) -> torch.Tensor:
    """Where the line through (d_lo, f_lo) and (d_hi, f_hi) crosses 0, kept inside [d_lo, d_hi]."""
    d = d_lo - f_lo * (d_hi - d_lo) / (f_hi - f_lo)
    return torch.minimum(torch.maximum(d, d_lo), d_hi)


@torch.no_grad()
def find_surface(
    logit_fn: LogitFn,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    n_steps: int = 64,
    n_secant: int = 8,
    level: float = 0.0,
    jitter: bool = False,
    max_points: int = 262144,
    near: torch.Tensor | None = None,
    far: torch.Tensor | None = None,
    generator: torch.Generator | None = None,
) -> SurfaceResult:
    """March ``n_steps`` samples between the unit-sphere entry and exit of each ray, return the first surface.

    ``logit_fn`` maps (M, 3) points to (M,) logits; the surface is where the logit crosses ``level``
    from below (free) to above (occupied).
    """
    _check_rays(origins, dirs)
    if n_steps < 2:
        raise ValueError(f"n_steps must be ≥ 2, got {n_steps}")
    if near is None or far is None:
        near, far, valid = sphere_bounds(origins, dirs)
    else:
        valid = far > near
    depths = sample_depths(near, far, n_steps, jitter, generator)  # (B, S) — small: no field values kept
    m = _MarchState.start(origins, near, far)
    _march(logit_fn, origins, dirs, depths, near, valid, level, max_points, m)

    hit = (m.status == HIT).nonzero().view(-1)
    if hit.numel() > 0:
        lo_d, hi_d, lo_f, hi_f = m.lo_d[hit], m.hi_d[hit], m.lo_f[hit], m.hi_f[hit]
        m.depth[hit] = secant(logit_fn, origins[hit], dirs[hit], lo_d, hi_d, lo_f + level, hi_f + level, n_secant,
                              level)
    return SurfaceResult(m.depth, m.status, near, far, m.max_depth)


@dataclass
class _MarchState:
    """Per-ray state of the march (B rays): status and depth so far, the largest logit − level seen and its depth,
    the bracket (depths, logits − level) of the first free → occupied change, and the last sample's logit."""

    status: torch.Tensor
    depth: torch.Tensor
    max_val: torch.Tensor
    max_depth: torch.Tensor
    lo_d: torch.Tensor
    hi_d: torch.Tensor
    lo_f: torch.Tensor
    hi_f: torch.Tensor
    prev: torch.Tensor

    @classmethod
    def start(cls, origins: torch.Tensor, near: torch.Tensor, far: torch.Tensor) -> _MarchState:
        """Every ray a MISS at ``far``, no logit seen yet (largest-logit depth: the chord's middle)."""
        B, dev, dt = origins.shape[0], origins.device, origins.dtype
        lo_d = torch.zeros(B, dtype=dt, device=dev)
        return cls(status=torch.full((B,), MISS, dtype=torch.int8, device=dev), depth=far.clone(),
                   max_val=torch.full((B,), -float("inf"), dtype=dt, device=dev), max_depth=0.5 * (near + far),
                   lo_d=lo_d, hi_d=torch.zeros_like(lo_d), lo_f=torch.zeros_like(lo_d), hi_f=torch.zeros_like(lo_d),
                   prev=torch.zeros(B, dtype=dt, device=dev))


def _march(logit_fn: LogitFn, origins: torch.Tensor, dirs: torch.Tensor, depths: torch.Tensor, near: torch.Tensor,
           valid: torch.Tensor, level: float, max_points: int, m: _MarchState) -> None:
    """Evaluate the samples ``depths`` (B, S) in blocks of ≤ ``max_points`` points, updating ``m`` in place; a ray
    leaves the work set once its first crossing is found (or its first sample is occupied: INSIDE)."""
    n_steps, dt = depths.shape[1], origins.dtype
    active = valid.nonzero().view(-1)
    block = max(1, min(n_steps, max_points // max(1, active.numel())))
    s0 = 0
    while s0 < n_steps and active.numel() > 0:
        s1 = min(n_steps, s0 + block)
        d_blk = depths[active, s0:s1]  # (A, s)
        pts = origins[active, None, :] + d_blk[..., None] * dirs[active, None, :]
        vals = logit_fn(pts.reshape(-1, 3)).to(dt).view(active.numel(), s1 - s0) - level
        # track the sample with the largest logit (used for rays inside the mask that miss)
        bmax, barg = vals.max(dim=1)
        better = bmax > m.max_val[active]
        m.max_val[active] = torch.where(better, bmax, m.max_val[active])
        m.max_depth[active] = torch.where(better, d_blk.gather(1, barg[:, None])[:, 0], m.max_depth[active])
        if s0 == 0:
            inside = vals[:, 0] >= 0
            m.status[active[inside]] = INSIDE
            m.depth[active[inside]] = near[active[inside]]
            vv, dd = vals, d_blk
        else:
            inside = torch.zeros_like(vals[:, 0], dtype=torch.bool)
            vv = torch.cat([m.prev[active, None], vals], dim=1)
            dd = torch.cat([depths[active, s0 - 1 : s0], d_blk], dim=1)
        cross = (vv[:, :-1] < 0) & (vv[:, 1:] >= 0)  # may have 0 columns (first block of width 1)
        found = cross.any(dim=1) & ~inside
        if found.any():
            f_idx = active[found]
            m.lo_d[f_idx], m.hi_d[f_idx], m.lo_f[f_idx], m.hi_f[f_idx] = _first_crossing(cross[found], vv[found],
                                                                                         dd[found])
            m.status[f_idx] = HIT
        m.prev[active] = vals[:, -1]
        active = active[~(found | inside)]
        s0 = s1


@torch.no_grad()
def find_surface_fixed(logit_fn: LogitFn, origins: torch.Tensor, dirs: torch.Tensor, fractions: torch.Tensor,
                       n_secant: int = 8, level: float = 0.0) -> SurfaceResult:
    """:func:`find_surface` with fixed shapes and no wait for the device, which a CUDA graph can hold: the samples at
    ``fractions`` (B, S) of each chord (:func:`sample_fractions`), every sample of every ray in one block, the secant
    on every ray (a harmless bracket where there is none) and the statuses chosen with ``where``, not by indexing.

    Equals ``find_surface`` with the same fractions; it evaluates the field at every sample, and the secant on every
    ray, so it costs more field evaluations (on CPU the eager version is the faster)."""
    _check_rays(origins, dirs)
    if fractions.ndim != 2 or fractions.shape[0] != origins.shape[0] or fractions.shape[1] < 2:
        raise ValueError(f"fractions must be (B, S ≥ 2) with B = {origins.shape[0]}, got {tuple(fractions.shape)}")
    near, far, valid = sphere_bounds(origins, dirs)
    depths = depths_at(near, far, fractions)
    pts = origins[:, None, :] + depths[..., None] * dirs[:, None, :]
    vals = logit_fn(pts.reshape(-1, 3)).to(origins.dtype).view(depths.shape) - level
    max_depth = torch.where(valid, depths.gather(1, vals.argmax(dim=1, keepdim=True))[:, 0], 0.5 * (near + far))
    inside = valid & (vals[:, 0] >= 0)
    cross = (vals[:, :-1] < 0) & (vals[:, 1:] >= 0)
    found = valid & cross.any(dim=1) & ~inside
    lo_d, hi_d, lo_f, hi_f = _first_crossing(cross, vals, depths)
    lo_f = torch.where(found, lo_f, torch.full_like(lo_f, -1.0))  # rays without a bracket: a harmless one
    hi_f = torch.where(found, hi_f, torch.ones_like(hi_f))
    root = secant(logit_fn, origins, dirs, lo_d, hi_d, lo_f + level, hi_f + level, n_secant, level)
    depth = torch.where(found, root, torch.where(inside, near, far))
    status = torch.where(found, HIT, torch.where(inside, INSIDE, MISS)).to(torch.int8)
    return SurfaceResult(depth, status, near, far, max_depth)


# ----------------------------------------------------------------------------- whole images (no autograd)
@torch.no_grad()
def render_rays(field: Field, origins: torch.Tensor, dirs: torch.Tensor, n_steps: int = 128, n_secant: int = 8,
                background: float = 0.0, chunk: int = 16384) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Colour, hit mask and depth for rays (B, 3): (B, 3), (B,), (B,)."""
    rgb = torch.full_like(origins, background)
    hit = torch.zeros(origins.shape[0], dtype=torch.bool, device=origins.device)
    depth = torch.zeros(origins.shape[0], dtype=origins.dtype, device=origins.device)
    for s in range(0, origins.shape[0], chunk):
        o, d = origins[s : s + chunk], dirs[s : s + chunk]
        res = find_surface(field.occupancy, o, d, n_steps=n_steps, n_secant=n_secant)
        h = res.hit
        hit[s : s + chunk] = h
        depth[s : s + chunk] = res.depth
        if h.any():
            p = o[h] + res.depth[h, None] * d[h]
            sub = rgb[s : s + chunk]
            sub[h] = field.texture(p).to(rgb.dtype)
    return rgb, hit, depth


@torch.no_grad()
def render_view(field: Field, data: SceneData, view: int, scale: float = 1.0, n_steps: int = 128,
                background: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Render view ``view`` of ``data`` (a SceneData) at ``scale`` × its resolution: (h, w, 3), (h, w)."""
    W, H = data.view_size(view)
    h, w = max(1, round(H * scale)), max(1, round(W * scale))
    dev = data.masks.device
    jj, ii = torch.meshgrid(torch.arange(w, device=dev) + 0.5, torch.arange(h, device=dev) + 0.5, indexing="xy")
    uv = torch.stack([jj * (W / w), ii * (H / h)], dim=-1).view(-1, 2).float()
    o, d = data.rays(torch.full((uv.shape[0],), view, device=dev, dtype=torch.long), uv)
    rgb, hit, _ = render_rays(field, o, d, n_steps=n_steps, background=background)
    return rgb.view(h, w, 3), hit.view(h, w)
