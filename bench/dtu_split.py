"""Where DTU's textured mesh misses its training photos: the squared error at the training views split into the
pixels where the automatic mask says object and the mesh is absent, the mesh is present outside the mask, and
both agree; on those, the PSNR per view raw, after fitting the view's colour gains, and against the photo blurred
by a Gaussian of ``--blur`` px (a texture as sharp as that blur scores alike). The agreeing pixels are also split by
the photo's colour (the red brick walls, the grey and white roofs and window frames), with each view's mean error on
the grey ones (a view that sees the roofs brighter or darker than the texture shows them); and the bench's PSNR per
view is given again with the smooth part of each view's error (a Gaussian of ``--smooth`` px over the agreeing
pixels) taken out: what no diffuse texture can show (shading that changes with the view, exposure) goes with it,
and what is left is the sharp part (where the views disagree about detail on this mesh). Run after ``python
bench/dtu_arm.py`` (it reads that arm's workspace):

    python bench/dtu_split.py [--blur 1.5] [--smooth 6] [--full bench/runs/dtu_all]
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


def colour_classes(photo: np.ndarray) -> dict[str, np.ndarray]:
    """(H, W) bool per class of a photo's pixels (RGB in [0, 1]): saturated red (brick), grey (saturation < 0.2:
    roofs, window frames, the base plate), the rest."""
    import cv2

    hsv = cv2.cvtColor((photo * 255).astype(np.uint8), cv2.COLOR_RGB2HSV)
    sat, hue = hsv[..., 1] / 255.0, hsv[..., 0]
    red, grey = (sat > 0.35) & ((hue < 15) | (hue > 160)), sat < 0.2
    return {"red": red, "grey": grey, "other": ~red & ~grey}


def without_smooth_error(img: np.ndarray, photo: np.ndarray, where: np.ndarray, sigma: float) -> np.ndarray:
    """The render ``img`` less the smooth part of its error against ``photo`` on the pixels ``where`` (the error
    blurred by a Gaussian of ``sigma`` px, normalised by the blurred weight of ``where``): the sharp error is left."""
    import cv2

    diff = (img - photo) * where[..., None]
    weight = cv2.GaussianBlur(where.astype(float), (0, 0), sigma)[..., None]
    smooth = cv2.GaussianBlur(diff, (0, 0), sigma) / np.maximum(weight, 1e-6)
    return img - smooth * where[..., None]


def main() -> None:
    import cv2

    from dvr.cameras import load_cameras
    from dvr.data import list_images
    from dvr.metrics import masked_psnr
    from pipeline.render.textured import render_textured

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--blur", type=float, default=1.5)
    ap.add_argument("--smooth", type=float, default=6.0, help="px of the Gaussian that takes the error's smooth part")
    ap.add_argument("--full", type=Path, default=ev.RUNS / "dtu_all", help="the arm's cameras, masks and photos")
    a = ap.parse_args()
    ws = ev.RUNS / "work" / "dtu_arm" / "ws"
    cams, paths = load_cameras(a.full / "cameras.npz"), list_images(a.full / "images")
    held, (tm, tex) = ev.dtu_heldout(len(paths)), ev.textured(ws)
    parts = {"mask_not_mesh": [0.0, 0], "mesh_not_mask": [0.0, 0], "both": [0.0, 0]}
    raw, fitted, blurred, gains = [], [], [], {}
    classes = {k: [0.0, 0] for k in ("red", "grey", "other")}
    grey_bias, bench, sharp_only, sharp_only_both = {}, [], [], []
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
        for key, m in colour_classes(photo).items():
            classes[key][0] += float(se[m & both].sum())
            classes[key][1] += int((m & both).sum())
            if key == "grey" and (m & both).any():
                grey_bias[path.stem] = round(float((img - photo)[m & both].mean()), 3)
        sharp = without_smooth_error(img, photo, both, a.smooth)
        bench.append(ev.image_psnr(img, hit, photo, mask))
        sharp_only.append(ev.image_psnr(sharp, hit, photo, mask))
        sharp_only_both.append(masked_psnr(sharp, photo, both))
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
        "both_by_colour": {k: {"share_of_error": round(se / total_se, 3), "share_of_pixels": round(n / total_px, 4),
                               "psnr": round(psnr(se / max(3 * n, 1)), 2)} for k, (se, n) in classes.items()},
        "grey_mean_error_per_view": grey_bias,
        "bench_psnr_per_view": {"as_is": round(float(np.mean(bench)), 2),
                                f"smooth_error_removed_{a.smooth:g}px": round(float(np.mean(sharp_only)), 2),
                                "same_on_both_only": round(float(np.mean(sharp_only_both)), 2)},
        "gains": gains}))


if __name__ == "__main__":
    main()
