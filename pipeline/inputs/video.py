"""A video instead of a photo folder: the frames the cameras stage works from.

Phone users often film the object walking around it rather than take photos. A clip given as ``--images`` (or
``make reconstruct IMAGES=clip.mp4``) is cut into ``n`` stretches of equal length and the sharpest frame of each
(the variance of its Laplacian, on a copy at most 480 pixels wide) is written to the workspace's ``frames/`` as a
JPEG, its longest side at most the SfM size; ``frames/frames.json`` says which frame of the clip each one is. The
clip itself is only read. Frames are turned upright as the clip's rotation tag says (OpenCV's FFmpeg reader).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from dvr.atomic import atomic_path, write_image, write_json
from pipeline.errors import StageError
from pipeline.inputs.photos import downscale

VIDEO_EXTS = {".mp4", ".mov", ".m4v", ".avi", ".mkv", ".webm", ".3gp", ".mts"}
SHARPNESS_SIDE = 480
"""Longest side of the grey copy a frame's sharpness is measured on (motion blur shows at any size)."""


def is_video(path: Path) -> bool:
    """A file whose extension names a video container."""
    return path.is_file() and path.suffix.lower() in VIDEO_EXTS


def sharpness(frame: np.ndarray) -> float:
    """Variance of the Laplacian of the frame's grey copy (at most :data:`SHARPNESS_SIDE` wide): low when blurred."""
    grey = cv2.cvtColor(downscale(frame, SHARPNESS_SIDE), cv2.COLOR_BGR2GRAY)
    return float(cv2.Laplacian(grey, cv2.CV_64F).var())


def choose_frames(scores: np.ndarray, n: int) -> list[int]:
    """Indices of the sharpest frame in each of ``n`` equal stretches of the clip (every frame when it has no more
    than ``n``; the first of equals)."""
    if n < 1:
        raise ValueError(f"n must be ≥ 1, got {n}")
    edges = np.linspace(0, len(scores), min(n, len(scores)) + 1).round().astype(int)
    return [int(a + np.argmax(scores[a:b])) for a, b in zip(edges[:-1], edges[1:])]


def _open(video: Path) -> cv2.VideoCapture:
    cap = cv2.VideoCapture(str(video), cv2.CAP_FFMPEG)
    if not cap.isOpened():
        raise StageError(f"{video}: cannot be read as a video (OpenCV's FFmpeg); convert it to MP4, or put its "
                         "frames in a folder and pass that")
    cap.set(cv2.CAP_PROP_ORIENTATION_AUTO, 1)  # upright, as the clip's rotation tag says
    return cap


def _frames(cap: cv2.VideoCapture):
    """(index, BGR frame) of every frame of an opened clip, in order; the clip is released at the end."""
    try:
        k = 0
        while True:
            ok, frame = cap.read()
            if not ok:
                return
            yield k, frame
            k += 1
    finally:
        cap.release()


def extract_frames(video: Path, out: Path, n: int, max_side: int) -> dict:
    """Write the sharpest frame of each of ``n`` equal stretches of ``video`` into the folder ``out`` (replaced as a
    whole, so a run cut short leaves no mix); returns the record written to ``out/frames.json`` (the clip, its frame
    count, and per frame taken its file, index in the clip, time and sharpness)."""
    cap = _open(video)
    fps = cap.get(cv2.CAP_PROP_FPS) or 0.0
    scores = np.array([sharpness(f) for _, f in _frames(cap)])
    if len(scores) < 3:
        raise StageError(f"{video}: {len(scores)} frame(s) could be read; at least 3 are needed (a clip walking "
                         "once around the object is typical)")
    chosen = choose_frames(scores, n)
    wanted = dict(zip(chosen, range(len(chosen))))
    taken = []
    with atomic_path(out, folder=True) as tmp:
        for k, frame in _frames(_open(video)):
            if k in wanted:
                name = f"frame{wanted[k]:04d}.jpg"
                write_image(tmp / name, downscale(frame, max_side), [cv2.IMWRITE_JPEG_QUALITY, 95])
                taken.append({"file": name, "frame": k, "seconds": round(k / fps, 3) if fps > 0 else None,
                              "sharpness": round(float(scores[k]), 2)})
        record = {"video": str(video), "frames_in_clip": int(len(scores)), "chosen": taken}
        write_json(tmp / "frames.json", record, indent=1)
    return record
