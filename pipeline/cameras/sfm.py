"""Structure from motion with an escalation ladder: start cheap, climb only while the model is short.

Each rung is a set of COLMAP settings an expert would try next on a capture that default SIFT starves (small
images, weakly textured objects, grazing views of a floor):

1. ``default``   SIFT (8 k features), every pair matched (for many photos each photo with its most similar ones,
                 :mod:`pipeline.cameras.pairs`), incremental mapping;
2. ``guided``    16 k features and guided matching (matches re-searched along the epipolar lines);
3. ``dsp``       DSP-SIFT with affine shape estimation (descriptors pooled over scales, robust to the affine
                 distortion of slanted surfaces), guided matching;
4. ``relaxed``   the same matches, mapper thresholds relaxed (fewer inliers to start and to register a view);
5. ``global``    the same matches, the global mapper (GLOMAP: rotation averaging + global positioning);
6. ``merge``     the best model so far absorbs the photos it lacks: incremental mapping continued from it (its own
                 features and matches, relaxed thresholds), so the photos of the partial models the mapper split
                 off register into the largest one (COLMAP's own merging needs photos common to both models,
                 which its partial models do not share).

A rung is *short* when a photo is unregistered, the reprojection error or track length is poor, or a view has too
few points (:func:`shortfalls`); its model then goes through the pose sanity check (:mod:`pipeline.cameras.pose_sanity`)
and the next rung runs. The first rung without shortfalls wins; otherwise the best sane model. Features and
matches are reused between rungs that share them. Every rung runs in a child process: a native crash inside
COLMAP (seen in poselib on a symmetric scene) fails that rung, not the stage.
"""

from __future__ import annotations

import json
import os
import shutil
import sqlite3
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from pipeline.cameras.progress import wait_with_progress

RUNG_NAMES = ("default", "guided", "dsp", "relaxed", "global", "merge")
KILL_GRACE = 15.0
"""Seconds past its deadline a rung may take to finish (the incremental mapper stops itself at the deadline)."""


@dataclass(frozen=True)
class Rung:
    """COLMAP settings of one rung."""

    name: str
    max_features: int = 8192
    dsp: bool = False
    guided: bool = False
    relaxed: bool = False
    mapper: str = "incremental"
    upsample: bool = True
    """SIFT starts from the photo upsampled twice (COLMAP's first octave -1); off for large photos (:func:`ladder`)."""
    pair_neighbours: int = 15
    """With matching ``similar``: each photo is matched with this many of its most similar photos."""
    max_h_inlier_ratio: float = 0.8
    """COLMAP's two-view verification: a pair whose homography explains more than this fraction of its epipolar
    inliers is "planar", and then keeps the homography's inliers when they are more (``cameras.max_h_inlier_ratio``;
    :func:`pipeline.cameras.mapping.keep_object_matches` verifies the stored matches again with 1.0)."""

    @property
    def features_key(self) -> str:
        """Name of the feature database this rung extracts into (rungs with the same features share it)."""
        return f"f{self.max_features}{'-dsp' if self.dsp else ''}{'' if self.upsample else '-o0'}"

    @property
    def matches_key(self) -> str:
        """Name of the match database this rung matches into (rungs with the same matches share it)."""
        return f"{self.features_key}{'-guided' if self.guided else ''}-h{self.max_h_inlier_ratio:g}"


LADDER = (
    Rung("default"),
    Rung("guided", max_features=16384, guided=True),
    Rung("dsp", max_features=16384, dsp=True, guided=True),
    Rung("relaxed", max_features=16384, dsp=True, guided=True, relaxed=True),
    Rung("global", max_features=16384, dsp=True, guided=True, mapper="global"),
    Rung("merge", max_features=16384, dsp=True, guided=True, relaxed=True, mapper="extend"),
)


MANY_PHOTOS = 30
"""Beyond this many photos every rung extracts fewer features (:func:`ladder`): matching all pairs costs the photo
count squared times the feature count squared."""
MIN_FIRST_FEATURES = 4096
"""The first rung's features per photo are never cut below this for many photos (the blowtorch's 67 photos: 4096
features match in 150 s where 8192 take 340 s; the first rung poses the same photos with either)."""
UPSAMPLE_BELOW = 1000
"""SIFT upsamples the photos SfM sees only when their longest side is below this (px) by default
(``cameras.sift-upsample-below``): a 1600-px photo has features enough at its own size, found in a third of the
time."""
PAIRS_PER_BLOCK = 50
"""Matching ``similar`` matches the pairs in blocks of this many."""
SIMILAR_PAIRS_ABOVE = 40
"""Matching ``auto`` matches every pair up to this many photos; beyond, each photo with its most similar ones
(:mod:`pipeline.cameras.pairs`)."""


def ladder(start: str, stop: str, max_features: int = 8192, max_h_inlier_ratio: float = 0.8,
           n_photos: int = 0, sfm_side: int = 0, pair_neighbours: int = Rung.pair_neighbours,
           upsample_below: int = UPSAMPLE_BELOW) -> list[Rung]:
    """The rungs from ``start`` to ``stop`` (names of :data:`RUNG_NAMES`), in order; the first rung extracts
    ``max_features`` features, the others at least twice that and 16 k; for ``n_photos`` more than
    :data:`MANY_PHOTOS` each rung that many fewer in proportion (matching them all then costs what it costs for
    :data:`MANY_PHOTOS`), the first rung not below :data:`MIN_FIRST_FEATURES` (nor above ``max_features``), the
    others never below the first rung's; every rung verifies its matches with ``max_h_inlier_ratio``
    (:class:`Rung`) and upsamples the photos for SIFT only when their longest side ``sfm_side`` is below
    ``upsample_below`` (0: unknown, upsampled), and matches each photo with its ``pair_neighbours`` most similar
    ones where the matching picks pairs by similarity."""
    for name in (start, stop):
        if name not in RUNG_NAMES:
            raise ValueError(f"unknown SfM rung '{name}' (one of {', '.join(RUNG_NAMES)})")
    if start == "merge":
        raise ValueError("the SfM rung 'merge' continues from an earlier rung's model; start at another rung")
    i, j = RUNG_NAMES.index(start), RUNG_NAMES.index(stop)
    if j < i:
        raise ValueError(f"the last SfM rung '{stop}' comes before the first '{start}'")
    first, more = max_features, max(16384, 2 * max_features)
    if n_photos > MANY_PHOTOS:
        def fewer(n: int) -> int:
            return 1024 * round(n * MANY_PHOTOS / n_photos / 1024)

        first = max(min(max_features, MIN_FIRST_FEATURES), fewer(max_features))
        more = max(first, fewer(more))
    return [replace(r, max_features=first if r.name == "default" else more, max_h_inlier_ratio=max_h_inlier_ratio,
                    upsample=sfm_side < upsample_below, pair_neighbours=pair_neighbours) for r in LADDER[i : j + 1]]


UPSAMPLE_COST = 3.0
"""SIFT on the photos upsampled twice takes about this many times as long (the blowtorch's 67 photos: 170 s, 57 s)."""
DSP_COST = 3.0
"""DSP-SIFT with affine shapes takes about this many times plain SIFT's time."""
GUIDED_COST = 3.5
"""Guided matching takes about this many times plain matching's time at the same features (the blowtorch's 589
pairs of 7168 features: over 240 s, its last blocks 65 s and more each, where 4096 features take 23.5 s unguided)."""


def rung_seconds(done: Rung, steps: dict, nxt: Rung) -> float:
    """Seconds the rung ``nxt`` will take, estimated from the rung ``done``, whose steps took ``steps`` seconds
    (``features``, ``matching``, ``mapping``): the features and matches it does not share with ``done``, features in
    proportion to SIFT's work, matches to the features' count squared (every feature of one photo against every one
    of the other's), and its mapping in proportion to the features."""
    if nxt.mapper == "extend":  # continues from a model with its own features and matches
        return 0.0
    features = 0.0
    if nxt.features_key != done.features_key:
        features = steps.get("features", 0.0) * (UPSAMPLE_COST ** (nxt.upsample - done.upsample)) * (
            DSP_COST ** (nxt.dsp - done.dsp))
    matching = 0.0
    if nxt.matches_key != done.matches_key:
        matching = steps.get("matching", 0.0) * (nxt.max_features / done.max_features) ** 2 * (
            GUIDED_COST ** (nxt.guided - done.guided))
    return features + matching + steps.get("mapping", 0.0) * nxt.max_features / done.max_features


# ----------------------------------------------------------------------------- one rung (child process)
def _extract(db: Path, images: Path, groups: list[list[str]], rung: Rung, camera_model: str,
             per_image: bool = False, threads: int = -1) -> None:
    """The rung's features into ``db``: one shared camera per group of images (a phone's portrait and landscape
    shots: two), or ``per_image`` a camera each; on ``threads`` threads (-1: all cores)."""
    from pipeline.colmaplib import pycolmap

    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    ext = pycolmap.FeatureExtractionOptions()
    ext.sift.max_num_features = rung.max_features
    ext.sift.domain_size_pooling = rung.dsp
    ext.sift.estimate_affine_shape = rung.dsp
    ext.sift.first_octave = -1 if rung.upsample else 0
    ext.num_threads = threads
    mode = pycolmap.CameraMode.PER_IMAGE if per_image else pycolmap.CameraMode.SINGLE
    for names in groups:
        pycolmap.extract_features(db, images, image_names=names, camera_mode=mode, reader_options=reader,
                                  extraction_options=ext)
    number_by_name(db)


PROBE_PHOTOS = 8
""":func:`median_features` extracts the features of this many of the photos."""


def median_features(work: Path, images: Path, names: list[str], rung: Rung, threads: int = -1) -> float:
    """SIFT's feature count in the median photo with ``rung``'s settings, from up to :data:`PROBE_PHOTOS` of the
    photos ``names`` (evenly spaced in their order) in ``images``: how much texture SIFT finds at that size. A
    white mouse on a white table gives 675 at 1600 px, a brass blowtorch on a carpet 5289."""
    sample = names[:: max(1, len(names) // PROBE_PHOTOS)][:PROBE_PHOTOS]
    db = work / "probe.db"
    db.unlink(missing_ok=True)
    _extract(db, images, [[f"{n}.png" for n in sample]], rung, "SIMPLE_RADIAL", per_image=True, threads=threads)
    con = sqlite3.connect(db)
    try:
        counts = [row[0] for row in con.execute("SELECT rows FROM keypoints")]
    finally:
        con.close()
    db.unlink()
    return float(np.median(counts)) if counts else 0.0


def number_by_name(db: Path) -> None:
    """Give the database's images (and their frames) ids in the order of their names. COLMAP numbers photos as
    its extraction threads finish them, so on several threads the ids, and with them the mapper's choices, would
    differ from run to run although each photo's features do not."""
    con = sqlite3.connect(db)
    try:
        old = [row[0] for row in con.execute("SELECT image_id FROM images ORDER BY name")]
        if old == sorted(old):
            return
        frames = dict(con.execute("SELECT data_id, frame_id FROM frame_data WHERE sensor_type = 0"))
        shift = 1 + max(old + list(frames.values()))  # two passes: no id is taken twice on the way
        new = {o: shift + i + 1 for i, o in enumerate(old)}
        with con:
            for table, column in (("images", "image_id"), ("keypoints", "image_id"), ("descriptors", "image_id"),
                                  ("frame_data", "data_id")):
                where = " AND sensor_type = 0" if table == "frame_data" else ""
                for o, n in new.items():
                    con.execute(f"UPDATE {table} SET {column} = ? WHERE {column} = ?{where}", (n, o))
            for o, n in new.items():
                if o in frames:
                    con.execute("UPDATE frames SET frame_id = ? WHERE frame_id = ?", (n, frames[o]))
                    con.execute("UPDATE frame_data SET frame_id = ? WHERE frame_id = ?", (n, frames[o]))
            for table, column in (("images", "image_id"), ("keypoints", "image_id"), ("descriptors", "image_id"),
                                  ("frame_data", "data_id"), ("frames", "frame_id"), ("frame_data", "frame_id")):
                con.execute(f"UPDATE {table} SET {column} = {column} - ? WHERE {column} > ?", (shift, shift))
    finally:
        con.close()


def match_features(db: Path, n_images: int, rung: Rung, matching: str, seed: int, threads: int = -1) -> None:
    """Match and verify the pairs ``matching`` names: every pair (``exhaustive``), each photo with the next ones
    in name order (``sequential``), each with the rung's ``pair_neighbours`` most similar (``similar``,
    :func:`pipeline.cameras.pairs.write_similar_pairs`), or ``auto`` (every pair up to :data:`SIMILAR_PAIRS_ABOVE`
    photos, else the similar ones); ``seed``: the verification's RANSAC seed (with -1, COLMAP verifies guided
    DSP-SIFT matches differently on every run)."""
    from pipeline.colmaplib import pycolmap

    opts = pycolmap.FeatureMatchingOptions()
    opts.guided_matching = rung.guided
    opts.num_threads = threads
    verify = pycolmap.TwoViewGeometryOptions()
    verify.ransac.random_seed = seed
    verify.max_H_inlier_ratio = rung.max_h_inlier_ratio
    if matching == "exhaustive" or (matching == "auto" and n_images <= SIMILAR_PAIRS_ABOVE):
        pycolmap.match_exhaustive(db, matching_options=opts, verification_options=verify)
    elif matching == "sequential":
        pycolmap.match_sequential(db, matching_options=opts, verification_options=verify)
    else:
        from pipeline.cameras.pairs import write_similar_pairs

        pairing = pycolmap.ImportedPairingOptions()
        pairing.match_list_path = str(db.with_name(db.stem + "-pairs.txt"))
        pairing.block_size = PAIRS_PER_BLOCK  # COLMAP logs each block: the progress lines count them
        n_pairs = write_similar_pairs(db, Path(pairing.match_list_path), rung.pair_neighbours)
        print(f"Matching {n_pairs} pairs of similar photos ({rung.pair_neighbours} per photo)", flush=True)
        pycolmap.match_image_pairs(db, matching_options=opts, pairing_options=pairing, verification_options=verify)


def _map(db: Path, images: Path, out: Path, rung: Rung, seed: int, base: str = "", threads: int = -1,
         deadline: float | None = None, min_mapping: float = 0.0) -> dict:
    """Map with the rung's mapper; ``base``: a model folder to continue from (the ``extend`` mapper); ``deadline``
    (time.time()): the incremental mapper stops there, or after ``min_mapping`` seconds when that is later, and
    returns the photos it registered so far."""
    from pipeline.colmaplib import pycolmap

    if rung.mapper == "global":
        opts = pycolmap.GlobalPipelineOptions()
        opts.random_seed = opts.mapper.random_seed = seed  # the global mapper's own options: set both levels
        opts.num_threads = opts.mapper.num_threads = threads
        return pycolmap.global_mapping(db, images, out, opts)
    opts = pycolmap.IncrementalPipelineOptions()
    opts.random_seed = seed
    opts.num_threads = threads
    if deadline is not None:
        opts.max_runtime_seconds = max(1, int(max(deadline - time.time(), min_mapping)))
    if rung.relaxed:
        opts.min_model_size = 3
        opts.mapper.init_min_num_inliers = 50
        opts.mapper.init_min_tri_angle = 8.0
        opts.mapper.abs_pose_min_num_inliers = 15
        opts.mapper.abs_pose_min_inlier_ratio = 0.15
    return pycolmap.incremental_mapping(db, images, out, opts, input_path=base)


def _run_rung(work: str, images: str, groups: list[list[str]], rung: dict, camera_model: str, matching: str,
              seed: int, base: list[str] | None = None, threads: int = -1, deadline: float | None = None,
              min_mapping: float = 0.0) -> None:
    """Child process: features (reused when another rung made them), matches (likewise), mapping; the largest
    model is written to ``work/<rung>/model`` and its timings to ``work/<rung>/result.json``. ``base``: (model
    folder, its database) to continue from instead (the ``extend`` mapper), or ("", a database) to map. Features
    and matches use every core whatever ``threads`` says: each photo's features and each pair's matches come out the
    same on any number of threads (each pair's RANSAC is seeded alone; photos are numbered by name,
    :func:`number_by_name`); ``threads`` is the mapper's."""
    from pipeline.colmaplib import info_to_stderr

    info_to_stderr()  # COLMAP's info lines are this rung's log
    r = Rung(**rung)
    work_p, images_p = Path(work), Path(images)
    if base is not None:
        _map_rung(work_p, images_p, r, Path(base[1]), seed, base[0], {"features": 0.0, "matching": 0.0}, threads,
                  deadline, min_mapping)
        return
    t0 = time.perf_counter()
    feats = work_p / f"features-{r.features_key}.db"
    if not feats.exists():
        tmp = feats.with_suffix(".tmp")
        tmp.unlink(missing_ok=True)
        _extract(tmp, images_p, groups, r, camera_model, threads=-1)
        tmp.rename(feats)
    t1 = time.perf_counter()
    db = work_p / f"matches-{r.matches_key}.db"
    if not db.exists():
        tmp = db.with_suffix(".tmp")
        shutil.copy(feats, tmp)
        match_features(tmp, sum(len(g) for g in groups), r, matching, seed, -1)
        tmp.rename(db)
    t2 = time.perf_counter()
    _map_rung(work_p, images_p, r, db, seed, "", {"features": round(t1 - t0, 2), "matching": round(t2 - t1, 2)},
              threads, deadline, min_mapping)


def _map_rung(work: Path, images: Path, r: Rung, db: Path, seed: int, base: str, seconds: dict,
              threads: int = -1, deadline: float | None = None, min_mapping: float = 0.0) -> None:
    """Mapping of one rung; the largest model goes to ``work/<rung>/model``, the timings to ``result.json``."""
    t0 = time.perf_counter()
    out = work / r.name
    shutil.rmtree(out, ignore_errors=True)
    (out / "models").mkdir(parents=True)
    recs = _map(db, images, out / "models", r, seed, base, threads, deadline, min_mapping)
    best = max(recs.values(), key=lambda rec: rec.num_reg_images()) if recs else None
    if best is not None:
        (out / "model").mkdir()
        best.write(out / "model")
    seconds = {**seconds, "mapping": round(time.perf_counter() - t0, 2)}
    from dvr.atomic import write_json

    write_json(out / "result.json", {"database": str(db), "seconds": seconds})  # last, whole: the rung's success


def run_rung(work: Path, images: Path, groups: list[list[str]], rung: Rung, camera_model: str, matching: str,
             seed: int = 0, base: tuple[Path | None, Path] | None = None, threads: int = -1,
             deadline: float | None = None, min_mapping: float | None = None):
    """Run one rung in a child process (``python -m pipeline.cameras.sfm``; COLMAP's log goes to ``work/<rung>.log``,
    a progress line every :data:`~pipeline.messages.PROGRESS_EVERY` s); ``base``: (model folder, its
    database) for the ``extend`` mapper to continue from, or (None, a database) to map that database's matches
    afresh; ``threads``: the mapper's threads (-1: all cores; 1: the
    same photos give the same model); ``deadline`` (time.time()): the incremental mapper stops there with the photos
    it registered, and a rung still running :data:`KILL_GRACE` s later is stopped; ``min_mapping`` (seconds): a rung
    that must give a model (the ladder's first) instead always finishes its features and matches, and its mapper
    has at least this long. Returns (model or None, database
    path, seconds per step, error or None)."""
    from pipeline.colmaplib import pycolmap

    args = [str(work), str(images), groups, asdict(rung), camera_model, matching, seed,
            None if base is None else [str(base[0] or ""), str(base[1])], threads, deadline, min_mapping or 0.0]
    log = work / f"{rung.name}.log"
    with open(log, "w") as f:
        child = [sys.executable, "-m", "pipeline.cameras.sfm", json.dumps(args), str(os.getpid())]  # it ends with us
        p = subprocess.Popen(child, stdout=f, stderr=subprocess.STDOUT, cwd=Path(__file__).resolve().parents[2])
        stop_at = None if deadline is None or min_mapping is not None else deadline + KILL_GRACE
        stopped = wait_with_progress(p, log, rung.name, stop_at)
    res = work / rung.name / "result.json"
    if stopped:
        return None, None, {}, "stopped at the end of the SfM time budget (cameras.sfm-seconds)"
    if p.returncode != 0 or not res.exists():
        from pipeline.colmaplib import raise_if_disk_full

        raise_if_disk_full(log)  # a full disk is the stage's one line, not a reason to climb to the next rung
        why = f"signal {-p.returncode}" if p.returncode < 0 else f"exit code {p.returncode}"
        return None, None, {}, f"COLMAP failed ({why}; see {log})"
    info = json.loads(res.read_text())
    model = work / rung.name / "model"
    rec = pycolmap.Reconstruction(model) if model.exists() else None
    return rec, Path(info["database"]), info["seconds"], None


# ----------------------------------------------------------------------------- given cameras
def triangulate_at(work: Path, images: Path, names: list[str], Ks: np.ndarray, Rs: np.ndarray, ts: np.ndarray,
                   matching: str, max_features: int, seed: int = 0, threads: int = -1,
                   max_h_inlier_ratio: float = 0.8):
    """Sparse points of photos whose cameras are given (``images/<name>.png``; intrinsics for those pixels, world →
    camera poses): the default rung's SIFT features and matches, then COLMAP's point triangulator at the given
    poses (no mapping, no pose refinement). Returns the model; its database is ``work/given.db``."""
    from pipeline.colmaplib import pycolmap, quiet

    work.mkdir(parents=True, exist_ok=True)
    db = work / "given.db"
    db.unlink(missing_ok=True)
    rung = ladder("default", "default", max_features, max_h_inlier_ratio)[0]
    _extract(db, images, [[f"{n}.png" for n in names]], rung, "PINHOLE", per_image=True, threads=threads)
    match_features(db, len(names), rung, matching, seed, threads)
    rec = pycolmap.Reconstruction()
    database = pycolmap.Database.open(str(db))
    try:
        for img in database.read_all_images():
            i = names.index(img.name.rsplit(".", 1)[0])
            cam = database.read_camera(img.camera_id)
            cam.model = pycolmap.CameraModelId.PINHOLE
            cam.params = [Ks[i][0, 0], Ks[i][1, 1], Ks[i][0, 2], Ks[i][1, 2]]
            rec.add_camera_with_trivial_rig(cam)
            image = pycolmap.Image(name=img.name, keypoints=database.read_keypoints(img.image_id)[:, :2],
                                   camera_id=img.camera_id, image_id=img.image_id)
            rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(Rs[i]), ts[i]))
    finally:
        database.close()
    out = work / "model"
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir()
    with quiet():
        return pycolmap.triangulate_points(rec, db, images, out)


# ----------------------------------------------------------------------------- final adjustment
def refine_model(rec, passes: int, error_ratio: float, min_points_per_view: int = 20, threads: int = -1):
    """A final bundle adjustment of a mapped model (a copy; ``rec`` is not modified): ``passes`` times, drop the
    observations whose reprojection error exceeds ``error_ratio`` × the model's mean error (and points left with
    fewer than two views or a small triangulation angle), then re-adjust poses, points and focal length with a
    Cauchy loss (1 px scale), on ``threads`` threads (-1: all cores; Ceres goes parallel above 50 k residuals, and
    the cameras stage asks for one thread, as from COLMAP's other steps, when ``cameras.deterministic``). Lens
    distortion is re-adjusted only where the model has some.

    COLMAP's mapper keeps observations up to 4 px off; on a rendered capture of 0.34 px mean error their tail held
    the rotation error at 0.059°, and this halves it (0.030°; the held-out photos' silhouettes then line up with the
    mesh). Returns (model, notes); the model as given, with a note, when a view would keep fewer than
    ``min_points_per_view`` points or the adjustment diverges."""
    from pipeline.colmaplib import pycolmap, quiet

    if passes <= 0:
        return rec, []
    out = pycolmap.Reconstruction(rec)
    e0, n0 = out.compute_mean_reprojection_error(), out.compute_num_observations()
    opts = pycolmap.BundleAdjustmentOptions()
    opts.print_summary = False
    opts.refine_extra_params = any(np.any(c.params[list(c.extra_params_idxs())]) for c in out.cameras.values())
    opts.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    opts.ceres.solver_options.num_threads = threads
    for _ in range(passes):
        pycolmap.ObservationManager(out).filter_all_points3D(error_ratio * out.compute_mean_reprojection_error(),
                                                             1.5)
        with quiet():
            pycolmap.bundle_adjustment(out, opts)
    poses = [np.asarray(out.image(i).cam_from_world().matrix()) for i in out.reg_image_ids()]
    if not (np.isfinite(poses).all() and np.isfinite(out.compute_mean_reprojection_error())):
        return rec, ["final adjustment diverged; the mapped model is kept"]
    fewest = min(out.image(i).num_points3D for i in out.reg_image_ids())
    if fewest < min_points_per_view:
        return rec, [f"final adjustment skipped: a view would keep {fewest} points (< {min_points_per_view})"]
    e1, n1 = out.compute_mean_reprojection_error(), out.compute_num_observations()
    return out, [f"final adjustment: {passes} passes kept {n1}/{n0} observations, mean reprojection error "
                 f"{e0:.3f} → {e1:.3f} px"]


def retriangulate(rec, database: Path, images: Path, work: Path, seed: int = 0, threads: int = -1):
    """The points of ``rec`` triangulated afresh from every match in ``database`` at its poses and intrinsics (COLMAP's
    point triangulator: poses and cameras stay as they are). After the final passes: they drop the observations
    above the error threshold to fit the poses, and with them a quarter to half of the sparse depths on the object
    (the cow keeps 110 of 212, the book 5879 of 7768), which the depth loss needs; at the adjusted poses most of those
    observations fit again. Returns (model, note)."""
    from pipeline.colmaplib import pycolmap, quiet

    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    n0 = rec.compute_num_observations()
    opts = pycolmap.IncrementalPipelineOptions()
    opts.random_seed, opts.num_threads = seed, threads
    with quiet():  # after a bundle adjustment COLMAP logs at info level: its triangulator's lines would show
        out = pycolmap.triangulate_points(pycolmap.Reconstruction(rec), database, images, work, clear_points=True,
                                          options=opts)
    return out, (f"points re-triangulated at the adjusted poses: {out.compute_num_observations()} observations "
                 f"(the passes kept {n0})")


def copy_unverified(database: Path, out: Path) -> None:
    """A copy ``out`` of the COLMAP ``database`` with its stored matches and without their verification (no two-view
    geometries), for a verification of its own."""
    from pipeline.colmaplib import pycolmap

    shutil.copy(database, out)
    db = pycolmap.Database.open(str(out))
    try:
        db.clear_two_view_geometries()
    finally:
        db.close()


def verify_again(database: Path, out: Path, max_h_inlier_ratio: float, seed: int, threads: int = -1) -> None:
    """A copy ``out`` of ``database`` whose stored matches are verified again with ``max_h_inlier_ratio`` (RANSAC
    seeded with ``seed``). On an unguided rung the same verified matches as matching again (the cow's 20 photos of
    960 × 720: 25 354 both), in 33 s instead of 35 (RANSAC is the cost). A guided rung's guided search is not done
    again. :func:`verify_at_poses` needs no RANSAC (``cameras.object_verification``). Each pair's RANSAC is seeded
    on its own, so every number of ``threads`` gives the same database (the 3× cow's 762 pairs, 1 and 2 threads:
    identical; 134 s against 67)."""
    from pipeline.colmaplib import pycolmap, quiet

    copy_unverified(database, out)
    geometry = pycolmap.TwoViewGeometryOptions()
    geometry.ransac.random_seed = seed
    geometry.max_H_inlier_ratio = max_h_inlier_ratio
    verifier = pycolmap.GeometricVerifierOptions()
    verifier.num_threads = threads
    with quiet():  # after a bundle adjustment COLMAP logs at info level: the verification's lines would show
        pycolmap.geometric_verification(out, verifier_options=verifier, two_view_geometry_options=geometry)


def verify_at_poses(rec, database: Path, out: Path, threads: int = -1) -> None:
    """A copy ``out`` of ``database`` whose stored matches are verified again against the poses and intrinsics of
    ``rec`` (COLMAP's guided geometric verifier, as hloc triangulates from known poses): each pair keeps the matches
    within COLMAP's epipolar error of its known relative pose, however many lie on one plane. No RANSAC: 0.2 s for
    the 190 pairs of 20 photos of 960 × 720 (309 object matches; :func:`verify_again` 33 s, 240)."""
    from pipeline.colmaplib import pycolmap, quiet

    copy_unverified(database, out)
    with quiet():
        pycolmap.guided_geometric_verification(rec, out, num_threads=threads)


# ----------------------------------------------------------------------------- judging a model


def model_stats(rec, names: list[str]) -> dict:
    """Registered photos, reprojection error, track length and the median number of points a view observes."""
    reg = [rec.image(i) for i in rec.reg_image_ids()]
    per_view = [im.num_points3D for im in reg]
    return {"registered": len(reg), "total": len(names),
            "mean_reprojection_error": float(rec.compute_mean_reprojection_error()),
            "mean_track_length": float(rec.compute_mean_track_length()), "points": int(rec.num_points3D()),
            "median_points_per_view": float(np.median(per_view)) if per_view else 0.0}


def shortfalls(stats: dict, max_error: float = 1.0, min_track: float = 2.5, min_points: int = 50,
               enough_registered: float = 1.0) -> list[str]:
    """Why a model is short (empty: good enough to stop climbing); registering ``enough_registered`` of the photos
    is enough (the ladder does not climb for the last photo or two)."""
    out = []
    if stats["registered"] < enough_registered * stats["total"]:
        out.append(f"{stats['registered']}/{stats['total']} registered")
    if stats["mean_reprojection_error"] > max_error:
        out.append(f"reprojection error {stats['mean_reprojection_error']:.2f} px > {max_error}")
    if stats["mean_track_length"] < min_track:
        out.append(f"mean track length {stats['mean_track_length']:.2f} < {min_track}")
    if stats["median_points_per_view"] < min_points:
        out.append(f"median {stats['median_points_per_view']:.0f} points per view < {min_points}")
    return out


if __name__ == "__main__":  # the child process of run_rung
    from pipeline.lock import end_with_parent

    end_with_parent(int(sys.argv[2]))  # a run killed leaves no rung writing in the workspace the next run holds
    _run_rung(*json.loads(sys.argv[1]))
