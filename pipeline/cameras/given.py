"""Cameras given with the photos (stage ``cameras`` without SfM's mapping): an IDR/NeuS/DVR ``cameras.npz`` or a
COLMAP sparse model. Features are still matched and triangulated at the given poses (:func:`triangulate_given`), so
sparse depth, the support plane and the masks' tracks exist as after our own SfM, and the model is undistorted and
normalised as that one is (:func:`pipeline.cameras.export.export_model`)."""

from __future__ import annotations

import shutil
import sys
import time
from pathlib import Path

import numpy as np

from dvr.atomic import copy_file, is_disk_full, write_image
from dvr.cameras import decompose_projection, load_cameras, save_cameras
from pipeline.cameras.config import CamerasConfig
from pipeline.cameras.export import export_model, report_sfm, write_points
from pipeline.cameras.mapping import prepare_sfm_input, sfm_threads
from pipeline.cameras.sfm import triangulate_at
from pipeline.colmaplib import write_model
from pipeline.errors import StageError
from pipeline.inputs.photos import downscale, read_photo
from pipeline.workspace import Workspace


def import_cameras(ws: Workspace, photos: list[Path], cam_file: Path, cfg: CamerasConfig) -> dict:
    """Use given cameras (IDR/NeuS/DVR cameras.npz, one world_mat per photo in sorted order): skip SfM."""
    try:
        n = len(load_cameras(cam_file).K)  # every entry checked: indices, shapes, numbers, decomposable
    except ValueError as exc:  # load_cameras' one line names the file, the entry and what to write
        raise StageError(str(exc)) from exc
    if n != len(photos):
        raise StageError(f"{cam_file}: {n} cameras for {len(photos)} photos; give one world_mat_i per photo")
    with np.load(cam_file) as z:  # the matrices as given, and whether a scale_mat was (load_cameras does not say)
        scale = next((np.asarray(z[k], float) for k in ("scale_mat", "scale_mat_0") if k in z.files), None)
        given = [decompose_projection(np.asarray(z[f"world_mat_{i}"], float)[:3, :4]) for i in range(n)]
    if cfg.triangulate_given:
        info = triangulate_given(ws, photos, cfg, given, scale)
        if info is not None:
            return {**info, "given": str(cam_file)}
    if ws.images.exists():
        shutil.rmtree(ws.images)
    ws.images.mkdir(parents=True)
    Ks, Rs, ts = [], [], []
    for p, (K, R, t) in zip(photos, given):
        full = read_photo(p)
        h, w = full.shape[:2]
        img = downscale(full, cfg.max_side)
        nh, nw = img.shape[:2]
        write_image(ws.images / f"{p.stem}.png", img)
        Ks.append(np.diag([nw / w, nh / h, 1.0]) @ K), Rs.append(R), ts.append(t)
    save_cameras(ws.cameras, np.stack(Ks), np.stack(Rs), np.stack(ts), np.eye(4) if scale is None else scale)
    write_points(ws.root / "points.ply", np.zeros((0, 3)), np.zeros((0, 3), np.uint8))
    return {"views": [p.stem for p in photos], "given": str(cam_file)}


def triangulate_given(ws: Workspace, photos: list[Path], cfg: CamerasConfig, given: list, scale: np.ndarray | None):
    """Given cameras (K for the full photo, R, t) get what our own SfM gives: features matched and triangulated at
    the given poses (:func:`pipeline.cameras.sfm.triangulate_at`), so sparse depth, the support plane and the masks'
    tracks exist too; a given scale_mat stays the object's sphere (else it is found as after SfM). None (and a warning)
    when too few points come out."""
    inp, _, shapes = prepare_sfm_input(ws, photos, cfg)
    names = [p.stem for p in photos]
    Ks = [np.diag([iw / w, ih / h, 1.0]) @ K for (K, _, _), ((h, w), (ih, iw)) in zip(given, shapes)]
    t0 = time.perf_counter()
    try:
        rec = triangulate_at(ws.root / "sfm" / "given", inp, names, np.stack(Ks), np.stack([g[1] for g in given]),
                             np.stack([g[2] for g in given]), cfg.matching, cfg.max_features, seed=cfg.seed,
                             threads=sfm_threads(cfg), max_h_inlier_ratio=cfg.max_h_inlier_ratio)
        n_points = rec.num_points3D()
    except Exception as exc:  # noqa: BLE001 — COLMAP failing here costs the depth, not the given cameras
        if is_disk_full(exc):  # unless the disk is full: the stage's one line (what follows would not fit either)
            raise
        rec, n_points = None, f"0 ({exc})"
    if rec is None or rec.num_points3D() < 50:
        print(f"warning: only {n_points} points triangulated at the given cameras: no sparse depth and no "
              "support plane (photos with little texture?)", file=sys.stderr)
        shutil.rmtree(ws.root / "sfm", ignore_errors=True)
        return None
    print(f"cameras: given cameras: {rec.num_points3D()} points triangulated at their poses "
          f"({rec.compute_mean_reprojection_error():.2f} px, track length {rec.compute_mean_track_length():.2f}) "
          f"in {time.perf_counter() - t0:.1f} s")
    write_model(rec, ws.root / "sfm" / "sparse" / "best")
    copy_file(ws.root / "sfm" / "given" / "given.db", ws.root / "sfm" / "database.db")
    info = report_sfm(rec, names, cfg)
    info.update(export_model(ws, rec, inp, cfg, names, scale_mat=scale))
    return info


def import_colmap_model(ws: Workspace, photos: list[Path], images: Path, model: Path, cfg: CamerasConfig) -> dict:
    """Use a given COLMAP sparse model (cameras/images/points3D .bin or .txt, image names relative to the photo
    folder): skip SfM, undistort and normalise as after our own SfM."""
    from pipeline.colmaplib import pycolmap

    try:
        rec = pycolmap.Reconstruction(model)
    except Exception as exc:  # noqa: BLE001
        raise StageError(f"{model}: not a COLMAP sparse model ({exc}); pass the folder holding cameras.bin, "
                         "images.bin and points3D.bin (or their .txt)") from exc
    missing = [rec.image(i).name for i in rec.reg_image_ids() if not (images / rec.image(i).name).exists()]
    if rec.num_reg_images() == 0 or missing:
        raise StageError(f"{model}: {len(missing) or 'no'} registered image(s) of the model not found in {images} "
                         f"({', '.join(missing[:5])}); pass the photo folder the model was made from")
    write_model(rec, ws.root / "sfm" / "sparse" / "best")
    names = [p.stem for p in photos]
    info = report_sfm(rec, names, cfg)
    info.update(export_model(ws, rec, images, cfg, names))
    info["given"] = str(model)
    return info
