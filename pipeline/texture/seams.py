"""Global seam levelling for the texture bake: per view, a colour offset per mesh vertex, solved in least squares.

Real photos of one surface differ by exposure, white balance and light that moves with the camera; blended as
they are, the texture shows a step wherever the blending weights hand over from one view to another. Every view
``v`` gets an offset field ``o_v`` (an RGB offset per mesh vertex, interpolated to texels by barycentrics) chosen
so that the corrected samples ``c_v + o_v`` of all views agree where views overlap:

    E = Σ_texels Σ_pairs (a, b) w_a w_b / W · |c_a + o_a − c_b − o_b|²      (pairwise agreement, W = Σ w)
      + λ Σ_views Σ_mesh edges (i, j) |o_v[i] − o_v[j]|²                     (smooth offsets)
      + μ Σ_views Σ_vertices |o_v[i]|²                                       (weak pull to zero)

The pairwise term equals, for one view with the others fixed, ``Σ_t w_v (W − w_v) / W · |c_v + o_v − m_¬v|²``
with ``m_¬v`` the weighted mean of the OTHER views' corrected samples: the fit is a block Gauss-Seidel over the
views (each view against the consensus of the others, one sparse SPD solve per view, its factorisation reused
across sweeps). Texels only one view sees carry no data; there the smoothness term carries the view's offset
over its whole footprint, so a view that is brighter everywhere is corrected everywhere. The sum is invariant to
a common shift of all views; that shift is removed (the samples' mean brightness is kept).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu


def mesh_edges(faces: np.ndarray) -> np.ndarray:
    """Unique undirected edges (E, 2), smaller vertex id first, of a triangle mesh's faces (F, 3)."""
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"mesh_edges: faces must have shape (F, 3), got {faces.shape}")
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).astype(np.int64)
    e.sort(axis=1)
    e = e[e[:, 0] != e[:, 1]]
    if not len(e):
        return e.reshape(0, 2)
    n = int(e.max()) + 1
    key = np.unique(e[:, 0] * n + e[:, 1])  # the rows' lexicographic order, as np.unique(e, axis=0), several × faster
    return np.stack([key // n, key % n], 1)


def texel_offsets(view_offsets: np.ndarray, texel_vertices: np.ndarray, texel_bary: np.ndarray) -> np.ndarray:
    """Offsets (K, 3) at texels: the barycentric mix of one view's per-vertex offsets (n_verts, 3) at the texels'
    face corners ``texel_vertices`` (K, 3) with weights ``texel_bary`` (K, 3)."""
    if view_offsets.ndim != 2 or view_offsets.shape[1] != 3:
        raise ValueError(f"texel_offsets: view_offsets must have shape (n_verts, 3), got {view_offsets.shape}")
    if texel_vertices.shape != texel_bary.shape or texel_vertices.ndim != 2 or texel_vertices.shape[1] != 3:
        raise ValueError(f"texel_offsets: texel_vertices {texel_vertices.shape} and texel_bary {texel_bary.shape} "
                         "must both have shape (K, 3)")
    planar = texel_offsets_planar(np.ascontiguousarray(view_offsets.T), texel_vertices.T, texel_bary.T)
    return np.ascontiguousarray(planar.T)


def texel_offsets_planar(view_offsets: np.ndarray, texel_vertices: np.ndarray, texel_bary: np.ndarray) -> np.ndarray:
    """:func:`texel_offsets` channel-major: offsets (3, n_verts), corners and barycentrics (3, K) → (3, K)."""
    bary = texel_bary.astype(view_offsets.dtype, copy=False)
    out = np.empty((len(view_offsets), texel_vertices.shape[1]), view_offsets.dtype)
    for o, channel in zip(out, view_offsets):
        np.multiply(bary[0], channel.take(texel_vertices[0]), out=o)
        o += bary[1] * channel.take(texel_vertices[1])
        o += bary[2] * channel.take(texel_vertices[2])
    return out


def _check_fit_inputs(sample_view, sample_texel, sample_colour, sample_weight, texel_vertices, texel_bary,
                      faces, n_verts, n_views):
    n = len(sample_view)
    if sample_view.ndim != 1 or sample_texel.shape != (n,) or sample_weight.shape != (n,):
        raise ValueError(f"fit_seam_offsets: sample_view {sample_view.shape}, sample_texel {sample_texel.shape} and "
                         f"sample_weight {sample_weight.shape} must all have shape (N,)")
    if sample_colour.shape != (n, 3):
        raise ValueError(f"fit_seam_offsets: sample_colour must have shape ({n}, 3), got {sample_colour.shape}")
    if texel_vertices.ndim != 2 or texel_vertices.shape[1] != 3 or texel_bary.shape != texel_vertices.shape:
        raise ValueError(f"fit_seam_offsets: texel_vertices {texel_vertices.shape} and texel_bary "
                         f"{texel_bary.shape} must both have shape (T, 3)")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"fit_seam_offsets: faces must have shape (F, 3), got {faces.shape}")
    if len(faces) and (faces.min() < 0 or faces.max() >= n_verts):
        raise ValueError(f"fit_seam_offsets: faces must index the {n_verts} vertices")
    if n and (sample_view.min() < 0 or sample_view.max() >= n_views):
        raise ValueError(f"fit_seam_offsets: sample_view must lie in [0, {n_views})")
    if n and (sample_texel.min() < 0 or sample_texel.max() >= len(texel_vertices)):
        raise ValueError(f"fit_seam_offsets: sample_texel must index the {len(texel_vertices)} texels")
    if len(texel_vertices) and (texel_vertices.min() < 0 or texel_vertices.max() >= n_verts):
        raise ValueError(f"fit_seam_offsets: texel_vertices must index the {n_verts} vertices")
    if not np.isfinite(sample_colour).all() or not np.isfinite(sample_weight).all() or (sample_weight < 0).any():
        raise ValueError("fit_seam_offsets: colours and weights must be finite, weights non-negative")


class _ViewSystem:
    """One view's least-squares system over the vertices its samples touch (factorised once)."""

    def __init__(self, texel, weight, others, texel_vertices, texel_bary, edges, n_verts, smoothness, zero_pull):
        corners = texel_vertices.take(texel, 0)  # (n, 3)
        used = np.zeros(n_verts, bool)
        used[corners] = True
        self.vertices = np.flatnonzero(used)
        n, n_loc = len(texel), len(self.vertices)
        pos = np.full(n_verts, -1)
        pos[self.vertices] = np.arange(n_loc)
        rows = np.repeat(np.arange(n), 3)
        self.B = sp.csr_matrix((texel_bary.take(texel, 0).ravel(), (rows, pos.take(corners).ravel())),
                               shape=(n, n_loc))
        data = weight * others / np.maximum(weight + others, 1e-12)  # w_v (W − w_v) / W
        self.data = data / max(float(data.mean()), 1e-12)  # mean 1: λ, μ are per sample
        per_vertex = n / max(n_loc, 1)
        ends = pos[edges]
        ends = ends[(ends >= 0).all(1)]
        adj = sp.coo_matrix((np.ones(len(ends)), (ends[:, 0], ends[:, 1])), shape=(n_loc, n_loc))
        adj = adj + adj.T
        lap = sp.diags(np.asarray(adj.sum(1)).ravel()) - adj
        system = (self.B.T @ sp.diags(self.data) @ self.B + smoothness * per_vertex * lap
                  + zero_pull * per_vertex * sp.identity(n_loc))
        # SPD: a symmetric fill-reducing order (several × less fill than splu's default COLAMD), no pivoting
        self.lu = splu(sp.csc_matrix(system), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                       options={"SymmetricMode": True})

    def offsets(self, target: np.ndarray) -> np.ndarray:
        """Per-vertex offsets (n_loc, 3) fitting the per-sample target offsets (n, 3)."""
        return self.lu.solve(np.asarray(self.B.T @ (self.data[:, None] * target)))


def fit_seam_offsets(sample_view: np.ndarray, sample_texel: np.ndarray, sample_colour: np.ndarray,
                     sample_weight: np.ndarray, texel_vertices: np.ndarray, texel_bary: np.ndarray,
                     faces: np.ndarray, n_verts: int, n_views: int, smoothness: float = 10.0,
                     zero_pull: float = 0.01, sweeps: int = 3) -> np.ndarray:
    """Per-view, per-vertex colour offsets (n_views, n_verts, 3) float32 that level the views (module docstring).

    The samples (N of them) are the views' colours at a subset of texels: ``sample_view`` (N,) view index,
    ``sample_texel`` (N,) texel index into ``texel_vertices`` / ``texel_bary`` (T, 3) (mesh vertex ids of the
    texel's face and its barycentrics), ``sample_colour`` (N, 3), ``sample_weight`` (N,) blending weight (robust
    down-weighting already applied). ``faces`` (F, 3) give the smoothness edges. ``smoothness`` (λ) and
    ``zero_pull`` (μ, > 0) are per sample of data: λ = 10 ties offsets over a few edges. Vertices a view's
    samples never touch take that view's mean offset.
    """
    sample_view, sample_texel = np.asarray(sample_view), np.asarray(sample_texel)
    sample_colour, sample_weight = np.asarray(sample_colour), np.asarray(sample_weight)
    texel_vertices, texel_bary, faces = np.asarray(texel_vertices), np.asarray(texel_bary), np.asarray(faces)
    _check_fit_inputs(sample_view, sample_texel, sample_colour, sample_weight, texel_vertices, texel_bary,
                      faces, n_verts, n_views)
    if not (zero_pull > 0 and smoothness >= 0 and sweeps >= 1):
        raise ValueError(f"fit_seam_offsets: need zero_pull > 0, smoothness >= 0, sweeps >= 1; got {zero_pull}, "
                         f"{smoothness}, {sweeps}")
    out = np.zeros((n_views, n_verts, 3), np.float32)
    view, texel, colour, weight = _by_view(sample_view, sample_texel, sample_colour, sample_weight)
    if not len(view):
        return out
    bounds = np.searchsorted(view, np.arange(n_views + 1))
    n_tex = len(texel_vertices)
    total = np.bincount(texel, weight, n_tex)
    corrected = colour.copy()
    acc = np.stack([np.bincount(texel, weight * c, n_tex) for c in colour])  # (3, n_tex)
    edges = mesh_edges(faces)
    systems: list[_ViewSystem | None] = [None] * n_views
    for _ in range(sweeps):
        for v in range(n_views):
            s = slice(bounds[v], bounds[v + 1])
            t, w = texel[s], weight[s]
            others = total.take(t) - w
            agree = others > 1e-9 * total.take(t)
            if not agree.any():
                continue  # nothing to agree with
            if systems[v] is None:
                systems[v] = _ViewSystem(t, w, others, texel_vertices, texel_bary, edges, n_verts,
                                         smoothness, zero_pull)
            others_mean = (acc.take(t, 1) - w * corrected[:, s]) / np.maximum(others, 1e-12)
            target = np.where(agree, others_mean - colour[:, s], 0.0)
            vertex_offsets = systems[v].offsets(target.T)
            new = colour[:, s] + (systems[v].B @ vertex_offsets).T
            delta = w * (new - corrected[:, s])
            for j in range(3):
                np.add.at(acc[j], t, delta[j])
            corrected[:, s] = new
            out[v, systems[v].vertices] = vertex_offsets
    _remove_common_shift(out, systems, weight, corrected, colour)
    return out


def _remove_common_shift(out: np.ndarray, systems: list, weight: np.ndarray, corrected: np.ndarray,
                         colour: np.ndarray) -> None:
    """In ``out`` (n_views, n_verts, 3): the weighted mean change of all samples' colours (``colour`` → ``corrected``,
    (3, N)) taken off every fitted view's offsets, and the vertices a view never sees given its mean offset."""
    shift = [np.dot(weight, c - c0) / max(float(weight.sum()), 1e-12) for c, c0 in zip(corrected, colour)]
    for v, system in enumerate(systems):
        if system is None:
            continue
        out[v, system.vertices] -= np.asarray(shift, np.float32)
        rest = np.ones(out.shape[1], bool)
        rest[system.vertices] = False
        out[v, rest] = out[v, system.vertices].mean(0)


def _by_view(view: np.ndarray, texel: np.ndarray, colour: np.ndarray, weight: np.ndarray):
    """The samples of positive weight in view order (each view's samples one slice; stable): view, texel, colour
    (3, N) float64 (channel-major), weight float64."""
    keep = np.flatnonzero(weight > 0)
    kept = view.take(keep)
    if len(kept) and (np.diff(kept) < 0).any():
        keep = keep.take(np.argsort(kept, kind="stable"))
    return (view.take(keep), texel.take(keep), np.asarray(colour.T.take(keep, 1), np.float64),
            weight.take(keep).astype(np.float64))
