"""Options of the ``mesh`` stage."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from dvr.options import PositiveInt


@dataclass
class MeshConfig:
    """Surface extraction and cleaning (stage mesh)."""

    resolution: PositiveInt = 256
    """Marching-cubes cells per axis over the working sphere's [-1, 1] cube (fine level)."""
    coarse_factor: PositiveInt = 4
    """The coarse level has resolution / this cells per axis; only cells near the surface are refined."""
    refine_steps: int = 2
    """Newton steps moving the vertices onto the surface; 0: off."""
    min_component_ratio: float = 0.02
    """Drop pieces with fewer faces than this fraction of the largest piece."""
    floater_support: float = 0.1
    """Drop a piece carrying fewer SfM points than this fraction of what its area should carry; 0: off."""
    floater_distance: float = 0.02
    """An SfM point lies on the mesh within this distance of its surface (working-sphere radii)."""
    footprint: float = 0.03
    """Below this height above the floor (working-sphere radii) the mesh is extruded straight down; 0: off."""
    smooth_iterations: int = 0
    """Taubin smoothing iterations of the clean mesh; 0: off."""
    max_faces: PositiveInt = 40000
    """Decimate the clean mesh to at most this many faces."""
    detail: str = ""
    """Detail levels also written (comma-separated): preview, reduced, medium, full (25k–250k faces), raw."""
    drop_unseen: bool = False
    """Remove the faces no photo sees (the back, the underside): an open mesh; off: one closed surface."""
    unseen_hole_ratio: float = 0.01
    """With drop-unseen: unseen patches smaller than this fraction of the mesh's faces stay."""
    unseen_rings: int = 2
    """With drop-unseen: rings of faces by which the seen part is opened (no shreds at its edge); 0: off."""
    frame: Literal["sfm", "normalized"] = "sfm"
    """Frame of the written meshes: sfm (that of cameras.npz; metres with a board) or normalized (unit sphere)."""
    device: str = "auto"
    """Device: auto (CUDA when present), cpu or cuda."""
