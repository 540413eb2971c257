"""The one mesh ray-caster every stage uses (:class:`MeshCaster`: trimesh's ray queries on Embree, ``embreex``),
and the rays it casts: through pixel centres (j + 0.5, i + 0.5), as COLMAP and ``grid_sample(align_corners=False)``
place them. ``tests/pipeline/render/zbuffer.py`` (a numpy z-buffer) is its test reference."""

from __future__ import annotations

from typing import Callable

import numpy as np
import trimesh

from dvr.cameras import project_points


def _intersector(mesh: trimesh.Trimesh):
    """trimesh's ray intersector for ``mesh``: Embree (``embreex``) when installed, else trimesh's own."""
    try:
        from trimesh.ray import ray_pyembree

        return ray_pyembree.RayMeshIntersector(mesh)
    except Exception:  # noqa: BLE001 - Embree is optional
        return trimesh.ray.ray_triangle.RayMeshIntersector(mesh)


class MeshCaster:
    """A triangle mesh ready to be ray-cast many times (its Embree scene built once). Rays are (N, 3) origins and
    unit directions in the mesh's frame."""

    def __init__(self, mesh: trimesh.Trimesh):
        self.mesh = mesh
        self._inter = _intersector(mesh)

    def first_hits(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The nearest hit of each ray that meets the mesh: (ray index, face index, point), one row per ray."""
        loc, ray, face = self._inter.intersects_location(origins, dirs, multiple_hits=False)
        if len(ray) and np.bincount(ray).max() > 1:  # a ray reported twice: keep its nearest hit
            dist = ((loc - origins[ray]) * dirs[ray]).sum(1)
            order = np.lexsort((dist, ray))
            keep = order[np.r_[True, ray[order][1:] != ray[order][:-1]]]
            loc, ray, face = loc[keep], ray[keep], face[keep]
        return ray, face, loc

    def first_hits_barycentric(self, origins: np.ndarray, dirs: np.ndarray
                               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The nearest hit of each ray that meets the mesh: (ray index, face index, distance along the ray,
        barycentrics (K, 3) in the face), one row per ray. Embree gives the barycentrics and distances itself (no
        points computed and projected back); without it, :meth:`first_hits`'s points give them."""
        scene = getattr(self._inter, "_scene", None)  # trimesh's Embree wrapper
        if scene is None or not hasattr(scene, "run"):
            ray, face, loc = self.first_hits(origins, dirs)
            bary = trimesh.triangles.points_to_barycentric(self.mesh.triangles[face], loc)
            return ray, face, ((loc - origins[ray]) * dirs[ray]).sum(1), bary
        out = scene.run(origins, dirs, output=1)
        ray = np.flatnonzero(out["primID"] >= 0)
        u, v = out["u"][ray].astype(np.float64), out["v"][ray].astype(np.float64)
        distance = out["tfar"][ray].astype(np.float64) / scene.scale
        return ray, out["primID"][ray].astype(np.intp), distance, np.stack([1.0 - u - v, u, v], 1)

    def first_faces(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """(N,) the face each ray meets first, −1 where it meets none."""
        return self._inter.intersects_first(origins, dirs)

    def any_hit(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """(N,) bool: whether each ray meets the mesh."""
        return self._inter.intersects_any(origins, dirs)

    def depth_map(self, K: np.ndarray, R: np.ndarray, center: np.ndarray, width: int, height: int) -> np.ndarray:
        """(height, width) ray depth (distance along the unit ray) of the first hit through every pixel centre of a
        pinhole camera (K, world→camera rotation R, camera centre); inf where the ray meets nothing. Only the rays
        of :func:`projected_box` are cast (all when it bounds nothing)."""

        def depths(o: np.ndarray, d: np.ndarray) -> np.ndarray:
            ray, _, loc = self.first_hits(o, d)
            out = np.full(len(d), np.inf)
            out[ray] = np.linalg.norm(loc - o[ray], axis=1)
            return out

        return self._in_box(K, R, center, width, height, depths, np.inf)

    def covered_pixels(self, K: np.ndarray, R: np.ndarray, center: np.ndarray, width: int, height: int) -> np.ndarray:
        """(height, width) bool: the pixels whose centre's ray meets the mesh; only the rays of
        :func:`projected_box` are cast (all when it bounds nothing)."""
        return self._in_box(K, R, center, width, height, self.any_hit, False)

    def _in_box(self, K: np.ndarray, R: np.ndarray, center: np.ndarray, width: int, height: int,
                per_ray: Callable[[np.ndarray, np.ndarray], np.ndarray], outside) -> np.ndarray:
        """(height, width): ``per_ray`` of the pixel-centre rays of :func:`projected_box` (origins, directions →
        one value per ray), ``outside`` at every other pixel (no ray there can meet the mesh)."""
        box = projected_box(self.mesh.vertices, K, R, center, width, height)
        y0, y1, x0, x1 = (0, height, 0, width) if box is None else box
        out = np.full((height, width), outside)
        if y1 > y0 and x1 > x0:
            o, d = pixel_center_rays(K, R, center, width, height, (y0, y1, x0, x1))
            out[y0:y1, x0:x1] = per_ray(o, d).reshape(y1 - y0, x1 - x0)
        return out


def pixel_center_rays(K: np.ndarray, R: np.ndarray, center: np.ndarray, width: int, height: int,
                      box: tuple[int, int, int, int] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Origins and unit directions (height·width, 3), row-major, through every pixel centre (j + 0.5, i + 0.5)
    of a pinhole camera (K, world→camera rotation R, camera centre); with ``box`` = (y0, y1, x0, x1) only through
    the pixels of rows y0..y1−1 and columns x0..x1−1, row-major."""
    y0, y1, x0, x1 = (0, height, 0, width) if box is None else box
    jj, ii = np.meshgrid(np.arange(x0, x1) + 0.5, np.arange(y0, y1) + 0.5)
    pix = np.stack([jj, ii, np.ones_like(jj)], -1).reshape(-1, 3)
    d = pix @ np.linalg.inv(K).T @ R
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.broadcast_to(np.asarray(center, float), d.shape), d


def projected_box(vertices: np.ndarray, K: np.ndarray, R: np.ndarray, center: np.ndarray, width: int,
                  height: int) -> tuple[int, int, int, int] | None:
    """(y0, y1, x0, x1): the pixels (rows y0..y1−1, columns x0..x1−1) around the bounding box of ``vertices`` as the
    camera projects them, a pixel wider on every side and clipped to the image: no other pixel's ray can meet a
    mesh of these vertices (each triangle in front of the camera projects into the triangle of its projected
    vertices). Empty (y0 == y1 or x0 == x1) when the mesh lies outside the image; None when a vertex lies on or
    behind the camera plane, whose projection bounds nothing."""
    if len(vertices) == 0:
        return 0, 0, 0, 0
    R = np.asarray(R, float)
    uv, z = project_points(K @ np.concatenate([R, -R @ np.asarray(center, float)[:, None]], 1),
                           np.asarray(vertices, float))
    if (z <= 1e-9).any():
        return None
    u, v = uv[:, 0], uv[:, 1]
    x0, x1 = int(np.clip(np.floor(u.min()) - 1, 0, width)), int(np.clip(np.ceil(u.max()) + 1, 0, width))
    y0, y1 = int(np.clip(np.floor(v.min()) - 1, 0, height)), int(np.clip(np.ceil(v.max()) + 1, 0, height))
    return y0, max(y0, y1), x0, max(x0, x1)
