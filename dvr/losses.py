"""DVR losses. Every loss is a MEAN over the rays or points it applies to (never a sum that grows with the
batch), and an empty subset gives an exact 0 that still belongs to the graph — no 0/0 = NaN."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def safe_mean(values: torch.Tensor) -> torch.Tensor:
    """Mean of ``values``; 0 for an empty tensor (the guard that keeps empty masks from giving NaN)."""
    if values.numel() == 0:
        return values.sum()  # 0, keeps dtype/device/graph
    return values.mean()


def rgb_loss(pred: torch.Tensor, target: torch.Tensor, clipped_level: float = float("inf")) -> torch.Tensor:
    """L1 between predicted and observed colours of rays that hit where the mask is set, (M, 3) each. An observed
    channel at or above ``clipped_level`` is over-exposed: it says only that the colour is at least that bright, so
    a brighter prediction costs nothing there (censored L1; what lets a view photographed brighter, through its
    per-view gain, agree with one photographed darker)."""
    if pred.shape != target.shape:
        raise ValueError(f"rgb_loss: pred {tuple(pred.shape)} vs target {tuple(target.shape)}")
    diff = pred - target
    residual = torch.where(target >= clipped_level, (-diff).clamp_min(0.0), diff.abs())
    return safe_mean(residual.mean(-1))


def freespace_loss(logits: torch.Tensor) -> torch.Tensor:
    """BCE towards occupancy 0 (stable for any logit: log-sum-exp form)."""
    return safe_mean(F.binary_cross_entropy_with_logits(logits, torch.zeros_like(logits), reduction="none"))


def occupancy_loss(logits: torch.Tensor) -> torch.Tensor:
    """BCE towards occupancy 1."""
    return safe_mean(F.binary_cross_entropy_with_logits(logits, torch.ones_like(logits), reduction="none"))


def depth_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """L1 between rendered and sparse depths (same ray-depth definition)."""
    if pred.shape != target.shape:
        raise ValueError(f"depth_loss: pred {tuple(pred.shape)} vs target {tuple(target.shape)}")
    return safe_mean((pred - target).abs())


def normal_smoothness_loss(n1: torch.Tensor, n2: torch.Tensor) -> torch.Tensor:
    """Mean distance between unit normals at surface points and at nearby points."""
    return safe_mean((n1 - n2).norm(dim=-1))


def psnr(pred: torch.Tensor, target: torch.Tensor) -> float:
    """PSNR in dB for colours in [0, 1]; +inf-safe (MSE floored at 1e-10)."""
    if pred.numel() == 0:
        return float("nan")
    mse = ((pred.detach() - target.detach()) ** 2).mean().clamp_min(1e-10)
    return float(-10.0 * torch.log10(mse))
