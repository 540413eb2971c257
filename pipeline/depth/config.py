"""Options of the ``depth`` stage."""

from __future__ import annotations

from dataclasses import dataclass

from dvr.options import PositiveInt


@dataclass
class DepthConfig:
    """Sparse depth from SfM tracks (stage ``depth``)."""

    min_track_length: PositiveInt = 3
    """Keep points observed in at least this many images."""
    max_reprojection_error: float = 1.5
    """Keep points whose mean reprojection error (px, SfM resolution) is at most this."""
