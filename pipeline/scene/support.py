"""The support surface: the floor, table or turntable the object stands on, or the wall it hangs on or the
backdrop it leans on, found in the SfM points.

Every object people photograph rests on something, and that something is textured, runs beyond the frame and
touches the object inside its bounding sphere: left alone, the masks, the sphere and the mesh take it for part
of the object. The support is looked for first as a floor, the plane that

* holds the most sparse points (RANSAC, then a least-squares refit on its inliers), at least ``min_inliers`` and
  ``min_fraction`` of the points around the object,
* is roughly horizontal: its normal lies within ``max_tilt_deg`` of the capture's up direction (the direction
  most orthogonal to every camera's x axis — photos are taken without roll, EXIF orientation applied),
* has the cameras above it (``min_cameras_above``) and the point the cameras converge on above it, nearer than
  ``max_height`` × the camera distance (the object stands on it where the cameras look),
* has (almost) nothing below it near the object (``max_below`` of the points there): a table hides what lies under
  it, while a plane through the object itself (window sills, a row of roof tiles) has points on both sides,
* lies around the object, on several sides (its inliers within 2.5 × the object's median footprint radius of the
  foot of the convergence point fall in at least ``min_sectors`` of 8 sectors) — a shelf or a backdrop behind the
  object does not —, and spreads at least about as wide as the object stands (median distance from the foot ≥ 0.6 ×
  that of the object's own points) — a plane tangent to the object's rounded bottom holds only a small cap of its
  points.

Without such a floor, the support is looked for in any direction (``backing``): the plane on the far side of the
object from the cameras — a wall a mounted head hangs on, a backdrop a plate leans on —, through points behind
where the cameras converge, its normal within ``BACKING_MAX_ANGLE_DEG`` of the mean direction to the cameras, with
every check above in its own direction ("above" is "in front of", "below" is "behind"), and one more: the object
touches it (:func:`_touches`: the points nearest the plane between it and the convergence point lie within
``max_gap`` × the convergence point's height), so that a backdrop some way behind an object, with empty space
between them, is never taken. A floor, when there is one, is
the support: the object stands on it and the wall behind it stays the background the masks find by colour.

No such plane (an object held, on a plain backdrop or a plain turntable top): ``None``, and every stage behaves as
without a support. Every stage reads the plane only through its normal (towards the cameras) and offset: the plane
and everything behind it are background, whichever way it faces.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

GROUND_BAND = 0.03
"""Height above the support plane (normalized frame: unit-sphere radii) below which a point or a depth belongs to
the support, not to the object (the plane's fit is good to ~0.01 radius on SfM points)."""


@dataclass
class SupportPlane:
    """Plane n·x + d = 0 (unit n pointing to the cameras' side) in the SfM frame, with what was measured."""

    normal: np.ndarray
    offset: float
    inliers: int
    tolerance: float
    object_height: float
    """Height above the plane of the highest object point (SfM units)."""
    kind: str = "points"
    """How it was found: "points" (SfM points on it), "board" (a printed board on it), "base" (a plain surface under
    the object's base, :mod:`pipeline.scene.plain_support`)."""

    @property
    def vector(self) -> np.ndarray:
        """The plane as (4,): (n, d) with n·x + d = 0."""
        return np.append(self.normal, self.offset)

    def height(self, points: np.ndarray) -> np.ndarray:
        """Signed height of points (M, 3) above the plane (positive on the cameras' side)."""
        return points @ self.normal + self.offset


def capture_up(R: np.ndarray) -> np.ndarray:
    """The capture's up direction from world→camera rotations (N, 3, 3): the unit vector most orthogonal to all
    camera x axes (no roll), signed like the cameras' −y axes."""
    x = R[:, 0, :]
    _, vecs = np.linalg.eigh(x.T @ x)
    up = vecs[:, 0]
    return up if (-R[:, 1, :].sum(0)) @ up >= 0 else -up


def _fit(points: np.ndarray) -> tuple[np.ndarray, float]:
    c = points.mean(0)
    _, _, vt = np.linalg.svd(points - c, full_matrices=False)
    n = vt[2]
    return n, -float(n @ c)


def plane_basis(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (e1, e2) spanning the plane orthogonal to the unit vector ``normal``, with e1 × e2 = normal."""
    e1 = np.cross(normal, [1.0, 0, 0] if abs(normal[0]) < 0.9 else [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(normal, e1)


def _sectors(points: np.ndarray, foot: np.ndarray, normal: np.ndarray, inner: float, outer: float) -> int:
    """How many of 8 angular sectors around ``foot`` (in the plane) hold at least 3 of ``points`` at a distance
    between ``inner`` and ``outer`` from it."""
    e1, e2 = plane_basis(normal)
    q = points - foot
    dist = np.linalg.norm(q, axis=1)
    near = (dist >= inner) & (dist < outer)
    ang = np.arctan2(q[near] @ e2, q[near] @ e1)
    counts = np.bincount(((ang + np.pi) / (2 * np.pi) * 8).astype(int).clip(0, 7), minlength=8)
    return int((counts >= 3).sum())


def _plausible(n: np.ndarray, d: float, near: np.ndarray, centers: np.ndarray, target: np.ndarray, scale: float,
               tol: float, min_cameras_above: float, max_height: float, max_below: float) -> bool:
    """The checks of a candidate plane that need no refit: cameras above it, the target above it and near,
    (almost) nothing below it around the object."""
    h_target = float(target @ n + d)
    if np.mean(centers @ n + d > 0) < min_cameras_above or not (0 < h_target < max_height * scale):
        return False
    around = near[np.linalg.norm(near - (target - h_target * n), axis=1) < scale]
    if not len(around):
        return True
    height = around @ n + d
    radial = np.linalg.norm(around - (target - h_target * n) - np.outer(height, n), axis=1)
    return np.mean(height < -_below_margin(height[radial > 0.5 * scale], tol)) <= max_below


def _below_margin(far_height: np.ndarray, tol: float) -> float:
    """How far below a plane a point must lie to count as below it: 1.5 ``tol``, or the plane's own noise where it
    is larger — the 99th percentile of the distances within 5 ``tol`` of it of the points far out on it
    (``far_height``: more than half the cameras' distance from the object's axis, where no object stands) — up to
    3 ``tol``. A video's compressed frames triangulate a floor more loosely: the cow's clip put 1.01 % of its floor
    points 1.5 ``tol`` below the floor's own fit, and a 1 % rule called the floor no support. A plane through an
    object's own points has none far out (a cap of a ball: its curved points near the plane are no noise)."""
    close = np.abs(far_height[np.abs(far_height) < 5 * tol])
    noise = float(np.percentile(close, 99)) if len(close) >= 30 else 0.0
    return min(max(1.5 * tol, noise), 3.0 * tol)


def _ransac(near: np.ndarray, up: np.ndarray, tol: float, max_tilt_deg: float, iterations: int, seed: int,
            plausible, pool: np.ndarray | None = None, min_count: float = 0
            ) -> tuple[tuple[np.ndarray, float] | None, int]:
    """The plane with the most inliers (the first drawn of equals) among those ``plausible(n, d)`` accepts whose
    normal (signed towards ``up``) lies within ``max_tilt_deg`` of ``up``; candidate planes through three points of
    ``pool`` (default: ``near``), inliers counted in ``near`` (all candidates at once, in blocks), ``plausible`` asked
    from the most inliers down, of candidates with at least ``min_count`` (None, 0 when none is)."""
    rng = np.random.default_rng(seed)
    pool = near if pool is None or len(pool) < 3 else pool
    a, b, c = pool[np.stack([rng.choice(len(pool), 3, replace=False) for _ in range(iterations)])].transpose(1, 0, 2)
    n = np.cross(b - a, c - a)
    norm = np.linalg.norm(n, axis=1)
    keep = norm >= 1e-12
    n = n[keep] / norm[keep, None]
    n *= np.where(n @ up >= 0, 1.0, -1.0)[:, None]
    tilt_ok = n @ up >= np.cos(np.radians(max_tilt_deg))
    n, a = n[tilt_ok], a[keep][tilt_ok]
    d = -np.einsum("ij,ij->i", n, a)
    block = max(1, 4_000_000 // max(len(near), 1))
    counts = np.concatenate([(np.abs(near @ n[s:s + block].T + d[s:s + block]) < tol).sum(0)
                             for s in range(0, len(n), block)]) if len(n) else np.zeros(0, int)
    for k in np.argsort(-counts, kind="stable"):
        if counts[k] < max(min_count, 1):
            break
        if plausible(n[k], float(d[k])):
            return (n[k], float(d[k])), int(counts[k])
    return None, 0


def find_support(points: np.ndarray, centers: np.ndarray, R: np.ndarray, target: np.ndarray,
                 tolerance: float = 0.01, max_tilt_deg: float = 15.0, min_cameras_above: float = 0.9,
                 max_height: float = 0.8, min_inliers: int = 30, min_fraction: float = 0.05, min_sectors: int = 3,
                 max_below: float = 0.01, iterations: int = 10000, seed: int = 0, backing: bool = True,
                 max_gap: float = 0.25) -> SupportPlane | None:
    """The support plane of an object-centric capture (see the module), or None.

    Args:
        points: sparse SfM points (M, 3); centers: camera centres (N, 3); R: world→camera rotations (N, 3, 3);
        target: the point the cameras converge on.
        tolerance: inlier distance as a fraction of the median camera distance to ``target``.
        backing: without a floor, look for a plane in any direction the object touches on its far side.
        max_gap: a backing plane's largest gap to the object, as a fraction of the convergence point's height.
    """
    if len(points) < min_inliers or len(centers) < 3:
        return None
    scale = float(np.median(np.linalg.norm(centers - target, axis=1)))
    tol = tolerance * scale
    up = capture_up(R)
    near = points[np.linalg.norm(points - target, axis=1) < 2.0 * scale]
    if len(near) < min_inliers:
        return None

    def plausible(n, d):
        """:func:`_plausible` of the plane n·x + d = 0 for this capture."""
        return _plausible(n, d, near, centers, target, scale, tol, min_cameras_above, max_height, max_below)

    min_count = max(min_inliers, min_fraction * len(near))

    def checked(best, count, side, touching):
        """The candidate plane ``best`` refitted on its inliers (its normal on the ``side`` of the cameras) as a
        SupportPlane when it passes every check, else None; ``touching``: the object must reach it."""
        if best is None or count < min_count:
            return None
        n, d = best
        for _ in range(3):  # refit on the inliers
            n, d = _fit(near[np.abs(near @ n + d) < tol])
            if n @ side < 0:
                n, d = -n, -d
        inl = near[np.abs(near @ n + d) < tol]
        if len(inl) < min_count or not plausible(n, d):
            return None
        foot = target - float(target @ n + d) * n
        obj = object_points(points, n, d, target, scale, tol)
        flat = obj - np.outer(obj @ n + d, n) - foot  # the object's points dropped onto the plane, from the foot
        footprint = float(np.median(np.linalg.norm(flat, axis=1))) if len(obj) >= 5 else 0.0
        # it lies around the object on several sides (a shelf behind it does not), and spreads at least as wide as
        # the object stands (a plane tangent to the object's own rounded bottom holds a small cap of its points)
        spread = float(np.median(np.linalg.norm(inl - foot, axis=1)))
        if _sectors(inl, foot, n, 0.0, max(2.5 * footprint, 0.25 * scale)) < min_sectors or spread < 0.6 * footprint:
            return None
        if touching and not _touches(near, n, d, target, tol, max_gap):
            return None
        return SupportPlane(n, d, int(len(inl)), tol, object_height(obj, n, d, target))

    # candidates through points below where the cameras converge (the support is below the object): on DTU the
    # table holds 10 % of the points, and 2000 triples from all of them found it in one SfM run and not the next
    below = near[(near - target) @ up < 0]
    floor = checked(*_ransac(near, up, tol, max_tilt_deg, iterations, seed, plausible, below, min_count), up, False)
    if floor is not None or not backing:
        return floor
    # no floor: a plane in any direction that the object touches on its far side from the cameras (a wall it hangs
    # on, a backdrop it leans on), through points behind where the cameras converge
    front = np.mean((centers - target) / np.linalg.norm(centers - target, axis=1, keepdims=True), axis=0)
    front /= max(float(np.linalg.norm(front)), 1e-12)
    behind = near[(near - target) @ front < 0]
    found = _ransac(near, front, tol, BACKING_MAX_ANGLE_DEG, iterations, seed, plausible, behind, min_count)
    return checked(*found, front, True)


BACKING_MAX_ANGLE_DEG = 80.0
"""Largest angle between a backing plane's normal and the mean direction from the object to the cameras (every
camera must be in front of it besides)."""


def _touches(points: np.ndarray, n: np.ndarray, d: float, target: np.ndarray, tol: float, max_gap: float) -> bool:
    """Whether the object the cameras converge on (at ``target``) reaches the plane n·x + d = 0: of the points
    between the plane and the target (more than 2 ``tol`` in front of the plane, within the target's height of the
    axis through it), the nearest to the plane (the 5th percentile of their heights) lie within ``max_gap`` × the
    target's height. A backdrop some way behind an object leaves empty space there; a wall the object hangs on
    does not (its few points near the wall, a mounting plate or a neck, are enough). Fewer than 5 such points: no
    sign of contact, False."""
    h_target = float(target @ n + d)
    h = points @ n + d
    radial = np.linalg.norm(points - target - np.outer(h - h_target, n), axis=1)
    between = h[(h > 2 * tol) & (h < h_target) & (radial < h_target)]
    return len(between) >= 5 and float(np.percentile(between, 5)) <= max_gap * h_target


def object_points(points: np.ndarray, n: np.ndarray, d: float, target: np.ndarray, scale: float,
                  tol: float) -> np.ndarray:
    """The SfM points of what stands on the plane n·x + d = 0: more than 2 ``tol`` above it and within ``scale`` of
    the foot of ``target`` (the point the cameras converge on)."""
    foot = target - float(target @ n + d) * n
    return points[(points @ n + d > 2 * tol) & (np.linalg.norm(points - foot, axis=1) < scale)]


def object_height(obj: np.ndarray, n: np.ndarray, d: float, target: np.ndarray) -> float:
    """Height of the object (:func:`object_points` ``obj``) above the plane: the 98th percentile of its points'
    heights; twice the target's height with fewer than 5 points."""
    return float(np.percentile(obj @ n + d, 98)) if len(obj) >= 5 else 2 * float(target @ n + d)


def footprint_prism(points: np.ndarray, ground: np.ndarray, margin: float, min_points: int,
                    top: float | None = None):
    """The space the object standing on the plane ``ground`` (4,) can fill, from its sparse points (M, 3), all in the
    normalized frame: the convex hull of the points inside the unit sphere and above ``GROUND_BAND``, dropped onto
    the plane and widened by ``margin`` in every direction along it, raised from just below the plane to the top
    of the unit sphere, or to ``top`` above the plane when given (a trimesh, watertight). A pixel whose ray misses
    it sees no object: the floor in front of the object, or beside it (and with ``top`` behind it), is background
    there however pale it is. ``None`` with fewer than ``min_points`` such points (a weakly textured object's few
    points need not span its footprint)."""
    import trimesh
    from scipy.spatial import ConvexHull, QhullError

    n, d = np.asarray(ground[:3], float), float(ground[3])
    h = points @ n + d
    obj = points[(h > GROUND_BAND) & (np.linalg.norm(points, axis=1) < 1.0)]
    if len(obj) < max(min_points, 3):
        return None
    e1, e2 = plane_basis(n)
    flat = np.stack([obj @ e1, obj @ e2], axis=1)
    try:
        flat = flat[ConvexHull(flat).vertices]
    except QhullError:  # collinear points: their ring below still bounds them
        pass
    th = np.linspace(0.0, 2 * np.pi, 24, endpoint=False)
    ring = (flat[:, None, :] + margin * np.stack([np.cos(th), np.sin(th)], 1)[None]).reshape(-1, 2)
    base = ring[:, :1] * e1 + ring[:, 1:] * e2 - d * n  # on the plane
    height = 1.0 + d + 0.005 if top is None else top
    verts = np.concatenate([base - 0.005 * n, base + height * n])
    return trimesh.convex.convex_hull(verts)
