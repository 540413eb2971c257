"""Stage ``texture``: UV atlas + texture baked from the PHOTOS → ``mesh/textured.{obj,mtl,png,glb}``.

1. xatlas charts the clean mesh; every face is rasterised into the atlas (OpenCV polygon fill with
   sub-texel precision, one call per face — no per-texel loop over faces), giving each texel its face,
   barycentrics, 3-D point and normal.
2. Every view renders a depth map of the mesh (z-buffer, pipeline/zbuffer.py: the ray depth at every pixel centre,
   as ray casting gives it); a texel is visible in a view when its projection's depth agrees with that map.
3. Colour (:mod:`pipeline.blend`) = weighted mean of the visible views' bilinear samples, weight =
   cos(angle)^p / distance² × a feather towards the image border; the weights are sharpened so the best views
   dominate. Colours come from 3-D points, so texels on both sides of a UV seam (same 3-D point) get the same
   colour: seams match.
4. Texels no photo sees take the trained texture field's colour; a gutter is dilated around every chart so
   mip-maps do not bleed background into the surface.
"""

from __future__ import annotations

import json
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import torch
import trimesh

from dvr.appearance import relative_gains
from dvr.cameras import Cameras, load_cameras, project_points, to_normalized, to_sfm, transform_points
from dvr.data import list_images, read_rgb
from dvr.device import resolve_device
from dvr.fields import Field, evaluate_in_chunks

from .blend import TexelSurface, bake, clipped_pixels
from .mesh import load_mesh_file, read_model
from .raycast import mesh_intersector, pixel_center_rays
from .workspace import Done, Job, StageError
from .zbuffer import ray_depth_map


@dataclass
class TextureConfig:
    """UV texturing from the photos (stage ``texture``)."""

    size: int = 2048
    """Largest texture side in texels (the atlas is sized by ``texel_density`` up to this)."""
    texel_density: float = 1.5
    """Texels per unit length on the object per photo pixel, where the photos see it best: the texture holds
    what the photos hold (400×300 photos need no 2048² atlas; 1.0 cost 0.16 dB held-out PSNR against 1.5 on the
    book scene, 2048² gained 0.1 dB in 7× the time); 0: the density that fills a ``size`` square."""
    padding: int = 4
    """Texels between charts in the atlas."""
    gutter: int = 8
    """Texels of colour dilated around every chart."""
    angle_power: float = 2.0
    """Sharpness of the view weighting by the cosine between normal and viewing direction (weight cos^this). Held
    out, against 4 (stop 31, same mapping and training): power 2 DTU 18.51 → 18.72 dB (its roofs look brighter from
    low views, and a flatter weighting averages that), the cow with GT cameras −0.03 (`balanced` 29.09 → 29.05);
    power 1 DTU 18.80, the jar from photos +0.16, the cow from photos −0.02, with GT cameras −0.06 (`balanced`
    28.99: on exact geometry the frontal views' sharper pixels count for more)."""
    min_cos: float = 0.1
    """Views seeing a surface more grazing than this cosine are ignored."""
    depth_tolerance: float = 0.01
    """Visibility test: |texel depth − rendered depth| below this (normalized units) counts as visible."""
    edge_px: int = 1
    """Photo pixels within this distance of a depth discontinuity or silhouette count as edge pixels."""
    edge_weight: float = 0.02
    """Weight factor of samples that use an edge pixel (they blend foreground and background in real photos)."""
    silhouette_px: int = 0
    """Photo pixels within this distance of the mesh's silhouette against the background (where the mesh is a
    little too large they show the background: the fringe) count only for texels nothing else sees, and those
    texels then take the fallback colour (texture field, else the nearest seen texel). 0: off, they count as edge
    pixels. 1 removes the fringe on a 3 % too large mesh but costs 0.7 dB at one held-out view of the exact-geometry
    cow (its silhouette pixels are right there), so it is off by default until measured on real captures."""
    edge_fallback_only: bool = True
    """Samples that use an edge pixel count only for texels that no clean sample sees (else they blend in at
    ``edge_weight``): background colour beside a silhouette does not reach a texel another view sees cleanly."""
    outlier_threshold: float = 0.1
    """Photo-consistency: a second blending pass weights every sample by 1 / (1 + (d / this)²), d its RMS colour
    distance to the texel's robust colour (per channel, the mean without the largest and smallest sample), so a
    highlight, shadow or occluder one view alone sees does not reach the texture; 0: off."""
    outlier_reject: float = 3.0
    """Samples farther than this × ``outlier_threshold`` from the robust colour are dropped where 3 or more views
    see the texel."""
    clipped_level: float = 0.98
    """With per-view gains fitted in training (``model/appearance.json``): a photo pixel with a channel at or above
    this level is over-exposed (clipped). It shows only that the surface is at least that bright, and undoing the
    view's gain turns it into too dark a colour. Above 1: off. (Without the gains the views differ by exposure
    anyway; keeping clipped pixels out would only prefer the darker views.)"""
    clipped_weight: float = 0.01
    """Weight factor of samples on over-exposed pixels (and their neighbours): they colour a texel where no view
    sees it unclipped."""
    sharpness_power: float = 0.5
    """Prefer sharp views: weights × (1 + c / ``sharpness_floor``)^this, c the photo's local contrast per unit
    length on the surface (blurred Sobel magnitude × focal / distance; lower in a defocused or shaken view); 0: off."""
    sharpness_floor: float = 2.0
    """Contrast (grey levels of 1 per normalized unit) below which a view counts as flat: weak texture barely
    changes the weights."""
    view_selection: bool = False
    """Discrete view selection (:mod:`pipeline.view_select`): one photo per face, the sharpest, most frontal, closest
    photo-consistent one, under a Potts smoothness so charts come from few views, blended with its neighbours' views
    at chart borders; the other views keep ``selection_floor`` of their weight. Off: every view blends by weight."""
    selection_smoothness: float = 1.0
    """Potts weight: cost of a label change between two adjacent faces, in units of −log of the data term's ratio
    to the face's best view (1: a view e times weaker is taken to spare one border edge)."""
    selection_sharpness: float = 2.0
    """Sharpness power of the selection's data term (as ``sharpness_power`` for the blend; the selection's choice
    between two views rests on it). Needs ``sharpness_power`` > 0 (the sharpness maps)."""
    selection_rings: int = 2
    """Rings of neighbouring faces over which the views of two charts blend at their border (0: hard seams)."""
    selection_floor: float = 0.02
    """Weight factor of the views a face did not select (they colour texels the chosen view does not see)."""
    seam_levelling: bool = True
    """Global seam levelling: per view an RGB offset per mesh vertex, solved in least squares (scipy sparse) so that
    overlapping views agree, added to the view's samples before blending (exposure, white balance and lighting
    steps between views do not become seams)."""
    seam_smoothness: float = 10.0
    """Weight of equal offsets at the two ends of a mesh edge, per sample of data (larger: smoother offsets)."""
    seam_zero_pull: float = 0.01
    """Weight of the pull of every offset towards 0, per sample of data (keeps the problem well posed)."""
    seam_fit_texels: int = 200000
    """Texels (drawn with a fixed seed) the offsets are fitted on; all texels get them."""
    frame: Literal["sfm", "normalized"] = "sfm"
    """Frame of the textured outputs: 'sfm' (that of cameras.npz) or 'normalized'."""
    device: str = "auto"
    """Device of the texture field used for unseen texels."""


ATLAS_UTILISATION = 0.45
"""Share of its square that xatlas's atlas fills with charts (these chart options, 4 texels of padding): 0.42-0.50
on DTU's mesh, the cow and the fuze bottle at 2048-texel sides, 0.30-0.42 at 1000."""


def filling_density(side: float, area: float) -> float:
    """Texels per unit length at which xatlas's atlas of a surface of ``area`` about fills a ``side`` square."""
    return side * float(np.sqrt(ATLAS_UTILISATION / max(area, 1e-12)))


def make_atlas(verts: np.ndarray, faces: np.ndarray, density: float, padding: int, max_side: int,
               min_side: int = 256):
    """xatlas at ``density`` texels per unit length (its atlas as large as that needs; re-charted at a density
    scaled to fit when its longer side falls outside [``min_side``, ``max_side``]) → (vmapping, faces into the new
    vertices, uvs in [0, 1] of a square texture, its side). The uvs keep xatlas's texel grid: a chart's texels and
    padding are texels of the texture (a non-square atlas sits in the square's lower left); only an atlas still
    past ``max_side`` after three tries is scaled down onto it."""
    import xatlas  # here, not at the top: the config tree imports this module

    co = xatlas.ChartOptions()
    co.max_iterations = 1  # 2-4× faster than the default 4; charts are slightly less round
    # charts grow in superlinear time on large flat regions (a 40 k-face book: 41 s); bounding their boundary
    # length to half the surface's scale takes 1-2 s, for ~20 % less atlas utilisation
    area = trimesh.Trimesh(verts, faces, process=False).area
    co.max_boundary_length = 0.5 * float(np.sqrt(area))
    # charting again costs as much as the first time: a density whose atlas would pass the cap starts below it
    density = min(density, filling_density(max_side, area))
    po = xatlas.PackOptions()
    po.padding = padding
    po.bilinear = True
    verts32, faces32 = verts.astype(np.float32), faces.astype(np.uint32)
    for _ in range(3):
        po.texels_per_unit = float(density)
        atlas = xatlas.Atlas()
        atlas.add_mesh(verts32, faces32)
        atlas.generate(co, po)
        w, h = atlas.width, atlas.height
        side = max(w, h)
        if min_side <= side <= max_side:
            break
        # the atlas's side scales about linearly with the density; 2 % inside the bound leaves room for the packing
        density *= (0.98 * max_side if side > max_side else 1.02 * min_side) / side
    vmap, idx, uvs = atlas[0]
    uvs = uvs.astype(np.float64) * np.array([w, h]) / side
    return vmap, idx.astype(np.int64), uvs, int(min(side, max_side))


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


def depth_maps(mesh: trimesh.Trimesh, cams: Cameras, sizes: list[tuple[int, int]]) -> list[np.ndarray]:
    """Per view, the ray depth of the first mesh hit at every pixel centre (inf where none): z-buffer rasterisation
    (:func:`pipeline.zbuffer.ray_depth_map`), ray casting for a view with a triangle across its camera plane."""
    verts, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    out, inter = [], None
    for i, (w, h) in enumerate(sizes):
        dep = ray_depth_map(verts, faces, cams.K[i], cams.R[i], cams.centers[i], w, h)
        if dep is None:
            inter = mesh_intersector(mesh) if inter is None else inter
            dep = ray_cast_depth(inter, cams.K[i], cams.R[i], cams.centers[i], w, h)
        out.append(dep)
    return out


def ray_cast_depth(inter, K: np.ndarray, R: np.ndarray, center: np.ndarray, w: int, h: int) -> np.ndarray:
    """(h, w) ray depth of the first hit of ``inter`` (:func:`pipeline.raycast.mesh_intersector`) through every pixel
    centre (inf where none)."""
    o, d = pixel_center_rays(K, R, center, w, h)
    loc, ir, _ = inter.intersects_location(o, d, multiple_hits=False)
    dep = np.full(len(d), np.inf)
    if len(ir):
        np.minimum.at(dep, ir, np.linalg.norm(loc - o[ir], axis=1))
    return dep.reshape(h, w)


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


def fill_unseen(pts: np.ndarray, col: np.ndarray, unseen: np.ndarray, field: Field | None = None,
                field_frame: np.ndarray | None = None, field_gain: np.ndarray | None = None) -> np.ndarray:
    """Colours of the texels no photo sees: the trained texture field's when there is one (``field_frame``:
    4×4 map of the field's frame to the frame of ``pts``; ``field_gain`` (3,): the per-view gains' common part,
    which the photos keep and the field lacks, :func:`undo_appearance`), else the colour of the nearest seen texel
    in 3-D (never black)."""
    if field is not None:
        dev = next(field.parameters()).device
        q = pts[unseen]
        if field_frame is not None:
            q = transform_points(np.linalg.inv(field_frame), q)
        with torch.no_grad():
            q = torch.from_numpy(q).float().to(dev)
            rgb = evaluate_in_chunks(field.texture, q, 65536, trailing_shape=(3,)).cpu().numpy()
        return rgb if field_gain is None else np.clip(rgb * np.asarray(field_gain, np.float32), 0.0, 1.0)
    if unseen.all():
        return np.full((int(unseen.sum()), 3), 0.5)
    from scipy.spatial import cKDTree

    _, nn = cKDTree(pts[~unseen]).query(pts[unseen], k=1)
    return col[~unseen][nn]


def photo_texel_density(mesh: trimesh.Trimesh, cams: Cameras, sizes: list[tuple[int, int]],
                        min_cos: float = 0.3) -> float:
    """Photo pixels per unit length on the surface where the photos see it best: per face, the largest
    focal / distance over the views that see it from the front (cos > ``min_cos``) inside the image; the
    area-weighted median over faces (0 when no view sees any face)."""
    cen, nrm, area = mesh.triangles_center, mesh.face_normals, mesh.area_faces
    best = np.zeros(len(cen))
    P = cams.P
    for i, (w, h) in enumerate(sizes):
        view = cams.centers[i] - cen
        dist = np.linalg.norm(view, axis=1).clip(1e-12)
        uv, z = project_points(P[i], cen)
        u, v = uv[:, 0], uv[:, 1]
        ok = (z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h) & ((nrm * view).sum(1) / dist > min_cos)
        best = np.maximum(best, np.where(ok, cams.K[i][0, 0] / dist, 0.0))
    seen = best > 0
    if not seen.any():
        return 0.0
    order = np.argsort(best[seen])
    cum = np.cumsum(area[seen][order])
    return float(best[seen][order][np.searchsorted(cum, 0.5 * cum[-1])])


def texels_per_unit(mesh: trimesh.Trimesh, cams: Cameras, sizes: list[tuple[int, int]], cfg: TextureConfig) -> float:
    """The atlas's density: ``cfg.texel_density`` texels per photo pixel on the object
    (:func:`photo_texel_density`); with ``texel_density`` 0 (or no view seeing the object), that which fills a
    ``cfg.size`` square (:func:`make_atlas` keeps the side ≤ ``cfg.size``)."""
    tpu = cfg.texel_density * photo_texel_density(mesh, cams, sizes) if cfg.texel_density > 0 else 0.0
    return tpu if tpu > 0 else filling_density(cfg.size, mesh.area)


def texture_mesh(verts_n: np.ndarray, faces: np.ndarray, images: list[np.ndarray], cams: Cameras, cfg: TextureConfig,
                 field: Field | None = None, field_frame: np.ndarray | None = None,
                 field_gain: np.ndarray | None = None, clipped: list[np.ndarray] | None = None):
    """Normalized-frame mesh → (new verts, new faces, uvs, texture (side, side, 3) float, stats); the side follows
    the photos' resolution on the object (:func:`texels_per_unit`). ``field_gain``: see :func:`fill_unseen`;
    ``clipped``: the photos' over-exposed pixels (:func:`pipeline.blend.clipped_pixels` of the photos as taken,
    before :func:`undo_appearance`), down-weighted by ``clipped_weight``; default: none."""
    images = [np.asarray(im, np.float32) for im in images]  # the bake's dtype: the extremes of float64 photos would
    # not round-trip through the float32 statistics of the photo-consistency pass
    base = trimesh.Trimesh(verts_n, faces, process=False)
    sizes = [(im.shape[1], im.shape[0]) for im in images]
    tpu = texels_per_unit(base, cams, sizes, cfg)
    with ThreadPoolExecutor(1) as pool:  # the depth maps beside the atlas (xatlas releases the GIL), on a mesh of
        # their own (trimesh's caches are not thread-safe)
        deps = pool.submit(depth_maps, trimesh.Trimesh(verts_n, faces, process=False), cams, sizes)
        vmap, nf, uvs, side = make_atlas(verts_n, faces, tpu, cfg.padding, cfg.size)
        nv = verts_n[vmap]
        normals = base.vertex_normals[vmap]
        fid = rasterize_atlas(uvs, nf, side)
        r, c, pts, nrm, face, bary = texel_geometry(fid, uvs, nf, nv, normals, with_bary=True)
        deps = deps.result()
    # the seam offsets live on the original vertices; xatlas keeps the faces' order, so ``face`` is a row of faces
    surface = TexelSurface(vmap[nf[face]], bary, np.asarray(faces), len(verts_n), face)
    col, wsum, band_only = bake(pts, nrm, images, cams, deps, cfg, surface, clipped)
    unseen = wsum <= 0
    fallback = unseen | band_only  # a colour only the silhouette band gives may be background: not trusted
    if fallback.any():
        col[fallback] = fill_unseen(pts, col, fallback, field, field_frame, field_gain)
    tex = np.zeros((side, side, 3), np.float32)
    tex[r, c] = col
    valid = fid >= 0
    tex, filled = dilate_gutter(tex, valid, cfg.gutter)
    covered_faces = np.unique(fid[valid])
    stats = {"size": side, "texels": int(valid.sum()), "unseen_frac": float(unseen.mean()) if len(unseen) else 0.0,
             "faces": int(len(nf)), "faces_with_texels": int(len(covered_faces)), "filled": filled}
    return nv, nf, uvs, tex, stats


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
        self.intersector = mesh_intersector(self.mesh)
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
        loc, ir, it = self.intersector.intersects_location(o[keep], d[keep], multiple_hits=False)
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


def upright(cams: Cameras, frame: str) -> tuple[np.ndarray, str]:
    """(T, source): T the 4×4 rigid transform from the mesh's ``frame`` ('sfm' or 'normalized') to glTF's display
    frame, ``source`` where its up came from ('support plane' or 'cameras'). +Y is up — the support plane's normal
    (a printed board's z) or, floating, the capture's up (:func:`pipeline.support.capture_up`); +Z points level at
    the first photo's camera (a viewer's default view then looks from there); the origin is the object's sphere
    centre, dropped onto the support plane when there is one. SfM's frame has no up of its own (COLMAP's is its
    first camera's, y down), and viewers put glTF's +Y up, so without this the object opened upside down or
    tilted."""
    from .support import capture_up

    if cams.ground is not None:
        up, source = np.asarray(cams.ground[:3], float), "support plane"
        origin = -float(cams.ground[3]) * up / float(up @ up)  # the sphere centre (0) dropped onto the plane
    else:
        up, source, origin = capture_up(cams.R), "cameras", np.zeros(3)
    up = up / np.linalg.norm(up)
    toward = cams.centers[0] - origin
    toward = toward - (toward @ up) * up
    if np.linalg.norm(toward) < 1e-9:  # the first camera straight above: any level direction
        toward = np.cross(up, np.eye(3)[np.argmin(np.abs(up))])
    z = toward / np.linalg.norm(toward)
    R = np.stack([np.cross(up, z), up, z])
    if frame == "sfm":  # a rotation and a shift in the mesh's own units (SfM's; metres with a board)
        origin = transform_points(cams.scale_mat, origin[None])[0]
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, -R @ origin
    return T, source


def read_textured(path: Path) -> tuple[trimesh.Trimesh, np.ndarray]:
    """The textured mesh of a ``textured.glb`` in the mesh stage's frame (its node's upright transform not applied)
    and its texture (float RGB); StageError naming it when it is damaged (a killed or interrupted write) or not ours."""
    scene = load_mesh_file(path, "glb", "GLB", "rerun the texture stage (texture --force)", process=True)
    try:
        geoms = list(scene.geometry.values()) if isinstance(scene, trimesh.Scene) else [scene]
        texture = geoms[0].visual.material.baseColorTexture.convert("RGB") if len(geoms) == 1 else None
    except Exception as e:  # noqa: BLE001 - trimesh and PIL raise what they meet (IndexError, JSON, struct errors)
        raise StageError(f"{path}: unreadable GLB ({type(e).__name__}); rerun the texture stage (texture --force)") \
            from e
    if texture is None:
        raise StageError(f"{path}: expected one textured mesh, found {len(geoms)} meshes; rerun the texture stage "
                         "(texture --force)")
    return geoms[0], np.asarray(texture, np.float32) / 255.0


GLTF_CLAMP_SAMPLER = {"magFilter": 9729, "minFilter": 9987, "wrapS": 33071, "wrapT": 33071}
"""Linear filtering with mip-maps, clamped to the edge (glTF's default wrap is REPEAT)."""


def clamped_textures(tree: dict) -> None:
    """Every texture of a glTF ``tree`` samples with :data:`GLTF_CLAMP_SAMPLER`: the atlas's charts reach to within
    a texel of its border, and with the default REPEAT wrap a viewer's bilinear and mip-map filtering there blends
    in the opposite border's texels."""
    if tree.get("textures"):
        tree["samplers"] = [dict(GLTF_CLAMP_SAMPLER)]
        for texture in tree["textures"]:
            texture["sampler"] = 0


def export_textured(out_dir: Path, verts: np.ndarray, faces: np.ndarray, uvs: np.ndarray, tex: np.ndarray,
                    display: np.ndarray | None = None) -> None:
    """``textured.glb`` (PBR material), ``textured.obj`` / ``.mtl`` and their texture ``textured.png`` in ``out_dir``.
    ``display``: the GLB's node transform (:func:`upright`; its vertices stay those given). The PNG is encoded once
    for the OBJ (in a thread: the encoder releases the GIL) while the GLB encodes its own."""
    from PIL import Image

    img = Image.fromarray((tex.clip(0, 1) * 255).round().astype(np.uint8))
    png = threading.Thread(target=img.save, args=(out_dir / "textured.png",))
    png.start()
    try:
        mat = trimesh.visual.material.PBRMaterial(baseColorTexture=img, metallicFactor=0.0, roughnessFactor=1.0)
        mesh = trimesh.Trimesh(verts, faces, visual=trimesh.visual.TextureVisuals(uv=uvs, material=mat),
                               process=False)
        scene = trimesh.Scene()
        scene.add_geometry(mesh, node_name="object", geom_name="textured",
                           transform=np.eye(4) if display is None else display)
        scene.export(out_dir / "textured.glb", tree_postprocessor=clamped_textures)
        simple = trimesh.visual.material.SimpleMaterial(name="textured", diffuse=(255, 255, 255, 255),
                                                        ambient=(255, 255, 255, 255), specular=(0, 0, 0, 255))
        mesh_obj = trimesh.Trimesh(verts, faces, visual=trimesh.visual.TextureVisuals(uv=uvs, material=simple),
                                   process=False)
        text, files = trimesh.exchange.obj.export_obj(mesh_obj, include_texture=True, return_texture=True,
                                                      mtl_name="textured.mtl")
        mtl = next(data.decode() for name, data in files.items() if name.endswith(".mtl"))
        (out_dir / "textured.mtl").write_text(mtl + "\nmap_Kd textured.png")  # the material's texture: textured.png
        (out_dir / "textured.obj").write_text(text)
    finally:
        png.join()


def read_appearance(path: Path) -> dict:
    """The per-view gains training wrote (``model/appearance.json``: image name → {"gain": [r, g, b]}), checked:
    a StageError naming the file when it is unreadable or a gain is not finite and positive (a hand-edited file)."""
    try:
        looks = json.loads(Path(path).read_text())
        gains = np.array([t["gain"] for t in looks.values()], np.float64)
    except (OSError, ValueError, TypeError, KeyError, AttributeError) as exc:
        raise StageError(f"{path}: unreadable per-view gains ({type(exc).__name__}); retrain (train --force)") from exc
    if gains.shape != (len(looks), 3):  # a scalar gain or a pair: training writes one gain per channel
        raise StageError(f"{path}: each view's gain must be 3 numbers (R, G, B); retrain (train --force)")
    if not (np.isfinite(gains).all() and (gains > 0).all()):
        raise StageError(f"{path}: per-view gains must be finite and positive; retrain (train --force)")
    return looks


def relative_looks(looks: dict) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Per image name of ``looks`` (``model/appearance.json``) its gain relative to the average view (3,), and the
    common gain (3,) (:func:`dvr.appearance.relative_gains`; ones without any gain). Gains are clamped at 1e-3: a
    hand-edited zero gives no inf or NaN."""
    fitted = {n: np.maximum(np.asarray(t["gain"], np.float64), 1e-3) for n, t in looks.items()}
    if not fitted:
        return {}, np.ones(3)
    rel, common = relative_gains(np.stack(list(fitted.values())))
    return dict(zip(fitted, rel)), common


def undo_appearance(images: list[np.ndarray], names: list[str], looks: dict) -> tuple[list[np.ndarray], np.ndarray]:
    """Each photo mapped back to the colour of the average view: ``photo / relative gain`` with the view's fitted
    transform (``model/appearance.json``) taken relative to all views' (:func:`dvr.appearance.relative_gains`), so
    views of different exposure agree before they are blended and a drift common to all gains does not tint the
    texture. Returns the photos and the common gain (3,), by which the field's colours are to be scaled."""
    rel_of, common = relative_looks(looks)
    out = [img if name not in rel_of else np.clip(img / rel_of[name].astype(np.float32), 0.0, 1.0)
           for img, name in zip(images, names)]
    return out, common


def photos_for_bake(paths: list[Path], looks: Path, cfg: TextureConfig):
    """The photos the bake blends, the common gain of the texture field's colours and the photos' over-exposed
    pixels: with per-view gains (``looks``, ``model/appearance.json``) the photos mapped back to the average view
    (:func:`undo_appearance`) and their clipped pixels, found in the photos as taken (undoing a gain moves them
    off 1); without, the photos as they are, a gain of 1 and no clipped pixels (``TextureConfig.clipped_level``)."""
    images = [read_rgb(p) for p in paths]
    if not looks.exists():
        return images, np.ones(3), None
    clipped = [clipped_pixels(im, cfg.clipped_level) for im in images]
    images, field_gain = undo_appearance(images, [p.stem for p in paths], read_appearance(looks))
    return images, field_gain, clipped


def read_clean_mesh(path: Path) -> trimesh.Trimesh:
    """The mesh stage's ``clean.ply`` (StageError naming it: unreadable, no triangles, empty)."""
    m = load_mesh_file(path, "ply", "mesh", "rerun the mesh stage (mesh --force)")
    if not isinstance(m, trimesh.Trimesh):
        raise StageError(f"{path}: holds no triangles ({type(m).__name__}); rerun the mesh stage (mesh --force)")
    if len(m.faces) == 0:
        raise StageError(f"{path}: empty mesh; retrain (train --force) or check the masks")
    return m


def run(job: Job) -> Done:
    """Stage ``texture`` (called by :func:`pipeline.stages.run_stage`): the clean mesh UV-unwrapped and baked from
    the photos (the texture field for texels no photo sees) → mesh/textured.obj/.mtl/.png and mesh/textured.glb."""
    ws, cfg = job.ws, job.cfg
    clean = ws.mesh / "clean.ply"
    final = ws.model / "final.pt"
    looks = ws.model / "appearance.json"  # per-view exposure and white balance fitted in training
    paths = list_images(ws.images)
    cams = load_cameras(ws.cameras, n_views=len(paths))
    S = cams.scale_mat
    m = read_clean_mesh(clean)
    try:
        mesh_frame = json.loads((ws.stages / "mesh.json").read_text()).get("frame", "sfm")
    except (OSError, ValueError):
        mesh_frame = "sfm"
    verts_n = np.asarray(m.vertices, np.float64)
    if mesh_frame == "sfm":
        verts_n = to_normalized(verts_n, S)
    images, field_gain, clipped = photos_for_bake(paths, looks, cfg)
    field, _, field_frame = read_model(final, resolve_device(cfg.device)) if final.exists() else (None, None, None)
    nv, nf, uvs, tex, stats = texture_mesh(verts_n, np.asarray(m.faces), images, cams, cfg, field, field_frame,
                                           field_gain, clipped)
    out_v = to_sfm(nv, S) if cfg.frame == "sfm" else nv
    display, up_from = upright(cams, cfg.frame)
    export_textured(ws.mesh, out_v, nf, uvs, tex, display)
    stats.pop("filled")
    stats["glb_up"] = {"from": up_from, "node_matrix": np.round(display, 9).tolist()}
    print(f"texture: {tex.shape[0]}² atlas, {100 * (1 - stats['unseen_frac']):.1f} % of texels from photos → "
          f"{ws.mesh / 'textured.glb'}")
    return Done(stats)
