"""The training's per-view appearance (model/appearance.json) undone on the photos before the bake."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from dvr.appearance import relative_gains
from dvr.data import read_rgb
from pipeline.errors import StageError
from pipeline.texture.blend import clipped_pixels
from pipeline.texture.config import TextureConfig


def read_appearance(path: Path) -> dict:
    """The per-view gains training wrote (``model/appearance.json``: image name → {"gain": [r, g, b]}), checked:
    a StageError naming the file when it is unreadable or a gain is not finite and positive (a hand-edited file)."""
    try:
        looks = json.loads(Path(path).read_text())
        gains = np.array([t["gain"] for t in looks.values()], np.float64)
    except (OSError, ValueError, TypeError, KeyError, AttributeError) as exc:
        raise StageError(f"{path}: unreadable per-view gains ({type(exc).__name__}); retrain (train --force)") from exc
    if gains.shape != (len(looks), 3):  # a scalar gain or a pair: training writes one gain per channel
        raise StageError(f"{path}: each view's gain must be 3 numbers (R, G, B); retrain (train --force)")
    if not (np.isfinite(gains).all() and (gains > 0).all()):
        raise StageError(f"{path}: per-view gains must be finite and positive; retrain (train --force)")
    return looks


def relative_looks(looks: dict) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Per image name of ``looks`` (``model/appearance.json``) its gain relative to the average view (3,), and the
    common gain (3,) (:func:`dvr.appearance.relative_gains`; ones without any gain). Gains are clamped at 1e-3: a
    hand-edited zero gives no inf or NaN."""
    fitted = {n: np.maximum(np.asarray(t["gain"], np.float64), 1e-3) for n, t in looks.items()}
    if not fitted:
        return {}, np.ones(3)
    rel, common = relative_gains(np.stack(list(fitted.values())))
    return dict(zip(fitted, rel)), common


def undo_appearance(images: list[np.ndarray], names: list[str], looks: dict) -> tuple[list[np.ndarray], np.ndarray]:
    """Each photo mapped back to the colour of the average view: ``photo / relative gain`` with the view's fitted
    transform (``model/appearance.json``) taken relative to all views' (:func:`dvr.appearance.relative_gains`), so
    views of different exposure agree before they are blended and a drift common to all gains does not tint the
    texture. Returns the photos and the common gain (3,), by which the field's colours are to be scaled."""
    rel_of, common = relative_looks(looks)
    out = [img if name not in rel_of else np.clip(img / rel_of[name].astype(np.float32), 0.0, 1.0)
           for img, name in zip(images, names)]
    return out, common


def photos_for_bake(paths: list[Path], looks: Path, cfg: TextureConfig):
    """The photos the bake blends, the common gain of the texture field's colours and the photos' over-exposed
    pixels: with per-view gains (``looks``, ``model/appearance.json``) the photos mapped back to the average view
    (:func:`undo_appearance`) and their clipped pixels, found in the photos as taken (undoing a gain moves them
    off 1); without, the photos as they are, a gain of 1 and no clipped pixels (``TextureConfig.clipped_level``)."""
    images = [read_rgb(p) for p in paths]
    if not looks.exists():
        return images, np.ones(3), None
    clipped = [clipped_pixels(im, cfg.clipped_level) for im in images]
    images, field_gain = undo_appearance(images, [p.stem for p in paths], read_appearance(looks))
    return images, field_gain, clipped
