"""The photos' exposure, measured on the SfM points before training: does a capture call for per-view appearance?

Phones and cameras on automatic set exposure and white balance per shot (or drift along a clip), so one object
point comes out brighter in one photo than in the next. Every SfM point is seen in several photos, which makes
that measurable before any training: in the log of the colour,

    log c[v, p] = log g[v] + log a[p]     (per channel; v a photo, p a point),

a gain per photo and an albedo per point, fitted by least squares with a Cauchy loss (a highlight, a shadow or a
wrong match is one outlier among a point's views), the gains taken relative to their mean over the photos. A
gain in linear light is a gain after the camera's gamma curve too (``dvr/appearance.py``), so sRGB photos do.

The cameras stage measures them once the photos are posed (``exposure.json``). The masks stage evens the photos
out by them before its plane-sweep stereo compares colours across views, and the train stage turns the per-view
appearance on (``--train.appearance auto``) when their spread says the photos differ: the bench's scenes without
exposure changes measure under 0.5 %, its cow photographed at ±25 % exposure 24 %, DTU's photos 28 %.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from dvr.atomic import write_json
from pipeline.errors import StageError

DARK, BRIGHT = 0.04, 0.96
"""Observations with a channel outside (DARK, BRIGHT) are left out: noise below, clipping above."""


@dataclass
class ExposureEstimate:
    """Per-view gains measured on the SfM points' colours."""

    names: list[str]
    """The photos' stems, in the order of ``gains``."""
    gains: np.ndarray
    """(N, 3) per-view per-channel gains relative to the photos' geometric mean (1: an average photo); 1 for a
    photo with too few points to say."""
    points: np.ndarray
    """(N,) observations that measured each photo's gains."""

    def spread(self) -> float:
        """How much the photos differ: the 90th percentile over the measured photos of their largest channel's
        |log gain| (0.1 ≈ 10 % brighter or darker than the average photo)."""
        measured = self.points > 0
        if not measured.any():
            return 0.0
        return float(np.percentile(np.abs(np.log(self.gains[measured])).max(1), 90))


def fit_gains(view: np.ndarray, point: np.ndarray, colour: np.ndarray, n_views: int, iters: int = 30,
              scale: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Per-view log-gains (n_views, 3) (mean over the measured views 0) and the observations per view (n_views,)
    from observations ``colour`` (M, 3) in (0, 1] of point ``point`` (M,) in view ``view`` (M,): log c = g[view] +
    a[point], least squares with a Cauchy loss of ``scale`` (log units), by reweighted alternating means. Points
    seen in one view only say nothing and are left out."""
    view, point, colour = np.asarray(view), np.asarray(point), np.asarray(colour, np.float64)
    if view.shape != point.shape or colour.shape != (*view.shape, 3):
        raise ValueError(f"view {view.shape}, point {point.shape} and colour {colour.shape} must be (M,), (M,), (M, 3)")
    if view.size and (view.min() < 0 or view.max() >= n_views):
        raise ValueError(f"view indices must lie in [0, {n_views}), got {view.min()}..{view.max()}")
    if view.size and not (np.isfinite(colour).all() and colour.min() > 0):
        raise ValueError("colours must be finite and positive")
    _, point = np.unique(point, return_inverse=True)
    seen_in = np.bincount(point)
    keep = seen_in[point] >= 2
    view, point, log_c = view[keep], point[keep], np.log(colour[keep])
    counts = np.bincount(view, minlength=n_views)
    g = np.zeros((n_views, 3))
    if not view.size:
        return g, counts
    n_points = int(point.max()) + 1
    w = np.ones_like(log_c)
    for _ in range(iters):
        a = _weighted_mean(point, log_c - g[view], w, n_points)
        g = _weighted_mean(view, log_c - a[point], w, n_views)
        g[counts > 0] -= g[counts > 0].mean(0)
        r = log_c - g[view] - a[point]
        w = 1.0 / (1.0 + (r / scale) ** 2)
    return g, counts


def _weighted_mean(group: np.ndarray, values: np.ndarray, weights: np.ndarray, n: int) -> np.ndarray:
    """Per group (n, 3) the weighted mean of ``values`` (M, 3); 0 for an empty group."""
    total = np.stack([np.bincount(group, values[:, c] * weights[:, c], n) for c in range(3)], 1)
    norm = np.stack([np.bincount(group, weights[:, c], n) for c in range(3)], 1)
    return np.where(norm > 0, total / np.maximum(norm, 1e-12), 0.0)


def point_colours(rec, images: list[Path]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The observations of the points of ``rec`` (the cameras stage's undistorted pycolmap model) in ``images`` (the
    workspace's photos, named by stem as the model's images): view index, point id and colour in [0, 1] (a 3×3
    mean at the observation, at the photo's size), only those with every channel within (DARK, BRIGHT)."""
    by_stem = {rec.image(i).name.rsplit(".", 1)[0]: rec.image(i) for i in rec.reg_image_ids()}
    views, points, colours = [], [], []
    for v, path in enumerate(images):
        im = by_stem.get(path.stem)
        if im is None:
            continue
        seen = [p for p in im.points2D if p.has_point3D()]
        if not seen:
            continue
        img = cv2.imread(str(path), cv2.IMREAD_COLOR)
        cam = rec.camera(im.camera_id)
        h, w = img.shape[:2]
        xy = np.array([p.xy for p in seen]) * (w / cam.width, h / cam.height)
        col = np.clip(xy.astype(int), 0, (w - 1, h - 1))  # pixel (x, y) holds continuous [x, x + 1)
        rgb = cv2.blur(img, (3, 3))[col[:, 1], col[:, 0], ::-1] / 255.0
        ok = ((rgb > DARK) & (rgb < BRIGHT)).all(1)
        views.append(np.full(int(ok.sum()), v))
        points.append(np.array([p.point3D_id for p in seen])[ok])
        colours.append(rgb[ok])
    if not views:
        return np.zeros(0, int), np.zeros(0, int), np.zeros((0, 3))
    return np.concatenate(views), np.concatenate(points), np.concatenate(colours)


def measure_exposure(rec, images: list[Path], min_points: int = 20) -> ExposureEstimate:
    """Per-view gains of the workspace's photos ``images`` measured on the points of the SfM model ``rec``; a photo
    with fewer than ``min_points`` usable observations keeps gain 1 and counts as unmeasured."""
    view, point, colour = point_colours(rec, images)
    log_g, counts = fit_gains(view, point, colour, len(images))
    few = counts < min_points
    log_g[few] = 0.0
    counts = np.where(few, 0, counts)
    if (~few).any():
        log_g[~few] -= log_g[~few].mean(0)
    return ExposureEstimate([p.stem for p in images], np.exp(log_g), counts)


def even_out(img: np.ndarray, gain: np.ndarray) -> np.ndarray:
    """A BGR uint8 photo divided by its RGB gain (3,) relative to the average photo: as the average photo's
    exposure would have taken it (clipped to 255)."""
    return np.clip(img.astype(np.float32) / np.asarray(gain, np.float32)[::-1], 0, 255).astype(np.uint8)


def write_exposure(path: Path, est: ExposureEstimate) -> None:
    """``est`` as JSON: per photo stem its gains and the observations that measured them."""
    write_json(path, {"views": {n: {"gain": [round(float(x), 5) for x in g], "points": int(k)}
                                for n, g, k in zip(est.names, est.gains, est.points)},
                      "spread": round(est.spread(), 5)}, indent=1)


def read_exposure(path: Path, names: list[str] | None = None) -> ExposureEstimate:
    """The estimate :func:`write_exposure` wrote, for the photos ``names`` (all of them when None; one the file
    lacks counts as unmeasured); a :class:`StageError` naming the file and the fix when it is not one."""
    try:
        views = json.loads(path.read_text())["views"]
        names = list(views) if names is None else names
        gains = np.array([views[n]["gain"] if n in views else [1.0, 1.0, 1.0] for n in names], float).reshape(-1, 3)
        points = np.array([views[n]["points"] if n in views else 0 for n in names], int)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise StageError(f"{path}: not an exposure record ({exc}); run the cameras stage again (--force)") from exc
    if not (np.isfinite(gains).all() and gains.min() > 0):
        raise StageError(f"{path}: gains must be finite and positive; run the cameras stage again (--force)")
    return ExposureEstimate(names, gains, points)
