"""Options of the ``mesh`` stage."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from dvr.options import PositiveInt


@dataclass
class MeshConfig:
    """Isosurface extraction and cleaning (stage ``mesh``)."""

    resolution: PositiveInt = 256
    """Marching-cubes cells per axis over [-1, 1] (fine level)."""
    coarse_factor: PositiveInt = 4
    """The coarse level is resolution / coarse_factor; only cells near the surface are refined."""
    refine_steps: int = 2
    """Newton steps moving vertices onto the level set (0: off)."""
    min_component_ratio: float = 0.02
    """Drop connected components with fewer faces than this fraction of the largest."""
    floater_support: float = 0.1
    """Drop a connected piece other than the largest as a floater when fewer SfM points (``points.ply``) lie on
    it than this fraction of what the largest piece's density of points (per unit area) would put there, where that
    is at least 10 points. A real part of the object is seen and matched as the rest of it is; a piece no point lies
    on explains some views' colours at a depth where nothing is (DTU: a 6000-face slab of roof hung above the house
    with 0 of the 270–330 points its area would carry, and a piece of wall at the sphere's edge with 0 of about 40,
    while the house carries 2018 of the 2179 points in the sphere). 0: off; no effect without points."""
    floater_distance: float = 0.02
    """A point lies on the mesh within this distance of its surface (working-sphere radii)."""
    footprint: float = 0.03
    """Height above the support plane (working-sphere radii) below which the mesh is the vertical extrusion of its
    cross-section at that height: the object meets its floor or table with the footprint of what stands just above,
    where automatic masks lose the lowest strip to the contact shadow (the lying book from photos: 23.4 → 24.3 dB
    held-out; cow, jar and DTU within ±0.03 dB). 0: off; no effect without a support plane."""
    smooth_iterations: int = 0
    """Taubin smoothing iterations of the clean mesh (0: off)."""
    max_faces: PositiveInt = 40000
    """Decimate the clean mesh to at most this many faces (quadric edge collapse)."""
    drop_unseen: bool = False
    """Remove the faces that no pixel centre of any photo sees first (ray-cast through every pixel of every view in
    cameras.npz): the back of an object photographed from one side, which otherwise closes along the working sphere
    and takes the texture field's guessed colours, and the underside where it stands. The mesh is then open, as
    photogrammetry's is; off: one closed surface."""
    unseen_hole_ratio: float = 0.01
    """With ``drop_unseen``: a patch of unseen faces with fewer faces than this fraction of the mesh's stays (a pit
    or a face between two pixels' rays inside what the photos see: a hole there is a tear, not the open back)."""
    unseen_rings: int = 2
    """With ``drop_unseen``: the seen faces are opened by this many rings of faces (eroded, then grown back within
    what is seen), so strips narrower than twice that, glimpsed at grazing angles beyond the outline, go with the
    unseen side instead of hanging off the edge as shreds (DTU: 67 open loops 31.8 working-sphere radii long → 2, 12.3).
    0: every seen face stays."""
    frame: Literal["sfm", "normalized"] = "sfm"
    """Frame of the written meshes: 'sfm' (the frame of cameras.npz) or 'normalized' (unit sphere)."""
    device: str = "auto"
    """'auto' (CUDA when present), 'cpu' or 'cuda'."""
