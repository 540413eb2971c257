"""Pose sanity: catch views that SfM "registered" at wrong poses before they reach training.

SfM can be confidently wrong on symmetric or repetitive scenes (a checkered sphere, a tiled or checkered floor):
a view matches the wrong copy of a repeated pattern and is placed where it never was, or the whole model
collapses several sides of the object onto one; and a view registered on a handful of points is placed anywhere.
Three checks that hold for every object-centric capture find it:

* **thin**: a view that observes fewer than ``min_points`` points of the model is not trusted.

* **aim**: the photographer points the camera at the object, so the optical axes converge. The convergence point
  is estimated robustly (iteratively from the views that agree); a view whose axis misses it by far more than the
  others do (> max(``min_aim_deg``, ``aim_factor`` × the median), or with it outside the photo), or that stands
  much nearer or farther than the others, is wrong. A wrong model as a whole (a checkered sphere: axes scattered
  by 40–120°) fails for most of its views. The floor ``min_aim_deg`` is 1°: in a precise capture (median 0.1°)
  a view 2° off is one whose translation its points hardly fix (a white cow before a far backdrop: placed 6 % of
  the orbit off at 0.26 px); hand-held captures (median ≥ 0.3°) are judged by ``aim_factor`` × their median.
* **collapse**: two views registered at the same pose must show the same picture. Pairs whose centres lie within
  ``coincident`` × the orbit radius and whose orientations differ by < 3° are compared photometrically (the
  rotation-only homography between them, normalised cross-correlation of blurred thumbnails); a low correlation
  means two sides of a symmetric scene were merged (a jar on tiles: views 90° apart at one pose).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from dvr.metrics import rotation_angle_deg
from pipeline.inputs.photos import read_photo


@dataclass
class View:
    """One registered image of an SfM model: its pose (world → camera R, t), intrinsics K and size."""

    name: str
    R: np.ndarray  # world → camera
    t: np.ndarray
    K: np.ndarray
    width: int
    height: int

    @property
    def center(self) -> np.ndarray:
        """Camera centre in the world frame."""
        return -self.R.T @ self.t


def model_views(rec) -> list[View]:
    """The registered views of a pycolmap Reconstruction (pinhole part of their camera)."""
    out = []
    for i in rec.reg_image_ids():
        im = rec.image(i)
        cam = rec.camera(im.camera_id)
        M = im.cam_from_world().matrix()
        out.append(View(im.name, M[:3, :3].copy(), M[:3, 3].copy(), cam.calibration_matrix(), cam.width, cam.height))
    return out


def axes_convergence(centers: np.ndarray, dirs: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Least-squares point closest to the optical axes (centre + s·dir), optionally weighted."""
    d = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    w = np.ones(len(d)) if weights is None else np.asarray(weights, float)
    M = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    A = (w[:, None, None] * M).sum(0)
    b = (w[:, None, None] * M @ centers[:, :, None]).sum(0)[:, 0]
    return np.linalg.lstsq(A, b, rcond=None)[0]


def aim_errors(views: list[View], point: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per view: angle (deg) between the optical axis and the direction to ``point`` (180 behind the camera), and
    whether ``point`` projects into the photo (5 % margin)."""
    err, inside = [], []
    for v in views:
        x = v.R @ point + v.t
        err.append(float(np.degrees(np.arctan2(np.linalg.norm(x[:2]), x[2]))) if x[2] > 0 else 180.0)
        u = v.K @ x
        ok = x[2] > 1e-12 and -0.05 * v.width <= u[0] / u[2] <= 1.05 * v.width and \
            -0.05 * v.height <= u[1] / u[2] <= 1.05 * v.height
        inside.append(bool(ok))
    return np.asarray(err), np.asarray(inside)


def _seen_by_most(views: list[View], C: np.ndarray, D: np.ndarray, max_pairs: int = 400,
                  distance_factor: float = 3.0) -> np.ndarray:
    """Which views see the point most views see, among the points nearest two views' axes (every pair of views, or
    ``max_pairs`` of them spread evenly), and stand within ``distance_factor`` × their median distance of it: the
    least-squares convergence of all axes can be pulled out of every photo by a few views placed far off (a global
    mapper's weakly tied photos at 9–550× the others' distance, whose axes pass the object by a small angle but
    far from its centre)."""
    i, j = np.triu_indices(len(views), 1)
    pick = np.linspace(0, len(i) - 1, min(len(i), max_pairs)).round().astype(int)
    best, best_score, best_point = None, (-1, 0.0), None
    for a, b in zip(i[pick], j[pick]):
        p = axes_convergence(C[[a, b]], D[[a, b]])
        err, inside = aim_errors(views, p)
        score = (int(inside.sum()), -float(err[inside].sum()))
        if score > best_score:
            best, best_score, best_point = inside, score, p
    if best is None or best.sum() < 2:
        return np.ones(len(views), bool)
    dist = np.linalg.norm(C - best_point, axis=1)
    near = best & (dist < distance_factor * np.median(dist[best]))
    return near if near.sum() >= 2 else best


def robust_convergence(views: list[View], rounds: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Convergence point of the axes, re-estimated from the views that agree with it, starting from those that see
    the point most of them see (:func:`_seen_by_most`); (point, aim errors, inside)."""
    C = np.stack([v.center for v in views])
    D = np.stack([v.R[2] for v in views])
    keep = _seen_by_most(views, C, D)
    for _ in range(rounds):
        c = axes_convergence(C[keep], D[keep])
        err, inside = aim_errors(views, c)
        keep = err <= 2 * np.median(err) + 1.0
        if keep.sum() < 2:
            keep = np.ones(len(views), bool)
    return c, err, inside


def aim_outliers(views: list[View], min_aim_deg: float = 1.0, aim_factor: float = 4.0,
                 distance_factor: float = 3.0) -> dict[str, str]:
    """Views that do not look at the object the others converge on, or stand far from the others' distance."""
    if len(views) < 3:
        return {}
    c, err, inside = robust_convergence(views)
    med = float(np.median(err))
    dist = np.array([np.linalg.norm(v.center - c) for v in views])
    md = float(np.median(dist))
    bad = {}
    for v, e, ok, d in zip(views, err, inside, dist):
        why = []
        if not ok:
            why.append("the object the other views converge on is not in this photo")
        elif e > max(min_aim_deg, aim_factor * med):
            why.append(f"aims {e:.0f}° off the object (median view {med:.1f}°)")
        if not (md / distance_factor < d < distance_factor * md):
            why.append(f"stands at {d / md:.2f}× the median distance")
        if why:
            bad[v.name] = "; ".join(why)
    return bad


def photo_correlation(img_a: np.ndarray, img_b: np.ndarray, H: np.ndarray, width: int = 100) -> float:
    """Normalised cross-correlation of grayscale ``img_b`` and ``img_a`` warped into it by homography ``H``
    (a → b pixels), on blurred thumbnails ``width`` wide, over the pixels both cover."""
    h, w = img_b.shape[:2]
    warped = cv2.warpPerspective(img_a.astype(np.float32), H, (w, h), flags=cv2.INTER_LINEAR)
    cover = cv2.warpPerspective(np.ones(img_a.shape[:2], np.float32), H, (w, h)) > 0.99
    s = width / w
    size = (width, max(2, round(h * s)))
    a = cv2.GaussianBlur(cv2.resize(warped, size, interpolation=cv2.INTER_AREA), (0, 0), 1.0)
    b = cv2.GaussianBlur(cv2.resize(img_b.astype(np.float32), size, interpolation=cv2.INTER_AREA), (0, 0), 1.0)
    m = cv2.resize(cover.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0
    if m.sum() < 50:
        return 1.0  # nothing to compare: no evidence against the pair
    a, b = a[m] - a[m].mean(), b[m] - b[m].mean()
    den = np.sqrt((a * a).sum() * (b * b).sum())
    return float((a * b).sum() / den) if den > 1e-9 else 1.0


def collapsed_views(views: list[View], image_dir: Path, coincident: float = 0.02, max_angle_deg: float = 3.0,
                    min_correlation: float = 0.9) -> dict[str, str]:
    """Views registered at (nearly) the same pose as another view whose photo differs from theirs."""
    if len(views) < 2:
        return {}
    C = np.stack([v.center for v in views])
    D = np.stack([v.R[2] for v in views])
    c = axes_convergence(C, D)
    radius = float(np.median(np.linalg.norm(C - c, axis=1)))
    bad: dict[str, str] = {}
    grey: dict[str, np.ndarray] = {}
    for i in range(len(views)):
        for j in range(i + 1, len(views)):
            a, b = views[i], views[j]
            if np.linalg.norm(a.center - b.center) > coincident * radius:
                continue
            rel = b.R @ a.R.T
            if rotation_angle_deg(rel) > max_angle_deg:
                continue
            for v in (a, b):
                if v.name not in grey:
                    grey[v.name] = cv2.cvtColor(read_photo(image_dir / v.name), cv2.COLOR_BGR2GRAY)
            H = b.K @ rel @ np.linalg.inv(a.K)  # rotation-only homography a → b
            ncc = photo_correlation(grey[a.name], grey[b.name], H)
            if ncc < min_correlation:
                for v, o in ((a, b), (b, a)):
                    bad[v.name] = f"registered at the pose of {o.name}, but the photos differ (correlation {ncc:.2f})"
    return bad


def thin_views(rec, min_points: int = 15) -> dict[str, str]:
    """Views that observe fewer than ``min_points`` points of the model: their poses rest on too little (a thin
    model of a capture SIFT starves placed two such views 8° and 17° off their true place on the orbit)."""
    out = {}
    for i in rec.reg_image_ids():
        im = rec.image(i)
        if im.num_points3D < min_points:
            out[im.name] = f"observes only {im.num_points3D} points of the model"
    return out


def rotation_disagreement(views: list[View], reference: list[View], tolerance_deg: float = 5.0) -> dict[str, float]:
    """Per photo that both models posed: the angle (degrees) between its rotation in ``views`` and in ``reference``
    once the two models' frames are aligned by the frame change most photos agree on (each photo's tried in turn,
    the one with most photos within ``tolerance_deg`` averaged over those). Rotations alone: no scale, no centres,
    so a model of a few photos along an arc is judged as well as a whole orbit."""
    ref = {v.name: v.R for v in reference}
    common = [v for v in views if v.name in ref]
    if not common:
        return {}
    change = np.stack([ref[v.name].T @ v.R for v in common])  # R_views = R_reference · change, per photo
    between = rotation_angle_deg(np.einsum("aji,bjk->abik", change, change))
    agree = between[np.argmax((between <= tolerance_deg).sum(1))] <= tolerance_deg
    u, _, vt = np.linalg.svd(change[agree].sum(0))  # chordal mean of the agreeing photos' frame changes
    mean = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    return dict(zip((v.name for v in common), rotation_angle_deg(np.einsum("ji,njk->nik", mean, change)).tolist()))


def pose_sanity(rec, image_dir: Path, min_points: int = 15) -> dict[str, str]:
    """Views of a reconstruction whose poses are not credible, with the reason (empty: all fine)."""
    views = model_views(rec)
    return {**thin_views(rec, min_points), **collapsed_views(views, image_dir), **aim_outliers(views)}
