"""The test reference of the mesh ray-caster's depth maps (:meth:`pipeline.render.raycast.MeshCaster.depth_map`):
z-buffer rasterisation in numpy, an independent construction of the same quantity — per pixel, the distance along
the ray through the pixel centre to the nearest triangle. Scanline spans, all triangles at once: per triangle and
pixel row the span between its edges at the row's centre line, then every pixel centre in the span, its depth
from the triangle's plane."""

from __future__ import annotations

import numpy as np

NEAR = 1e-6
"""Triangles with a corner this close to the camera plane (or behind it, with another in front) are not rasterised:
:func:`ray_depth_map` declines (returns None)."""


def ray_depth_map(verts: np.ndarray, faces: np.ndarray, K: np.ndarray, R: np.ndarray, center: np.ndarray,
                  width: int, height: int, batch: int = 1 << 17) -> np.ndarray | None:
    """(height, width) float64 ray depth of the first triangle hit through every pixel centre (j + 0.5, i + 0.5)
    of a pinhole camera (K, world→camera rotation R, camera centre); inf where none. A pixel centre on an edge
    belongs to both triangles (no gaps between them). Triangles wholly behind the camera are skipped; None when one
    crosses the camera plane (ray-cast those views instead). ``batch``: about how many pixels are rasterised at once
    (~200 bytes each; larger batches are slower where fresh memory is costly to map)."""
    faces = np.asarray(faces, np.int64)
    cam = ((np.asarray(verts, np.float64) - np.asarray(center, np.float64)) @ np.asarray(R, np.float64).T).T
    front = cam[2] > NEAR
    corners_front = front.take(faces)
    keep = corners_front.all(1)
    if (~keep & corners_front.any(1)).any():
        return None
    x, y, _ = np.asarray(K, np.float64) @ cam / np.where(front, cam[2], 1.0)  # pixel coordinates, centres at j + 0.5
    f = faces[keep]
    fy = y.take(f)
    top = np.ceil(fy.min(1) - 0.5).astype(np.int64).clip(0, None)  # the first and last pixel row crossing it
    rows = (np.floor(fy.max(1) - 0.5).astype(np.int64).clip(None, height - 1) - top + 1).clip(0)
    fx = x.take(f)
    box = rows * (np.ceil(fx.max(1) - fx.min(1)).astype(np.int64) + 1)  # bounds the triangle's pixels
    todo = np.flatnonzero(rows)
    ends = np.cumsum(box.take(todo))
    edges, plane = _edges(x, y, f), _planes(cam, f)
    depth = np.full(height * width, np.inf)
    K_inv, start = np.linalg.inv(np.asarray(K, np.float64)), 0
    while start < len(todo):
        stop = max(int(np.searchsorted(ends, (ends[start - 1] if start else 0) + batch, "right")), start + 1)
        sel = todo[start:stop]
        _rasterise(np.repeat(sel, rows.take(sel)), rows.take(sel), top, edges, plane, K_inv, width, depth)
        start = stop
    return depth.reshape(height, width)


def _edges(x: np.ndarray, y: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Per triangle (corner vertex ids ``f`` (F, 3)) and edge, x = x0 + (y − y0) · slope on it for y in [y_lo, y_hi]:
    (5, 3, F) = (x0, y0, slope, y_lo, y_hi) × edge × triangle. Each edge from its lower vertex id, so two triangles
    sharing it compute its x bit for bit alike; horizontal edges never count (y_lo = inf)."""
    out = np.empty((5, 3, len(f)))
    for e in range(3):
        a, b = np.minimum(f[:, e], f[:, (e + 1) % 3]), np.maximum(f[:, e], f[:, (e + 1) % 3])
        xa, ya, xb, yb = x.take(a), y.take(a), x.take(b), y.take(b)
        flat = ya == yb
        out[0, e], out[1, e] = xa, ya
        out[2, e] = (xb - xa) / np.where(flat, 1.0, yb - ya)
        out[3, e] = np.where(flat, np.inf, np.minimum(ya, yb))
        out[4, e] = np.maximum(ya, yb)
    return out


def _planes(cam: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Camera-frame plane n·X = d of every triangle: (4, F) = (n, d); n = 0 for a degenerate one."""
    p = [cam[:, f[:, j]] for j in range(3)]
    u, v = p[1] - p[0], p[2] - p[0]
    n = np.stack([u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]])
    return np.concatenate([n, (n * p[0]).sum(0, keepdims=True)])


def _rasterise(face, rows, top, edges, plane, K_inv, width, depth) -> None:
    """Triangles ``face``, each repeated once per pixel row it crosses (``rows`` per triangle): per row the span
    between its edges at the row's centre, per pixel centre in the span the ray depth to the triangle's plane, the
    nearest kept in ``depth``."""
    row = np.arange(len(face)) - np.repeat(np.cumsum(rows) - rows, rows) + top.take(face)
    py = row + 0.5
    left, right = np.full(len(face), np.inf), np.full(len(face), -np.inf)
    for e in range(3):
        x0, y0, slope, lo, hi = (a.take(face) for a in edges[:, e])
        cross = (py >= lo) & (py <= hi)
        xe = x0 + (py - y0) * slope
        left = np.where(cross & (xe < left), xe, left)
        right = np.where(cross & (xe > right), xe, right)
    first = np.ceil(np.where(np.isfinite(left), left, 0.0) - 0.5).clip(0, None).astype(np.int64)
    last = np.floor(np.where(np.isfinite(right), right, -1.0) - 0.5).clip(-1, width - 1).astype(np.int64)
    n = (last - first + 1).clip(0)
    span = np.repeat(np.arange(len(face)), n)
    col = np.arange(len(span)) - np.repeat(np.cumsum(n) - n, n) + first.take(span)
    row, face = row.take(span), face.take(span)
    px, py = col + 0.5, row + 0.5
    ray = [K_inv[j, 0] * px + K_inv[j, 1] * py + K_inv[j, 2] for j in range(3)]  # camera-frame ray, not unit
    nx, ny, nz, d = (a.take(face) for a in plane)
    dist = d / (nx * ray[0] + ny * ray[1] + nz * ray[2]) * np.sqrt(ray[0] ** 2 + ray[1] ** 2 + ray[2] ** 2)
    ok = np.flatnonzero(np.isfinite(dist) & (dist > 0))  # a degenerate triangle (n = 0) hides nothing
    np.minimum.at(depth, row.take(ok) * width + col.take(ok), dist.take(ok))
