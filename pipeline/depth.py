"""Stage ``depth``: sparse depth per view from the SfM tracks → ``depth/<stem>.npz``.

Only the views that observe a point get it; points are kept when their track is long enough, their
reprojection error small, and they lie inside the object's unit sphere (and above the support plane, when the
object stands on one). Each file holds ``uv`` (K, 2)
continuous pixel coordinates of images/ (pixel centres at +0.5), ``depth`` (K,) the Euclidean distance from
the camera centre along the ray in the NORMALIZED frame (dvr's ray depth), ``confidence`` (K,) in (0, 1].
"""

from __future__ import annotations

import shutil
import time

import cv2
import numpy as np

from dvr.cameras import load_cameras, plane_height
from dvr.data import list_images

from .cameras_config import DepthConfig
from .config import config_hash
from .support import GROUND_BAND
from .workspace import Workspace


def run(ws: Workspace, cfg: DepthConfig, force: bool = False) -> bool:
    ws.require(ws.images, ws.cameras, hint="run the cameras stage first")
    model = ws.root / "sfm" / "undistorted" / "sparse"
    paths = list_images(ws.images)
    h = config_hash(cfg)
    if not force and ws.up_to_date("depth", h, [ws.cameras, ws.root / "sfm"], [ws.depth]):
        print(f"depth: up to date ({ws.depth})")
        return False
    ws.clear("depth")
    t0 = time.perf_counter()
    if ws.depth.exists():
        shutil.rmtree(ws.depth)
    if not model.exists():
        print(f"depth: no SfM model ({model}; cameras were given), no sparse depth written")
        ws.mark_done("depth", h, time.perf_counter() - t0, {"points": 0})
        return True
    import pycolmap

    rec = pycolmap.Reconstruction(model)
    cams = load_cameras(ws.cameras, n_views=len(paths))
    S = cams.scale_mat
    ws.depth.mkdir(parents=True)
    by_name = {rec.image(i).name.rsplit(".", 1)[0]: rec.image(i) for i in rec.reg_image_ids()}
    total = 0
    for v, p in enumerate(paths):
        im = by_name.get(p.stem)
        if im is None:
            continue
        cam = rec.camera(im.camera_id)
        img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        sx, sy = img.shape[1] / cam.width, img.shape[0] / cam.height
        center = cams.centers[v]
        uv, dep, conf = [], [], []
        for p2 in im.points2D:
            if not p2.has_point3D():
                continue
            P3 = rec.points3D[p2.point3D_id]
            tl = P3.track.length()
            if tl < cfg.min_track_length or P3.error > cfg.max_reprojection_error:
                continue
            xn = (np.asarray(P3.xyz) - S[:3, 3]) / S[0, 0]
            if np.linalg.norm(xn) >= 1.0 or (cams.ground is not None and plane_height(cams.ground, xn) < GROUND_BAND):
                continue  # outside the object's sphere, or on the floor it stands on
            uv.append((p2.xy[0] * sx, p2.xy[1] * sy))
            dep.append(np.linalg.norm(xn - center))
            conf.append(min(1.0, (tl - 1) / 4.0) * float(np.exp(-0.5 * (P3.error / cfg.max_reprojection_error) ** 2)))
        np.savez(ws.depth / f"{p.stem}.npz", uv=np.asarray(uv, np.float32).reshape(-1, 2),
                 depth=np.asarray(dep, np.float32), confidence=np.asarray(conf, np.float32))
        total += len(dep)
    ws.mark_done("depth", h, time.perf_counter() - t0, {"points": total})
    print(f"depth: {total} sparse depths in {len(paths)} views → {ws.depth}")
    return True
