"""Where DTU's textured mesh misses its training photos: the squared error at the training views split into the
pixels where the automatic mask says object and the mesh is absent, the mesh is present outside the mask, and
both agree; on those, the PSNR per view raw, after fitting the view's colour gains, and against the photo blurred
by a Gaussian of ``--blur`` px (a texture as sharp as that blur scores alike). Run after ``python bench/dtu_arm.py``
(it reads that arm's workspace):

    python bench/dtu_split.py [--blur 1.5] [--full bench/runs/dtu_all]
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import evaluate as ev  # noqa: E402


def psnr(mse: float) -> float:
    return float(10 * np.log10(1.0 / max(mse, 1e-12)))


def main() -> None:
    import cv2

    from dvr.cameras import load_cameras
    from dvr.data import list_images
    from dvr.metrics import masked_psnr
    from pipeline.texture import render_textured

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--blur", type=float, default=1.5)
    ap.add_argument("--full", type=Path, default=ev.RUNS / "dtu_all", help="the arm's cameras, masks and photos")
    a = ap.parse_args()
    ws = ev.RUNS / "work" / "dtu_arm" / "ws"
    cams, paths = load_cameras(a.full / "cameras.npz"), list_images(a.full / "images")
    held, (tm, tex) = ev.dtu_heldout(len(paths)), ev.textured(ws)
    parts = {"mask_not_mesh": [0.0, 0], "mesh_not_mask": [0.0, 0], "both": [0.0, 0]}
    raw, fitted, blurred, gains = [], [], [], {}
    for i, path in enumerate(paths):
        if i in held:
            continue
        photo = ev._read_rgb(path)
        img, hit = render_textured(tm.vertices, tm.faces, tm.visual.uv, tex, cams.K[i], cams.R[i],
                                   cams.sfm_centers[i], photo.shape[1], photo.shape[0])
        mask = ev._read_mask(a.full / "masks" / f"{path.stem}.png")
        se = ((img - photo) ** 2).sum(-1)
        for key, m in (("mask_not_mesh", mask & ~hit), ("mesh_not_mask", ~mask & hit), ("both", mask & hit)):
            parts[key][0] += float(se[m].sum())
            parts[key][1] += int(m.sum())
        both = mask & hit
        gains[path.stem] = [round(float(x), 3) for x in ev.photo_gains(img, photo, both)]
        raw.append(ev.image_psnr(img, both, photo, both))
        fitted.append(ev.image_psnr(img, both, photo, both, gain_fit=True))
        blurred.append(masked_psnr(img, cv2.GaussianBlur(photo, (0, 0), a.blur), both))
    total_se, total_px = sum(v[0] for v in parts.values()), sum(v[1] for v in parts.values())
    print(json.dumps({
        "parts": {k: {"share_of_error": round(se / total_se, 3), "share_of_pixels": round(n / total_px, 4),
                      "psnr": round(psnr(se / max(3 * n, 1)), 2)} for k, (se, n) in parts.items()},
        "both_per_view": {"raw": round(float(np.mean(raw)), 2), "gains_fitted": round(float(np.mean(fitted)), 2),
                          f"against_photo_blurred_{a.blur}px": round(float(np.mean(blurred)), 2)},
        "gains": gains}))


if __name__ == "__main__":
    main()
