"""Options of the ``cameras`` stage."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from dvr.options import PositiveFloat, PositiveInt


@dataclass
class CamerasConfig:
    """Camera estimation (stage ``cameras``)."""

    max_side_sfm: PositiveInt = 1600
    """Longest image side SfM works on (photos are downscaled to it, never upscaled)."""
    max_side: PositiveInt = 400
    """Longest side of the training images written to images/."""
    video_frames: PositiveInt = 48
    """Frames taken from a video given instead of a photo folder (``--images clip.mp4``): the sharpest of each of
    this many equal stretches of the clip, into frames/ (``pipeline/inputs/video.py``)."""
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
    """Random seed of COLMAP's mapper, its geometric verification's RANSAC and the re-triangulation."""
    deterministic: bool = True
    """Run COLMAP (features, matching, mapping) on one thread: the same photos then give the same cameras, and the
    whole pipeline the same mesh. On all cores its runs differ (two runs of the cow's 40 photos: pose matrices
    1–3e-3 apart; over the bench's runs the floating cow scored 16.8–23 dB held-out, the jar 32.0–34.1); one
    thread costs the cow's cameras stage 14 → 21 s (1600×1200: 120 → 176 s). Off: all cores. The object matches'
    verification again (``object_verification`` "ransac") runs on all cores either way: its RANSAC is seeded per
    pair, and the result is the same on any number of threads."""
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
    final_passes: int = 0
    """Passes of a final bundle adjustment after mapping (0: off, the model as mapped; 3 to use it): each drops the
    observations more than ``final_error_ratio`` × the mean reprojection error off and re-adjusts with a robust
    (Cauchy) loss. Where the camera model is exact it halves the pose error (a rendered cow: rotation 0.057° →
    0.030°). One SfM mapping each, with and without the passes (held-out PSNR, default preset; stop 27's saved
    mappings, then the bench's one-thread mappings of stop 28): the cow +0.4 / +0.54 dB (`balanced` +0.6 / +0.72),
    the floating cow +6.0 / +8.1, the jar −0.2 / −1.36, the book −0.4 / −0.74, DTU −1.05 (stop 28) (the passes
    take a quarter to half of the book's sparse depths with them; see ``final_retriangulate``). Degrees mislead:
    the jar's rotation error falls (0.070 → 0.051°) while its held-out views' picture of the object moves further
    from the truth (0.13 → 0.19 px, ``bench/object_px.py``), and held-out photos are rendered at the poses SfM gave
    them; with each held-out camera re-aimed onto its photo (``bench/reaim.py``, stop 42) the jar gains 0.17 dB
    and the cow 1.06, but the book loses 0.63 and DTU 0.64 in the mesh itself. On real photos the error tail is
    partly model misfit (DTU's principal point is off-centre). Off by default for a model from the ladder's first
    rung; a later rung's model gets ``climbed_passes``."""
    climbed_passes: int = 3
    """Passes of the final adjustment (as ``final_passes``, whichever is more) for a model that a later rung of the
    ladder gave: the first rung's model fell short, and the later rungs' features (16 k, guided matching, DSP-SIFT)
    fit looser (the cameras table: 0.7–0.85 px mean reprojection error against 0.33–0.6 px at the first rung). The
    four synthetic captures that climb, one SfM mapping each (stop 30), held-out PSNR (default preset) as mapped →
    passes → passes and points re-triangulated: the floating cow (dsp) 17.00 → 20.50 → 20.43 dB, the cow on a
    parquet (dsp) 21.99 → 22.61 → 18.61, the cow's 16 views (dsp) 24.05 → 16.70 → 24.97, the jar's 24 views of
    320×240 (dsp) 32.26 → 32.89 → 32.53 (``bench/pair.py``; ``climbed_retriangulate`` picks the column). The
    scenes that lose by the passes (jar, book, DTU: −0.7 to −1.4 dB) map at the first rung. 0: no passes but
    ``final_passes``."""
    climbed_retriangulate: bool = True
    """After the climbed passes (``climbed_passes``), triangulate the points afresh (as ``final_retriangulate``)
    where the passes take the object's sphere below the 20 points it is fitted to (points seen inside most views,
    ``SPHERE_MIN_POINTS``) and the model as mapped had them: the passes take points with the observations they
    drop, and where views are few the object's own go (the cow's 16 views: 22 → 7, the sphere falls back to the
    images' bound, about 1.7× larger; masks 0.984 → 0.954 IoU, held-out 24.05 → 16.70 dB; re-triangulated
    24.97). Elsewhere re-triangulating does harm: from every match, the parquet's regular planks bring wrong
    matches back (0.32 → 0.96 px), no support plane is found and the masks take the floor (IoU 0.99 → 0.48,
    held-out 22.61 → 18.61 dB); the floating cow and the jar's 24 views lose 0.07 and 0.36 dB (figures under
    ``climbed_passes``). Off: never after the climbed passes."""
    final_error_ratio: PositiveFloat = 2.5
    """Observations above this multiple of the model's mean reprojection error are dropped in each final pass."""
    final_retriangulate: bool = False
    """After the final passes, triangulate the points afresh from every match at the adjusted poses (COLMAP's point
    triangulator; poses unchanged). The passes drop a quarter to half of the object's sparse depths with the
    observations (the cow 212 → 110, the book 7768 → 5879); this brings them back (208, 7777) and the book's held-out
    PSNR with the passes 23.68 → 24.40 dB (24.09 without the passes). The observations it brings back include
    wrong matches, whose points the masks stage draws as hard background seeds: without masks.seed-max-error (now
    on by default) they cut a horn out of four of the floating cow's masks (IoU 0.9986 → 0.9874, 22.82 → 18.32
    dB; with it 22.53 dB). Off by default, as are the passes: the weakly textured jar loses by it (32.10 → 31.6 dB
    with the passes)."""
    max_features: PositiveInt = 8192
    """SIFT features per image on the first rung (later rungs: at least 16 k)."""
    max_h_inlier_ratio: float = 0.8
    """Two-view verification (COLMAP's ``max_H_inlier_ratio``, its 0.8): a pair whose homography explains more than
    this fraction of its epipolar inliers is "planar", and keeps the homography's inliers when they outnumber them.
    1.0 everywhere broke the floating cow (its far backdrop's pairs, nearly a pure rotation, then count as general:
    mask IoU 0.987 → 0.938, 20.5 → 12.0 dB); ``object_matches`` uses it only where needed."""
    object_matches: bool = True
    """Photos twice the working size or larger (a phone's), and a model that leaves the object's sphere fewer than 20
    sparse points (:data:`SPHERE_MIN_POINTS`, :data:`LARGE_PHOTOS`): verify the stored matches again
    (``object_verification``) and triangulate the points again at the same poses. An object on a textured floor
    photographed larger than the working size: most of a pair's matches lie on the floor, the pair is "planar",
    and it keeps the homography's inliers — the floor's alone. The cow on its floor at 1200 × 900: 7 points on the
    object (28 verified object matches in all pairs; 346 again), so its sphere came from the floor's points (twice
    too large) and the masks lost its legs (IoU 0.955)."""
    object_verification: Literal["ransac", "poses"] = "ransac"
    """How ``object_matches`` verifies the stored matches again: "ransac" estimates each pair's geometry again with
    ``max_h_inlier_ratio`` 1.0 (33 s for the 190 pairs of 20 photos of 960 × 720); "poses" keeps each pair's matches
    within the epipolar error of the model's known relative pose (COLMAP's guided verifier, no RANSAC: 0.2 s there),
    faster and a little less accurate: the cow's 40 photos of 1200 × 900, cameras stage 318 → 184 s, held-out
    26.04 → 25.56 dB (as JPEGs 354 → 211 s, 24.96 → 24.63 dB); the ``fast`` preset uses it."""
    min_registered_fraction: float = 0.5
    """Fail when fewer images than this fraction register (the list of unregistered images is printed)."""
    radius_margin: PositiveFloat = 1.3
    """Unit sphere radius = margin × robust object radius from the sparse points (the points sample the object
    sparsely: at 1.1 the corners of a plate and the cow's hooves fell outside, and masks and hull cut them)."""
    min_track_length: PositiveInt = 3
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
    board_square_mm: PositiveFloat = 35.0
    """Side of one board square as printed (mm): measure it with a ruler; the metric scale is exactly as good."""
    board_marker_mm: PositiveFloat = 26.0
    """Side of one ArUco marker of the board as printed (mm), smaller than a square."""
    board_dictionary: str = "DICT_4X4_50"
    """ArUco dictionary of the board's markers (an OpenCV name, e.g. DICT_4X4_50, DICT_5X5_100)."""
