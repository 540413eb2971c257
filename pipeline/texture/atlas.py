"""The UV atlas: xatlas charts, every face rasterised into it, each texel's surface point, normal and face, and the
gutter grown around the charts."""

from __future__ import annotations

import cv2
import numpy as np
import trimesh

ATLAS_UTILISATION = 0.45
"""Share of its square that xatlas's atlas fills with charts (these chart options, 4 texels of padding): 0.42-0.50
on DTU's mesh, the cow and the fuze bottle at 2048-texel sides, 0.30-0.42 at 1000."""


def filling_density(side: float, area: float) -> float:
    """Texels per unit length at which xatlas's atlas of a surface of ``area`` about fills a ``side`` square."""
    return side * float(np.sqrt(ATLAS_UTILISATION / max(area, 1e-12)))


PIECE_FACES = 40_000
"""A mesh of at least twice as many faces is charted as pieces of about this many faces each (:func:`split_faces`),
which xatlas charts side by side on all cores and, each chart growing within a smaller piece, in less time: DTU's
250 k-face level in 5.8 s instead of 23.5 charted whole (6 pieces), its 338 k-face raw level in 7.0 s instead of 51.6
(8); each piece's charts are bounded by the piece's own scale (:func:`make_atlas`)."""

MAX_PIECES = 16
"""The most pieces a mesh is charted as (:data:`PIECE_FACES`): each piece's border is a chart border."""

RECHART_FACES = 100_000
"""Meshes of more faces are not charted again when their atlas comes out past the largest side: charting again
costs as much as the first time (DTU's 338 k-face raw level: 46 s a time), and the atlas is scaled onto the side."""


def make_atlas(verts: np.ndarray, faces: np.ndarray, density: float, padding: int, max_side: int,
               min_side: int = 256):
    """xatlas at ``density`` texels per unit length (its atlas as large as that needs; re-charted at a density
    scaled to fit when its longer side falls outside [``min_side``, ``max_side``]) → (vmapping, faces into the new
    vertices, uvs in [0, 1] of a square texture, its side). The uvs keep xatlas's texel grid: a chart's texels and
    padding are texels of the texture (a non-square atlas sits in the square's lower left); only an atlas still
    past ``max_side`` after three tries, or at once for a mesh of more than :data:`RECHART_FACES` faces, is scaled
    down onto it (its padding shrinks by as much)."""
    import xatlas  # here, not at the top: the config tree imports this module

    co = xatlas.ChartOptions()
    co.max_iterations = 1  # 2-4× faster than the default 4; charts are slightly less round
    pieces = split_faces(verts, faces, min(MAX_PIECES, max(1, len(faces) // PIECE_FACES)))
    # charts grow in superlinear time on large flat regions (a 40 k-face book: 41 s); bounding their boundary
    # length to half the surface's scale (a piece's, for a mesh charted in pieces) takes 1-2 s, for ~20 % less
    # atlas utilisation
    area = trimesh.Trimesh(verts, faces, process=False).area
    co.max_boundary_length = 0.5 * float(np.sqrt(area / len(pieces)))
    # charting again costs as much as the first time: a density whose atlas would pass the cap starts below it
    density = min(density, filling_density(max_side, area))
    po = xatlas.PackOptions()
    po.padding = padding
    po.bilinear = True
    verts32 = verts.astype(np.float32)
    local = [np.unique(faces[p], return_inverse=True) for p in pieces]  # each piece's vertices, its faces into them
    for _ in range(3):
        po.texels_per_unit = float(density)
        atlas = xatlas.Atlas()
        for used, corners in local:
            atlas.add_mesh(verts32[used], corners.reshape(-1, 3).astype(np.uint32))
        atlas.generate(co, po)
        w, h = atlas.width, atlas.height
        side = max(w, h)
        if min_side <= side <= max_side or (side > max_side and len(faces) > RECHART_FACES):
            break
        # the atlas's side scales about linearly with the density; 2 % inside the bound leaves room for the packing
        density *= (0.98 * max_side if side > max_side else 1.02 * min_side) / side
    vmap, idx, uvs = _joined(atlas, local, pieces)
    uvs = uvs.astype(np.float64) * np.array([w, h]) / side
    return vmap, idx, uvs, int(min(side, max_side))


def split_faces(verts: np.ndarray, faces: np.ndarray, n: int) -> list[np.ndarray]:
    """The faces' indices cut into ``n`` pieces of equal counts (± 1), each piece a box of space: a piece meant to
    hold k pieces is cut across its longest side at the face centres' k // 2 : k − k // 2 quantile, each side cut
    again the same way."""
    centres = np.asarray(verts, np.float64)[np.asarray(faces)].mean(1)

    def cut(piece: np.ndarray, k: int) -> list[np.ndarray]:
        if k <= 1:
            return [np.sort(piece)]
        axis = int(np.argmax(np.ptp(centres[piece], axis=0)))
        order = piece[np.argsort(centres[piece, axis], kind="stable")]
        at = round(len(order) * (k // 2) / k)
        return cut(order[:at], k // 2) + cut(order[at:], k - k // 2)

    return cut(np.arange(len(faces)), max(1, n))


def _joined(atlas, local: list[tuple[np.ndarray, np.ndarray]], pieces: list[np.ndarray]):
    """One mesh from xatlas's charted pieces: (vmapping into the whole mesh's vertices, faces in the whole mesh's
    order into the new vertices, uvs)."""
    vmaps, corner_rows, uvs, start = [], [], [], 0
    for i, (used, _) in enumerate(local):
        vmap, idx, uv = atlas[i]
        vmaps.append(used[vmap])
        corner_rows.append(idx.astype(np.int64) + start)
        uvs.append(uv)
        start += len(vmap)
    faces = np.empty((sum(len(p) for p in pieces), 3), np.int64)
    faces[np.concatenate(pieces)] = np.concatenate(corner_rows)
    return np.concatenate(vmaps), faces, np.concatenate(uvs)


def rasterize_atlas(uvs: np.ndarray, faces: np.ndarray, size: int) -> np.ndarray:
    """(size, size) int32 face index per texel (−1: empty). Row 0 is v = 1 (image convention)."""
    shift = 4
    scale = float(1 << shift)
    xy = np.stack([uvs[:, 0] * size - 0.5, (1.0 - uvs[:, 1]) * size - 0.5], 1)
    tri = np.round(xy[faces] * scale).astype(np.int32)  # (F, 3, 2) fixed point
    ids = np.full((size, size, 3), 255, np.uint8)
    for f in range(len(faces)):
        c = ((f >> 16) & 255, (f >> 8) & 255, f & 255)
        cv2.fillConvexPoly(ids, tri[f], c, lineType=cv2.LINE_8, shift=shift)
    fid = (ids[..., 0].astype(np.int64) << 16) | (ids[..., 1].astype(np.int64) << 8) | ids[..., 2]
    fid[fid == 0xFFFFFF] = -1
    return fid.astype(np.int32)


def texel_geometry(fid: np.ndarray, uvs: np.ndarray, faces: np.ndarray, verts: np.ndarray, normals: np.ndarray,
                   with_bary: bool = False):
    """Texel rows/cols, their 3-D points and (interpolated) normals; ``with_bary``: also each texel's face index
    (M,) and barycentrics (M, 3). Computed coordinate by coordinate (contiguous 1-D arrays, several × faster than
    (M, 3) rows) in chunks of texels; the (M, 3) results are transposes of (3, M) arrays."""
    size = fid.shape[0]
    r, c = np.nonzero(fid >= 0)
    f = fid[r, c]
    pts, nrm, bary = np.empty((3, len(f))), np.empty((3, len(f))), np.empty((3, len(f)))
    corners = np.ascontiguousarray(faces.T)
    uv, vert, normal = np.ascontiguousarray(uvs.T), np.ascontiguousarray(verts.T), np.ascontiguousarray(normals.T)
    for s in range(0, len(f), 1 << 18):  # chunks: their temporaries stay small (cheap to allocate, in cache)
        part = slice(s, s + (1 << 18))
        corner = corners.take(f[part], 1)
        bary[:, part] = _barycentrics(uv, corner, (c[part] + 0.5) / size, 1.0 - (r[part] + 0.5) / size)
        for values, out in ((vert, pts), (normal, nrm)):  # per coordinate, the barycentric mix of the corners' values
            for x, o in zip(values, out[:, part]):
                np.add(x.take(corner[0]) * bary[0, part] + x.take(corner[1]) * bary[1, part],
                       x.take(corner[2]) * bary[2, part], out=o)
    nrm /= np.sqrt(nrm[0] * nrm[0] + nrm[1] * nrm[1] + nrm[2] * nrm[2]).clip(1e-12)
    if with_bary:
        return r, c, pts.T, nrm.T, f, bary.T
    return r, c, pts.T, nrm.T


def _barycentrics(uv: np.ndarray, corner: np.ndarray, px: np.ndarray, py: np.ndarray) -> np.ndarray:
    """(3, n) barycentrics of the points (px, py) in the UV triangles of corner vertex ids ``corner`` (3, n) (uv:
    (2, V)), clipped to the triangle."""
    u, v = uv
    ax, ay = u.take(corner[0]), v.take(corner[0])
    v0x, v0y = u.take(corner[1]) - ax, v.take(corner[1]) - ay
    v1x, v1y = u.take(corner[2]) - ax, v.take(corner[2]) - ay
    v2x, v2y = px - ax, py - ay
    den = v0x * v1y - v1x * v0y
    den = np.where(np.abs(den) < 1e-20, 1e-20, den)
    w1 = (v2x * v1y - v1x * v2y) / den
    w2 = (v0x * v2y - v2x * v0y) / den
    bary = np.stack([np.clip(1 - w1 - w2, 0, 1), np.clip(w1, 0, 1), np.clip(w2, 0, 1)])
    bary /= bary[0] + bary[1] + bary[2]
    return bary


def dilate_gutter(tex: np.ndarray, valid: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Grow colours ``n`` texels outwards from valid texels (mean of valid neighbours). Each step visits only the
    texels it grows (the ring around the valid ones), not the whole texture."""
    h, w = valid.shape
    tex, grown = tex.copy(), valid.copy()
    work = np.zeros((h + 2, w + 2, tex.shape[2]), tex.dtype)  # the valid colours, 0 elsewhere and on a 1-texel border
    work[1:-1, 1:-1][valid] = tex[valid]
    flat_work, flat_valid = work.reshape(-1, tex.shape[2]), np.pad(valid, 1).ravel()
    ring = [dy * (w + 2) + dx for dy in (-1, 0, 1) for dx in (-1, 0, 1)]
    for _ in range(n):
        r, c = np.nonzero(cv2.dilate(grown.view(np.uint8), np.ones((3, 3), np.uint8)).view(bool) & ~grown)
        if not len(r):
            break
        at = (r + 1) * (w + 2) + c + 1
        total = sum(flat_work.take(at + d, 0) for d in ring)
        count = sum(flat_valid.take(at + d).astype(tex.dtype) for d in ring)
        tex[r, c] = flat_work[at] = total / count[:, None]
        grown[r, c] = flat_valid[at] = True
    return tex, grown
