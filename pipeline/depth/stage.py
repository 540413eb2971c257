"""Stage ``depth``: sparse depth per view from the SfM tracks → ``depth/<stem>.npz``.

Only the views that observe a point get it; points are kept when their track is long enough, their
reprojection error small, and they lie inside the object's unit sphere (and above the support plane, when the
object stands on one). Each file holds ``uv`` (K, 2)
continuous pixel coordinates of images/ (pixel centres at +0.5), ``depth`` (K,) the Euclidean distance from
the camera centre along the ray in the NORMALIZED frame (dvr's ray depth), ``confidence`` (K,) in (0, 1].
"""

from __future__ import annotations

import shutil

import numpy as np
from PIL import Image

from dvr.atomic import save_npz
from dvr.cameras import Cameras, load_cameras, plane_height, to_normalized
from dvr.data import list_images
from pipeline.depth.config import DepthConfig
from pipeline.readers import read_stage_model
from pipeline.scene.support import GROUND_BAND
from pipeline.workspace import Done, Job


def _view_depths(rec, im, scale_xy: tuple[float, float], center: np.ndarray, cams: Cameras, cfg: DepthConfig):
    """The sparse depths one registered view sees: pixel positions (at the training image size), distances from its
    camera centre in the normalised frame, and confidences from track length and reprojection error."""
    S = cams.scale_mat
    uv, dep, conf = [], [], []
    for p2 in im.points2D:
        if not p2.has_point3D():
            continue
        P3 = rec.points3D[p2.point3D_id]
        tl = P3.track.length()
        if tl < cfg.min_track_length or P3.error > cfg.max_reprojection_error:
            continue
        xn = to_normalized(np.asarray(P3.xyz), S, uniform=True)
        if np.linalg.norm(xn) >= 1.0 or (cams.ground is not None and plane_height(cams.ground, xn) < GROUND_BAND):
            continue  # outside the object's sphere, or on the floor it stands on
        uv.append((p2.xy[0] * scale_xy[0], p2.xy[1] * scale_xy[1]))
        dep.append(np.linalg.norm(xn - center))
        conf.append(min(1.0, (tl - 1) / 4.0) * float(np.exp(-0.5 * (P3.error / cfg.max_reprojection_error) ** 2)))
    return (np.asarray(uv, np.float32).reshape(-1, 2), np.asarray(dep, np.float32), np.asarray(conf, np.float32))


def run(job: Job) -> Done:
    """Stage ``depth`` (called by :func:`pipeline.stages.run_stage`): per view, the SfM points it observes with
    their distance from the camera → depth/<view>.npz (nothing without an SfM model: given cameras)."""
    ws, cfg = job.ws, job.cfg
    model = ws.sfm_model
    paths = list_images(ws.images)
    if ws.depth.exists():
        shutil.rmtree(ws.depth)
    if not model.exists():
        print(f"depth: no SfM model ({model}; cameras were given), no sparse depth written")
        return Done({"points": 0})
    rec = read_stage_model(model)
    cams = load_cameras(ws.cameras, n_views=len(paths))
    ws.depth.mkdir(parents=True)
    by_name = {rec.image(i).name.rsplit(".", 1)[0]: rec.image(i) for i in rec.reg_image_ids()}
    total = 0
    for v, p in enumerate(paths):
        im = by_name.get(p.stem)
        if im is None:
            continue
        cam = rec.camera(im.camera_id)
        with Image.open(p) as img:  # its size only: the header
            width, height = img.size
        uv, dep, conf = _view_depths(rec, im, (width / cam.width, height / cam.height),
                                     cams.centers[v], cams, cfg)
        save_npz(ws.depth / f"{p.stem}.npz", uv=uv, depth=dep, confidence=conf)
        total += len(dep)
    print(f"depth: {total} sparse depths in {len(paths)} views → {ws.depth}")
    return Done({"points": total})
