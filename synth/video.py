"""A synthetic scene's frames written as a hand-held video: what a phone user films instead of taking photos.

The renders of a scene whose cameras follow one path (``cameras.orbit_turns``) become the frames of a clip, every
``shake_every``-th frame smeared by a linear motion blur of ``shake_px`` pixels, as a walking hand shakes the phone
now and then. ``out.with_suffix('.json')`` records which frames are shaken, so tests can check that the sharp ones
are chosen.

Codecs: ``mp4v`` (MPEG-4 part 2) and ``MJPG`` through OpenCV's own writer; ``h264`` (8-bit, as most phones and
cameras record) and ``hevc`` (10-bit in a QuickTime ``.mov`` tagged ``hvc1``, as iPhones record) through the
FFmpeg binary of ``imageio-ffmpeg``, because OpenCV's wheels carry no H.264 or HEVC encoder. Those two can also
store the frames as a phone held upright does (``rotation``): the sensor's frame turned, with the container's
display-rotation tag saying how a player turns it back.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import cv2
import numpy as np

OPENCV_CODECS = {"mp4v", "MJPG"}
FFMPEG_CODECS = {  # x264 in plain C on one thread: its SIMD paths and thread count change the frames it encodes
    "h264": ["-c:v", "libx264", "-pix_fmt", "yuv420p", "-crf", "18", "-threads", "1", "-x264-params", "asm=0"],
    "hevc": ["-c:v", "libx265", "-pix_fmt", "yuv420p10le", "-tag:v", "hvc1", "-crf", "20",
             "-x265-params", "log-level=error"],
}


def motion_blur(img: np.ndarray, length: int, angle_deg: float) -> np.ndarray:
    """``img`` smeared along a line of ``length`` pixels at ``angle_deg`` (a camera shake during the exposure)."""
    k = np.zeros((length, length), np.float32)
    k[length // 2, :] = 1.0
    rot = cv2.getRotationMatrix2D(((length - 1) / 2, (length - 1) / 2), angle_deg, 1.0)
    k = cv2.warpAffine(k, rot, (length, length))
    return cv2.filter2D(img, -1, k / k.sum(), borderType=cv2.BORDER_REFLECT)


def write_video(images: Path, out: Path, fps: float = 30.0, shake_every: int = 3, shake_px: int = 9,
                codec: str = "mp4v", rotation: int = 0) -> Path:
    """Write the PNG renders of ``images`` (sorted) as the frames of the video ``out``; frame k is shaken when
    ``shake_every`` > 0 and k % shake_every == 1.

    ``codec``: 'mp4v' (.mp4) or 'MJPG' (.avi) through OpenCV, 'h264' (.mp4, .mov) or 'hevc' (.mov) through FFmpeg.
    ``rotation`` (0, 90, 180, 270; FFmpeg codecs only): degrees clockwise a player turns the stored frames to show
    them upright, as a phone's clip is tagged (OpenCV's ``CAP_PROP_ORIENTATION_META``); the frames are stored
    turned the other way, so the upright clip shows the renders."""
    if codec not in OPENCV_CODECS | FFMPEG_CODECS.keys():
        raise ValueError(f"codec must be one of {sorted(OPENCV_CODECS | FFMPEG_CODECS.keys())}, got {codec!r}")
    if rotation not in (0, 90, 180, 270) or (rotation and codec in OPENCV_CODECS):
        raise ValueError(f"rotation must be 0, 90, 180 or 270, and 0 for OpenCV's codecs; got {rotation} ({codec})")
    paths = sorted(Path(images).glob("*.png"))
    frames, shaken = [], []
    for k, p in enumerate(paths):
        img = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if shake_every > 0 and k % shake_every == 1:
            img = motion_blur(img, shake_px, 37.0 * k)
            shaken.append(k)
        frames.append(np.ascontiguousarray(np.rot90(img, rotation // 90)))
    out.parent.mkdir(parents=True, exist_ok=True)
    if codec in OPENCV_CODECS:
        _write_opencv(frames, out, fps, codec)
    else:
        _write_ffmpeg(frames, out, fps, FFMPEG_CODECS[codec], rotation)
    out.with_suffix(".json").write_text(json.dumps({"frames": len(frames), "shaken": shaken, "fps": fps,
                                                    "codec": codec, "rotation": rotation}))
    return out


def _write_opencv(frames: list[np.ndarray], out: Path, fps: float, codec: str) -> None:
    h, w = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(out), cv2.VideoWriter_fourcc(*codec), fps, (w, h))
    if not writer.isOpened():
        raise RuntimeError(f"{out}: OpenCV cannot write {codec} here")
    for img in frames:
        writer.write(img)
    writer.release()


def _write_ffmpeg(frames: list[np.ndarray], out: Path, fps: float, encode: list[str], rotation: int) -> None:
    import imageio_ffmpeg

    exe = imageio_ffmpeg.get_ffmpeg_exe()
    h, w = frames[0].shape[:2]
    plain = out.with_name(out.stem + ".untagged" + out.suffix)
    # bit-exact colour conversion: the same clip on every machine (with x264's options above)
    quiet = [exe, "-hide_banner", "-loglevel", "error", "-y", "-sws_flags", "accurate_rnd+bitexact"]
    subprocess.run([*quiet, "-f", "rawvideo", "-pix_fmt", "bgr24", "-s", f"{w}x{h}", "-r", str(fps), "-i", "-",
                    *encode, str(plain)], input=b"".join(f.tobytes() for f in frames), check=True)
    # the tag in a second pass that copies the stream: set on the raw input, FFmpeg would turn the frames instead
    subprocess.run([*quiet, "-display_rotation", str(-rotation), "-i", str(plain), "-c", "copy", str(out)], check=True)
    plain.unlink()
