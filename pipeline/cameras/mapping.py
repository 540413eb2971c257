"""Posing the photos by SfM: the ladder's rungs tried in turn, the kept model's final adjustment and its object
matches."""

from __future__ import annotations

import shutil
import sqlite3
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import NamedTuple

import numpy as np

from dvr.atomic import copy_file, write_image
from pipeline.cameras.config import CamerasConfig
from pipeline.cameras.export import (
    SPHERE_MIN_POINTS,
    central_points,
    model_points,
)
from pipeline.cameras.pose_sanity import axes_convergence, model_views, pose_sanity, rotation_disagreement
from pipeline.cameras.sfm import (
    RUNG_NAMES,
    Rung,
    ladder,
    median_features,
    model_stats,
    refine_model,
    retriangulate,
    run_rung,
    rung_seconds,
    shortfalls,
    verify_again,
    verify_at_poses,
)
from pipeline.cameras.visibility import (
    count_conflicts,
    database_without,
    doubts,
    misjoined,
    unexplained_matches,
    unexplained_pairs,
)
from pipeline.colmaplib import pair_images, write_model
from pipeline.errors import StageError
from pipeline.inputs.photos import (
    downscale,
    read_photo,
)
from pipeline.messages import heartbeat, names_or_count
from pipeline.scene.support import find_support
from pipeline.workspace import Workspace

MIN_RUNG_SECONDS = 5.0
"""A rung starts only with at least this much of the SfM time budget left."""
REJOINED = "rejoined"
"""The name of a model mapped again where a pair of photos' matches showed a group joined at the wrong side
(:func:`_regrouped`): its rung's suffix and its database's name."""
LARGE_PHOTOS = 2.0
""":func:`keep_object_matches` runs when SfM saw the photos at least this many times the working size (a phone's): at
the working size it makes the bench's weakly textured jars and the mug worse (held-out PSNR 1.8, 4.0 and 1.1 dB
lower) and helps none of its eight scenes by more than their runs' spread."""


def sphere_points(rec, cfg: CamerasConfig) -> int:
    """How many of the COLMAP model's points the object's sphere would be fitted to (:func:`central_points`, with
    the support plane as the stage finds it; the model's pinhole intrinsics, distortion aside)."""
    pts = model_points(rec, cfg.min_track_length)[0]
    views = model_views(rec)
    Rs, centers = np.stack([v.R for v in views]), np.stack([v.center for v in views])
    support = find_support(pts, centers, Rs, axes_convergence(centers, Rs[:, 2, :])) if cfg.support else None
    Ps = np.stack([v.K @ np.concatenate([v.R, v.t[:, None]], 1) for v in views])
    sizes = np.array([(v.width, v.height) for v in views], float)
    return len(central_points(pts, Ps, sizes, support)[1])


def prepare_sfm_input(ws: Workspace, photos: list[Path], cfg: CamerasConfig
                      ) -> tuple[Path, list[list[str]], list[tuple[tuple[int, int], tuple[int, int]]]]:
    """Upright copies of the photos (longest side ≤ max_side_sfm) in ``sfm/input``, grouped by size; per photo the
    (height, width) of the upright photo and of its copy."""
    sfm = ws.root / "sfm"
    if sfm.exists():
        shutil.rmtree(sfm)
    inp = sfm / "input"
    inp.mkdir(parents=True)
    groups: dict[tuple[int, int], list[str]] = {}
    shapes = []
    for p in photos:
        full = read_photo(p)
        if full is None:
            raise StageError(f"{p}: unreadable image; remove it from the folder")
        img = downscale(full, cfg.max_side_sfm)
        write_image(inp / f"{p.stem}.png", img)
        groups.setdefault(img.shape[:2], []).append(f"{p.stem}.png")
        shapes.append((full.shape[:2], img.shape[:2]))
    return inp, list(groups.values()), shapes


def _drop_views(rec, names: set[str]) -> None:
    for i in list(rec.reg_image_ids()):
        if rec.image(i).name in names:
            rec.deregister_frame(rec.image(i).frame_id)


def run_sfm(ws: Workspace, photos: list[Path], cfg: CamerasConfig):
    """Climb the SfM ladder (:mod:`pipeline.cameras.sfm`) until a rung registers every photo with sane poses, then the
    final adjustment (:func:`finish_model`); returns (model, folder of the images SfM saw, summary of the rungs
    tried)."""
    rec, inp, database, rung, tried, doubtful = map_photos(ws, photos, cfg)
    if doubtful:
        a, b, n, _ = doubtful[0]
        more = f" and {len(doubtful) - 1} more pairs" if len(doubtful) > 1 else ""
        print(f"warning: the cameras' model does not explain the {n} verified matches of {Path(a).stem} with "
              f"{Path(b).stem}{more}: a group of photos may be posed at the wrong side of the object (the same "
              "pattern on two sides); look at the mesh, and if it is wrong, add photos between its sides",
              file=sys.stderr)
    reg = {rec.image(i).name for i in rec.reg_image_ids()}
    matches = {Path(n).stem: k for n, k in verified_matches(database, reg).items()}
    with heartbeat("cameras: final adjustment of the model"):
        rec, final, object_note = finish_model(ws, rec, database, inp, cfg, rung)
    return rec, inp, {"rung": rung, "rungs": tried, "rejoined": rung.endswith(f"-{REJOINED}"),
                      "final_adjustment": final, "object_matches": object_note,
                      "matches": matches, "unexplained_pairs": [[Path(a).stem, Path(b).stem, n, e]
                                                                for a, b, n, e in doubtful]}


def final_adjustment(cfg: CamerasConfig, rung: str) -> tuple[int, str]:
    """The final adjustment for a model from the ladder's ``rung``: (passes, when to re-triangulate after them:
    "always", "when short" — when the passes take the object's sphere below ``SPHERE_MIN_POINTS`` points, which
    the model as mapped had — or "never"). ``cfg.final_passes`` and ``cfg.final_retriangulate``; past the first
    rung at least ``cfg.climbed_passes``, re-triangulated when short if ``cfg.climbed_retriangulate``."""
    climbed = rung != RUNG_NAMES[0] and cfg.climbed_passes > 0
    passes = max(cfg.final_passes, cfg.climbed_passes) if climbed else cfg.final_passes
    if cfg.final_retriangulate:
        return passes, "always"
    return passes, "when short" if climbed and cfg.climbed_retriangulate else "never"


def sfm_threads(cfg: CamerasConfig) -> int:
    """COLMAP's threads: 1 when ``cfg.deterministic``, else -1 (all cores)."""
    return 1 if cfg.deterministic else -1


def sfm_budget(cfg: CamerasConfig, n_photos: int) -> float:
    """Seconds the SfM ladder may take for ``n_photos`` photos (``sfm_seconds`` + ``sfm_seconds_per_photo`` each)."""
    return cfg.sfm_seconds + cfg.sfm_seconds_per_photo * n_photos


def map_photos(ws: Workspace, photos: list[Path], cfg: CamerasConfig):
    """The SfM ladder, within its time budget (:func:`sfm_budget`): the first rung always finishes (its mapper stops
    at the budget's end, or after half the budget when that is later), later rungs run in what is left of it, each
    only when its features, matches and mapping, estimated from the last rung that made its own
    (:func:`pipeline.cameras.sfm.rung_seconds`), fit in what is left. At the first rung that does not fit, and when
    the ladder ends, COLMAP's global mapper maps the matches of the incremental mapper's best model when that leaves
    out photos with matches (:func:`_mapped_globally`); a model from it that is enough ends the ladder, and merging
    continues from it.
    Returns (model as mapped, folder of the images SfM saw, its COLMAP database, the rung's name, summary of the
    rungs tried, the model's :func:`~pipeline.cameras.visibility.unexplained_pairs`)."""
    with heartbeat(f"cameras: reading the {len(photos)} photos"):
        inp, groups, shapes = prepare_sfm_input(ws, photos, cfg)
    names = [p.stem for p in photos]
    sfm_side = max(max(seen) for _, seen in shapes)
    work = ws.root / "sfm" / "ladder"
    work.mkdir()
    budget = sfm_budget(cfg, len(names))
    deadline = time.time() + budget
    tried, best, rejected, measured, made_by, globalled = [], None, {}, None, {}, set()
    rungs = ladder(cfg.start_rung, cfg.last_rung, cfg.max_features, cfg.max_h_inlier_ratio, len(names), sfm_side,
                   cfg.pair_neighbours, cfg.sift_upsample_below)
    rungs = _upsampled_when_weak(rungs, work, inp, names, cfg)
    for step, rung in enumerate(rungs):
        base = None
        if rung.mapper == "extend":  # continue from the best model so far: only when it lacks photos
            if best is None or best.model.num_reg_images() >= len(names):
                continue
            base = (work / "merge-base", best.database)
            write_model(best.model, base[0])
        if step > 0 and time.time() > deadline - MIN_RUNG_SECONDS:  # the first rung always runs
            left = [r.name for r in rungs[step:]]
            print(f"cameras: the SfM time budget ({budget:.0f} s for {len(names)} photos: cameras.sfm-seconds, "
                  f"cameras.sfm-seconds-per-photo) is spent; rungs not tried: {', '.join(left)}")
            tried += [{"rung": r, "skipped": "time budget spent"} for r in left]
            break
        need, left = (0.0 if measured is None else rung_seconds(*measured, rung)), deadline - time.time()
        if step > 0 and need > left - MIN_RUNG_SECONDS:  # it would not finish its mapping
            why = f"its features, matches and mapping would take about {need:.0f} s, {left:.0f} s of the SfM time "\
                  "budget left"
            print(f"cameras: rung {rung.name} not tried: {why}")
            tried.append({"rung": rung.name, "skipped": why})
            if best is not None:  # the matches there are, mapped by the global mapper before any merging
                best, short = _mapped_globally(best, made_by, globalled, work, inp, groups, cfg, names, budget, tried)
                if short == []:
                    break
            continue
        t0 = time.perf_counter()
        rec, database, secs, err = run_rung(work, inp, groups, rung, cfg.camera_model, cfg.matching, cfg.seed,
                                            base, sfm_threads(cfg), deadline, budget / 2 if step == 0 else None)
        if secs.get("features", 0) > 0 and secs.get("matching", 0) > 0:  # both made afresh: the costs to scale
            measured = (rung, secs)
        if database is not None and rung.mapper != "extend":
            made_by.setdefault(database, rung)  # the rung whose features and matches these are
        references = [best.model] if rung.mapper == "global" and best is not None else []  # the ladder's global rung
        judged = _judge(rec, rung.name, time.perf_counter() - t0, secs, err, inp, names, cfg, rejected, tried,
                        references)
        if judged is None:
            continue
        best = _better(best, judged[0], rec, rung, database)
        if not judged[1]:
            break
    if best is not None:  # the ladder is over
        best, _ = _mapped_globally(best, made_by, globalled, work, inp, groups, cfg, names, budget, tried)
        best, doubtful = _regrouped(best, work, inp, groups, cfg, names, budget, tried)
    _require_credible(None if best is None else best.model, rejected, inp, len(names), cfg.min_registered_fraction)
    return best.model, inp, best.database, best.rung.name, tried, doubtful


def _upsampled_when_weak(rungs: list[Rung], work: Path, inp: Path, names: list[str], cfg: CamerasConfig
                         ) -> list[Rung]:
    """The ladder's rungs, upsampling the photos for SIFT when they do not already and SIFT finds fewer than
    ``cfg.sift_upsample_features`` features in the median photo at their size (:func:`median_features`): weakly
    textured photos — a white mouse on a white table — give 3 × the points upsampled, and the masks and the depth
    loss are built on them."""
    if rungs[0].upsample or cfg.sift_upsample_features <= 0:
        return rungs
    found = median_features(work, inp, names, rungs[0], sfm_threads(cfg))
    if found >= cfg.sift_upsample_features:
        return rungs
    print(f"cameras: SIFT finds {found:.0f} features in the median photo at the size SfM sees them (fewer than "
          f"cameras.sift-upsample-features {cfg.sift_upsample_features}): the photos are upsampled for SIFT")
    return [replace(r, upsample=True) for r in rungs]


def _judge(rec, name: str, seconds: float, steps: dict, err: str | None, inp: Path, names: list[str],
           cfg: CamerasConfig, rejected: dict | None, tried: list, references: list) -> tuple[dict, list] | None:
    """A rung's model as the ladder judges it, said on a line and added to ``tried``: None when there is none or it
    is rejected (more than ``max_bad_pose_fraction`` of its views fail :func:`pose_sanity`, or disagree with the
    ``references``' rotations, :func:`disagreeing_views`; the former go to ``rejected`` unless it is None), else
    (its stats with the failing views dropped, why it is short: empty when enough to reconstruct from)."""
    if rec is None or rec.num_reg_images() < 2:
        print(f"cameras: rung {name}: {err or 'no model'} ({seconds:.1f} s)")
        tried.append({"rung": name, "seconds": round(seconds, 1), "error": err or "no model"})
        return None
    bad = pose_sanity(rec, inp)
    disagree = {n: why for ref in references for n, why in disagreeing_views(rec, ref, cfg.global_agreement_deg)}
    n_reg = rec.num_reg_images()
    if len(bad | disagree) > cfg.max_bad_pose_fraction * n_reg:
        why = (f"{len(bad)} poses are not credible" if len(bad) >= len(disagree) else
               f"{len(disagree)} rotations disagree with the incremental mapper's by over "
               f"{cfg.global_agreement_deg:g}° (cameras.global-agreement-deg)")
        print(f"cameras: rung {name}: {n_reg} registered but {why}, model rejected ({seconds:.1f} s)")
        if rejected is not None:
            rejected.update(bad)
        tried.append({"rung": name, "seconds": round(seconds, 1), "registered": n_reg, "rejected": len(bad | disagree)})
        return None
    bad |= disagree
    _drop_views(rec, set(bad))
    stats = model_stats(rec, names)
    short = shortfalls(stats, cfg.max_reprojection_error, enough_registered=cfg.enough_registered)
    dropped = f", dropped {len(bad)} views with wrong poses ({names_or_count(sorted(bad))})" if bad else ""
    print(f"cameras: rung {name}: registered {stats['registered']}/{len(names)}, "
          f"{stats['mean_reprojection_error']:.2f} px, track length {stats['mean_track_length']:.2f}"
          f"{dropped} in {seconds:.1f} s → {'; '.join(short) if short else 'enough to reconstruct from'}")
    tried.append({"rung": name, "seconds": round(seconds, 1), **{k: stats[k] for k in ("registered",
                  "mean_reprojection_error", "mean_track_length")}, "dropped": sorted(bad), "steps": steps})
    return stats, short


class _Kept(NamedTuple):
    """The ladder's best model so far: its photos and error, the model, the rung that made it, its database."""

    registered: int
    error: float
    model: object
    rung: Rung
    database: Path


def _better(best: _Kept | None, stats: dict, rec, rung: Rung, database: Path) -> _Kept:
    """The better of the ladder's ``best`` so far and this model: more photos, then a smaller error."""
    new = _Kept(stats["registered"], stats["mean_reprojection_error"], rec, rung, database)
    return new if best is None or (new.registered, -new.error) > (best.registered, -best.error) else best


def _mapped_globally(best: _Kept, made_by: dict, globalled: set, work: Path, inp: Path, groups: list[list[str]],
                     cfg: CamerasConfig, names: list[str], budget: float, tried: list) -> tuple[_Kept, list | None]:
    """The ladder's ``best`` model, or the global mapper's model of the same matches when it poses more
    (:func:`_global_on_same_matches`, stopped past half the ``budget``), and why that one is short (None: not run
    or rejected). It runs with ``cfg.global_mapper`` when the incremental mapper made ``best`` (or the model it was
    merged from: ``made_by``, database → rung), that model leaves out photos with matches, and the global mapper has
    not mapped these matches yet (``globalled``, the matches' keys, is updated)."""
    source = made_by.get(best.database, best.rung)
    if not cfg.global_mapper or source.mapper != "incremental" or source.matches_key in globalled or \
            not matched_but_left_out(best.model, best.database):
        return best, None
    globalled.add(source.matches_key)
    again = _global_on_same_matches(work, inp, groups, source, cfg, names, time.time() + budget / 2, tried)
    return (best, None) if again is None else (_better(best, *again[:4]), again[4])


def _global_on_same_matches(work: Path, inp: Path, groups: list[list[str]], rung: Rung, cfg: CamerasConfig,
                            names: list[str], deadline: float, tried: list):
    """COLMAP's global mapper on the features and matches of the incremental ``rung`` (reused, not made again),
    judged against the models the incremental mapper made of them (:func:`_judge`); stopped at ``deadline``
    (time.time()). Returns (stats, model, its rung, database, why it is short) or None."""
    t0 = time.perf_counter()
    again = replace(rung, name=f"{rung.name}-global", mapper="global")
    rec, database, steps, err = run_rung(work, inp, groups, again, cfg.camera_model, cfg.matching, cfg.seed, None,
                                         sfm_threads(cfg), deadline)
    judged = _judge(rec, again.name, time.perf_counter() - t0, steps, err, inp, names, cfg, None, tried,
                    incremental_models(work / rung.name / "models"))
    return None if judged is None else (judged[0], rec, again, database, judged[1])


def _regrouped(best: _Kept, work: Path, inp: Path, groups: list[list[str]], cfg: CamerasConfig, names: list[str],
               budget: float, tried: list) -> tuple[_Kept, list[tuple[str, str, int, int]]]:
    """The ladder's ``best`` model, or, where it joined a group of photos to the others at the wrong side of the
    object (with ``cfg.regroup``), the incremental mapper's model of the same matches without the pairs that
    joined them; each mapping stopped past half the ``budget``. Returns the model kept and its
    :func:`~pipeline.cameras.visibility.unexplained_pairs`. Two signs find the group, in turn: its views' points lie
    in front of what the others observe (:func:`_regrouped_by_conflicts`), or a pair of photos with many verified
    matches is one the model does not explain (:func:`_rejoined`)."""
    if cfg.regroup:
        best = _regrouped_by_conflicts(best, work, inp, groups, cfg, names, budget, tried)
    doubtful, found = doubts(best.model, best.database)
    if found is None or not cfg.regroup:
        return best, doubtful
    return _rejoined(best, doubtful, *found, work, inp, groups, cfg, names, budget, tried)


def _regrouped_by_conflicts(best: _Kept, work: Path, inp: Path, groups: list[list[str]], cfg: CamerasConfig,
                            names: list[str], budget: float, tried: list) -> _Kept:
    """:func:`_regrouped` by the conflicts: ``best``, or its model mapped again without the pairs that join the group
    they point to, when that poses as many photos with at most half the conflicts and fewer at points three or more
    views observe."""
    found = misjoined(best.model, best.database)
    if found is None:
        return best
    group, cut, before = found
    _say_mapping_again(f"{before[0]} times a point of the model lies in front of one a view observes", group, cut)
    again = _mapped_without(best, cut, "regrouped", work, inp, groups, cfg, names, budget, tried)
    after = None if again is None else count_conflicts(again.model)
    if again is None or again.registered < best.registered or after[0] > before[0] / 2 or after[1] >= before[1]:
        why = "no model" if again is None else f"{again.registered} photos, {after[0]} conflicts"
        print(f"cameras: the first model is kept ({why} mapped again)")
        return best
    print(f"cameras: the model mapped again is kept: {after[0]} conflicts")
    return again


def _rejoined(best: _Kept, doubtful: list[tuple[str, str, int, int]], group: list[str], cut: list[tuple[str, str]],
              work: Path, inp: Path, groups: list[list[str]], cfg: CamerasConfig, names: list[str], budget: float,
              tried: list) -> tuple[_Kept, list[tuple[str, str, int, int]]]:
    """:func:`_regrouped` by the pairs in doubt (``doubtful``, which set apart ``group``, joined to the others by the
    pairs ``cut``): ``best``, or its model mapped again without ``cut`` when that poses as many photos and leaves
    under half as many of those matches unexplained (with a warning); the model kept and its pairs in doubt."""
    a, b, n, _ = doubtful[0]
    _say_mapping_again(f"the model does not explain the {n} verified matches of {Path(a).stem} with {Path(b).stem}",
                       group, cut)
    again = _mapped_without(best, cut, REJOINED, work, inp, groups, cfg, names, budget, tried)
    left = None if again is None else unexplained_pairs(again.model, best.database)
    n_left = None if left is None else unexplained_matches(left)
    if again is None or again.registered < best.registered or n_left * 2 >= unexplained_matches(doubtful):
        why = "no model" if again is None else f"{again.registered} photos, {n_left} matches of pairs unexplained"
        print(f"cameras: the first model is kept ({why} mapped again)")
        return best, doubtful
    print(f"cameras: the model mapped again is kept: {n_left} matches of pairs unexplained")
    print("warning: the cameras stage mapped a group of photos again that its first model had posed at the wrong "
          "side of the object (the same pattern on two sides); part of them can still be off: look at the mesh, and "
          "if it is wrong, add photos between its sides", file=sys.stderr)
    return again, left


def _say_mapping_again(sign: str, group: list[str], cut: list[tuple[str, str]]) -> None:
    """The line that says the model is mapped again: the ``sign`` of a misjoined ``group`` (photo names) and the
    pairs ``cut`` that joined it."""
    print(f"cameras: {sign}: {names_or_count([Path(n).stem for n in group])} may be joined to the others at the wrong "
          f"side of the object (the same pattern on two sides): mapping again without the {len(cut)} pairs that join "
          "them", flush=True)


def _mapped_without(best: _Kept, cut: list[tuple[str, str]], name: str, work: Path, inp: Path,
                    groups: list[list[str]], cfg: CamerasConfig, names: list[str], budget: float, tried: list
                    ) -> _Kept | None:
    """The incremental mapper's model of ``best``'s matches without the photo pairs ``cut`` (judged as the ladder's
    rungs are, :func:`_judge`; stopped past half the ``budget``), or None; its rung is ``best``'s, ``name``
    appended, and its database ``work/<name>.db``."""
    t0 = time.perf_counter()
    database = database_without(best.database, cut, work / f"{name}.db")
    rung = replace(best.rung, name=f"{best.rung.name}-{name}", mapper="incremental")
    rec, _, steps, err = run_rung(work, inp, groups, rung, cfg.camera_model, cfg.matching, cfg.seed,
                                  (None, database), sfm_threads(cfg), time.time() + budget / 2)
    judged = _judge(rec, rung.name, time.perf_counter() - t0, steps, err, inp, names, cfg, None, tried, [])
    if judged is None:
        return None
    return _Kept(judged[0]["registered"], judged[0]["mean_reprojection_error"], rec, rung, database)


def matched_but_left_out(rec, database: Path) -> list[str]:
    """The photos (file names as SfM saw them) the model ``rec`` did not register that share verified matches with
    some photo in its ``database``: another mapper may pose them; a photo matching nothing cannot be."""
    registered = {rec.image(i).name for i in rec.reg_image_ids()}
    return sorted(n for n, (_, total) in verified_matches(database, registered).items()
                  if total > 0 and n not in registered)


def incremental_models(folder: Path) -> list:
    """The models (of at least two photos) an incremental rung mapped into ``folder`` (``<rung>/models``)."""
    from pipeline.colmaplib import pycolmap

    recs = [pycolmap.Reconstruction(d) for d in sorted(folder.iterdir()) if d.is_dir()] if folder.is_dir() else []
    return [r for r in recs if r.num_reg_images() >= 2]


def disagreeing_views(rec, reference, tolerance_deg: float) -> list[tuple[str, str]]:
    """Views of ``rec`` whose rotation, the two models' frames aligned (:func:`rotation_disagreement`), differs
    from the ``reference`` model's by more than ``tolerance_deg``, with the reason."""
    angles = rotation_disagreement(model_views(rec), model_views(reference), tolerance_deg)
    return [(n, f"rotation {a:.0f}° from the incremental mapper's") for n, a in angles.items() if a > tolerance_deg]


def verified_matches(database: Path, registered: set[str]) -> dict[str, tuple[int, int]]:
    """Per photo file name (as SfM saw it), its verified inlier matches (with the ``registered`` photos, with any
    photo), from the COLMAP ``database``'s two-view geometries."""
    con = sqlite3.connect(f"file:{database}?mode=ro", uri=True)
    try:
        ids = dict(con.execute("select image_id, name from images"))
        out: dict[str, tuple[int, int]] = {}
        for pair_id, rows in con.execute("select pair_id, rows from two_view_geometries where rows > 0"):
            a, b = (ids.get(i) for i in pair_images(pair_id))
            for one, other in ((a, b), (b, a)):
                if one is not None:
                    posed, total = out.get(one, (0, 0))
                    out[one] = (posed + rows * (other in registered), total + rows)
    finally:
        con.close()
    return out


def finish_model(ws: Workspace, rec, database: Path, inp: Path, cfg: CamerasConfig, rung: str):
    """The model ``rec`` that the ladder's ``rung`` mapped, as the cameras stage keeps it: pinhole where the
    distortion is negligible, the final adjustment (:func:`final_adjustment`: passes, then re-triangulation);
    written to sfm/sparse/best with its ``database`` beside (sfm/database.db, where COLMAP puts it); the object's
    matches kept (:func:`keep_object_matches`). Returns (model, notes of the final adjustment, the object matches'
    note or None)."""
    threads = sfm_threads(cfg)
    rec, notes = prefer_pinhole(rec, cfg.pinhole_tolerance, threads)
    passes, again = final_adjustment(cfg, rung)
    adjusted, final = refine_model(rec, passes, cfg.final_error_ratio, threads=threads)
    if passes > cfg.final_passes:
        final = [f"{note} (the model came from the ladder's rung '{rung}': cameras.climbed-passes)" for note in final]
    if adjusted is not rec and again == "when short":
        before, left = sphere_points(rec, cfg), sphere_points(adjusted, cfg)
        again = "always" if left < SPHERE_MIN_POINTS <= before else "never"
        final.append(f"the passes left the object's sphere {left} of its {before} points (it needs "
                     f"{SPHERE_MIN_POINTS}): " + ("points re-triangulated" if again == "always" else
                                                  "points kept as adjusted"))
    if adjusted is not rec and again == "always":
        adjusted, note = retriangulate(adjusted, database, inp, ws.root / "sfm" / "ladder" / "final", cfg.seed,
                                       threads)
        final.append(note)
    object_note = None
    if cfg.object_matches:
        adjusted, database, object_note = keep_object_matches(ws, adjusted, database, inp, cfg)
    for note in notes + final + ([object_note] if object_note else []):
        print(f"cameras: {note}")
    best_dir = ws.root / "sfm" / "sparse" / "best"
    write_model(adjusted, best_dir)  # whole or absent, as every file the stage writes (dvr.atomic)
    copy_file(database, ws.root / "sfm" / "database.db")
    return adjusted, final, object_note


def keep_object_matches(ws: Workspace, rec, database: Path, inp: Path, cfg: CamerasConfig):
    """``rec`` with its points triangulated again, at the same poses, from its ``database``'s stored matches verified
    again (``object_verification``: against the model's poses, :func:`pipeline.cameras.sfm.verify_at_poses`, or by
    RANSAC keeping every pair's epipolar inliers, :func:`pipeline.cameras.sfm.verify_again`; either way a "planar"
    pair keeps its object's inliers too, not its floor's alone), when SfM saw the photos at :data:`LARGE_PHOTOS` ×
    the working size or more, the model leaves the object's sphere fewer than :data:`SPHERE_MIN_POINTS` points, and
    that gives it more (``object_matches``). Returns (model, its database, a note or None)."""
    sfm_side = max(max(c.width, c.height) for c in rec.cameras.values())
    if sfm_side < LARGE_PHOTOS * cfg.max_side:
        return rec, database, None
    before = sphere_points(rec, cfg)
    if before >= SPHERE_MIN_POINTS:
        return rec, database, None
    work = ws.root / "sfm" / "ladder"
    work.mkdir(parents=True, exist_ok=True)  # the benchmark's saved mappings come without the ladder's folder
    threads = sfm_threads(cfg)
    if cfg.object_verification == "poses":
        db, how = work / f"{database.stem}-posed.db", "again at the model's poses"
        verify_at_poses(rec, database, db, threads)
    else:
        db, how = work / f"{database.stem}-h1.db", "keeping each pair's epipolar inliers"
        verify_again(database, db, 1.0, cfg.seed, -1)  # all cores even when deterministic: the same either way
    out, _ = retriangulate(rec, db, inp, work / "object", cfg.seed, threads)
    after = sphere_points(out, cfg)
    note = (f"{before} sparse points for the object's sphere (it needs {SPHERE_MIN_POINTS}); matches verified {how} "
            f"and points triangulated again at the same poses: {after}")
    return (out, db, note) if after > before else (rec, database, note + ", kept as mapped")


def _require_credible(rec, rejected: dict, inp: Path, n_photos: int, min_fraction: float) -> None:
    """The SfM ladder's failures as a StageError: no model at all (``rec`` None), or, when models were rejected for
    poses that cannot be (``rejected``), a kept model that registers fewer than ``min_fraction`` of the photos."""
    views = names_or_count(sorted(Path(n).stem for n in rejected), "views")
    if rec is None:
        if rejected:
            raise StageError(f"{inp.parent.parent}: SfM poses are inconsistent for every setting tried (views {views}"
                             "): a symmetric or repetitive object or floor — "
                             "put a textured mat (a newspaper) under the object, or add texture around it")
        raise StageError(f"{inp}: SfM found no model (too few matches): photograph the object with more overlap "
                         "(≥ 60 % between neighbours), more texture, and sharp, well-lit images")
    if rejected and rec.num_reg_images() < max(3, min_fraction * n_photos):
        raise StageError(f"{inp.parent.parent}: SfM registered {rec.num_reg_images()}/{n_photos} photos with "
                         f"credible poses; other settings placed views {views} "
                         "where they cannot be: a symmetric or repetitive object or floor — put a textured mat (a "
                         "newspaper) under the object, or add texture around it")


def prefer_pinhole(rec, tolerance: float, threads: int = -1):
    """Set the lens distortion to zero and re-adjust focal lengths and poses (bundle adjustment on ``threads``
    threads, -1: all cores); keep that pinhole model when its mean reprojection error grows by at most
    ``tolerance`` (relative, +0.01 px); returns (model, notes).

    Object-centric captures hardly constrain distortion against focal length: on a synthetic pinhole scene
    COLMAP fitted k = 0.11 with the focal length 11 % long, and the pinhole re-fit recovered the true focal
    length to 0.01 % at the same reprojection error; undistorting by the spurious model cost ~13 dB held-out
    PSNR. A real lens keeps its distortion because a pinhole explains its tracks clearly worse.
    """
    from pipeline.colmaplib import pycolmap, quiet

    if tolerance < 0:
        return rec, []
    trial = pycolmap.Reconstruction(rec)
    changed = []
    for cid, cam in trial.cameras.items():
        idx = list(cam.extra_params_idxs())
        if not idx or not np.any(cam.params[idx]):
            continue
        p = cam.params.copy()
        changed.append(f"camera {cid}: distortion {np.round(p[idx], 4).tolist()}, focal "
                       f"{np.round(p[list(cam.focal_length_idxs())], 1).tolist()}")
        p[idx] = 0.0
        cam.params = p
    if not changed:
        return rec, []
    opts = pycolmap.BundleAdjustmentOptions()
    opts.refine_extra_params = False
    opts.print_summary = False
    opts.ceres.solver_options.num_threads = threads
    with quiet():
        pycolmap.bundle_adjustment(trial, opts)
    e0, e1 = rec.compute_mean_reprojection_error(), trial.compute_mean_reprojection_error()
    if e1 > (1 + tolerance) * e0 + 0.01:
        return rec, [f"lens distortion kept: as a pinhole the reprojection error grows from {e0:.3f} to {e1:.3f} px"]
    focal = [np.round(c.params[list(c.focal_length_idxs())], 1).tolist() for c in trial.cameras.values()]
    return trial, [f"{c} → pinhole" for c in changed] + [f"pinhole focal {focal}, mean reprojection error "
                                                         f"{e0:.3f} → {e1:.3f} px"]
