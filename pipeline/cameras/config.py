"""Options of the ``cameras`` stage."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from dvr.options import PositiveFloat, PositiveInt


@dataclass
class CamerasConfig:
    """Camera poses from the photos by structure from motion (stage cameras)."""

    max_side_sfm: PositiveInt = 1600
    """Longest image side (px) SfM works at; larger photos are downscaled to it, never upscaled."""
    sift_upsample_below: PositiveInt = 1000
    """SIFT finds features on the photos upsampled twice when SfM sees them smaller than this (px): 3× the time."""
    sift_upsample_features: int = 1500
    """Larger photos are upsampled too when SIFT finds fewer features than this in the median photo (0: never)."""
    max_side: PositiveInt = 400
    """Longest side (px) of the training images written to images/."""
    video_frames: PositiveInt = 48
    """Frames taken from a video given as --images: the sharpest of each of this many equal stretches of it."""
    matching: Literal["auto", "exhaustive", "similar", "sequential"] = "auto"
    """Image pairs to match: auto = every pair up to 40 photos, beyond that each photo with its most similar ones."""
    pair_neighbours: PositiveInt = 15
    """With matching similar (auto beyond 40 photos): the photos each photo is matched with, the most similar first."""
    start_rung: Literal["default", "guided", "dsp", "relaxed", "global", "merge"] = "default"
    """First rung of the SfM ladder; a later rung runs only when the previous one leaves the model short."""
    last_rung: Literal["default", "guided", "dsp", "relaxed", "global", "merge"] = "merge"
    """Last rung the SfM ladder may climb to (default: a single COLMAP run)."""
    sfm_seconds: PositiveFloat = 60.0
    """Time budget of the SfM ladder: this many seconds plus sfm-seconds-per-photo for each photo."""
    sfm_seconds_per_photo: PositiveFloat = 4.0
    """The SfM ladder's budget per photo; at its end the mapper stops and the best model so far is kept."""
    enough_registered: float = 0.9
    """A model that registers this fraction of the photos ends the ladder; the photos it lacks are left out."""
    global_mapper: bool = True
    """Where the incremental mapper leaves photos out, map the same matches with COLMAP's global mapper too."""
    global_agreement_deg: PositiveFloat = 5.0
    """The global mapper's views whose rotations differ from the incremental mapper's by more are dropped."""
    regroup: bool = True
    """Where views see the model's points in front of what they observe, or it cannot hold a pair's many matches (an
    object with the same pattern on two sides, photos joined at its wrong side), map again without the pairs that
    join them; the better model is kept."""
    max_reprojection_error: float = 1.0
    """Mean reprojection error (px) above which a model counts as short and the ladder climbs."""
    max_bad_pose_fraction: float = 0.3
    """Reject a model when more than this fraction of its views fail the pose check; fewer are dropped."""
    seed: int = 0
    """Random seed of COLMAP's mapper, its RANSAC and the re-triangulation."""
    deterministic: bool = True
    """Map on one thread, so the same photos give the same cameras; off: all cores, faster, not repeatable."""
    triangulate_given: bool = True
    """With --given-cameras: triangulate matched features at the given poses; off: the cameras alone, no points."""
    camera_model: str = "SIMPLE_RADIAL"
    """COLMAP camera model fitted to the photos, which are then undistorted (e.g. SIMPLE_RADIAL, PINHOLE, OPENCV)."""
    pinhole_tolerance: float = 0.1
    """Use a pinhole model when its reprojection error is at most this fraction larger; negative: keep SfM's fit."""
    final_passes: int = 0
    """Robust bundle-adjustment passes after mapping, at any rung of the ladder; 0: off."""
    climbed_passes: int = 3
    """Passes for a model from a later rung of the ladder, when more than final-passes; 0: final-passes alone."""
    climbed_retriangulate: bool = True
    """Re-triangulate points after the climbed passes where these leave the object too few; off: never."""
    final_error_ratio: PositiveFloat = 2.5
    """Each final pass drops observations above this multiple of the model's mean reprojection error."""
    final_retriangulate: bool = False
    """After the final passes, triangulate the points afresh from every match at the adjusted poses."""
    max_features: PositiveInt = 8192
    """SIFT features per image at the ladder's first rung (later rungs 16k); beyond 30 photos fewer in proportion."""
    max_h_inlier_ratio: float = 0.8
    """Two-view check: a pair whose homography explains more than this share of its inliers counts as planar."""
    object_matches: bool = True
    """Large photos whose model leaves the object under 20 points: verify matches again and re-triangulate."""
    object_verification: Literal["ransac", "poses"] = "ransac"
    """How object-matches verifies: ransac (each pair's geometry again) or poses (the model's poses, faster)."""
    min_registered_fraction: float = 0.5
    """Fail when fewer than this fraction of the photos register (the unregistered ones are listed)."""
    radius_margin: PositiveFloat = 1.3
    """Radius of the object's sphere as a multiple of the sparse points' robust radius."""
    min_track_length: PositiveInt = 3
    """Sparse points that size the object's sphere need at least this many observations."""
    support: bool = True
    """Find the floor or table the object stands on (no floor: the wall it hangs on); later stages treat it and all
    behind it as background."""
    plain_support: bool = True
    """No support in the SfM points: look in the photos for a plain one (a white table) under the object's base."""
    board: bool = True
    """Look for a printed ChArUco board; when seen, cameras and meshes are in metres and it is the floor."""
    board_squares: tuple[int, int] = (5, 7)
    """Squares of the printed board (columns, rows)."""
    board_square_mm: PositiveFloat = 35.0
    """Side of one board square as printed (mm): measure it with a ruler."""
    board_marker_mm: PositiveFloat = 26.0
    """Side of one ArUco marker of the board as printed (mm), smaller than a square."""
    board_dictionary: str = "DICT_4X4_50"
    """ArUco dictionary of the board's markers (an OpenCV name, e.g. DICT_4X4_50, DICT_5X5_100)."""
