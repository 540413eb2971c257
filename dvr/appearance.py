"""Per-view appearance: the colour transform each photo's camera applied (exposure, white balance).

Real photos differ from view to view (auto exposure and white balance), and a texture field shared by all views
averages that into mud while the geometry bends to explain it. Each view v gets a per-channel gain,

    c_v = exp(g_v) ⊙ c,

applied to the shared texture field's colour before the RGB loss, starting at identity (g = 0) and regularised
towards it. No offset: exposure and white balance are gains, and a gain and an offset per view trade against each
other on the few colours one object shows (with both, the fitted gains came out 8 % off the true ones on a
mid-grey scene; gain only: 1.4 %, `tests/dvr/test_appearance.py`). A gain in linear light is also a gain after the
camera's gamma curve ((g·x)^γ = g^γ·x^γ), so the model fits sRGB photos as well as the renderer's linear ones.
The field should keep the colour of the average view (what the held-out views see), but the regulariser fixes
the common scale only softly: where the field cannot reach the brightest colours, every view's gain drifts the same
way (1.07 / 1.05 / 1.01 on a cow photographed with no exposure change at all). So whoever uses the gains takes
them relative to their per-channel geometric mean over the views (:func:`relative_gains`): the texture bake divides
each photo by its relative gain and scales the field's colours by the common gain.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn as nn


class ViewAppearance(nn.Module):
    """Per-view per-channel log-gains ``log_gain`` (N, 3), identity at start."""

    def __init__(self, n_views: int):
        super().__init__()
        if n_views < 1:
            raise ValueError(f"ViewAppearance needs at least one view, got {n_views}")
        self.log_gain = nn.Parameter(torch.zeros(n_views, 3))

    def forward(self, colour: torch.Tensor, view: torch.Tensor) -> torch.Tensor:
        """Colours (M, 3) of the shared field as view ``view`` (M,) (long) photographed them."""
        if colour.ndim != 2 or colour.shape[-1] != 3:
            raise ValueError(f"colour must be (M, 3), got {tuple(colour.shape)}")
        if view.shape != colour.shape[:1] or view.dtype != torch.long:
            raise ValueError(f"view must be (M,) long, got {tuple(view.shape)} {view.dtype}")
        return colour * torch.exp(self.log_gain[view])

    def regulariser(self) -> torch.Tensor:
        """Mean squared log-gain: pulls every view towards identity, and fixes the overall scale that the field
        and the gains could otherwise trade (the field keeps the average view's colour)."""
        return (self.log_gain ** 2).mean()

    def gains(self) -> torch.Tensor:
        """Per-view per-channel gains (N, 3)."""
        return torch.exp(self.log_gain.detach())

    def undo(self, colour: torch.Tensor, view: int) -> torch.Tensor:
        """A photo's colours (..., 3) of view ``view`` mapped back to the shared field's (the bake divides by the gain
        relative to the average view instead, :func:`relative_gains`)."""
        return colour / torch.exp(self.log_gain[view].detach())


def relative_gains(gains: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-view gains (N, 3) split into gains relative to the average view (N, 3) and the common gain (3,): their
    per-channel geometric mean over the views, the part of the gains that the field and the gains could trade."""
    gains = np.asarray(gains, np.float64)
    if gains.ndim != 2 or gains.shape[1] != 3 or len(gains) == 0:
        raise ValueError(f"relative_gains: gains must be (N, 3) with N ≥ 1, got {gains.shape}")
    if not (np.isfinite(gains).all() and (gains > 0).all()):
        raise ValueError("relative_gains: gains must be finite and positive")
    common = np.exp(np.log(gains).mean(0))
    return gains / common, common
