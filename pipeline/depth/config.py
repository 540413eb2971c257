"""Options of the ``depth`` stage."""

from __future__ import annotations

from dataclasses import dataclass

from dvr.options import PositiveInt


@dataclass
class DepthConfig:
    """Sparse depth maps from the SfM points (stage depth)."""

    min_track_length: PositiveInt = 3
    """Keep points observed in at least this many images."""
    max_reprojection_error: float = 1.5
    """Keep points whose mean reprojection error is at most this (px, at the SfM resolution)."""
