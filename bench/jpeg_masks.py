"""What a clip's compression does to the automatic masks: the bench's filmed cow (``bench/video.py``'s one-turn path,
96 frames, every second one taken) through the cameras and masks stages: the lossless renders (``png``), the renders
saved as JPEGs at the working size (``jpeg``, 400×300 as the stages use them), the frames of the MPEG-4 clip as
decoded, saved losslessly (``decoded``; every third frame shaken, as ``bench/video.py``'s clip), the same clip with
no frame shaken (``decoded_still``), and the renders enlarged twice (bicubic) and saved as JPEGs (``jpeg_x2``:
a photo larger than the working size, which the cameras stage shrinks, as it does a phone's photos). The scene
rendered at 3 × the size (``photo_scale``: 1200 × 900, as a phone's photos or an HD clip's frames, which the
cameras stage shrinks): as JPEGs (``jpeg_3x``), and as its MPEG-4 clip decoded (``decoded_3x``; the shake 3 × as
long, the same blur at the working size).

    python bench/jpeg_masks.py [--quality 95] [--arms png jpeg decoded decoded_still jpeg_x2 jpeg_3x decoded_3x]
                               [--picture FILE.jpg]

Prints per arm: frames registered, mask IoU against the true masks (mean, and the five worst frames).
``--picture``: two frames, the photo and the masks' errors of the lossless and the JPEG arm (red: background taken
as object; blue: object missed).
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import evaluate as ev  # noqa: E402

OVER = {"cameras": {"n_views": 96, "orbit_turns": 1.0, "rings": 0, "heldout": 4}}  # bench/video.py's one-turn clip
TAKEN = list(range(0, 96, 2))
ARMS = ("png", "jpeg", "decoded", "decoded_still", "jpeg_x2", "jpeg_3x", "decoded_3x")
SHAKE_PX = 9
"""``synth.video.write_video``'s shake at the working size."""


def arm_photos(syn: Path, arm: str, out: Path, quality: int) -> Path:
    """The taken frames as the arm writes them into ``out`` (``syn``: the scene at the arm's size)."""
    import cv2

    from synth.phone import save_jpeg
    from synth.video import write_video

    out.mkdir(parents=True)
    frames = None
    if arm.startswith("decoded"):
        shake = {"shake_every": 0} if arm == "decoded_still" else {"shake_px": SHAKE_PX * (3 if "3x" in arm else 1)}
        clip = write_video(syn / "images", out.parent / "clip.mp4", codec="mp4v", **shake)
        cap = cv2.VideoCapture(str(clip))
        frames = []
        while (got := cap.read())[0]:
            frames.append(got[1])
    for k in TAKEN:
        src = syn / "images" / f"{k:06d}.png"
        if arm == "png":
            shutil.copy2(src, out / src.name)
        elif arm.startswith("jpeg"):
            img = cv2.imread(str(src))
            if arm == "jpeg_x2":
                img = cv2.resize(img, None, fx=2, fy=2, interpolation=cv2.INTER_CUBIC)
            save_jpeg(img, out / f"{k:06d}.jpg", quality=quality)  # PIL, 4:2:0 as phones: photos_folder's
        else:
            cv2.imwrite(str(out / src.name), frames[k])
    return out


def error_view(img: np.ndarray, mask: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """The photo dimmed, object taken right brightened, red where background was taken, blue where object missed."""
    v = (img * 0.5).astype(np.uint8)
    v[mask & gt] = (img[mask & gt] * 0.8 + 40).astype(np.uint8)
    v[mask & ~gt] = (0, 0, 255)
    v[gt & ~mask] = (255, 0, 0)
    return v


def main() -> None:
    import cv2

    from dvr.data import list_images

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quality", type=int, default=95, help="JPEG quality of the jpeg arm")
    ap.add_argument("--arms", nargs="+", default=list(ARMS), choices=ARMS)
    ap.add_argument("--picture", type=Path, default=None, help="needs the png and jpeg arms")
    a = ap.parse_args()
    syn = ev.scene("cow", OVER)
    syn_3x = None  # rendered when an arm needs it (≈ 8 min)
    work = ev.RUNS / "jpeg_masks"
    masks = {}
    for arm in a.arms:
        shutil.rmtree(work / arm, ignore_errors=True)
        ws = work / arm / "ws"
        if "3x" in arm and syn_3x is None:
            syn_3x = ev.scene("cow", {"cameras": {**OVER["cameras"], "photo_scale": 3}})
        ev.stages(("cameras", "masks"), ws, ev.config("default"),
                  images=arm_photos(syn_3x if "3x" in arm else syn, arm, work / arm / "photos", a.quality))
        names = [p.stem for p in list_images(ws / "images")]
        gt = {n: syn / "gt" / "masks" / f"{n}.png" for n in names}
        per = {n: ev.view_mask_iou(ws / "masks" / f"{n}.png", gt[n]) for n in names}
        masks[arm] = ws
        print(json.dumps({"arm": arm, "quality": a.quality if arm.startswith("jpeg") else None,
                          "registered": f"{len(names)}/{len(TAKEN)}", "mask_iou": float(np.mean(list(per.values()))),
                          "worst": [[n, round(v, 4)] for n, v in sorted(per.items(), key=lambda x: x[1])[:5]]}),
              flush=True)
    if a.picture is not None and {"png", "jpeg"} <= set(masks):
        rows = []
        for n in ("000016", "000022"):
            img = cv2.imread(str(masks["png"] / "images" / f"{n}.png"))
            gt = cv2.imread(str(syn / "gt" / "masks" / f"{n}.png"), 0) > 127
            rows.append(np.hstack([img] + [error_view(img, cv2.imread(str(masks[arm] / "masks" / f"{n}.png"), 0) > 127,
                                                      gt) for arm in ("png", "jpeg")]))
        cv2.imwrite(str(a.picture), np.vstack(rows), [cv2.IMWRITE_JPEG_QUALITY, 90])


if __name__ == "__main__":
    main()
