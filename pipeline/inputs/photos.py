"""Reading a photo folder as it comes from a camera or a phone.

Every photo is read UPRIGHT (its EXIF orientation applied: phones write portrait shots as landscape pixels plus
a flag 6 or 8, upside-down ones with 3) as 8-bit BGR: grayscale photos become three equal channels, an alpha
channel is dropped, 16-bit PNG/TIFF are scaled to 8 bits, HEIC/HEIF (the iPhone default) is decoded with
pillow-heif. The same upright pixels go to SfM and to every later stage.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from dvr.data import IMAGE_EXTS as TRAINING_EXTS
from pipeline.errors import StageError

HEIF_EXTS = {".heic", ".heif"}
PHOTO_EXTS = set(TRAINING_EXTS) | HEIF_EXTS


def _read_heif(path: Path) -> np.ndarray | None:
    try:
        from PIL import Image, ImageOps
        from pillow_heif import register_heif_opener
    except ImportError:  # pragma: no cover - pillow-heif is a declared dependency
        return None
    register_heif_opener()
    try:
        with Image.open(path) as im:
            rgb = np.asarray(ImageOps.exif_transpose(im).convert("RGB"))
    except Exception:  # noqa: BLE001 - any decoder failure means "unreadable"
        return None
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)


def read_photo(path: str | Path) -> np.ndarray | None:
    """(H, W, 3) uint8 BGR, upright; None when the file cannot be decoded."""
    path = Path(path)
    if path.suffix.lower() in HEIF_EXTS:
        return _read_heif(path)
    img = cv2.imread(str(path), cv2.IMREAD_COLOR | cv2.IMREAD_ANYDEPTH)  # EXIF orientation applied
    if img is None:
        return None
    if img.dtype == np.uint16:
        img = np.round(img.astype(np.float32) / 257.0).astype(np.uint8)
    elif img.dtype != np.uint8:
        img = np.clip(img.astype(np.float32) * (255.0 if img.max() <= 1.0 else 1.0), 0, 255).astype(np.uint8)
    return img


def is_readable(path: Path) -> bool:
    """Cheap check that a photo decodes (JPEGs at 1/8 scale)."""
    if path.suffix.lower() in HEIF_EXTS:
        return _read_heif(path) is not None
    return cv2.imread(str(path), cv2.IMREAD_REDUCED_GRAYSCALE_8) is not None or read_photo(path) is not None


def read_upright(path: Path, max_side: int) -> np.ndarray | None:
    """:func:`read_photo` downscaled (INTER_AREA) so its longest side ≤ ``max_side`` (never upscaled)."""
    img = read_photo(path)
    return None if img is None else downscale(img, max_side)


def downscale(img: np.ndarray, max_side: int) -> np.ndarray:
    """``img`` downscaled (INTER_AREA) so its longest side ≤ ``max_side``; itself when it already is."""
    h, w = img.shape[:2]
    s = min(1.0, max_side / max(h, w))
    if s < 1.0:
        img = cv2.resize(img, (max(1, round(w * s)), max(1, round(h * s))), interpolation=cv2.INTER_AREA)  # a
        # panorama strip's short side would round to 0 (OpenCV's "inv_scale_x > 0" assertion)
    return img


def list_photos(folder: Path) -> tuple[list[Path], list[str]]:
    """Readable photos (sorted) and warnings about the files skipped; several photos with one stem (IMG_1.jpg and
    IMG_1.heic) are an error, since every later stage names its files by stem."""
    if not folder.is_dir():
        raise StageError(f"{folder}: not a folder of photos or a video; pass --images DIR (or a video file)")
    ok, skipped = [], []
    for p in sorted(folder.iterdir()):
        if not p.is_file() or p.name.startswith("."):
            continue
        if p.suffix.lower() not in PHOTO_EXTS:
            skipped.append(f"{p.name} (not an image file)")
            continue
        if not is_readable(p):
            skipped.append(f"{p.name} (unreadable)")
            continue
        ok.append(p)
    by_stem: dict[str, list[str]] = {}
    for p in ok:
        by_stem.setdefault(p.stem, []).append(p.name)
    dup = sorted(" and ".join(v) for v in by_stem.values() if len(v) > 1)
    if dup:
        raise StageError(f"{folder}: {'; '.join(dup[:3])}{' …' if len(dup) > 3 else ''} share a name with different "
                         "extensions (the same shot twice?); keep one of each or rename them")
    return ok, skipped
