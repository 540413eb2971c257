"""Options of the ``masks`` stage."""

from __future__ import annotations

from dataclasses import dataclass

from dvr.options import PositiveFloat, PositiveInt


@dataclass
class MasksConfig:
    """Object masks (stage ``masks``)."""

    hull_res: PositiveInt = 128
    """Resolution of the visual hull used for multi-view consistency."""
    carve_min_views: int = 2
    """A point is background only if at least this many views see it outside their mask."""
    vote_rounds: int = 2
    """Rounds of multi-view voting (hull of the current masks → GrabCut inside its silhouette)."""
    floor_rounds: int = 6
    """With a support plane, after the vote rounds: at most this many more (0: off), which change only the pixels
    whose ray passes under the object lower than ``floor_band`` (:func:`low_band`). The floor between an object's
    legs lies in its shadow and only the views along the legs see it, so the first masks take it and the GLB gets
    a web between the legs; each round's hull carves what the last round freed, and the web goes in two or three
    rounds (the cow from photos, one SfM mapping, `balanced`, three training seeds: mask IoU 0.9929 → 0.9963,
    F-score 0.980 → 0.990, Chamfer 0.29 → 0.27 %, held-out PSNR within the seeds' spread, mean 25.94 → 25.92 dB;
    with 16 views the band's dark hooves erode a little, IoU 0.9888 → 0.9883). More rounds everywhere also carve
    thin parts that a few views miss (the floating cow's horn tips: IoU 0.9870 → 0.9831 after 6 rounds), hence
    the band."""
    floor_band: float = 0.35
    """Height above the support plane (unit-sphere radii) under which a pixel's ray must pass the object's vertical
    axis for the floor rounds to change it."""
    floor_settle: float = 0.002
    """The floor rounds stop once a round changes fewer than this fraction of the masks' object pixels."""
    grabcut_iters: int = 5
    """GrabCut iterations per pass. Fewer save little: 5 → 3 → 2 took the masks stage 34.8 → 33.1 → 28.0 s on the
    cow (IoU 0.9963 → 0.9960 → 0.9960), 34.7 → 31.2 → 24.1 s on the jar (0.9965 → 0.9963 → 0.9960), 29.8 → 25.7 →
    25.5 s on the book (0.9955 → 0.9953 → 0.9949); one saved mapping each, stop 43."""
    grabcut_margin: float = 0.05
    """GrabCut runs on the bounding box of each view's pixels that are not certain background (in the floor rounds:
    of those in the low band), widened by this fraction of the image's larger side (its background colour model
    then learns the colours near the object); 1: the whole image. 0.05 against the whole image, before the floor
    rounds' box, one saved mapping each (stop 44): the masks stage 38.2 → 30.9 s on the cow (again, in the other
    order: 36.2 → 32.5 s; IoU 0.9963 → 0.9967), 34.2 → 29.7 s on the jar (0.9965 → 0.9963), 30.7 → 27.3 s on the
    book (0.9955 → 0.9966); DTU, whose building fills the frames, 63.3 → 64.7 s. The floor rounds' box then: cow
    28.7 → 27.2 s (IoU 0.9973), jar 27.3 → 26.2 s (0.9964), book 23.3 → 22.9 s (0.9965)."""
    seed_radius: int = 2
    """Radius (px) of the disc drawn around each projected seed point."""
    seed_max_error: float = 1.0
    """Seed only from the SfM observations that reproject within this multiple of the model's mean reprojection
    error (0: every observation). A wrong match lets a view "observe" a backdrop point that lies behind the object,
    and its hard background disc cuts the object there: the floating cow's masks lost a horn in four views (IoU
    0.9859 with every observation; 1.0: 0.9979, 2.5: 0.9904), where the cow, jar and book on their floors go
    0.9946 → 0.9952, 0.9964 → 0.9964, 0.9937 → 0.9953 with 1.0 (one saved mapping each)."""
    band_px: int = 3
    """Half-width of the uncertain band around the hull silhouette in the refinement pass."""
    user_threshold: int = 127
    """User masks: grey values above this are object."""
    stereo: bool = True
    """Seed GrabCut with plane-sweep stereo evidence: photo-consistent inside the object sphere → object,
    beyond it → background (works where the object has the backdrop's colours)."""
    even_exposure: bool = True
    """The stereo compares the photos evened out by the exposure gains the cameras stage measured (exposure.json):
    an auto-exposed capture's colours differ by 10–30 % between photos (the cow at ±25 %: IoU 0.976 → 0.997)."""
    stereo_scale: PositiveFloat = 0.5
    """Image scale the plane sweep runs at (its labels are only seeds)."""
    stereo_depths: PositiveInt = 32
    """Depth hypotheses of the plane sweep (uniform in inverse depth)."""
    stereo_ratio: float = 0.5
    """A pixel is labelled when its best cost on one side is below this fraction of the other side's."""
    footprint_margin: float = 0.1
    """With a support plane: pixels that see past the object's footprint (the convex hull of its sparse points on
    the plane, widened by this many unit-sphere radii, up to the sphere's top) are background seeds — the table
    in front of an object, however much it has the object's colours. Negative: off."""
    footprint_min_points: int = 100
    """The footprint needs at least this many sparse points on the object (fewer need not span it)."""
    footprint_hull_height: float = 0.1
    """With fewer points than that (a weakly textured object), the footprint is that of the visual hull of the
    first masks: its cells higher than this above the plane (unit-sphere radii; the table the masks took lies
    below it, as the low views carve the space above it). 0: off."""
    footprint_union: bool = True
    """With the footprint from sparse points: the first masks take beyond the points' prism as only probably
    background (:func:`soften_beyond`), and the vote rounds, as hard background, what lies beyond the union of it
    and the first masks' hull footprint (:func:`united_footprint`). The points' prism cuts what overhangs it without
    points of its own (the cow's plain ear tips: held-out 21.7 dB, with this 24.6), the hull's misses an object
    lying flat below ``footprint_hull_height`` (the book: 24.7 → 18.6 dB); the union keeps both (book, DTU and the
    checkered sphere on its board level). Off: the points' prism alone, hard background beyond it from the start."""
    speck_fraction: float = 0.001
    """Holes and islands of an automatic mask smaller than this fraction of the image are filled / dropped (seed
    noise); larger holes stay."""
