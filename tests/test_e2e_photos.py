"""End to end through COLMAP on a synthetic scene (no GT cameras or masks given to the pipeline):
cameras → masks → depth → train → mesh → texture with the default preset; Chamfer ≤ 2 % of the GT diagonal
after Sim(3) alignment, and PSNR ≥ 25 dB of the textured mesh rendered at the held-out views' GT poses (they lie
between the training views), over the object's pixels in the photo OR the rendering (a silhouette error counts
against it).

The held-out photos come from the camera SfM calibrated, so they are rendered with its estimated focal length
(as NeRF evaluations on COLMAP poses do). Orbit captures hardly fix the focal length against the object's
scale: on this scene the bundle-adjustment error with GT poses is flat over ±0.5 % of focal (0.1907–0.1912
px), and COLMAP lands 0.4–0.6 % short; pairing the GT focal with the reconstruction measures that gauge, not
the reconstruction (≈ 26 dB here, 24.9 dB on one CI machine). That number is printed and must stay ≥ 23 dB,
so a focal length really off still fails."""

import json

import cv2
import numpy as np
import pytest
import trimesh

from dvr.cameras import load_cameras
from dvr.metrics import chamfer_fscore, umeyama
from pipeline.cli import main
from pipeline.synth import load_scene_file, write_scene
from pipeline.texture import render_textured
from tests.conftest import ROOT

pytestmark = pytest.mark.slow


def _centres(c):
    return c.centers @ c.scale_mat[:3, :3].T + c.scale_mat[:3, 3]


def test_photos_to_textured_mesh(tmp_path):
    syn = tmp_path / "synthetic"
    write_scene(load_scene_file(ROOT / "configs" / "scenes" / "torus_smooth_backdrop.yaml"), syn)
    ws = tmp_path / "ws"
    cfg = ["--config", str(ROOT / "configs" / "default.yaml")]
    assert main(["cameras", str(ws), "--images", str(syn / "images"), *cfg]) == 0
    assert main(["masks", str(ws), *cfg]) == 0
    assert main(["depth", str(ws), *cfg]) == 0
    assert main(["train", str(ws), *cfg, "--train.no-progress"]) == 0
    assert main(["mesh", str(ws), *cfg]) == 0
    assert main(["texture", str(ws), *cfg, "--texture.size", "1024"]) == 0

    est, gt_cams = load_cameras(ws / "cameras.npz"), load_cameras(syn / "cameras.npz")
    s, R, t = umeyama(_centres(gt_cams), _centres(est))  # GT world → SfM frame
    gt = trimesh.load(syn / "gt" / "mesh.ply")
    gt.apply_transform(np.block([[s * R, t[:, None]], [np.zeros((1, 3)), np.ones((1, 1))]]))
    pred = trimesh.load(ws / "mesh" / "clean.ply")
    geo = chamfer_fscore(pred, gt, n=50000)

    tm = trimesh.load(ws / "mesh" / "textured.glb", force="mesh")
    tex = np.asarray(tm.visual.material.baseColorTexture.convert("RGB"), np.float32) / 255.0
    hc = load_cameras(syn / "gt" / "heldout" / "cameras.npz")
    K_est = est.K.mean(0)  # one camera: SfM's shared intrinsics
    psnrs, psnrs_gt_focal = [], []
    for i in range(len(hc)):
        Rg = hc.R[i] @ R.T  # the held-out camera in the SfM frame
        cg = s * R @ _centres(hc)[i] + t
        h, w = 240, 320
        photo = cv2.cvtColor(cv2.imread(str(syn / "gt" / "heldout" / "images" / f"{i:06d}.png")), cv2.COLOR_BGR2RGB)
        gmask = cv2.imread(str(syn / "gt" / "heldout" / "masks" / f"{i:06d}.png"), 0) > 127
        for K, out in ((K_est, psnrs), (hc.K[i], psnrs_gt_focal)):
            img, hit = render_textured(tm.vertices, tm.faces, tm.visual.uv, tex, K, Rg, cg, w, h)
            m = gmask | hit  # the object's pixels, in the photo or in the rendering
            out.append(-10 * np.log10(((img - photo / 255.0)[m] ** 2).mean()))
    print(json.dumps({**geo, "focal_est": K_est[0, 0], "focal_gt": hc.K[0][0, 0],
                      "psnr_heldout": [round(p, 2) for p in psnrs],
                      "psnr_heldout_gt_focal": [round(p, 2) for p in psnrs_gt_focal]}))
    assert geo["chamfer_rel"] <= 0.02
    assert geo["fscore"] >= 0.9
    assert np.mean(psnrs) >= 25.0
    assert np.mean(psnrs_gt_focal) >= 23.0
