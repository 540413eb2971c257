"""Stage ``texture``: UV atlas + texture baked from the PHOTOS → ``mesh/textured.{obj,mtl,png,glb}``.

1. xatlas charts the clean mesh; every face is rasterised into the atlas (OpenCV polygon fill with
   sub-texel precision, one call per face — no per-texel loop over faces), giving each texel its face,
   barycentrics, 3-D point and normal.
2. Every view renders a depth map of the mesh by ray casting (trimesh, Embree when installed); a texel is
   visible in a view when its projection's depth agrees with that map.
3. Colour = weighted mean of the visible views' bilinear samples, weight = cos(angle)^p / distance² × a
   feather towards the image border; the weights are sharpened so the best views dominate. Colours come from
   3-D points, so texels on both sides of a UV seam (same 3-D point) get the same colour: seams match.
4. Texels no photo sees take the trained texture field's colour; a gutter is dilated around every chart so
   mip-maps do not bleed background into the surface.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np
import torch
import trimesh
import xatlas

from dvr.cameras import load_cameras
from dvr.data import list_images
from dvr.device import resolve_device
from dvr.trainer import load_model

from .cameras_config import TextureConfig
from .config import config_hash
from .raycast import mesh_intersector, pixel_center_rays
from .seams import fit_seam_offsets, texel_offsets
from .workspace import StageError, Workspace


def make_atlas(verts: np.ndarray, faces: np.ndarray, size: int, padding: int):
    """xatlas: (vmapping, faces into the new vertices, uvs in [0, 1])."""
    atlas = xatlas.Atlas()
    atlas.add_mesh(verts.astype(np.float32), faces.astype(np.uint32))
    po = xatlas.PackOptions()
    po.resolution = size
    po.padding = padding
    po.bilinear = True
    co = xatlas.ChartOptions()
    co.max_iterations = 1  # 2-4× faster than the default 4; charts are slightly less round
    # charts grow in superlinear time on large flat regions (a 40 k-face book: 41 s); bounding their boundary
    # length to half the surface's scale takes 1-2 s, for ~20 % less atlas utilisation
    co.max_boundary_length = 0.5 * float(np.sqrt(trimesh.Trimesh(verts, faces, process=False).area))
    atlas.generate(co, po)
    vmap, idx, uvs = atlas[0]
    return vmap, idx.astype(np.int64), uvs.astype(np.float64)


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
    (M,) and barycentrics (M, 3)."""
    size = fid.shape[0]
    r, c = np.nonzero(fid >= 0)
    f = fid[r, c]
    p = np.stack([(c + 0.5) / size, 1.0 - (r + 0.5) / size], 1)
    a, b, d = uvs[faces[f, 0]], uvs[faces[f, 1]], uvs[faces[f, 2]]
    v0, v1, v2 = b - a, d - a, p - a
    den = v0[:, 0] * v1[:, 1] - v1[:, 0] * v0[:, 1]
    den = np.where(np.abs(den) < 1e-20, 1e-20, den)
    w1 = (v2[:, 0] * v1[:, 1] - v1[:, 0] * v2[:, 1]) / den
    w2 = (v0[:, 0] * v2[:, 1] - v2[:, 0] * v0[:, 1]) / den
    bary = np.clip(np.stack([1 - w1 - w2, w1, w2], 1), 0, 1)
    bary /= bary.sum(1, keepdims=True)
    pts = (verts[faces[f]] * bary[:, :, None]).sum(1)
    nrm = (normals[faces[f]] * bary[:, :, None]).sum(1)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True).clip(1e-12)
    if with_bary:
        return r, c, pts, nrm, f, bary
    return r, c, pts, nrm


def depth_maps(mesh: trimesh.Trimesh, cams, sizes: list[tuple[int, int]]) -> list[np.ndarray]:
    """Per view, the ray depth of the first mesh hit at every pixel centre (inf where none)."""
    inter = mesh_intersector(mesh)
    out = []
    for i, (w, h) in enumerate(sizes):
        o, d = pixel_center_rays(cams.K[i], cams.R[i], cams.centers[i], w, h)
        loc, ir, _ = inter.intersects_location(o, d, multiple_hits=False)
        dep = np.full(len(d), np.inf)
        if len(ir):
            dist = np.linalg.norm(loc - o[ir], axis=1)
            np.minimum.at(dep, ir, dist)
        out.append(dep.reshape(h, w))
    return out


def depth_edges(depth: np.ndarray, tol: float, px: int) -> np.ndarray:
    """Pixels within ``px`` of a depth discontinuity (> 10 × tol) or of the silhouette."""
    d = np.where(np.isfinite(depth), depth, 1e6).astype(np.float32)
    k = np.ones((3, 3), np.uint8)
    jump = (cv2.dilate(d, k) - cv2.erode(d, k)) > 10 * tol
    if px > 0:
        jump = cv2.dilate(jump.astype(np.uint8), np.ones((2 * px + 1,) * 2, np.uint8)) > 0
    return jump


def sample_bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear lookup at continuous (x, y) where integer coordinates are pixel centres (edges clamped)."""
    h, w = img.shape[:2]
    x = x.clip(0, w - 1)
    y = y.clip(0, h - 1)
    x0, y0 = np.floor(x).astype(int).clip(0, w - 2), np.floor(y).astype(int).clip(0, h - 2)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    return ((img[y0, x0] * (1 - fx) + img[y0, x0 + 1] * fx) * (1 - fy)
            + (img[y0 + 1, x0] * (1 - fx) + img[y0 + 1, x0 + 1] * fx) * fy)


def sample_visible(img: np.ndarray, depth: np.ndarray, edges: np.ndarray, x: np.ndarray, y: np.ndarray,
                   dist: np.ndarray, tol: np.ndarray):
    """Depth-aware bilinear lookup at continuous (x, y) (integer = pixel centre).

    Of the four pixels around (x, y), only those whose rendered depth agrees with the texel's depth ``dist``
    (within ``tol``) contribute: a pixel of an occluder, or of the background beside a silhouette, never
    mixes in. Returns colours (M, C), the support (sum of the bilinear weights used; 0 = not visible) and
    whether an edge pixel was used.
    """
    h, w = depth.shape
    x0 = np.floor(x).astype(np.int64).clip(0, w - 2)
    y0 = np.floor(y).astype(np.int64).clip(0, h - 2)
    fx, fy = (x - x0).clip(0, 1), (y - y0).clip(0, 1)
    base = y0 * w + x0
    flat_img, flat_depth, flat_edges = img.reshape(h * w, -1), depth.ravel(), edges.ravel()
    col = np.zeros((len(x), flat_img.shape[1]), np.result_type(img.dtype, np.float32))
    sup = np.zeros(len(x), col.dtype)
    edge = np.zeros(len(x), bool)
    for step, wt in ((0, (1 - fx) * (1 - fy)), (1, fx * (1 - fy)), (w, (1 - fx) * fy), (w + 1, fx * fy)):
        k = base + step
        ok = np.abs(flat_depth[k] - dist) < tol  # inf (no surface there) never agrees
        wk = np.where(ok, wt, 0.0).astype(col.dtype)
        col += wk[:, None] * flat_img[k]
        sup += wk
        edge |= ok & (wt > 0) & flat_edges[k]
    col /= np.maximum(sup, 1e-12)[:, None]
    return col, sup, edge


def without_silhouette(depth: np.ndarray, px: int) -> np.ndarray:
    """The depth map with the object pixels within ``px`` of the background (no surface: inf) set to inf, so that
    the depth test never samples them: where the mesh is a little larger than the object, they show background."""
    if depth.ndim != 2:
        raise ValueError(f"without_silhouette: depth must have shape (h, w), got {depth.shape}")
    if px <= 0:
        return depth
    background = (~np.isfinite(depth)).astype(np.uint8)
    near = cv2.dilate(background, np.ones((2 * px + 1, 2 * px + 1), np.uint8)) > 0
    return np.where(near, np.inf, depth)


def sharpness_map(img: np.ndarray, exclude: np.ndarray | None = None, sigma_px: float = 2.0) -> np.ndarray:
    """Local sharpness (h, w) float32 of a photo (h, w, C): the Sobel gradient magnitude of its grey image per
    pixel (kornia), 0 at ``exclude`` (silhouettes and depth edges, whose contrast is not the surface's), then
    Gaussian-blurred over ``sigma_px``."""
    import kornia

    if img.ndim != 3 or img.shape[0] < 3 or img.shape[1] < 3:
        raise ValueError(f"sharpness_map: img must have shape (h, w, C) with h, w >= 3, got {img.shape}")
    if exclude is not None and exclude.shape != img.shape[:2]:
        raise ValueError(f"sharpness_map: exclude must have shape {img.shape[:2]}, got {exclude.shape}")
    grey = torch.from_numpy(np.ascontiguousarray(img, np.float32).mean(2))[None, None]
    grad = kornia.filters.sobel(grey, eps=0.0)
    if exclude is not None:
        grad = grad * torch.from_numpy(~exclude)[None, None].float()
    k = 2 * int(np.ceil(2.5 * sigma_px)) + 1
    return kornia.filters.gaussian_blur2d(grad, (k, k), (sigma_px, sigma_px))[0, 0].numpy()


def _rows_times(p: np.ndarray, M: np.ndarray, t) -> np.ndarray:
    """``p @ M.T + t`` for (N, 3) rows and a small (k, 3) ``M``, column by column (BLAS on N × 3 is slow when other
    threads, torch's, compete for the cores)."""
    out = np.empty((len(p), len(M)), p.dtype)
    t = np.broadcast_to(np.asarray(t, p.dtype), (len(M),))
    for j in range(len(M)):
        out[:, j] = p[:, 0] * M[j, 0] + p[:, 1] * M[j, 1] + p[:, 2] * M[j, 2] + t[j]
    return out


class ViewSampler:
    """The photos' samples of a set of texel points, one view at a time (nothing texels × views is held).

    :meth:`samples` of view ``i`` gives the texels it sees (in front, inside the image, facing it with cos >
    ``min_cos``, depth test of :func:`sample_visible`) with their colours, blending weights (cos^p / distance² ×
    a feather towards the image border × the support × the sharpness factor) and tiers: 0 clean, 1 touches a depth
    edge, 2 seen only through the silhouette band (:func:`without_silhouette`).
    """

    def __init__(self, pts: np.ndarray, nrm: np.ndarray, images: list[np.ndarray], cams, depths: list[np.ndarray],
                 cfg: TextureConfig, maps: tuple | None = None):
        if pts.ndim != 2 or pts.shape[1] != 3 or nrm.shape != pts.shape:
            raise ValueError(f"ViewSampler: pts {pts.shape} and nrm {nrm.shape} must both have shape (M, 3)")
        if not (len(images) == len(depths) == len(cams)):
            raise ValueError(f"ViewSampler: {len(images)} images, {len(depths)} depth maps, {len(cams)} cameras")
        self.pts, self.nrm = pts.astype(np.float32), nrm.astype(np.float32)
        self.facing = np.einsum("ij,ij->i", self.nrm, self.pts)  # n·p: n·(c − p) = n·c − n·p per view
        self.images, self.cfg, self.full_depths = images, cfg, depths
        self.depths = [without_silhouette(d, cfg.silhouette_px) for d in depths]
        self.band = [cv2.dilate((np.isfinite(f) & ~np.isfinite(d)).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
                     for f, d in zip(depths, self.depths)]  # silhouette band, grown by a pixel
        self.K, self.R = cams.K.astype(np.float32), cams.R.astype(np.float32)
        self.t, self.centers = cams.t.astype(np.float32), cams.centers.astype(np.float32)
        self.edges, self.sharp = maps if maps is not None else self._maps()

    def _maps(self):
        cfg = self.cfg
        edges = [depth_edges(d, cfg.depth_tolerance, cfg.edge_px) for d in self.depths]
        if cfg.sharpness_power <= 0:
            return edges, None
        grow = np.ones((3, 3), np.uint8)  # the edges one pixel wider: depth_edges(…, edge_px + 1)
        sharp = [sharpness_map(im, cv2.dilate(e.astype(np.uint8), grow) > 0) for im, e in zip(self.images, edges)]
        return edges, sharp

    def subset(self, sel: np.ndarray) -> "ViewSampler":
        """The same views sampling only the texels ``sel`` (indices into this sampler's points)."""
        out = object.__new__(ViewSampler)
        out.__dict__.update(self.__dict__)
        out.pts, out.nrm, out.facing = self.pts[sel], self.nrm[sel], self.facing[sel]
        return out

    def samples(self, i: int):
        """View ``i``'s samples: texel indices (k,), colours (k, 3), weights (k,), tiers (k,) int8."""
        cfg, img = self.cfg, self.images[i]
        h, w = img.shape[:2]
        facing = _rows_times(self.nrm, self.centers[i][None], 0.0)[:, 0] - self.facing
        idx = np.flatnonzero(facing > 0)
        p = self.pts[idx]
        view = self.centers[i] - p
        dist = np.sqrt(np.einsum("ij,ij->i", view, view)).clip(1e-9)
        cos = facing[idx] / dist
        pix = _rows_times(p, self.K[i] @ self.R[i], self.K[i] @ self.t[i])
        z = np.where(pix[:, 2] > 1e-9, pix[:, 2], 1.0)
        u, v = pix[:, 0] / z, pix[:, 1] / z
        ok = (cos > cfg.min_cos) & (pix[:, 2] > 1e-9) & (u >= 0.5) & (u <= w - 0.5) & (v >= 0.5) & (v <= h - 0.5)
        idx, dist, cos, u, v = idx[ok], dist[ok], cos[ok], u[ok], v[ok]
        f = float(self.K[i][0, 0])
        # depth change across one pixel on a surface tilted by θ: (dist / f) · tan θ
        tol = cfg.depth_tolerance + 1.5 * dist / f * np.sqrt(1 - cos ** 2) / np.maximum(cos, 1e-6)
        col, sup, edge = sample_visible(img, self.depths[i], self.edges[i], u - 0.5, v - 0.5, dist, tol)
        tier = edge.astype(np.int8)
        retry = (sup <= 0.05) & self.band[i][v.astype(np.int64).clip(0, h - 1), u.astype(np.int64).clip(0, w - 1)]
        if retry.any():  # the silhouette band: a last resort
            col[retry], sup[retry], _ = sample_visible(img, self.full_depths[i], self.edges[i], u[retry] - 0.5,
                                                       v[retry] - 0.5, dist[retry], tol[retry])
            tier[retry] = 2
        keep = sup > 0.05
        idx, col, sup, tier, dist, cos, u, v = idx[keep], col[keep], sup[keep], tier[keep], dist[keep], cos[keep], \
            u[keep], v[keep]
        border = np.minimum(np.minimum(u, w - u), np.minimum(v, h - v))
        feather = np.clip(border / (0.05 * max(w, h)), 0.05, 1.0)
        weight = cos ** cfg.angle_power / dist ** 2 * feather * sup
        if self.sharp is not None:  # image contrast per unit length on the surface: lower in a blurred view
            px = np.minimum(v.astype(np.int64), h - 1) * w + np.minimum(u.astype(np.int64), w - 1)
            contrast = self.sharp[i].ravel()[px] * f / dist
            weight = weight * (1.0 + contrast / max(cfg.sharpness_floor, 1e-6)) ** cfg.sharpness_power
        return idx, col, weight.astype(np.float32), tier


def robust_weights(col: np.ndarray, reference: np.ndarray, count: np.ndarray, threshold: float, reject: float,
                   min_views: int = 3) -> np.ndarray:
    """Photo-consistency factor (k,) of samples ``col`` (k, 3) against the texels' robust colour ``reference``
    (k, 3): Cauchy ``1 / (1 + (d / threshold)²)`` of the RMS colour distance d, and 0 beyond ``reject`` ×
    ``threshold`` where ``count`` (k,) ≥ ``min_views`` views see the texel (with fewer, who is wrong is unknown)."""
    if col.ndim != 2 or col.shape[1] != 3 or reference.shape != col.shape or count.shape != col.shape[:1]:
        raise ValueError(f"robust_weights: col {col.shape} and reference {reference.shape} must be (k, 3), "
                         f"count {count.shape} (k,)")
    if not threshold > 0:
        raise ValueError(f"robust_weights: threshold must be positive, got {threshold}")
    d = np.sqrt(((col - reference) ** 2).mean(1))
    out = 1.0 / (1.0 + (d / threshold) ** 2)
    return np.where((count >= min_views) & (d > reject * threshold), 0.0, out).astype(np.float32)


class BlendAccumulator:
    """Running sums of a weighted blend of N texels, per sample tier (0 clean, 1 edge, 2 silhouette band) apart;
    with ``extremes``, per texel and channel the largest and smallest sample and their weights (a trimmed mean)."""

    TIERS = (0, 1, 2)

    def __init__(self, n: int, extremes: bool = False):
        self.acc = {k: np.zeros((n, 3)) for k in self.TIERS}
        self.weight = {k: np.zeros(n) for k in self.TIERS}
        self.count = np.zeros(n, np.int32)
        self.extremes = extremes
        if extremes:
            self.hi, self.lo = np.full((n, 3), -np.inf, np.float32), np.full((n, 3), np.inf, np.float32)
            self.hi_w, self.lo_w = np.zeros((n, 3), np.float32), np.zeros((n, 3), np.float32)

    def add(self, idx: np.ndarray, col: np.ndarray, weight: np.ndarray, tier: np.ndarray) -> None:
        """One view's samples (``idx`` unique)."""
        for k in self.TIERS:
            s = tier == k
            if s.any():
                self.acc[k][idx[s]] += weight[s, None] * col[s]
                self.weight[k][idx[s]] += weight[s]
        self.count[idx] += 1
        if self.extremes:
            wt = np.broadcast_to(weight[:, None], col.shape)
            for val, w, better in ((self.hi, self.hi_w, np.greater), (self.lo, self.lo_w, np.less)):
                cur = val[idx]
                up = better(col, cur)
                val[idx] = np.where(up, col, cur)
                w[idx] = np.where(up, wt, w[idx])

    def tier(self, edge_fallback_only: bool) -> np.ndarray:
        """Per texel the tier :meth:`blend` takes: the first with any weight (with ``edge_fallback_only`` clean before
        edge, else the two together as 0), the silhouette band last; −1 where nothing sees the texel."""
        out = np.full(len(self.count), -1, np.int8)
        order = (2, 1, 0) if edge_fallback_only else (2, 0)
        for k in order:
            w = self.weight[k] + (self.weight[1] if (k == 0 and not edge_fallback_only) else 0.0)
            out[w > 0] = k
        return out

    def blend(self, edge_fallback_only: bool) -> tuple[np.ndarray, np.ndarray]:
        """Colours (N, 3) and weights (N,) of the samples of each texel's :meth:`tier`."""
        tier = self.tier(edge_fallback_only)
        acc, wsum = np.zeros_like(self.acc[0]), np.zeros_like(self.weight[0])
        for k in self.TIERS:
            s = tier == k if (edge_fallback_only or k != 1) else tier == 0
            acc[s] += self.acc[k][s]
            wsum[s] += self.weight[k][s]
        return acc / np.maximum(wsum, 1e-300)[:, None], wsum

    def reference(self, edge_fallback_only: bool, min_views: int = 3) -> np.ndarray:
        """Robust colour (N, 3): per channel, the weighted mean without the largest and the smallest sample where
        ``min_views`` or more views see the texel (their median for three), else :meth:`blend`."""
        out, _ = self.blend(edge_fallback_only)
        if not self.extremes:
            return out
        acc, wsum = sum(self.acc.values()), sum(self.weight.values())[:, None]
        rest = wsum - self.hi_w - self.lo_w
        ok = (self.count[:, None] >= min_views) & (rest > 1e-6 * wsum)
        hi, lo = np.where(ok, self.hi, 0.0), np.where(ok, self.lo, 0.0)
        trimmed = (acc - self.hi_w * hi - self.lo_w * lo) / np.where(ok, rest, 1.0)
        return np.where(ok, trimmed, out)


class TexelSurface(NamedTuple):
    """Where the texels lie on the mesh, for the seam levelling: the mesh vertex ids (M, 3) of each texel's face
    and its barycentrics (M, 3); the mesh's faces (F, 3) over ``n_verts`` vertices (UV-seam copies merged)."""

    texel_vertices: np.ndarray
    texel_bary: np.ndarray
    faces: np.ndarray
    n_verts: int


def blend_views(sampler: ViewSampler, cfg: TextureConfig, offsets: np.ndarray | None = None,
                surface: TexelSurface | None = None, reference: np.ndarray | None = None,
                count: np.ndarray | None = None, extremes: bool = False) -> BlendAccumulator:
    """One pass over the views: every sample, with its view's seam offsets added (``offsets`` (V, n_verts, 3) on
    ``surface``), weighted (edge samples × ``edge_weight``; with a ``reference`` (M, 3) and view ``count`` (M,), ×
    :func:`robust_weights`), summed into a :class:`BlendAccumulator`."""
    out = BlendAccumulator(len(sampler.pts), extremes)
    for i in range(len(sampler.images)):
        idx, col, weight, tier = sampler.samples(i)
        if not len(idx):
            continue
        if offsets is not None:
            col = col + texel_offsets(offsets[i], surface.texel_vertices[idx], surface.texel_bary[idx])
        weight = weight * np.where(tier > 0, np.float32(cfg.edge_weight), np.float32(1.0))
        if reference is not None:
            weight = weight * robust_weights(col, reference[idx], count[idx], cfg.outlier_threshold,
                                             cfg.outlier_reject)
        out.add(idx, col, weight, tier)
    return out


def fit_view_offsets(sampler: ViewSampler, surface: TexelSurface, cfg: TextureConfig) -> np.ndarray:
    """Seam-levelling offsets (V, n_verts, 3) (:func:`pipeline.seams.fit_seam_offsets`) fitted on at most
    ``seam_fit_texels`` texels drawn with a fixed seed; edge samples left out, outliers down-weighted against the
    texels' trimmed-mean colour."""
    n = len(sampler.pts)
    if len(surface.texel_vertices) != n or len(surface.texel_bary) != n:
        raise ValueError(f"fit_view_offsets: surface describes {len(surface.texel_vertices)} texels, sampler {n}")
    sel = np.arange(n)
    if n > cfg.seam_fit_texels:
        sel = np.sort(np.random.default_rng(0).choice(n, cfg.seam_fit_texels, replace=False))
    sub = sampler.subset(sel)
    stats = BlendAccumulator(len(sel), extremes=cfg.outlier_threshold > 0)
    views, texels, cols, weights = [], [], [], []
    for i in range(len(sampler.images)):
        idx, col, weight, tier = sub.samples(i)
        idx, col, weight = idx[tier == 0], col[tier == 0], weight[tier == 0]
        stats.add(idx, col, weight, np.zeros(len(idx), np.int8))
        views.append(np.full(len(idx), i, np.int32)), texels.append(idx), cols.append(col), weights.append(weight)
    texel, col, weight = np.concatenate(texels), np.concatenate(cols), np.concatenate(weights).astype(np.float64)
    if cfg.outlier_threshold > 0 and len(texel):
        ref = stats.reference(True)
        weight = weight * robust_weights(col, ref[texel], stats.count[texel], cfg.outlier_threshold,
                                         cfg.outlier_reject)
    return fit_seam_offsets(np.concatenate(views), texel, col, weight, surface.texel_vertices[sel],
                            surface.texel_bary[sel], surface.faces, surface.n_verts, len(sampler.images),
                            cfg.seam_smoothness, cfg.seam_zero_pull)


def bake(pts: np.ndarray, nrm: np.ndarray, images: list[np.ndarray], cams, depths: list[np.ndarray],
         cfg: TextureConfig, surface: TexelSurface | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Colours (M, 3) in [0, 1], total weights (M,) of texel points seen by the photos, and which texels only the
    silhouette band sees (M,) bool (their colour may be background: the caller gives them the fallback colour).

    Samples and weights per view: :class:`ViewSampler` (depth test, cos^p / distance², border feather, sharpness).
    Samples touching a depth discontinuity or silhouette (where real photos blend foreground and background) are
    down-weighted by ``edge_weight`` and, with ``edge_fallback_only``, count only where no clean sample sees the
    texel; pixels in the silhouette band (``silhouette_px``) count only where nothing else does. With
    ``seam_levelling`` and a ``surface``, each view's samples get its fitted colour offsets
    (:func:`fit_view_offsets`) first. With ``outlier_threshold`` > 0 a second pass re-weights every sample by its
    photo-consistency (:func:`robust_weights`) against the first pass's per-channel trimmed mean, so a highlight,
    shadow or occluder that one view alone sees does not reach the texture.
    """
    sampler = ViewSampler(pts, nrm, images, cams, depths, cfg)
    offsets = fit_view_offsets(sampler, surface, cfg) if cfg.seam_levelling and surface is not None else None
    robust = cfg.outlier_threshold > 0
    first = blend_views(sampler, cfg, offsets, surface, extremes=robust)
    col, wsum = first.blend(cfg.edge_fallback_only)
    tier = first.tier(cfg.edge_fallback_only)
    if robust:
        reference, count = first.reference(cfg.edge_fallback_only), first.count
        del first
        second = blend_views(sampler, cfg, offsets, surface, reference=reference, count=count)
        robust_col, robust_wsum = second.blend(cfg.edge_fallback_only)
        ok = (second.tier(cfg.edge_fallback_only) == tier) & (robust_wsum > 1e-6 * wsum)  # else keep the first pass
        col[ok] = robust_col[ok]
    return np.clip(col, 0.0, 1.0), wsum, tier == 2


def dilate_gutter(tex: np.ndarray, valid: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Grow colours ``n`` texels outwards from valid texels (mean of valid neighbours)."""
    tex = tex.copy()
    valid = valid.copy()
    k = np.ones((3, 3), np.float32)
    for _ in range(n):
        m = valid.astype(np.float32)
        s = cv2.filter2D(tex * m[..., None], -1, k, borderType=cv2.BORDER_CONSTANT)
        cnt = cv2.filter2D(m, -1, k, borderType=cv2.BORDER_CONSTANT)
        grow = (~valid) & (cnt > 0)
        if not grow.any():
            break
        tex[grow] = s[grow] / cnt[grow, None]
        valid |= grow
    return tex, valid


def fill_unseen(pts: np.ndarray, col: np.ndarray, unseen: np.ndarray, field=None,
                field_frame: np.ndarray | None = None) -> np.ndarray:
    """Colours of the texels no photo sees: the trained texture field's when there is one (``field_frame``:
    4×4 map of the field's frame to the frame of ``pts``), else the colour of the nearest seen texel in 3-D
    (never black)."""
    if field is not None:
        dev = next(field.parameters()).device
        q = pts[unseen]
        if field_frame is not None:
            inv = np.linalg.inv(field_frame)
            q = q @ inv[:3, :3].T + inv[:3, 3]
        with torch.no_grad():
            q = torch.from_numpy(q).float().to(dev)
            return torch.cat([field.texture(q[s : s + 65536]) for s in range(0, len(q), 65536)]).cpu().numpy()
    if unseen.all():
        return np.full((int(unseen.sum()), 3), 0.5)
    from scipy.spatial import cKDTree

    _, nn = cKDTree(pts[~unseen]).query(pts[unseen], k=1)
    return col[~unseen][nn]


def photo_texel_density(mesh: trimesh.Trimesh, cams, sizes: list[tuple[int, int]], min_cos: float = 0.3) -> float:
    """Photo pixels per unit length on the surface where the photos see it best: per face, the largest
    focal / distance over the views that see it from the front (cos > ``min_cos``) inside the image; the
    area-weighted median over faces (0 when no view sees any face)."""
    cen, nrm, area = mesh.triangles_center, mesh.face_normals, mesh.area_faces
    best = np.zeros(len(cen))
    hom = np.concatenate([cen, np.ones((len(cen), 1))], 1)
    for i, (w, h) in enumerate(sizes):
        view = cams.centers[i] - cen
        dist = np.linalg.norm(view, axis=1).clip(1e-12)
        x = hom @ cams.P[i].T
        z = np.where(np.abs(x[:, 2]) < 1e-12, 1e-12, x[:, 2])
        u, v = x[:, 0] / z, x[:, 1] / z
        ok = (x[:, 2] > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h) & ((nrm * view).sum(1) / dist > min_cos)
        best = np.maximum(best, np.where(ok, cams.K[i][0, 0] / dist, 0.0))
    seen = best > 0
    if not seen.any():
        return 0.0
    order = np.argsort(best[seen])
    cum = np.cumsum(area[seen][order])
    return float(best[seen][order][np.searchsorted(cum, 0.5 * cum[-1])])


def atlas_size(mesh: trimesh.Trimesh, cams, sizes: list[tuple[int, int]], cfg: TextureConfig,
               utilisation: float = 0.6) -> int:
    """Side of the texture: about ``cfg.texel_density`` texels per photo pixel on the object (the surface area at
    :func:`photo_texel_density`, over xatlas' typical utilisation), a multiple of 128 in [256, ``cfg.size``];
    ``cfg.size`` when ``texel_density`` is 0."""
    if cfg.texel_density <= 0:
        return cfg.size
    tpu = cfg.texel_density * photo_texel_density(mesh, cams, sizes)
    side = np.sqrt(mesh.area * tpu * tpu / utilisation)
    return int(min(cfg.size, max(256, 128 * np.ceil(side / 128))))


def texture_mesh(verts_n: np.ndarray, faces: np.ndarray, images: list[np.ndarray], cams, cfg: TextureConfig,
                 field=None, field_frame: np.ndarray | None = None):
    """Normalized-frame mesh → (new verts, new faces, uvs, texture (side, side, 3) float, stats); the side follows
    the photos' resolution on the object (:func:`atlas_size`)."""
    base = trimesh.Trimesh(verts_n, faces, process=False)
    sizes = [(im.shape[1], im.shape[0]) for im in images]
    side = atlas_size(base, cams, sizes, cfg)
    vmap, nf, uvs = make_atlas(verts_n, faces, side, cfg.padding)
    nv = verts_n[vmap]
    normals = base.vertex_normals[vmap]
    fid = rasterize_atlas(uvs, nf, side)
    r, c, pts, nrm, face, bary = texel_geometry(fid, uvs, nf, nv, normals, with_bary=True)
    deps = depth_maps(base, cams, sizes)
    surface = TexelSurface(vmap[nf[face]], bary, np.asarray(faces), len(verts_n))  # offsets on the original vertices
    col, wsum, band_only = bake(pts, nrm, images, cams, deps, cfg, surface)
    unseen = wsum <= 0
    fallback = unseen | band_only  # a colour only the silhouette band gives may be background: not trusted
    if fallback.any():
        col[fallback] = fill_unseen(pts, col, fallback, field, field_frame)
    tex = np.zeros((side, side, 3), np.float32)
    tex[r, c] = col
    valid = fid >= 0
    tex, filled = dilate_gutter(tex, valid, cfg.gutter)
    covered_faces = np.unique(fid[valid])
    stats = {"size": side, "texels": int(valid.sum()), "unseen_frac": float(unseen.mean()) if len(unseen) else 0.0,
             "faces": int(len(nf)), "faces_with_texels": int(len(covered_faces)), "filled": filled}
    return nv, nf, uvs, tex, stats


def render_textured(verts: np.ndarray, faces: np.ndarray, uvs: np.ndarray, tex: np.ndarray, K: np.ndarray,
                    R: np.ndarray, center: np.ndarray, w: int, h: int) -> tuple[np.ndarray, np.ndarray]:
    """Ray-cast a UV-textured mesh (same frame as the camera): image (h, w, 3) and hit mask (h, w)."""
    mesh = trimesh.Trimesh(verts, faces, process=False)
    o, d = pixel_center_rays(K, R, center, w, h)
    loc, ir, it = mesh_intersector(mesh).intersects_location(o, d, multiple_hits=False)
    img = np.zeros((h * w, 3))
    hit = np.zeros(h * w, bool)
    if len(ir):
        bary = trimesh.triangles.points_to_barycentric(mesh.triangles[it], loc)
        uv = (uvs[faces[it]] * bary[:, :, None]).sum(1)
        S = tex.shape[0]
        img[ir] = sample_bilinear(tex, uv[:, 0] * S - 0.5, (1 - uv[:, 1]) * S - 0.5)
        hit[ir] = True
    return img.reshape(h, w, 3), hit.reshape(h, w)


def export_textured(out_dir: Path, verts: np.ndarray, faces: np.ndarray, uvs: np.ndarray, tex: np.ndarray) -> None:
    from PIL import Image

    img = Image.fromarray((tex.clip(0, 1) * 255).round().astype(np.uint8))
    mat = trimesh.visual.material.PBRMaterial(baseColorTexture=img, metallicFactor=0.0, roughnessFactor=1.0)
    mesh = trimesh.Trimesh(verts, faces, visual=trimesh.visual.TextureVisuals(uv=uvs, material=mat), process=False)
    mesh.export(out_dir / "textured.glb")
    simple = trimesh.visual.material.SimpleMaterial(image=img, name="textured", diffuse=(255, 255, 255, 255),
                                                    ambient=(255, 255, 255, 255), specular=(0, 0, 0, 255))
    mesh_obj = trimesh.Trimesh(verts, faces, visual=trimesh.visual.TextureVisuals(uv=uvs, material=simple),
                               process=False)
    text, files = trimesh.exchange.obj.export_obj(mesh_obj, include_texture=True, return_texture=True,
                                                  mtl_name="textured.mtl")
    for name, data in files.items():  # the MTL and its texture, renamed to the contract's textured.png
        if name.endswith(".mtl"):
            mtl = data.decode()
            for other in files:
                if not other.endswith(".mtl"):
                    mtl = mtl.replace(other, "textured.png")
            (out_dir / "textured.mtl").write_text(mtl)
    (out_dir / "textured.obj").write_text(text)
    img.save(out_dir / "textured.png")


def undo_appearance(images: list[np.ndarray], names: list[str], looks: dict) -> list[np.ndarray]:
    """Each photo mapped back to the shared colour of the texture field: ``photo / gain`` with the view's
    fitted transform (``model/appearance.json``), so views of different exposure agree before they are blended."""
    out = []
    for img, name in zip(images, names):
        t = looks.get(name)
        if t is None:
            out.append(img)
            continue
        out.append(np.clip(img / np.maximum(np.asarray(t["gain"], np.float32), 1e-3), 0.0, 1.0))
    return out


def run(ws: Workspace, cfg: TextureConfig, force: bool = False) -> bool:
    clean = ws.mesh / "clean.ply"
    final = ws.model / "final.pt"
    ws.require(clean, hint="run the mesh stage first")
    ws.require(ws.images, ws.cameras, hint="run the cameras stage first")
    h = config_hash(cfg)
    outs = [ws.mesh / f"textured.{e}" for e in ("obj", "mtl", "png", "glb")]
    looks = ws.model / "appearance.json"  # per-view exposure and white balance fitted in training
    ins = [clean, ws.images, ws.cameras] + [p for p in (final, looks) if p.exists()]
    if not force and ws.up_to_date("texture", h, ins, outs):
        print(f"texture: up to date ({outs[-1]})")
        return False
    ws.clear("texture")
    t0 = time.perf_counter()
    paths = list_images(ws.images)
    cams = load_cameras(ws.cameras, n_views=len(paths))
    S = cams.scale_mat
    m = trimesh.load(clean, process=False)
    if len(m.faces) == 0:
        raise StageError(f"{clean}: empty mesh; retrain (train --force) or check the masks")
    try:
        mesh_frame = json.loads((ws.stages / "mesh.json").read_text()).get("frame", "sfm")
    except (OSError, ValueError):
        mesh_frame = "sfm"
    verts_n = np.asarray(m.vertices, np.float64)
    if mesh_frame == "sfm":
        verts_n = (verts_n - S[:3, 3]) @ np.linalg.inv(S[:3, :3]).T
    images = [cv2.cvtColor(cv2.imread(str(p), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0
              for p in paths]
    if looks.exists():
        images = undo_appearance(images, [p.stem for p in paths], json.loads(looks.read_text()))
    field, _, field_frame = load_model(final, resolve_device(cfg.device)) if final.exists() else (None, None, None)
    nv, nf, uvs, tex, stats = texture_mesh(verts_n, np.asarray(m.faces), images, cams, cfg, field, field_frame)
    out_v = nv @ S[:3, :3].T + S[:3, 3] if cfg.frame == "sfm" else nv
    export_textured(ws.mesh, out_v, nf, uvs, tex)
    stats.pop("filled")
    ws.mark_done("texture", h, time.perf_counter() - t0, stats)
    print(f"texture: {tex.shape[0]}² atlas, {100 * (1 - stats['unseen_frac']):.1f} % of texels from photos → "
          f"{ws.mesh / 'textured.glb'}")
    return True
