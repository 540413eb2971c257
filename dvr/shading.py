"""View-dependent shading in training: what a diffuse texture cannot show (highlights that move with the camera).

A diffuse texture field gives every view the same colour at a surface point, but a glossy object reflects its
lights into the views near the mirror direction only. Left to the diffuse field, the highlights are averaged into
the texture and the geometry bends to put them where the views agree least badly. In training a small residual

    c(p, d) = c_diffuse(p) + r(p, d),    r = max_shading · tanh(MLP(fourier(p), ω_r, SH(ω_r), n·d)),

explains them instead (Ref-NeRF's idea, small): ω_r = d − 2 (d·n) n is the ray reflected about the surface normal,
so a highlight of a distant light is a function of ω_r (the MLP shapes its lobe from ω_r and its spherical harmonics
of degree ≤ 2), modulated over the surface by low-frequency Fourier features of the point (glossy parts, not
texture detail). The normals come in detached: shading does not shape the geometry through them. The last layer
starts at zero (identity), and an L1 pull towards zero (:meth:`ViewShading.regulariser`) keeps everything the views
agree on in the diffuse field. Only the diffuse field is baked and exported: the GLB shows the object without the
photos' highlights.
"""

from __future__ import annotations

import torch
import torch.nn as nn

from dvr.fields import fourier_encode
from dvr.losses import safe_mean


def sh_degree2(dirs: torch.Tensor) -> torch.Tensor:
    """Real spherical harmonics of degree ≤ 2 (9 values, orthonormal constants) of unit directions (M, 3)."""
    x, y, z = dirs.unbind(-1)
    return torch.stack([
        torch.full_like(x, 0.28209479177387814),
        0.4886025119029199 * y, 0.4886025119029199 * z, 0.4886025119029199 * x,
        1.0925484305920792 * x * y, 1.0925484305920792 * y * z,
        0.31539156525252005 * (3.0 * z * z - 1.0),
        1.0925484305920792 * x * z, 0.5462742152960396 * (x * x - y * y),
    ], -1)


def reflect(dirs: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
    """Directions (M, 3) reflected about unit normals (M, 3): d − 2 (d·n) n."""
    return dirs - 2.0 * (dirs * normals).sum(-1, keepdim=True) * normals


class ViewShading(nn.Module):
    """Residual colour ``r(p, d, n)`` (M, 3) added to the diffuse field's in training; zero at start."""

    def __init__(self, hidden: int = 32, n_freqs: int = 2, max_shading: float = 0.5):
        super().__init__()
        if hidden < 1 or n_freqs < 0 or max_shading <= 0:
            raise ValueError(f"ViewShading: hidden ≥ 1, n_freqs ≥ 0, max_shading > 0; got {hidden}, {n_freqs}, "
                             f"{max_shading}")
        self.max_shading = max_shading
        self.register_buffer("freqs", 2.0 ** torch.arange(n_freqs) * torch.pi, persistent=False)
        self.net = nn.Sequential(nn.Linear(3 + 6 * n_freqs + 3 + 9 + 1, hidden), nn.ReLU(),
                                 nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, 3))
        nn.init.zeros_(self.net[-1].weight)
        nn.init.zeros_(self.net[-1].bias)

    def forward(self, points: torch.Tensor, dirs: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
        """Residual colours (M, 3) at surface points (M, 3) seen along unit ray directions (M, 3), with the surface's
        unit normals (M, 3) there."""
        if points.ndim != 2 or points.shape[-1] != 3 or dirs.shape != points.shape or normals.shape != points.shape:
            raise ValueError(f"ViewShading: points, dirs and normals must all be (M, 3), got {tuple(points.shape)}, "
                             f"{tuple(dirs.shape)} and {tuple(normals.shape)}")
        r = reflect(dirs, normals)
        x = torch.cat([fourier_encode(points, self.freqs), r, sh_degree2(r),
                       (dirs * normals).sum(-1, keepdim=True)], -1)
        return self.max_shading * torch.tanh(self.net(x))

    @staticmethod
    def regulariser(residual: torch.Tensor) -> torch.Tensor:
        """Mean absolute residual (0 for none): what the views agree on belongs to the diffuse field."""
        return safe_mean(residual.abs())
