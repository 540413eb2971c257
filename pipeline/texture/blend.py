"""Blending the photos into texels (stage ``texture``, :mod:`pipeline.texture.stage`): per view, the visible texels'
bilinear samples (depth-map visibility, edge pixels only as a fallback), weighted by the viewing angle, distance,
the image border and the photo's local sharpness; a robust second pass (Cauchy weights on the distance to a
trimmed mean) that keeps highlights, shadows and occluders one view alone sees out of the texture; and the
per-view seam-levelling offsets (:mod:`pipeline.texture.seams`) added before blending. Texels are baked in chunks, each
sampling every view once, on a few threads (numpy releases the GIL)."""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from typing import TYPE_CHECKING, NamedTuple

import cv2
import numpy as np

from dvr.cameras import Cameras
from pipeline.texture.seams import fit_seam_offsets, texel_offsets_planar
from pipeline.texture.view_select import chart_weights, face_adjacency, select_views

if TYPE_CHECKING:  # for annotations only
    from pipeline.texture.config import TextureConfig


def depth_edges(depth: np.ndarray, tol: float, px: int) -> np.ndarray:
    """Pixels within ``px`` of a depth discontinuity (> 10 × tol) or of the silhouette."""
    d = np.where(np.isfinite(depth), depth, 1e6).astype(np.float32)
    k = np.ones((3, 3), np.uint8)
    jump = (cv2.dilate(d, k) - cv2.erode(d, k)) > 10 * tol
    if px > 0:
        jump = cv2.dilate(jump.astype(np.uint8), np.ones((2 * px + 1,) * 2, np.uint8)) > 0
    return jump


def sample_visible(img: np.ndarray, depth: np.ndarray, edges: np.ndarray, x: np.ndarray, y: np.ndarray,
                   dist: np.ndarray, tol: np.ndarray):
    """Depth-aware bilinear lookup at continuous (x, y) (integer = pixel centre).

    Of the four pixels around (x, y), only those whose rendered depth agrees with the texel's depth ``dist``
    (within ``tol``) contribute: a pixel of an occluder, or of the background beside a silhouette, never
    mixes in. Returns colours (M, C), the support (sum of the bilinear weights used; 0 = not visible) and
    whether an edge pixel was used.
    """
    col, sup, edge = _sample_planes(_planes(img), depth, edges, x, y, dist, tol)
    return col.T, sup, edge


def _planes(img: np.ndarray) -> np.ndarray:
    """An (h, w, C) image as C contiguous planes (C, h·w)."""
    return np.ascontiguousarray(np.moveaxis(img.reshape(img.shape[0] * img.shape[1], -1), -1, 0))


def _sample_planes(planes: np.ndarray, depth: np.ndarray, edges: np.ndarray, x: np.ndarray, y: np.ndarray,
                   dist: np.ndarray, tol: np.ndarray):
    """:func:`sample_visible` of an image given as planes (C, h·w) (:func:`_planes`): colours (C, M), support (M,),
    edge (M,). Channel by channel, every step is a contiguous 1-D array operation."""
    h, w = depth.shape
    x0 = np.floor(x).astype(np.intp).clip(0, w - 2)
    y0 = np.floor(y).astype(np.intp).clip(0, h - 2)
    fx, fy = (x - x0).clip(0, 1), (y - y0).clip(0, 1)
    base = y0 * w + x0
    flat_depth, flat_edges = depth.ravel(), edges.ravel()
    col = np.zeros((len(planes), len(x)), np.result_type(planes.dtype, np.float32))
    sup = np.zeros(len(x), col.dtype)
    edge = np.zeros(len(x), bool)
    for step, wt in ((0, (1 - fx) * (1 - fy)), (1, fx * (1 - fy)), (w, (1 - fx) * fy), (w + 1, fx * fy)):
        k = base + step
        ok = np.abs(flat_depth.take(k) - dist) < tol  # inf (no surface there) never agrees
        wk = np.where(ok, wt, 0.0).astype(col.dtype)
        for c, plane in zip(col, planes):
            c += wk * plane.take(k)
        sup += wk
        edge |= ok & (wt > 0) & flat_edges.take(k)
    col /= np.maximum(sup, 1e-12)
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


def clipped_pixels(img: np.ndarray, level: float) -> np.ndarray:
    """(h, w) bool: the photo's over-exposed pixels (a channel at or above ``level``), grown by one pixel (the
    bilinear lookups beside them blend them in)."""
    if img.ndim != 3:
        raise ValueError(f"clipped_pixels: img must have shape (h, w, C), got {img.shape}")
    over = (img >= level).any(-1).astype(np.uint8)
    return cv2.dilate(over, np.ones((3, 3), np.uint8)) > 0


def sharpness_map(img: np.ndarray, exclude: np.ndarray | None = None, sigma_px: float = 2.0) -> np.ndarray:
    """Local sharpness (h, w) float32 of a photo (h, w, C): the Sobel gradient magnitude of its grey image per
    pixel (kernel normalised to 1/8, edges replicated), 0 at ``exclude`` (silhouettes and depth edges, whose contrast
    is not the surface's), then Gaussian-blurred over ``sigma_px`` (edges reflected). OpenCV; what kornia's ``sobel``
    and ``gaussian_blur2d`` give to float rounding, without torch's thread start-up on small images."""
    if img.ndim != 3 or img.shape[0] < 3 or img.shape[1] < 3:
        raise ValueError(f"sharpness_map: img must have shape (h, w, C) with h, w >= 3, got {img.shape}")
    if exclude is not None and exclude.shape != img.shape[:2]:
        raise ValueError(f"sharpness_map: exclude must have shape {img.shape[:2]}, got {exclude.shape}")
    h, w = img.shape[:2]
    grey, gx, gy, grad, out = (_aligned((h, w)) for _ in range(5))  # OpenCV's SIMD rounds by the buffers' alignment
    np.mean(np.ascontiguousarray(img, np.float32), axis=2, out=grey)
    for dx, g in ((1, gx), (0, gy)):
        cv2.Sobel(grey, cv2.CV_32F, dx, 1 - dx, dst=g, ksize=3, scale=0.125, borderType=cv2.BORDER_REPLICATE)
    cv2.magnitude(gx, gy, magnitude=grad)
    if exclude is not None:
        grad[exclude] = 0.0
    k = 2 * int(np.ceil(2.5 * sigma_px)) + 1
    cv2.GaussianBlur(grad, (k, k), sigma_px, dst=out, sigmaY=sigma_px, borderType=cv2.BORDER_REFLECT_101)
    return out


def _aligned(shape: tuple[int, int], align: int = 64) -> np.ndarray:
    """An empty C-contiguous float32 array whose data starts on an ``align``-byte boundary: OpenCV's vectorised
    filters round the last bit by where a row starts, so the same photo gave another sharpness map from run to run
    (28 of 40 calls differed) with numpy's 16-byte alignment."""
    n = int(np.prod(shape)) * 4
    raw = np.empty(n + align, np.uint8)
    start = -raw.ctypes.data % align
    return raw[start : start + n].view(np.float32).reshape(shape)


def _affine(p: np.ndarray, M: np.ndarray, t) -> list[np.ndarray]:
    """The rows of ``M @ p + t`` for channel-major points ``p`` (3, N) and a small (k, 3) ``M``: k arrays (N,), row by
    row (BLAS on N × 3 is slow when other threads, torch's, compete for the cores)."""
    t = np.broadcast_to(np.asarray(t, p.dtype), (len(M),))
    return [p[0] * M[j, 0] + p[1] * M[j, 1] + p[2] * M[j, 2] + t[j] for j in range(len(M))]


def channel_rows(a: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Rows ``idx`` of an (N, C) array whose channels are contiguous (the transpose of a (C, N) array, as the
    sampler's colours are), laid out the same way."""
    return a.T.take(idx, 1).T


class ViewSampler:
    """The photos' samples of a set of texel points, one view at a time (nothing texels × views is held).

    :meth:`samples` of view ``i`` gives the texels it sees (in front, inside the image, facing it with cos >
    ``min_cos``, depth test of :func:`sample_visible`) with their colours, blending weights (cos^p / distance² ×
    a feather towards the image border × the support × the sharpness factor × ``clipped_weight`` on over-exposed
    pixels) and tiers: 0 clean, 1 touches a depth edge, 2 seen only through the silhouette band
    (:func:`without_silhouette`). Points, normals and colours are held channel by channel (``pts`` is the transpose
    of a (3, M) array). ``clipped``: per view, its over-exposed pixels (:func:`clipped_pixels`; default: none).
    """

    def __init__(self, pts: np.ndarray, nrm: np.ndarray, images: list[np.ndarray], cams: Cameras,
                 depths: list[np.ndarray], cfg: TextureConfig, maps: tuple | None = None,
                 clipped: list[np.ndarray] | None = None):
        if pts.ndim != 2 or pts.shape[1] != 3 or nrm.shape != pts.shape:
            raise ValueError(f"ViewSampler: pts {pts.shape} and nrm {nrm.shape} must both have shape (M, 3)")
        if not (len(images) == len(depths) == len(cams)):
            raise ValueError(f"ViewSampler: {len(images)} images, {len(depths)} depth maps, {len(cams)} cameras")
        self._set_points(pts, nrm)
        self.images, self.cfg, self.full_depths = images, cfg, depths
        self.planes = [_planes(im) for im in images]
        self.depths = [without_silhouette(d, cfg.silhouette_px) for d in depths]
        self.band = [(cv2.dilate((np.isfinite(f) & ~np.isfinite(d)).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0)
                     .ravel() for f, d in zip(depths, self.depths)]  # silhouette band, grown by a pixel
        self.K, self.R = cams.K.astype(np.float32), cams.R.astype(np.float32)
        self.t, self.centers = cams.t.astype(np.float32), cams.centers.astype(np.float32)
        self.edges, self.sharp = maps if maps is not None else self._maps()
        if clipped is not None and [c.shape for c in clipped] != [im.shape[:2] for im in images]:
            raise ValueError("ViewSampler: one clipped-pixel map per image, of its height and width")
        self.clipped = None if clipped is None else [c.ravel() for c in clipped]

    def _maps(self):
        cfg = self.cfg
        edges = [depth_edges(d, cfg.depth_tolerance, cfg.edge_px) for d in self.depths]
        if cfg.sharpness_power <= 0:
            return edges, None
        grow = np.ones((3, 3), np.uint8)  # the edges one pixel wider: depth_edges(…, edge_px + 1)
        sharp = [sharpness_map(im, cv2.dilate(e.astype(np.uint8), grow) > 0) for im, e in zip(self.images, edges)]
        return edges, sharp

    def _set_points(self, pts: np.ndarray, nrm: np.ndarray) -> None:
        """The points (M, 3) and normals (M, 3) sampled, held channel by channel, and n·p per point."""
        self.p3, self.n3 = np.array(pts.T, np.float32, order="C"), np.array(nrm.T, np.float32, order="C")
        self.pts = self.p3.T
        self.facing = self.n3[0] * self.p3[0] + self.n3[1] * self.p3[1] + self.n3[2] * self.p3[2]

    def at(self, pts: np.ndarray, nrm: np.ndarray, cfg: TextureConfig | None = None) -> "ViewSampler":
        """The same views (photos, depth and sharpness maps) sampling other points ``pts`` with normals ``nrm``,
        weighted by ``cfg`` (default: this sampler's)."""
        out = object.__new__(ViewSampler)
        out.__dict__.update(self.__dict__)
        out.cfg = cfg or self.cfg
        out._set_points(pts, nrm)
        return out

    def subset(self, sel) -> "ViewSampler":
        """The same views sampling only the texels ``sel`` (indices or a slice into this sampler's points)."""
        out = object.__new__(ViewSampler)
        out.__dict__.update(self.__dict__)
        out.p3, out.n3, out.facing = self.p3[:, sel], self.n3[:, sel], self.facing[sel]
        out.pts = out.p3.T
        return out

    def samples(self, i: int):
        """View ``i``'s samples: texel indices (k,), colours (k, 3) (channels contiguous: the transpose of a (3, k)
        array), weights (k,), tiers (k,) int8."""
        cfg = self.cfg
        h, w = self.images[i].shape[:2]
        facing = _affine(self.n3, self.centers[i][None], 0.0)[0] - self.facing
        idx = np.flatnonzero(facing > 0)
        p = self.p3.take(idx, 1)
        view = self.centers[i][:, None] - p
        dist = np.sqrt(view[0] * view[0] + view[1] * view[1] + view[2] * view[2]).clip(1e-9)
        cos = facing.take(idx) / dist
        pix = _affine(p, self.K[i] @ self.R[i], self.K[i] @ self.t[i])
        z = np.where(pix[2] > 1e-9, pix[2], 1.0)
        u, v = pix[0] / z, pix[1] / z
        ok = (cos > cfg.min_cos) & (pix[2] > 1e-9) & (u >= 0.5) & (u <= w - 0.5) & (v >= 0.5) & (v <= h - 0.5)
        idx, dist, cos, u, v = idx[ok], dist[ok], cos[ok], u[ok], v[ok]
        f = float(self.K[i][0, 0])
        # depth change across one pixel on a surface tilted by θ: (dist / f) · tan θ
        tol = cfg.depth_tolerance + 1.5 * dist / f * np.sqrt(np.maximum(1 - cos * cos, 0.0)) / np.maximum(cos, 1e-6)
        col, sup, edge = _sample_planes(self.planes[i], self.depths[i], self.edges[i], u - 0.5, v - 0.5, dist, tol)
        tier = edge.astype(np.int8)
        pixel = v.astype(np.int64).clip(0, h - 1) * w + u.astype(np.int64).clip(0, w - 1)
        retry = np.flatnonzero((sup <= 0.05) & self.band[i].take(pixel))
        if len(retry):  # the silhouette band: a last resort
            col[:, retry], sup[retry], _ = _sample_planes(self.planes[i], self.full_depths[i], self.edges[i],
                                                          u[retry] - 0.5, v[retry] - 0.5, dist[retry], tol[retry])
            tier[retry] = 2
        keep = np.flatnonzero(sup > 0.05)
        idx, sup, tier, dist, cos, u, v = (a.take(keep) for a in (idx, sup, tier, dist, cos, u, v))
        col = col.take(keep, 1)
        border = np.minimum(np.minimum(u, w - u), np.minimum(v, h - v))
        feather = np.clip(border / (0.05 * max(w, h)), 0.05, 1.0)
        weight = cos ** cfg.angle_power / dist ** 2 * feather * sup
        px = np.minimum(v.astype(np.int64), h - 1) * w + np.minimum(u.astype(np.int64), w - 1)
        if self.clipped is not None:  # an over-exposed pixel only bounds the colour from below
            weight = np.where(self.clipped[i].take(px), weight * cfg.clipped_weight, weight)
        if self.sharp is not None:  # image contrast per unit length on the surface: lower in a blurred view
            contrast = self.sharp[i].ravel().take(px) * f / dist
            weight = weight * (1.0 + contrast / max(cfg.sharpness_floor, 1e-6)) ** cfg.sharpness_power
        return idx, col.T, weight.astype(np.float32), tier


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
    with ``extremes``, per tier, texel and channel the largest and smallest sample and their weights (a trimmed
    mean of the samples :meth:`blend` takes)."""

    TIERS = (0, 1, 2)

    def __init__(self, n: int, extremes: bool = False):
        self.sums = np.zeros((4, len(self.TIERS), n))  # (R, G, B, weight) × tier × texel
        self.acc = {k: self.sums[:3, k].T for k in self.TIERS}  # (n, 3) views
        self.weight = {k: self.sums[3, k] for k in self.TIERS}
        self.counts = np.zeros((len(self.TIERS), n), np.int32)  # samples per tier and texel
        self.extremes = extremes
        if extremes:
            # (tier, channel, texel): each channel of a tier contiguous, as the samples' colours are
            t = len(self.TIERS)
            self.hi, self.lo = np.full((t, 3, n), -np.inf, np.float32), np.full((t, 3, n), np.inf, np.float32)
            self.hi_w, self.lo_w = np.zeros((t, 3, n), np.float32), np.zeros((t, 3, n), np.float32)

    @property
    def count(self) -> np.ndarray:
        """Samples (views) per texel (N,), all tiers."""
        return self.counts.sum(0, dtype=np.int32)

    def add(self, idx: np.ndarray, col: np.ndarray, weight: np.ndarray, tier: np.ndarray) -> None:
        """Samples of one or more views (texel ``idx`` unique within each view), in view order: texel indices (k,),
        colours (k, 3), weights (k,), tiers (k,). All views in one call sum exactly as one call per view would."""
        n = self.counts.shape[1]
        key = idx + n * tier.astype(np.intp) if tier.any() else idx
        wcol = weight[:, None] * col
        for j in range(4):
            self.sums[j] += np.bincount(key, wcol[:, j] if j < 3 else weight, len(self.TIERS) * n).reshape(-1, n)
        self.counts += np.bincount(key, minlength=len(self.TIERS) * n).reshape(-1, n).astype(np.int32)
        if self.extremes:
            for k in self.TIERS:
                s = np.flatnonzero(tier == k)
                if not len(s):
                    continue
                at, val, w = idx.take(s), col.take(s, 0), weight.take(s)
                for j in range(3):
                    self._extreme(at, val[:, j], w, self.hi[k, j], self.hi_w[k, j], np.fmax, np.greater)
                    self._extreme(at, val[:, j], w, self.lo[k, j], self.lo_w[k, j], np.fmin, np.less)

    @staticmethod
    def _extreme(idx, value, weight, best, best_w, pick, better) -> None:
        """Per texel the extreme ``value`` (``pick``: np.fmax or np.fmin) into ``best`` and the weight of the first
        sample that has it into ``best_w``, where it is ``better`` than the one already there."""
        new = np.full(len(best), np.nan, best.dtype)  # nan: no sample
        pick.at(new, idx, value)
        at = np.flatnonzero(value == new.take(idx))
        first = np.full(len(best), len(idx))
        np.minimum.at(first, idx.take(at), at)
        up = np.flatnonzero(better(new, best))  # nan (no sample) never is
        best[up] = new.take(up)
        best_w[up] = weight.take(first.take(up))

    def tier(self, edge_fallback_only: bool) -> np.ndarray:
        """Per texel the tier :meth:`blend` takes: the first with any weight (with ``edge_fallback_only`` clean before
        edge, else the two together as 0), the silhouette band last; −1 where nothing sees the texel."""
        out = np.full(self.counts.shape[1], -1, np.int8)
        order = (2, 1, 0) if edge_fallback_only else (2, 0)
        for k in order:
            w = self.weight[k] + (self.weight[1] if (k == 0 and not edge_fallback_only) else 0.0)
            out[w > 0] = k
        return out

    def blend(self, edge_fallback_only: bool) -> tuple[np.ndarray, np.ndarray]:
        """Colours (N, 3) and weights (N,) of the samples of each texel's :meth:`tier`."""
        acc, wsum = np.zeros_like(self.acc[0]), np.zeros_like(self.weight[0])
        for k, s in self._tier_rows(edge_fallback_only):
            acc[s] += self.acc[k][s]
            wsum[s] += self.weight[k][s]
        return acc / np.maximum(wsum, 1e-300)[:, None], wsum

    def _tier_rows(self, edge_fallback_only: bool) -> list[tuple[int, np.ndarray]]:
        """(tier, texels (N,) bool whose :meth:`tier` blends that tier's samples) for each tier."""
        tier = self.tier(edge_fallback_only)
        return [(k, tier == k if (edge_fallback_only or k != 1) else tier == 0) for k in self.TIERS]

    def tier_count(self, edge_fallback_only: bool) -> np.ndarray:
        """Per texel (N,) the number of samples of its :meth:`tier` (the views :meth:`blend` averages)."""
        out = np.zeros(self.counts.shape[1], np.int32)
        for k, s in self._tier_rows(edge_fallback_only):
            out[s] += self.counts[k][s]
        return out

    def reference(self, edge_fallback_only: bool, min_views: int = 3) -> np.ndarray:
        """Robust colour (N, 3): per channel, the weighted mean of the samples of the texel's :meth:`tier` without
        their largest and smallest where ``min_views`` or more of them see the texel (their median for three), else
        :meth:`blend`. A down-weighted edge sample (it may be background) never stands in for a clean extreme."""
        out, _ = self.blend(edge_fallback_only)
        if not self.extremes:
            return out
        n = self.counts.shape[1]
        acc, wsum, count = np.zeros((n, 3)), np.zeros((n, 1)), self.tier_count(edge_fallback_only)
        hi, lo = np.full((3, n), -np.inf, np.float32), np.full((3, n), np.inf, np.float32)
        hi_w, lo_w = np.zeros((3, n), np.float32), np.zeros((3, n), np.float32)
        for k, s in self._tier_rows(edge_fallback_only):
            acc[s] += self.acc[k][s]
            wsum[s, 0] += self.weight[k][s]
            up, down = s & (self.hi[k] > hi), s & (self.lo[k] < lo)
            hi, hi_w = np.where(up, self.hi[k], hi), np.where(up, self.hi_w[k], hi_w)
            lo, lo_w = np.where(down, self.lo[k], lo), np.where(down, self.lo_w[k], lo_w)
        hi, lo, hi_w, lo_w = hi.T, lo.T, hi_w.T, lo_w.T
        rest = wsum - hi_w - lo_w
        ok = (count[:, None] >= min_views) & (rest > 1e-6 * wsum)
        hi, lo = np.where(ok, hi, 0.0), np.where(ok, lo, 0.0)
        trimmed = (acc - hi_w * hi - lo_w * lo) / np.where(ok, rest, 1.0)
        return np.where(ok, trimmed, out)


class TexelSurface(NamedTuple):
    """Where the texels lie on the mesh, for the seam levelling and the view selection: the mesh vertex ids (M, 3)
    of each texel's face and its barycentrics (M, 3); the mesh's faces (F, 3) over ``n_verts`` vertices (UV-seam
    copies merged); each texel's face (M,) (row of ``faces``)."""

    texel_vertices: np.ndarray
    texel_bary: np.ndarray
    faces: np.ndarray
    n_verts: int
    texel_faces: np.ndarray | None = None


BAKE_CHUNK = 1 << 16
"""Texels baked together by :func:`bake`: their samples in all views are held at once (~25 bytes per sample, about a
dozen samples per texel) and reused by the robust pass."""
BAKE_THREADS = min(4, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)
"""Threads of the bake: chunks of texels (and the views of the seam-levelling fit) at once."""


def view_samples(sampler: ViewSampler, cfg: TextureConfig, offsets: np.ndarray | None = None,
                 surface: TexelSurface | None = None, charts: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    """All views' samples (:meth:`ViewSampler.samples`), view after view: texel indices (k,), colours (k, 3) with each
    view's seam offsets added (``offsets`` (V, n_verts, 3) on ``surface``, whose texels are the sampler's), weights
    (k,) × ``edge_weight`` on edge samples × the view's factor on the texel's face in ``charts`` (F, V) (the view
    selection, :func:`view_charts`; needs ``surface.texel_faces``), tiers (k,)."""
    out = []
    if offsets is not None:  # channel-major: (V, 3, n_verts) offsets, (3, M) texel corners and barycentrics
        planes = offsets.transpose(0, 2, 1).copy()
        corners, bary = surface.texel_vertices.T.copy(), np.array(surface.texel_bary.T, np.float32, order="C")
    for i in range(len(sampler.images)):
        idx, col, weight, tier = sampler.samples(i)
        col = col.T  # (3, k)
        if offsets is not None:
            col = col + texel_offsets_planar(planes[i], corners.take(idx, 1), bary.take(idx, 1))
        weight = weight * np.where(tier > 0, np.float32(cfg.edge_weight), np.float32(1.0))
        if charts is not None:
            weight = weight * charts[:, i].take(surface.texel_faces.take(idx))
        out.append((idx, col, weight, tier))
    if not out:
        return np.zeros(0, np.intp), np.zeros((0, 3), np.float32), np.zeros(0, np.float32), np.zeros(0, np.int8)
    idx, col, weight, tier = zip(*out)
    return np.concatenate(idx), np.concatenate(col, 1).T, np.concatenate(weight), np.concatenate(tier)


def blend_views(samples: tuple[np.ndarray, ...], n: int, cfg: TextureConfig, reference: np.ndarray | None = None,
                count: np.ndarray | None = None, extremes: bool = False) -> BlendAccumulator:
    """The views' ``samples`` (:func:`view_samples`) of ``n`` texels summed into a :class:`BlendAccumulator`; with a
    ``reference`` (n, 3) and view ``count`` (n,), each weight × :func:`robust_weights`."""
    idx, col, weight, tier = samples
    if reference is not None and len(idx):
        weight = weight * robust_weights(col, channel_rows(reference, idx), count.take(idx), cfg.outlier_threshold,
                                         cfg.outlier_reject)
    out = BlendAccumulator(n, extremes)
    out.add(idx, col, weight, tier)
    return out


def clean_samples(sampler: ViewSampler) -> tuple[np.ndarray, ...]:
    """Every view's clean (tier 0) samples of the sampler's points, view after view (the views sampled on
    :data:`BAKE_THREADS` threads): view ids (k,) int32, point indices (k,), colours (k, 3) (channels contiguous),
    weights (k,)."""
    with ThreadPoolExecutor(BAKE_THREADS) as pool:
        per_view = list(pool.map(sampler.samples, range(len(sampler.images))))
    views, texels, cols, weights = [], [], [], []
    for i, (idx, col, weight, tier) in enumerate(per_view):
        clean = np.flatnonzero(tier == 0)
        views.append(np.full(len(clean), i, np.int32)), texels.append(idx.take(clean))
        cols.append(col.T.take(clean, 1)), weights.append(weight.take(clean))
    return np.concatenate(views), np.concatenate(texels), np.concatenate(cols, 1).T, np.concatenate(weights)


def consistency(texel: np.ndarray, col: np.ndarray, weight: np.ndarray, n: int, cfg: TextureConfig) -> np.ndarray:
    """Photo-consistency factor (k,) of samples of ``n`` points (:func:`clean_samples`): :func:`robust_weights`
    against each point's per-channel trimmed mean over its samples; 1 with ``outlier_threshold`` 0."""
    if cfg.outlier_threshold <= 0 or not len(texel):
        return np.ones(len(texel), np.float32)
    stats = BlendAccumulator(n, extremes=True)
    stats.add(texel, col, weight, np.zeros(len(texel), np.int8))
    return robust_weights(col, channel_rows(stats.reference(True), texel), stats.count.take(texel),
                          cfg.outlier_threshold, cfg.outlier_reject)


def fit_view_offsets(sampler: ViewSampler, surface: TexelSurface, cfg: TextureConfig) -> np.ndarray:
    """Seam-levelling offsets (V, n_verts, 3) (:func:`pipeline.texture.seams.fit_seam_offsets`) fitted on at most
    ``seam_fit_texels`` texels drawn with a fixed seed; edge samples left out, outliers down-weighted against the
    texels' trimmed-mean colour."""
    n = len(sampler.pts)
    if len(surface.texel_vertices) != n or len(surface.texel_bary) != n:
        raise ValueError(f"fit_view_offsets: surface describes {len(surface.texel_vertices)} texels, sampler {n}")
    sel = np.arange(n)
    if n > cfg.seam_fit_texels:
        sel = np.sort(np.random.default_rng(0).choice(n, cfg.seam_fit_texels, replace=False))
    view, texel, col, weight = clean_samples(sampler.subset(sel))
    weight = weight.astype(np.float64) * consistency(texel, col, weight, len(sel), cfg)
    return fit_seam_offsets(view, texel, col, weight, surface.texel_vertices[sel],
                            surface.texel_bary[sel], surface.faces, surface.n_verts, len(sampler.images),
                            cfg.seam_smoothness, cfg.seam_zero_pull)


def face_view_scores(sampler: ViewSampler, surface: TexelSurface, cfg: TextureConfig) -> np.ndarray:
    """The view selection's data term (F, V): each view's clean blending weight (:meth:`ViewSampler.samples`, with
    the sharpness power ``selection_sharpness``) at the centre of each face's texels (their mean point and normal),
    × its photo-consistency (:func:`consistency`) against the face's robust colour over all views; 0 where the view
    does not see it."""
    n_faces, n_views = len(surface.faces), len(sampler.images)
    face = surface.texel_faces
    count = np.bincount(face, minlength=n_faces).astype(np.float64)
    has = np.flatnonzero(count > 0)
    centre = np.stack([np.bincount(face, sampler.p3[j], n_faces) for j in range(3)], 1)[has] / count[has, None]
    normal = np.stack([np.bincount(face, sampler.n3[j], n_faces) for j in range(3)], 1)[has]
    normal /= np.linalg.norm(normal, axis=1, keepdims=True).clip(1e-12)
    view, face_at, col, weight = clean_samples(sampler.at(centre, normal,
                                                           replace(cfg, sharpness_power=cfg.selection_sharpness)))
    scores = np.zeros((n_faces, n_views), np.float32)
    scores[has.take(face_at), view] = weight * consistency(face_at, col, weight, len(has), cfg)
    return scores


def view_charts(sampler: ViewSampler, surface: TexelSurface, cfg: TextureConfig) -> np.ndarray:
    """The view selection's factor (F, V) on each view's weights per face (:mod:`pipeline.texture.view_select`): a
    view per face from :func:`face_view_scores` under the Potts smoothness ``selection_smoothness``, blended over
    ``selection_rings`` rings of faces at the charts' borders, the other views at ``selection_floor``."""
    if surface.texel_faces is None or len(surface.texel_faces) != len(sampler.pts):
        raise ValueError("view_charts: the surface must give each of the sampler's texels its face")
    scores = face_view_scores(sampler, surface, cfg)
    adjacency = face_adjacency(surface.faces)
    labels = select_views(scores, adjacency, cfg.selection_smoothness)
    return chart_weights(labels, len(sampler.images), adjacency, cfg.selection_rings, cfg.selection_floor)


def _bake_texels(sampler: ViewSampler, cfg: TextureConfig, offsets: np.ndarray | None,
                 surface: TexelSurface | None, charts: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`bake` of the sampler's texels, their views' samples drawn once for both passes."""
    samples = view_samples(sampler, cfg, offsets, surface, charts)
    n, robust = len(sampler.pts), cfg.outlier_threshold > 0
    first = blend_views(samples, n, cfg, extremes=robust)
    col, wsum = first.blend(cfg.edge_fallback_only)
    tier = first.tier(cfg.edge_fallback_only)
    if robust:
        reference, count = first.reference(cfg.edge_fallback_only), first.tier_count(cfg.edge_fallback_only)
        del first
        second = blend_views(samples, n, cfg, reference=reference, count=count)
        robust_col, robust_wsum = second.blend(cfg.edge_fallback_only)
        ok = (second.tier(cfg.edge_fallback_only) == tier) & (robust_wsum > 1e-6 * wsum)  # else keep the first pass
        col[ok] = robust_col[ok]
    return np.clip(col, 0.0, 1.0), wsum, tier == 2


def bake(pts: np.ndarray, nrm: np.ndarray, images: list[np.ndarray], cams: Cameras, depths: list[np.ndarray],
         cfg: TextureConfig, surface: TexelSurface | None = None, clipped: list[np.ndarray] | None = None
         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Colours (M, 3) in [0, 1], total weights (M,) of texel points seen by the photos, and which texels only the
    silhouette band sees (M,) bool (their colour may be background: the caller gives them the fallback colour).

    Samples and weights per view: :class:`ViewSampler` (depth test, cos^p / distance², border feather, sharpness,
    over-exposed pixels (``clipped``) at ``clipped_weight``).
    Samples touching a depth discontinuity or silhouette (where real photos blend foreground and background) are
    down-weighted by ``edge_weight`` and, with ``edge_fallback_only``, count only where no clean sample sees the
    texel; pixels in the silhouette band (``silhouette_px``) count only where nothing else does. With
    ``seam_levelling`` and a ``surface``, each view's samples get its fitted colour offsets
    (:func:`fit_view_offsets`) first. With ``outlier_threshold`` > 0 a second pass re-weights every sample by its
    photo-consistency (:func:`robust_weights`) against the first pass's per-channel trimmed mean, so a highlight,
    shadow or occluder that one view alone sees does not reach the texture. Texels are baked :data:`BAKE_CHUNK` at a
    time, :data:`BAKE_THREADS` chunks at once (every texel's result depends on its own samples only).
    """
    sampler = ViewSampler(pts, nrm, images, cams, depths, cfg, clipped=clipped)
    offsets = fit_view_offsets(sampler, surface, cfg) if cfg.seam_levelling and surface is not None else None
    select = cfg.view_selection and surface is not None and surface.texel_faces is not None
    charts = view_charts(sampler, surface, cfg) if select else None
    n = len(sampler.pts)
    col, wsum, band = np.zeros((n, 3)), np.zeros(n), np.zeros(n, bool)

    def bake_chunk(start: int) -> None:
        """Bake the texels start … start + BAKE_CHUNK into ``col``, ``wsum``, ``band``."""
        s = slice(start, start + BAKE_CHUNK)
        part = None if surface is None else surface._replace(
            texel_vertices=surface.texel_vertices[s], texel_bary=surface.texel_bary[s],
            texel_faces=None if surface.texel_faces is None else surface.texel_faces[s])
        col[s], wsum[s], band[s] = _bake_texels(sampler.subset(s), cfg, offsets, part, charts)

    with ThreadPoolExecutor(BAKE_THREADS) as pool:  # numpy releases the GIL in the chunks' array operations
        list(pool.map(bake_chunk, range(0, n, BAKE_CHUNK)))
    return col, wsum, band
