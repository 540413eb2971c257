"""Whole-image rendering of a trained field (no autograd): previews and held-out evaluation."""

from __future__ import annotations

import torch

from dvr.data import SceneData
from dvr.fields import Field
from dvr.march import find_surface


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
