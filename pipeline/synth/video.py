"""A synthetic scene's frames written as a hand-held video: what a phone user films instead of taking photos.

The renders of a scene whose cameras follow one path (``cameras.orbit_turns``) become the frames of an MP4
(MPEG-4 part 2, the encoder OpenCV's wheels carry), every ``shake_every``-th frame smeared by a linear motion blur
of ``shake_px`` pixels, as a walking hand shakes the phone now and then. ``out.with_suffix('.json')`` records which
frames are shaken, so tests can check that the sharp ones are chosen.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np


def motion_blur(img: np.ndarray, length: int, angle_deg: float) -> np.ndarray:
    """``img`` smeared along a line of ``length`` pixels at ``angle_deg`` (a camera shake during the exposure)."""
    k = np.zeros((length, length), np.float32)
    k[length // 2, :] = 1.0
    rot = cv2.getRotationMatrix2D(((length - 1) / 2, (length - 1) / 2), angle_deg, 1.0)
    k = cv2.warpAffine(k, rot, (length, length))
    return cv2.filter2D(img, -1, k / k.sum(), borderType=cv2.BORDER_REFLECT)


def write_video(images: Path, out: Path, fps: float = 30.0, shake_every: int = 3, shake_px: int = 9,
                codec: str = "mp4v") -> Path:
    """Write the PNG renders of ``images`` (sorted) as the frames of the video ``out`` (``codec``: a FourCC OpenCV
    writes, 'mp4v' for .mp4, 'MJPG' for .avi); frame k is shaken when ``shake_every`` > 0 and k % shake_every == 1."""
    frames = sorted(Path(images).glob("*.png"))
    first = cv2.imread(str(frames[0]), cv2.IMREAD_COLOR)
    h, w = first.shape[:2]
    out.parent.mkdir(parents=True, exist_ok=True)
    writer = cv2.VideoWriter(str(out), cv2.VideoWriter_fourcc(*codec), fps, (w, h))
    if not writer.isOpened():
        raise RuntimeError(f"{out}: OpenCV cannot write {codec} here")
    shaken = []
    for k, p in enumerate(frames):
        img = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if shake_every > 0 and k % shake_every == 1:
            img = motion_blur(img, shake_px, 37.0 * k)
            shaken.append(k)
        writer.write(img)
    writer.release()
    out.with_suffix(".json").write_text(json.dumps({"frames": len(frames), "shaken": shaken, "fps": fps}))
    return out
