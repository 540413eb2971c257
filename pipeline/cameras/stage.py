"""Stage ``cameras``: photos → ``sfm/`` (COLMAP database + sparse model), ``images/``, ``cameras.npz``, ``points.ply``.

SfM runs in-process with pycolmap: SIFT, matching chosen by image count, incremental (or global) mapping,
undistortion to PINHOLE. EXIF orientation: every photo is read with its EXIF orientation APPLIED
(OpenCV's default), and that upright copy is what SfM sees (``sfm/input/``) and what training sees
(``images/``) — COLMAP itself ignores the flag, so feeding it the originals would give it other pixels.
Inputs are never modified; everything is written inside the workspace.
"""

from __future__ import annotations

import sys
from pathlib import Path

from dvr.data import list_images
from pipeline.cameras.board_poses import (
    require_board_cameras,
)
from pipeline.cameras.config import CamerasConfig
from pipeline.cameras.export import (
    export_board_cameras,
    export_model,
    report_sfm,
)
from pipeline.cameras.mapping import (
    run_sfm,
)
from pipeline.errors import StageError
from pipeline.inputs.photos import (
    list_photos,
)
from pipeline.inputs.video import extract_frames, is_video
from pipeline.messages import heartbeat
from pipeline.readers import read_stage_model
from pipeline.scene.exposure import measure_exposure, write_exposure
from pipeline.workspace import Done, Job, Workspace

# ----------------------------------------------------------------------------- inputs


# ----------------------------------------------------------------------------- normalisation


# ----------------------------------------------------------------------------- SfM


def run(job: Job) -> Done:
    """Stage ``cameras`` (called by :func:`pipeline.stages.run_stage`): the photos in ``job.sources.images`` posed by
    the SfM ladder, by given cameras (``job.sources.given_cameras``: a cameras.npz or a COLMAP model) or by a
    printed board → images/, cameras.npz, points.ply, sfm/."""
    ws, cfg, images, given = job.ws, job.cfg, job.sources.images, job.sources.given_cameras
    ws.root.mkdir(parents=True, exist_ok=True)
    video = None
    if is_video(images):
        clip, images = images, ws.root / "frames"
        record = extract_frames(clip, images, cfg.video_frames, cfg.max_side_sfm)
        video = {"clip": clip.name, "frames_in_clip": record["frames_in_clip"], "taken": len(record["chosen"])}
        print(f"cameras: {video['taken']} of the {video['frames_in_clip']} frames of {clip.name}, the sharpest of each "
              f"equal stretch → {images}")
    photos, skipped = list_photos(images)
    if video is not None:  # the frames' own record is no skipped photo
        skipped = [s for s in skipped if not s.startswith("frames.json ")]
    for s in skipped:
        print(f"warning: skipping {images / s.split(' (')[0]}: {s.split(' (', 1)[1][:-1]}", file=sys.stderr)
    if len(photos) < 3:
        raise StageError(f"{images}: {len(photos)} usable photo(s); at least 3 are needed (20–60 around the object is "
                         "typical)")
    info = pose_photos(ws, photos, images, given, cfg)
    print(f"cameras: {len(info['views'])} views → {ws.cameras}")
    if video is not None:
        info["video"] = video
    spread = record_exposure(ws)
    if spread is not None:
        info["exposure_spread"] = round(spread, 4)
    return Done({k: v for k, v in info.items() if k != "views"})


def pose_photos(ws: Workspace, photos: list[Path], images: Path, given: Path | None, cfg: CamerasConfig) -> dict:
    """The cameras of ``photos``: from a given COLMAP model folder or cameras.npz, else by the SfM ladder, else (SfM
    cannot pose them: a symmetric object) by a printed board in view. Returns the stage's record."""
    if given is not None:
        from pipeline.cameras.given import import_cameras, import_colmap_model  # they finish as SfM's model does, here

        return (import_colmap_model(ws, photos, images, given, cfg) if given.is_dir()
                else import_cameras(ws, photos, given, cfg))
    try:
        rec, inp, ladder_info = run_sfm(ws, photos, cfg)
        info = report_sfm(rec, [p.stem for p in photos], cfg, ladder_info.pop("matches"))
        info.update(ladder_info)
        with heartbeat("cameras: undistorting the photos, the object's sphere"):
            info.update(export_model(ws, rec, inp, cfg, [p.stem for p in photos]))
        return info
    except StageError as exc:  # SfM cannot pose them (a symmetric object): a printed board in view still can
        return export_board_cameras(ws, photos, cfg, require_board_cameras(photos, cfg, exc), str(exc))


def record_exposure(ws: Workspace) -> float | None:
    """The photos' per-view gains measured on the stage's SfM points → exposure.json (:mod:`pipeline.scene.exposure`);
    their spread, or None (and no file) without an SfM model (cameras from a board, or given without points)."""
    ws.exposure.unlink(missing_ok=True)
    if not ws.sfm_model.exists():
        return None
    est = measure_exposure(read_stage_model(ws.sfm_model), list_images(ws.images))
    write_exposure(ws.exposure, est)
    spread = est.spread()
    print(f"cameras: the photos' exposure differs by {100 * spread:.1f} % (SfM points' colours, 90th "
          f"percentile of the photos against the average photo) → {ws.exposure}")
    return spread
