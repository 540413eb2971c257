"""Ray casting against triangle meshes, shared by the stages: Embree when present, pixel-centre rays."""

from __future__ import annotations

import numpy as np
import trimesh


def mesh_intersector(mesh: trimesh.Trimesh):
    """trimesh ray intersector for ``mesh``: Embree (``embreex``) when installed, else trimesh's own."""
    try:
        from trimesh.ray import ray_pyembree

        return ray_pyembree.RayMeshIntersector(mesh)
    except Exception:  # noqa: BLE001 - Embree is optional
        return trimesh.ray.ray_triangle.RayMeshIntersector(mesh)


def pixel_center_rays(K: np.ndarray, R: np.ndarray, center: np.ndarray, width: int,
                      height: int) -> tuple[np.ndarray, np.ndarray]:
    """Origins and unit directions (height·width, 3), row-major, through every pixel centre (j + 0.5, i + 0.5)
    of a pinhole camera (K, world→camera rotation R, camera centre)."""
    jj, ii = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    pix = np.stack([jj, ii, np.ones_like(jj)], -1).reshape(-1, 3)
    d = pix @ np.linalg.inv(K).T @ R
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.broadcast_to(np.asarray(center, float), d.shape), d
