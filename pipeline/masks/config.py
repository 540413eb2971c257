"""Options of the ``masks`` stage."""

from __future__ import annotations

from dataclasses import dataclass

from dvr.options import Fraction, PositiveFloat, PositiveInt


@dataclass
class MasksConfig:
    """Object masks: automatic (GrabCut with multi-view voting) or the user's (stage masks)."""

    hull_res: PositiveInt = 128
    """Resolution (cells per axis) of the visual hull used for multi-view consistency."""
    carve_min_views: int = 2
    """A point is background only when at least this many views see it outside their mask."""
    carve_fraction: Fraction = 0.0
    """A point is background only when this share of the views that see it, too, see it outside their mask; 0: off."""
    carve_fraction_px: float = 10.0
    """With carve_fraction: it holds within this many pixels of a view's mask (farther: carve_min_views); 0: all."""
    keep_min_views: int = 3
    """No visual hull carves a sparse point inside the object's sphere that this many views observe; 0: off."""
    settle_height: float = 0.08
    """The hull's parts lower than this above the support plane (unit-sphere radii) rest on it; 0: off."""
    vote_rounds: int = 2
    """Rounds of multi-view voting: the hull of the current masks, then GrabCut inside its silhouette."""
    floor_rounds: int = 6
    """With a floor: at most this many more rounds that clear the floor seen under the object; 0: off."""
    floor_band: float = 0.35
    """Height above the floor (unit-sphere radii) under which a pixel's ray must pass for the floor rounds."""
    floor_settle: float = 0.002
    """The floor rounds stop once a round changes fewer than this fraction of the masks' object pixels."""
    grabcut_iters: int = 5
    """GrabCut iterations of the first pass (from the geometry's seeds)."""
    round_iters: int = 5
    """GrabCut iterations per pass in the vote and floor rounds (inside the hull's bound)."""
    grabcut_margin: float = 0.05
    """GrabCut's box around the uncertain pixels, widened by this fraction of the image side; 1: whole image."""
    seed_radius: int = 2
    """Radius (px) of the disc drawn around each projected SfM point used as a seed."""
    seed_max_error: float = 1.0
    """Seed only from observations within this multiple of the mean reprojection error; 0: every observation."""
    band_px: int = 3
    """Half-width (px) of the uncertain band around the hull silhouette in the refinement pass."""
    user_threshold: int = 127
    """User masks: grey values (0–255) above this are object."""
    stereo: bool = True
    """Seed GrabCut with plane-sweep stereo evidence (helps where the object has the backdrop's colours)."""
    even_exposure: bool = True
    """Even out the photos' exposure differences (measured by the cameras stage) for the stereo's comparison."""
    stereo_scale: PositiveFloat = 0.5
    """Image scale the plane sweep runs at (1: the training images' size)."""
    stereo_depths: PositiveInt = 32
    """Depth hypotheses of the plane sweep (uniform in inverse depth)."""
    stereo_ratio: float = 0.5
    """The stereo labels a pixel when its best cost on one side is below this fraction of the other side's."""
    footprint_margin: float = 0.1
    """Floor seen past the object's footprint plus this (unit-sphere radii) is background; negative: off."""
    footprint_min_points: int = 100
    """Sparse points on the object needed to take its footprint from them (fewer: from the visual hull)."""
    footprint_hull_height: float = 0.1
    """Footprint from the visual hull: its cells higher than this above the floor (unit-sphere radii); 0: off."""
    footprint_union: bool = True
    """Hard background only beyond both the points' footprint and the hull's; off: beyond the points' alone."""
    saliency: bool = False
    """A salient-object model votes in the masks always (off: where saliency_check asks); the views' vote decides."""
    saliency_check: Fraction = 0.07
    """Redo the masks with saliency when its model sees more than this share of their area beyond them; 0: off."""
    speck_fraction: float = 0.001
    """Automatic masks: fill holes and drop islands smaller than this fraction of the image."""
