"""Options of the ``texture`` stage."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from dvr.options import PositiveInt


@dataclass
class TextureConfig:
    """UV texturing from the photos (stage texture)."""

    size: PositiveInt = 2048
    """Largest texture side (texels); the atlas is sized by texel-density up to this."""
    texel_density: float = 1.5
    """Texels per photo pixel on the object, where the photos see it best; 0: fill a size × size atlas."""
    padding: int = 4
    """Texels between charts in the atlas."""
    gutter: int = 8
    """Texels of colour dilated around every chart."""
    angle_power: float = 2.0
    """Weight each view by the cosine between normal and view direction to this power (higher: more frontal)."""
    min_cos: float = 0.1
    """Ignore views that see a surface at a cosine below this (too grazing)."""
    depth_tolerance: float = 0.01
    """A texel counts as visible when its depth is within this of the rendered depth (normalized units)."""
    edge_px: int = 1
    """Photo pixels within this distance (px) of a depth edge or silhouette count as edge pixels."""
    edge_weight: float = 0.02
    """Weight factor of samples on edge pixels (they mix object and background)."""
    silhouette_px: int = 0
    """Pixels within this distance (px) of the mesh's outline colour only texels nothing else sees; 0: off."""
    edge_fallback_only: bool = True
    """Edge-pixel samples colour only texels no clean sample sees; off: they blend in at edge-weight."""
    outlier_threshold: float = 0.1
    """Colour distance (0–1) scale of the robust pass that keeps one view's highlight or occluder out; 0: off."""
    outlier_reject: float = 3.0
    """Drop samples farther than this × outlier-threshold from the robust colour (texels seen by 3+ views)."""
    clipped_level: float = 0.98
    """With per-view gains: photo values (0–1) at or above this count as over-exposed; above 1: off."""
    clipped_weight: float = 0.01
    """Weight factor of samples on over-exposed pixels (and their neighbours)."""
    sharpness_power: float = 0.5
    """Prefer sharp views: weight × (1 + contrast / sharpness-floor) to this power; 0: off."""
    sharpness_floor: float = 2.0
    """Local contrast below which a view counts as flat (weak texture barely changes the weights)."""
    view_selection: bool = False
    """Colour each face from one chosen photo, blended at chart borders; off: every view blends by weight."""
    selection_smoothness: float = 1.0
    """View selection: cost of a change of view between adjacent faces (higher: fewer, larger charts)."""
    selection_sharpness: float = 2.0
    """View selection: sharpness power of its choice of view (needs sharpness-power > 0)."""
    selection_rings: int = 2
    """View selection: rings of faces over which two charts' views blend at their border; 0: hard seams."""
    selection_floor: float = 0.02
    """View selection: weight factor of the views a face did not select."""
    seam_levelling: bool = True
    """Level colour steps between views (exposure, white balance) so they do not show as seams."""
    seam_smoothness: float = 10.0
    """Seam levelling: weight of equal offsets at the two ends of a mesh edge (higher: smoother)."""
    seam_zero_pull: float = 0.01
    """Seam levelling: weight of the pull of every offset towards 0."""
    seam_fit_texels: int = 200000
    """Seam levelling: texels (a fixed random sample) the offsets are fitted on."""
    normal_map: bool = True
    """Bake a tangent-space normal map of the trained field's normals (a light mesh shades like the full one)."""
    occlusion_reach: float = 0.2
    """Ambient-occlusion map: how far (working-sphere radii) the field is searched for what shades a point; 0: none."""
    levels_from_photos: bool = False
    """Bake each detail level from the photos (slower); off: a level takes the default mesh's colours."""
    frame: Literal["sfm", "normalized"] = "sfm"
    """Frame of the textured outputs: sfm (that of cameras.npz) or normalized (unit sphere)."""
    device: str = "auto"
    """Device of the texture field that colours unseen texels: auto, cpu or cuda."""
