"""Renders of a textured mesh at a camera: ray-cast, the texture sampled bilinearly at each hit's UV."""

from __future__ import annotations

import numpy as np
import trimesh

from pipeline.render.raycast import MeshCaster, pixel_center_rays


def sample_bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear lookup at continuous (x, y) where integer coordinates are pixel centres (edges clamped)."""
    h, w = img.shape[:2]
    x = x.clip(0, w - 1)
    y = y.clip(0, h - 1)
    x0, y0 = np.floor(x).astype(int).clip(0, w - 2), np.floor(y).astype(int).clip(0, h - 2)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    return ((img[y0, x0] * (1 - fx) + img[y0, x0 + 1] * fx) * (1 - fy)
            + (img[y0 + 1, x0] * (1 - fx) + img[y0 + 1, x0 + 1] * fx) * fy)


def render_textured(verts: np.ndarray, faces: np.ndarray, uvs: np.ndarray, tex: np.ndarray, K: np.ndarray,
                    R: np.ndarray, center: np.ndarray, w: int, h: int) -> tuple[np.ndarray, np.ndarray]:
    """Ray-cast a UV-textured mesh (same frame as the camera): image (h, w, 3) and hit mask (h, w)."""
    return TexturedCaster(verts, faces, uvs, tex).render(K, R, center, w, h)


class TexturedCaster:
    """A UV-textured mesh ready to be ray-cast from many cameras (its ray intersector built once)."""

    def __init__(self, verts: np.ndarray, faces: np.ndarray, uvs: np.ndarray, tex: np.ndarray):
        self.mesh = trimesh.Trimesh(verts, faces, process=False)
        self.caster = MeshCaster(self.mesh)
        self.uvs, self.tex = uvs, tex

    def render(self, K: np.ndarray, R: np.ndarray, center: np.ndarray, w: int, h: int,
               box: tuple[int, int, int, int] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Image (h, w, 3) and hit mask (h, w) at a pinhole camera; with ``box`` = (y0, y1, x0, x1) only the rays
        of those pixels are cast (the rest black, not hit)."""
        o, d = pixel_center_rays(K, R, center, w, h)
        keep = np.arange(h * w)
        if box is not None:
            y0, y1, x0, x1 = box
            keep = (np.arange(y0, y1)[:, None] * w + np.arange(x0, x1)[None]).ravel()
        ir, it, loc = self.caster.first_hits(o[keep], d[keep])
        img = np.zeros((h * w, 3))
        hit = np.zeros(h * w, bool)
        if len(ir):
            ir = keep[ir]
            bary = trimesh.triangles.points_to_barycentric(self.mesh.triangles[it], loc)
            uv = (self.uvs[self.mesh.faces[it]] * bary[:, :, None]).sum(1)
            S = self.tex.shape[0]
            img[ir] = sample_bilinear(self.tex, uv[:, 0] * S - 0.5, (1 - uv[:, 1]) * S - 0.5)
            hit[ir] = True
        return img.reshape(h, w, 3), hit.reshape(h, w)
