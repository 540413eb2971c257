"""Occupancy field f_θ(p) → logit and texture field t_θ(p) → RGB ∈ [0, 1].

Two representations:

* ``grid`` (default): occupancy = a learnable dense logit grid, initialised from the visual hull of the masks
  (training starts from a good shape), optionally plus a residual from tri-plane features and a small MLP
  (``occ_plane_res``, off by default). Texture = multi-resolution tri-plane features + a small MLP.
  Chosen by measurement on 2 CPU cores (README, "Method notes"): a tri-plane shares each plane texel along a
  whole line through the volume, so photometric updates of a seen surface also move unseen surfaces on the
  same lines (ridges under objects); a 1-channel dense grid has no such coupling and is cheaper, while for
  colour the tri-plane's coupling is harmless and its 2-D ``grid_sample`` is ~10× cheaper than 3-D features.
* ``mlp``: the reference, a plain ReLU MLP on Fourier-encoded xyz (the original DVR family), slow on CPU.

Both map points in the normalized frame (object inside the unit sphere) and work on any device, and both
implement the :class:`Field` interface that the trainer, the renderer and the extraction use.
:func:`evaluate_in_chunks` evaluates a field (or any point function) over many points in bounded memory.
"""

from __future__ import annotations

import abc
from typing import Callable

import torch
import torch.nn as nn
import torch.nn.functional as F

from dvr.config import FieldConfig

SUPPORT_SLOPE = 500.0
"""Logit per unit of depth below the support plane: one grid cell (2/96) below it the logit is −10."""


class SupportClip:
    """Occupancy clipped to the half-space above a support plane: min(f(p), slope · height(p)).

    Nothing below the floor or table an object stands on can be occupied, and where the object touches it the
    level set is the plane itself: the extracted mesh is closed by a flat cap. Mixed into :class:`Field`."""

    support: torch.Tensor | None = None

    def set_support(self, plane) -> None:
        """Clip to the plane (4,) n·x + d = 0 of the field's frame (unit n pointing up); None removes the clip."""
        self.support = None if plane is None else torch.as_tensor(plane, dtype=torch.float32).clone()

    def clip_to_support(self, p: torch.Tensor, logit: torch.Tensor) -> torch.Tensor:
        """``logit`` (M,) at points p (M, 3) clipped to min(logit, slope · height above the plane), if one is set."""
        if self.support is None:
            return logit
        if self.support.device != p.device:  # moved once: on CUDA a copy per call waited for the device every time
            self.support = self.support.to(p.device)
        pl = self.support.to(dtype=logit.dtype)
        h = p.to(logit.dtype) @ pl[:3] + pl[3]
        return torch.minimum(logit, SUPPORT_SLOPE * h)


class Field(SupportClip, nn.Module, abc.ABC):
    """What every occupancy + texture field provides (points (M, 3) in the normalized frame, any device).

    The trainer reads the parameter groups, initialises from the visual hull, regularises with ``tv_loss`` and,
    when ``supports_resize``, trains coarse to fine through ``resize_base``; rendering and extraction only use
    ``occupancy``, ``texture`` and the support clip (``set_support`` / ``clip_to_support``)."""

    cfg: FieldConfig

    supports_resize: bool = False
    """Whether :meth:`resize_base` can change the resolution of the occupancy (coarse-to-fine training)."""

    @abc.abstractmethod
    def occupancy(self, p: torch.Tensor) -> torch.Tensor:
        """Occupancy logit at points p (M, 3) → (M,) (> 0 inside; clipped to the support plane when set)."""

    @abc.abstractmethod
    def texture(self, p: torch.Tensor) -> torch.Tensor:
        """RGB in [0, 1] at points p (M, 3) → (M, 3)."""

    @abc.abstractmethod
    def init_occupancy(self, logits: torch.Tensor) -> None:
        """Start the occupancy from a (R+1)³ logit volume indexed [x, y, z] over [-1, 1]³ (the visual hull)."""

    @abc.abstractmethod
    def occupancy_parameters(self) -> list[nn.Parameter]:
        """The parameters the occupancy depends on (what the implicit depth gradient flows into)."""

    @abc.abstractmethod
    def grid_parameters(self) -> list[nn.Parameter]:
        """The parameters trained with the grid learning rate (the others get the MLP learning rate)."""

    @abc.abstractmethod
    def tv_loss(self) -> torch.Tensor:
        """Total-variation regulariser of the occupancy (0-d; exactly 0 where it does not apply)."""

    @property
    def grid_resolution(self) -> int | None:
        """Cells per axis of the resizable occupancy grid now (None: the field has none)."""
        return None

    def grid_resolution_in(self, state: dict[str, torch.Tensor]) -> int | None:
        """Cells per axis of the occupancy grid in a state_dict of this kind of field (None: it has none)."""
        return None

    def resize_base(self, res: int) -> tuple[nn.Parameter, nn.Parameter]:
        """Resample the occupancy to ``res`` cells per axis; returns (old, new) parameter so an optimizer can swap
        them. Only for fields with ``supports_resize``."""
        raise NotImplementedError(f"{type(self).__name__} cannot change its resolution (supports_resize is False); "
                                  "coarse-to-fine training needs field.kind 'grid'")


class TriPlane(nn.Module):
    """Multi-resolution tri-plane features: concat over levels, sum over the xy/xz/yz planes."""

    def __init__(self, resolutions: tuple[int, ...], channels: int, init_std: float = 1e-2):
        super().__init__()
        self.planes = nn.ParameterList(
            [nn.Parameter(torch.randn(3, channels, r, r) * init_std) for r in resolutions]
        )
        self.out_dim = channels * len(resolutions)

    def forward(self, p: torch.Tensor) -> torch.Tensor:
        """Features (M, channels × levels) at points p (M, 3)."""
        # slices, not index lists: a list is copied to the device at each call (a wait on CUDA, none in a graph)
        q = torch.stack([p[:, 0:2], p[:, 0::2], p[:, 1:3]]).unsqueeze(2)  # (3, M, 1, 2): the xy, xz, yz planes
        q = q.to(self.planes[0].dtype)
        feats = []
        for planes in self.planes:
            f = F.grid_sample(planes, q, mode="bilinear", padding_mode="border", align_corners=True)
            feats.append(f.sum(0)[:, :, 0].T)  # (M, C)
        return torch.cat(feats, dim=-1)


def _mlp(inp: int, hidden: int, out: int, layers: int, zero_last: bool = False) -> nn.Sequential:
    mods: list[nn.Module] = []
    d = inp
    for _ in range(layers):
        mods += [nn.Linear(d, hidden), nn.Softplus(beta=10.0)]
        d = hidden
    last = nn.Linear(d, out)
    if zero_last:
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)
    mods.append(last)
    return nn.Sequential(*mods)


class GridField(Field):
    """Dense logit grid (+ hull prior) + tri-plane residual; tri-plane texture.

    The grid ``base`` (1, 1, R+1, R+1, R+1) is stored [z, y, x] (``grid_sample``'s order for coordinates (x, y, z));
    ``init_occupancy`` takes volumes indexed [x, y, z] and transposes them."""

    supports_resize = True

    def __init__(self, cfg: FieldConfig):
        super().__init__()
        self.cfg = cfg
        r = cfg.base_res + 1
        self.base = nn.Parameter(torch.zeros(1, 1, r, r, r))
        self.occ_planes = TriPlane(tuple(cfg.occ_plane_res), cfg.plane_features) if cfg.occ_plane_res else None
        self.occ_head = _mlp(self.occ_planes.out_dim, cfg.hidden, 1, 1, zero_last=True) if cfg.occ_plane_res \
            else None
        self.tex_planes = TriPlane(cfg.plane_res, cfg.plane_features, init_std=1e-1)
        self.tex_head = _mlp(self.tex_planes.out_dim, cfg.hidden, 3, 1)

    @torch.no_grad()
    def init_occupancy(self, logits: torch.Tensor) -> None:
        """Set the dense grid from a (R+1)³ logit volume indexed [x, y, z] over [-1, 1]³."""
        vol = logits.to(self.base).clamp(-self.cfg.logit_clamp, self.cfg.logit_clamp)
        if vol.shape[-1] != self.base.shape[-1]:
            vol = F.interpolate(vol[None, None], size=self.base.shape[-3:], mode="trilinear", align_corners=True)[0, 0]
        # grid_sample indexes volumes as [z, y, x] for coordinates (x, y, z)
        self.base.copy_(vol.permute(2, 1, 0)[None, None])

    @torch.no_grad()
    def resize_base(self, res: int) -> tuple[nn.Parameter, nn.Parameter]:
        """Resample the dense logit grid to ``res`` cells per axis (trilinear, same function); returns
        (old, new) parameter so an optimizer can swap them."""
        old = self.base
        if old.shape[-1] == res + 1:
            return old, old
        vol = F.interpolate(old.data, size=(res + 1,) * 3, mode="trilinear", align_corners=True)
        self.base = nn.Parameter(vol.contiguous())
        return old, self.base

    @property
    def grid_resolution(self) -> int:
        """Cells per axis of the dense logit grid now."""
        return self.base.shape[-1] - 1

    def grid_resolution_in(self, state: dict[str, torch.Tensor]) -> int | None:
        """Cells per axis of the dense logit grid in a state_dict of a GridField."""
        return state["base"].shape[-1] - 1 if "base" in state else None

    def base_logit(self, p: torch.Tensor) -> torch.Tensor:
        """Trilinear lookup of the dense logit grid at points p (M, 3) → (M,) (border values outside [-1, 1]³)."""
        g = p.to(self.base.dtype).view(1, -1, 1, 1, 3)
        return F.grid_sample(self.base, g, mode="bilinear", padding_mode="border", align_corners=True).view(-1)

    def occupancy(self, p: torch.Tensor) -> torch.Tensor:
        """Occupancy logit at points p (M, 3) → (M,) (clipped to the support plane when there is one)."""
        logit = self.base_logit(p)
        if self.occ_planes is not None:
            logit = logit + self.occ_head(self.occ_planes(p)).view(-1)
        return self.clip_to_support(p, logit)

    def texture(self, p: torch.Tensor) -> torch.Tensor:
        """RGB in [0, 1] at points p (M, 3) → (M, 3)."""
        return torch.sigmoid(self.tex_head(self.tex_planes(p)))

    def occupancy_parameters(self) -> list[nn.Parameter]:
        """The dense grid (and the occupancy tri-plane and head when present)."""
        if self.occ_planes is None:
            return [self.base]
        return [self.base, *self.occ_planes.parameters(), *self.occ_head.parameters()]

    def grid_parameters(self) -> list[nn.Parameter]:
        """The dense grid and every tri-plane (the MLP heads are not grids)."""
        occ = [] if self.occ_planes is None else list(self.occ_planes.parameters())
        return [self.base, *occ, *self.tex_planes.parameters()]

    def tv_loss(self) -> torch.Tensor:
        """Mean squared differences between neighbouring cells of the dense grid and the planes."""
        b = self.base
        tv = ((b[..., 1:, :, :] - b[..., :-1, :, :]) ** 2).mean()
        tv = tv + ((b[..., 1:, :] - b[..., :-1, :]) ** 2).mean() + ((b[..., 1:] - b[..., :-1]) ** 2).mean()
        for planes in [] if self.occ_planes is None else self.occ_planes.planes:
            tv = tv + ((planes[..., 1:, :] - planes[..., :-1, :]) ** 2).mean()
            tv = tv + ((planes[..., 1:] - planes[..., :-1]) ** 2).mean()
        return tv


def fourier_encode(p: torch.Tensor, freqs: torch.Tensor) -> torch.Tensor:
    """Points (..., 3) with the sines and cosines of ``freqs`` (L,) × each coordinate → (..., 3 + 6 L), in the
    dtype of ``freqs``."""
    x = p[..., None] * freqs.to(p.dtype)
    return torch.cat([p, torch.sin(x).flatten(-2), torch.cos(x).flatten(-2)], dim=-1).to(freqs.dtype)


class FourierMLPField(Field):
    """Reference: plain MLPs on Fourier-encoded xyz (occupancy + texture). One resolution: no ``resize_base``."""

    supports_resize = False

    def __init__(self, cfg: FieldConfig):
        super().__init__()
        self.cfg = cfg
        self.register_buffer("freqs", 2.0 ** torch.arange(cfg.mlp_frequencies) * torch.pi)
        d = 3 + 6 * cfg.mlp_frequencies
        self.occ = _mlp(d, cfg.hidden, 1, cfg.mlp_layers)
        self.tex = _mlp(d, cfg.hidden, 3, cfg.mlp_layers)
        self.prior_radius = 0.5
        with torch.no_grad():  # start near a sphere of radius 0.5 (logit > 0 inside)
            self.occ[-1].bias.fill_(0.0)

    def _enc(self, p: torch.Tensor) -> torch.Tensor:
        return fourier_encode(p, self.freqs)

    def occupancy(self, p: torch.Tensor) -> torch.Tensor:
        """Occupancy logit (M,): the MLP plus a sphere prior of radius ``prior_radius``, support-clipped."""
        sphere = 10.0 * (self.prior_radius - p.norm(dim=-1))
        return self.clip_to_support(p, self.occ(self._enc(p)).view(-1) + sphere.to(self.freqs.dtype))

    def texture(self, p: torch.Tensor) -> torch.Tensor:
        """RGB in [0, 1] at points p (M, 3) → (M, 3)."""
        return torch.sigmoid(self.tex(self._enc(p)))

    @torch.no_grad()
    def init_occupancy(self, logits: torch.Tensor) -> None:
        """Ignored: the reference starts from its sphere prior."""
        return None

    def occupancy_parameters(self) -> list[nn.Parameter]:
        """The occupancy MLP."""
        return list(self.occ.parameters())

    def grid_parameters(self) -> list[nn.Parameter]:
        """None: every parameter is an MLP weight."""
        return []

    def tv_loss(self) -> torch.Tensor:
        """Exactly 0 (no grid to regularise)."""
        return torch.zeros((), device=self.freqs.device)


def make_field(cfg: FieldConfig) -> Field:
    """Build the field named by ``cfg.kind``."""
    if cfg.kind == "grid":
        return GridField(cfg)
    if cfg.kind == "mlp":
        return FourierMLPField(cfg)
    raise ValueError(f"unknown field kind '{cfg.kind}' (use 'grid' or 'mlp')")


def evaluate_in_chunks(fn: Callable[[torch.Tensor], torch.Tensor], points: torch.Tensor, chunk: int = 65536,
                       trailing_shape: tuple[int, ...] = (), dtype: torch.dtype | None = None) -> torch.Tensor:
    """``fn`` over ``points`` (M, ...) in chunks of at most ``chunk`` rows, concatenated: fn(points) in bounded memory.

    ``fn`` maps (m, ...) rows to (m, *trailing_shape) results (e.g. ``field.occupancy``: (), ``field.texture``:
    (3,)). An empty input returns ``torch.zeros(0, *trailing_shape, dtype=dtype)`` on the points' device without
    calling ``fn`` (``dtype`` None: torch's default). Gradient mode is the caller's (wrap in ``torch.no_grad()``).
    """
    if chunk < 1:
        raise ValueError(f"chunk must be ≥ 1, got {chunk}")
    if points.shape[0] == 0:
        return torch.zeros((0, *trailing_shape), dtype=dtype, device=points.device)
    return torch.cat([fn(points[s : s + chunk]) for s in range(0, points.shape[0], chunk)])


def central_difference_gradient(logit_fn: Callable[[torch.Tensor], torch.Tensor], p: torch.Tensor,
                                h: float) -> torch.Tensor:
    """∇f at points p (M, 3) → (M, 3) by central differences of step ``h`` (one call of ``logit_fn`` on 6M points)."""
    offs = torch.eye(3, dtype=p.dtype, device=p.device) * h
    pts = torch.cat([p + o for o in offs] + [p - o for o in offs], dim=0)
    v = logit_fn(pts).view(6, -1)
    return (v[:3] - v[3:]).T / (2 * h)


def finite_difference_normals(logit_fn: Callable[[torch.Tensor], torch.Tensor], p: torch.Tensor,
                              h: float = 5e-3) -> torch.Tensor:
    """Unit outward normals −∇f/|∇f| by central differences (differentiable, no double backward)."""
    g = central_difference_gradient(logit_fn, p, h)
    n = -g / g.norm(dim=-1, keepdim=True).clamp_min(1e-6)
    return n

