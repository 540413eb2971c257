"""A synthetic scene's photos written as a phone's folder: what users bring.

Phones store the sensor's pixels and an EXIF orientation flag telling viewers how to turn them upright: 1 (as
is), 6 (turn 90° clockwise: a portrait shot), 3 (180°: upside down), 8 (90° counter-clockwise). A rendered view
stored with flag f is therefore the photo of a camera ROLLED accordingly: its upright image is the render turned
as the flag says (portrait for 6 and 8). :func:`upright_roll` gives that roll, so tests compare poses with it.
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

FLAGS = (1, 6, 3, 8)
ROLL_DEG = {1: 0.0, 6: 90.0, 3: 180.0, 8: 270.0}
"""Clockwise turn of the stored pixels that a viewer applies for each flag (the camera's roll, seen upright)."""


def upright_roll(R: np.ndarray, flag: int) -> np.ndarray:
    """World→camera rotation of the upright photo of a view rendered with ``R`` and stored with ``flag``: the
    image turned clockwise by θ is the camera rolled about its optical axis (for 90°: x' = −y, y' = x)."""
    th = np.radians(ROLL_DEG[flag])
    c, s = np.cos(th), np.sin(th)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ R


def save_jpeg(img_bgr: np.ndarray, path: Path, flag: int = 1, quality: int = 92) -> None:
    """JPEG with an EXIF orientation tag (the pixels are stored as given)."""
    im = Image.fromarray(cv2.cvtColor(img_bgr, cv2.COLOR_BGR2RGB))
    exif = Image.Exif()
    exif[0x0112] = flag
    buf = io.BytesIO()
    im.save(buf, "JPEG", quality=quality, exif=exif.tobytes())
    path.write_bytes(buf.getvalue())


def write_phone_folder(images: Path, out: Path, upscale_every: int = 4) -> Path:
    """Write the PNG renders of ``images`` into ``out`` as a phone's JPEGs: flags 1, 6, 3, 8 in turn (pixels as
    rendered), every ``upscale_every``-th photo stored at twice the size (another camera), file names with spaces;
    ``out/../phone_flags.json`` maps each stem to (source stem, flag, scale)."""
    out.mkdir(parents=True, exist_ok=True)
    record = {}
    for k, p in enumerate(sorted(Path(images).glob("*.png"))):
        img = cv2.imread(str(p), cv2.IMREAD_COLOR)
        flag = FLAGS[k % len(FLAGS)]
        scale = 2 if upscale_every and k % upscale_every == upscale_every - 1 else 1
        if scale > 1:
            img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_CUBIC)
        stem = f"IMG {p.stem}"
        save_jpeg(img, out / f"{stem}.jpg", flag)
        record[stem] = {"source": p.stem, "flag": flag, "scale": scale}
    (out.parent / "phone_flags.json").write_text(json.dumps(record, indent=1))
    return out
