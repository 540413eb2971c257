"""Textures carried from one textured mesh onto another mesh of the same surface (the detail levels take the default
mesh's): each texel of the new atlas takes the value of the textured mesh's texture where a ray along the texel's
normal meets that mesh, sampled bilinearly. The photos are baked once; every level shows the same colours."""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import numpy as np

from pipeline.render.raycast import MeshCaster
from pipeline.render.textured import sample_uv


@dataclass
class BakedMesh:
    """A textured mesh: vertices (V, 3), faces (F, 3), uvs (V, 2) in [0, 1] (v up), its colour texture (side, side,
    3) float with row 0 at v = 1 (:func:`pipeline.texture.atlas.rasterize_atlas`'s convention), its occlusion map (any
    side) and its normal map's normals in the mesh's frame with their sureness (side, side, 4)
    (:meth:`pipeline.texture.surface_maps.SurfaceMaps.object_normals`); None: not baked."""

    verts: np.ndarray
    faces: np.ndarray
    uvs: np.ndarray
    texture: np.ndarray
    occlusion: np.ndarray | None = None
    normals: np.ndarray | None = None
    _casters: threading.local = field(default_factory=threading.local, init=False, repr=False)

    @property
    def caster(self) -> MeshCaster:
        """The mesh ready for ray casting, one per thread (the levels textured side by side each cast their own:
        neither trimesh's caches nor the Embree wrapper are made for threads), built on first use."""
        if getattr(self._casters, "caster", None) is None:
            import trimesh

            self._casters.caster = MeshCaster(trimesh.Trimesh(self.verts, self.faces, process=False))
        return self._casters.caster


def carried_uvs(source: BakedMesh, points: np.ndarray, normals: np.ndarray, reach: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """Where the surface ``points`` (M, 3) of another mesh lie in ``source``'s texture: (rows found (K,), their uvs
    (K, 2)). A point is found where ``source`` has a face turned its way (its unit normal, ``normals`` (M, 3))
    within ``reach`` along that normal: a ray from ``reach`` below the point outwards meets such a face first, or,
    for the points that one misses (the far side of a part thinner than the reach is met first), a ray from
    ``reach`` above it inwards."""
    points, normals = np.asarray(points, np.float64), np.asarray(normals, np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or normals.shape != points.shape:
        raise ValueError(f"expected points and normals (M, 3); got {points.shape}, {normals.shape}")
    if reach <= 0:
        raise ValueError(f"reach must be > 0, got {reach}")
    rows, faces, barys = [np.zeros(0, np.intp)], [np.zeros(0, np.intp)], [np.zeros((0, 3))]
    todo = np.arange(len(points))
    for side in (-1.0, 1.0):  # from below, outwards; then from above, inwards
        if not len(todo):
            break
        origins, dirs = points[todo] + side * reach * normals[todo], -side * normals[todo]
        ray, face, along, bary = source.caster.first_hits_barycentric(origins, dirs)
        ok = (along <= 2 * reach) & ((source.caster.mesh.face_normals[face] * normals[todo][ray]).sum(1) > 0)
        rows.append(todo[ray[ok]]), faces.append(face[ok]), barys.append(bary[ok])
        todo = np.setdiff1d(todo, todo[ray[ok]], assume_unique=True)
    rows, faces, bary = np.concatenate(rows), np.concatenate(faces), np.concatenate(barys)
    bary = np.clip(bary, 0.0, None)
    bary /= bary.sum(1, keepdims=True).clip(1e-12)
    return rows, np.einsum("kc,kcd->kd", bary, source.uvs[source.faces[faces]])


def carried(texture: np.ndarray, rows: np.ndarray, uvs: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``texture`` (side, side, C) sampled at the uvs of :func:`carried_uvs` for ``n`` points: values (n, C), 0 where
    not found, and whether each was found (n,)."""
    values, found = np.zeros((n, texture.shape[2]), np.float32), np.zeros(n, bool)
    values[rows] = sample_uv(texture, uvs)
    found[rows] = True
    return values, found
