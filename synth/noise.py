"""Procedural value noise, shared by the object's albedo and the ground's patterns."""

from __future__ import annotations

import numpy as np


def procedural_noise(p: np.ndarray, scale: float, seed: int, levels: int = 0) -> np.ndarray:
    """Multi-scale colour noise on 3-D points, (M, 3) in [0, 1]. ``levels`` > 0 quantises each channel to
    that many steps: sharp edges and corners, which SIFT needs to register views."""
    rng = np.random.default_rng(seed)
    out = np.zeros((p.shape[0], 3))
    for c in range(3):
        acc = np.zeros(p.shape[0])
        for k in range(24):
            f = scale * 2 ** rng.uniform(0, 3.0)
            v = rng.normal(size=3)
            v /= np.linalg.norm(v)
            acc += np.sin(f * 2 * np.pi * (p @ v) + rng.uniform(0, 2 * np.pi)) / (1 + 0.3 * k) ** 0.5
        val = 0.5 + 0.5 * np.tanh(acc / 2.0)
        if levels > 0:
            val = (np.floor(val * levels) + 0.5) / levels
        out[:, c] = val
    return out
