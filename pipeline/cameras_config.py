"""Configs of the stages cameras, masks, depth and texture (apart from their modules, so that config.py and
the CLI do not import pycolmap or xatlas)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal


@dataclass
class CamerasConfig:
    """Camera estimation (stage ``cameras``)."""

    max_side_sfm: int = 1600
    """Longest image side SfM works on (photos are downscaled to it, never upscaled)."""
    max_side: int = 400
    """Longest side of the training images written to images/."""
    matching: Literal["auto", "exhaustive", "sequential"] = "auto"
    """Pairs to match: 'auto' = exhaustive up to 80 images, sequential (with loop closure off) beyond."""
    start_rung: Literal["default", "guided", "dsp", "relaxed", "global", "merge"] = "default"
    """First rung of the SfM ladder: default SIFT → guided matching → DSP-SIFT + affine shape → relaxed mapper →
    global mapper → merge (the best model so far absorbs the photos it lacks). A rung runs only when the one before
    left the model short (a photo unregistered, a poor reprojection error or track length, too few points per
    view) or with poses that fail the sanity check."""
    last_rung: Literal["default", "guided", "dsp", "relaxed", "global", "merge"] = "merge"
    """Last rung of the SfM ladder ('default': one COLMAP run, as before the ladder)."""
    max_reprojection_error: float = 1.0
    """A model whose mean reprojection error (px) exceeds this is short: the ladder climbs."""
    max_bad_pose_fraction: float = 0.3
    """A model in which more than this fraction of the views fail the pose sanity check (axes that miss the
    object the others converge on, or two sides of a symmetric scene merged) is rejected as a whole; fewer such
    views are dropped from it (and listed as unregistered)."""
    seed: int = 0
    """Random seed of COLMAP's mapper."""
    triangulate_given: bool = True
    """With given cameras (--cameras FILE): match SIFT features and triangulate them at the given poses, so the
    later stages get sparse depth, the support plane and SfM tracks as after our own SfM (about 10 s for 36 photos
    of 400×300); off: the given cameras alone, no points."""
    camera_model: str = "SIMPLE_RADIAL"
    """COLMAP camera model estimated before undistortion."""
    pinhole_tolerance: float = 0.1
    """After SfM the pinhole model (distortion 0, focal length and poses re-adjusted) replaces the fitted lens
    distortion when its mean reprojection error is at most this fraction larger: on object-centric captures
    distortion and focal length trade off (a pinhole render came out with k = 0.11 and an 11 % long focal length
    at the same error). Negative: keep whatever SfM fits."""
    max_features: int = 8192
    """SIFT features per image on the first rung (later rungs: at least 16 k)."""
    min_registered_fraction: float = 0.5
    """Fail when fewer images than this fraction register (the list of unregistered images is printed)."""
    radius_margin: float = 1.3
    """Unit sphere radius = margin × robust object radius from the sparse points (the points sample the object
    sparsely: at 1.1 the corners of a plate and the cow's hooves fell outside, and masks and hull cut them)."""
    min_track_length: int = 3
    """Sparse points used for normalisation need at least this many observations."""
    support: bool = True
    """Find the surface the object stands on (a robust plane fit of the SfM points: horizontal, under the cameras,
    under the point they converge on, around the object); every later stage then treats it as background and
    nothing below it as object. Without one (held, hung, plain backdrop), nothing changes."""
    board: bool = True
    """Look for a printed ChArUco board in the photos (``python -m pipeline board board.png`` prints one). When its
    corners are seen, the SfM frame becomes the board's: cameras.npz, points and meshes in metres (origin at the
    board's centre, z up), the board's plane is the support plane, and ``board.json`` says what was found. No
    board seen: nothing changes."""
    board_squares: tuple[int, int] = (5, 7)
    """Squares of the printed board (columns, rows)."""
    board_square_mm: float = 35.0
    """Side of one board square as printed (mm): measure it with a ruler; the metric scale is exactly as good."""
    board_marker_mm: float = 26.0
    """Side of one ArUco marker of the board as printed (mm), smaller than a square."""
    board_dictionary: str = "DICT_4X4_50"
    """ArUco dictionary of the board's markers (an OpenCV name, e.g. DICT_4X4_50, DICT_5X5_100)."""


@dataclass
class MasksConfig:
    """Object masks (stage ``masks``)."""

    hull_res: int = 128
    """Resolution of the visual hull used for multi-view consistency."""
    carve_min_views: int = 2
    """A point is background only if at least this many views see it outside their mask."""
    vote_rounds: int = 2
    """Rounds of multi-view voting (hull of the current masks → GrabCut inside its silhouette)."""
    grabcut_iters: int = 5
    """GrabCut iterations per pass."""
    seed_radius: int = 2
    """Radius (px) of the disc drawn around each projected seed point."""
    band_px: int = 3
    """Half-width of the uncertain band around the hull silhouette in the refinement pass."""
    user_threshold: int = 127
    """User masks: grey values above this are object."""
    stereo: bool = True
    """Seed GrabCut with plane-sweep stereo evidence: photo-consistent inside the object sphere → object,
    beyond it → background (works where the object has the backdrop's colours)."""
    stereo_scale: float = 0.5
    """Image scale the plane sweep runs at (its labels are only seeds)."""
    stereo_depths: int = 32
    """Depth hypotheses of the plane sweep (uniform in inverse depth)."""
    stereo_ratio: float = 0.5
    """A pixel is labelled when its best cost on one side is below this fraction of the other side's."""
    speck_fraction: float = 0.001
    """Holes and islands of an automatic mask smaller than this fraction of the image are filled / dropped (seed
    noise); larger holes stay."""


@dataclass
class DepthConfig:
    """Sparse depth from SfM tracks (stage ``depth``)."""

    min_track_length: int = 3
    """Keep points observed in at least this many images."""
    max_reprojection_error: float = 1.5
    """Keep points whose mean reprojection error (px, SfM resolution) is at most this."""


@dataclass
class TextureConfig:
    """UV texturing from the photos (stage ``texture``)."""

    size: int = 2048
    """Largest texture side in texels (the atlas is sized by ``texel_density`` up to this)."""
    texel_density: float = 1.5
    """Texels per unit length on the object per photo pixel, where the photos see it best: the texture holds
    what the photos hold (400×300 photos need no 2048² atlas; 1.0 cost 0.16 dB held-out PSNR against 1.5 on the
    book scene, 2048² gained 0.1 dB in 7× the time); 0: always ``size``."""
    padding: int = 4
    """Texels between charts in the atlas."""
    gutter: int = 8
    """Texels of colour dilated around every chart."""
    angle_power: float = 4.0
    """Sharpness of the view weighting by the cosine between normal and viewing direction."""
    min_cos: float = 0.1
    """Views seeing a surface more grazing than this cosine are ignored."""
    depth_tolerance: float = 0.01
    """Visibility test: |texel depth − rendered depth| below this (normalized units) counts as visible."""
    edge_px: int = 1
    """Photo pixels within this distance of a depth discontinuity or silhouette count as edge pixels."""
    edge_weight: float = 0.02
    """Weight factor of samples that use an edge pixel (they blend foreground and background in real photos)."""
    silhouette_px: int = 0
    """Photo pixels within this distance of the mesh's silhouette against the background (where the mesh is a
    little too large they show the background: the fringe) count only for texels nothing else sees, and those
    texels then take the fallback colour (texture field, else the nearest seen texel). 0: off, they count as edge
    pixels. 1 removes the fringe on a 3 % too large mesh but costs 0.7 dB at one held-out view of the exact-geometry
    cow (its silhouette pixels are right there), so it is off by default until measured on real captures."""
    edge_fallback_only: bool = True
    """Samples that use an edge pixel count only for texels that no clean sample sees (else they blend in at
    ``edge_weight``): background colour beside a silhouette does not reach a texel another view sees cleanly."""
    outlier_threshold: float = 0.1
    """Photo-consistency: a second blending pass weights every sample by 1 / (1 + (d / this)²), d its RMS colour
    distance to the texel's robust colour (per channel, the mean without the largest and smallest sample), so a
    highlight, shadow or occluder one view alone sees does not reach the texture; 0: off."""
    outlier_reject: float = 3.0
    """Samples farther than this × ``outlier_threshold`` from the robust colour are dropped where 3 or more views
    see the texel."""
    sharpness_power: float = 0.5
    """Prefer sharp views: weights × (1 + c / ``sharpness_floor``)^this, c the photo's local contrast per unit
    length on the surface (blurred Sobel magnitude × focal / distance; lower in a defocused or shaken view); 0: off."""
    sharpness_floor: float = 2.0
    """Contrast (grey levels of 1 per normalized unit) below which a view counts as flat: weak texture barely
    changes the weights."""
    view_selection: bool = False
    """Discrete view selection (:mod:`pipeline.view_select`): one photo per face, the sharpest, most frontal, closest
    photo-consistent one, under a Potts smoothness so charts come from few views, blended with its neighbours' views
    at chart borders; the other views keep ``selection_floor`` of their weight. Off: every view blends by weight."""
    selection_smoothness: float = 1.0
    """Potts weight: cost of a label change between two adjacent faces, in units of −log of the data term's ratio
    to the face's best view (1: a view e times weaker is taken to spare one border edge)."""
    selection_sharpness: float = 2.0
    """Sharpness power of the selection's data term (as ``sharpness_power`` for the blend; the selection's choice
    between two views rests on it). Needs ``sharpness_power`` > 0 (the sharpness maps)."""
    selection_rings: int = 2
    """Rings of neighbouring faces over which the views of two charts blend at their border (0: hard seams)."""
    selection_floor: float = 0.02
    """Weight factor of the views a face did not select (they colour texels the chosen view does not see)."""
    seam_levelling: bool = True
    """Global seam levelling: per view an RGB offset per mesh vertex, solved in least squares (scipy sparse) so that
    overlapping views agree, added to the view's samples before blending (exposure, white balance and lighting
    steps between views do not become seams)."""
    seam_smoothness: float = 10.0
    """Weight of equal offsets at the two ends of a mesh edge, per sample of data (larger: smoother offsets)."""
    seam_zero_pull: float = 0.01
    """Weight of the pull of every offset towards 0, per sample of data (keeps the problem well posed)."""
    seam_fit_texels: int = 200000
    """Texels (drawn with a fixed seed) the offsets are fitted on; all texels get them."""
    frame: Literal["sfm", "normalized"] = "sfm"
    """Frame of the textured outputs: 'sfm' (that of cameras.npz) or 'normalized'."""
    device: str = "auto"
    """Device of the texture field used for unseen texels."""
