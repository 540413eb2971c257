"""The support under an object standing on a plain surface — a white table, a plain turntable top — that holds no
SfM points, found from the object's base and the photos.

With no support plane, nothing carves the space under such an object: every photo sees it from above, so the space
below the object's base projects inside its silhouette in all of them, and the mesh grows a cone of table-coloured
skirt beneath it. The plane is found in two steps:

* its direction, from the object's own lowest points (:func:`base_direction`): the plane with the most of them
  within 2 ``tol`` that has almost none below it (``max_below``), its normal within ``max_tilt_deg`` of the
  capture's up, its points spread around the object (``min_sectors`` of 8 sectors; their median distance from the
  object's axis at least 0.6 × that of all its points), every camera above it — the rim of the object's base, seen
  all around;
* its height, by a plane sweep (:func:`sweep_height`): a ring of points around the base (1.05–1.4 × the object's
  own radius in each direction) is moved down from the lowest points, and at each height each point's colour is
  read in the photos that see it from the near side; where the ring lies on the surface the photos agree (its faint
  grain, the object's contact shadow), above or below it they each see a different spot of the surface. The height
  is taken where the disagreement has a clear dip (at most ``max_dip`` × what surrounds it); none (an object
  floating before a textured backdrop, whose ring never lies on anything): no support.

The base's points can stand well above the surface — the lowest band of a rounded or shadowed base gives SIFT
nothing — so the sweep reaches down to half the object's height.
"""

from __future__ import annotations

import cv2
import numpy as np

from pipeline.scene.support import SupportPlane, _ransac, _sectors, capture_up, object_height, plane_basis

RING_RADII = (1.05, 1.12, 1.2, 1.3, 1.4)
"""The sweep's ring: these multiples of the object's radius in each direction from its axis."""
RING_DIRECTIONS = 96
"""Directions of the sweep's ring around the object."""


def base_direction(points: np.ndarray, centers: np.ndarray, R: np.ndarray, target: np.ndarray, tol: float,
                   max_tilt_deg: float = 20.0, max_below: float = 0.01, min_sectors: int = 5,
                   min_inliers: int = 15, iterations: int = 10000, seed: int = 0) -> tuple[np.ndarray, float] | None:
    """The plane (n, d) through the lowest points of the object the cameras converge on (``target``; its points are
    those of ``points`` within the cameras' median distance of it), n towards the cameras, with at most ``max_below``
    of them more than ``tol`` below it; shifted down to their 1st percentile. None when no plane passes."""
    scale = float(np.median(np.linalg.norm(centers - target, axis=1)))
    up = capture_up(R)
    near = points[np.linalg.norm(points - target, axis=1) < scale]
    if len(near) < max(min_inliers, 3):
        return None
    height = (near - target) @ up
    lowest = near[height <= np.percentile(height, 20)]

    def plausible(n: np.ndarray, d: float) -> bool:
        """Cameras above, almost nothing below, the rim all around."""
        h = near @ n + d
        if np.mean(centers @ n + d > 0) < 1.0 or np.mean(h < -tol) > max_below:
            return False
        foot = target - float(target @ n + d) * n
        radial = np.linalg.norm(near - foot - np.outer(h - float(foot @ n + d), n), axis=1)
        rim = np.abs(h) < 2 * tol
        if np.median(radial[rim]) < 0.6 * np.median(radial):  # a cap under a round bottom, not a rim
            return False
        return _sectors(near[rim], foot, n, 0.0, scale) >= min_sectors

    best, _ = _ransac(near, up, 2 * tol, max_tilt_deg, iterations, seed, plausible, lowest, min_inliers)
    if best is None:
        return None
    n, d = best
    return n, d - float(np.percentile(near @ n + d, 1))


def ring_points(obj: np.ndarray, n: np.ndarray, d: float, foot: np.ndarray) -> np.ndarray:
    """Points (M, 3) on the plane n·x + d = 0 around the object's points ``obj``: in each of
    :data:`RING_DIRECTIONS` directions from ``foot``, at :data:`RING_RADII` × the object's radius there (the 95th
    percentile of its points' distances from the axis in that direction's 16th of the circle)."""
    e1, e2 = plane_basis(n)
    q = obj - foot
    ang = np.arctan2(q @ e2, q @ e1)
    dist = np.hypot(q @ e1, q @ e2)
    sector = ((ang + np.pi) / (2 * np.pi) * 16).astype(int).clip(0, 15)
    overall = float(np.percentile(dist, 95))
    radius = np.array([np.percentile(dist[sector == k], 95) if np.sum(sector == k) >= 3 else overall
                       for k in range(16)])
    theta = (np.arange(RING_DIRECTIONS) + 0.5) / RING_DIRECTIONS * 2 * np.pi - np.pi
    r = radius[((theta + np.pi) / (2 * np.pi) * 16).astype(int).clip(0, 15)][:, None] * np.asarray(RING_RADII)
    flat = r[..., None] * np.stack([np.cos(theta), np.sin(theta)], 1)[:, None, :]
    return foot + flat.reshape(-1, 2) @ np.stack([e1, e2])


def ring_colours(images: list[np.ndarray], P: np.ndarray, centers: np.ndarray, ring: np.ndarray, n: np.ndarray,
                 foot: np.ndarray) -> np.ndarray:
    """The colours (N, M, 3) of the ``ring``'s points (M, 3) in the photos that see them from the near side of the
    object (the object hides the far side) inside their frame, NaN where unseen. ``images``: RGB or BGR, uint8 or
    float; ``P``: (N, 3, 4) projections."""
    colours = np.full((len(images), len(ring), 3), np.nan, np.float32)
    outward = ring - foot
    outward -= np.outer(outward @ n, n)
    for i, (img, Pi) in enumerate(zip(images, P)):
        xy = np.c_[ring, np.ones(len(ring))] @ Pi.T
        z = xy[:, 2]
        uv = xy[:, :2] / np.where(np.abs(z) > 1e-12, z, 1e-12)[:, None]
        h, w = img.shape[:2]
        toward = centers[i] - foot
        seen = (z > 0) & (outward @ (toward - (toward @ n) * n) > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (
            uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
        if not seen.any():
            continue
        px = cv2.remap(img, uv[seen, :1].astype(np.float32), uv[seen, 1:].astype(np.float32), cv2.INTER_LINEAR)
        colours[i, seen] = px.reshape(-1, 3)
    return colours


def disagreement(colours: np.ndarray) -> float:
    """How much the photos disagree on the ring's colours (N, M, 3; :func:`ring_colours`): per point the median
    absolute deviation of its colour over the photos that see it, the mean over points seen by three or more (NaN
    when none is)."""
    ok = np.sum(~np.isnan(colours[..., 0]), axis=0) >= 3
    if not ok.any():
        return float("nan")
    c = colours[:, ok]
    return float(np.mean(np.nanmedian(np.abs(c - np.nanmedian(c, axis=0)), axis=0)))


def sweep_height(images: list[np.ndarray], P: np.ndarray, centers: np.ndarray, obj: np.ndarray, n: np.ndarray,
                 d: float, target: np.ndarray, tol: float, depth: float, max_dip: float = 0.85
                 ) -> tuple[float | None, np.ndarray]:
    """The offset of the plane parallel to n·x + d = 0, at most ``depth`` below it, on which the photos agree about
    the ring around the object (:func:`disagreement`, each photo's colours divided by its exposure), or None without a
    clear dip; and the disagreement at each height swept (steps of ``tol`` / 2, from the plane down)."""
    steps = np.arange(0.0, depth + 1e-12, tol / 2)
    foot = target - float(target @ n + d) * n
    base = ring_points(obj, n, d, foot)
    colours = [ring_colours(images, P, centers, base - s * n, n, foot - s * n) for s in steps]
    # each photo's exposure from what it saw of the ring at every height: the same surface in every photo
    gains = np.nanmedian(np.concatenate(colours, axis=1).reshape(len(images), -1), axis=1)
    gains = np.where(np.isfinite(gains) & (gains > 0), gains, 1.0) / max(float(np.nanmedian(gains)), 1e-6)
    scores = np.array([disagreement((c / gains[:, None, None]).astype(np.float32)) for c in colours])
    if len(steps) < 5 or not np.isfinite(scores).all():
        return None, scores
    k = int(np.argmin(scores))
    if k == 0 or k == len(steps) - 1:
        return None, scores
    around = min(float(scores[0]), float(scores[k:].max()))
    return (d + float(steps[k]) if scores[k] <= max_dip * around else None), scores


def find_plain_support(points: np.ndarray, centers: np.ndarray, R: np.ndarray, P: np.ndarray, target: np.ndarray,
                       images: list[np.ndarray], tolerance: float = 0.01) -> SupportPlane | None:
    """The plain surface the object stands on (see the module), or None.

    Args:
        points: sparse SfM points (M, 3); centers: camera centres (N, 3); R: world→camera rotations (N, 3, 3);
        P: projections (N, 3, 4) into ``images`` (N, colour, any scale: the disagreement is relative to the
        photos' own level); target: the point the cameras converge on.
        tolerance: as :func:`pipeline.scene.support.find_support`'s, a fraction of the median camera distance.
    """
    scale = float(np.median(np.linalg.norm(centers - target, axis=1)))
    tol = tolerance * scale
    found = base_direction(points, centers, R, target, tol)
    if found is None:
        return None
    n, d = found
    near = points[np.linalg.norm(points - target, axis=1) < scale]
    obj = near[near @ n + d > -tol]
    top = float(np.percentile(obj @ n + d, 98))
    offset, _ = sweep_height(images, P, centers, obj, n, d, target, tol, 0.5 * top)
    if offset is None:
        return None
    rim = int(np.sum(np.abs(near @ n + d) < 2 * tol))
    return SupportPlane(n, offset, rim, tol, object_height(obj, n, offset, target), kind="base")
