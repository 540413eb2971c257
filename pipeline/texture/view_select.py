"""Discrete view selection for the texture bake: one photo per mesh face, chosen for a sharp, frontal, close,
unoccluded and photo-consistent look, with a smoothness term so that charts come from few views.

The labelling minimises a Potts energy over the mesh's face adjacency (as photogrammetry texturers do, e.g.
Waechter et al., "Let there be color!", ECCV 2014):

    E(l) = Σ_faces −log(D[f, l_f] / max_v D[f, v]) + λ Σ_(f, g) adjacent [l_f ≠ l_g]

with D the view's blending weight at the face (cos^p / distance² × border feather × depth-test support × local
sharpness, :class:`pipeline.texture.blend.ViewSampler`) × its photo-consistency against the face's robust colour over
all views (:func:`pipeline.texture.blend.robust_weights`, so a highlight or occluder one view alone sees is not
picked). It is solved by iterated conditional modes from the best view per face (half of the faces, drawn with a fixed
seed, move per sweep so that neighbours do not flip together). Local blending across the charts' borders: the one-hot
labels are averaged over ``rings`` rings of neighbouring faces, so a texel near a border mixes the views on both sides;
every other view keeps ``floor`` of its weight (a texel the chosen view does not see still gets a colour).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import trimesh


def face_adjacency(faces: np.ndarray) -> sp.csr_matrix:
    """Symmetric (F, F) 0/1 matrix of faces sharing an edge (trimesh's ``face_adjacency``)."""
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"face_adjacency: faces must have shape (F, 3), got {faces.shape}")
    n = len(faces)
    pairs = trimesh.graph.face_adjacency(faces) if len(faces) else np.zeros((0, 2), np.int64)
    a, b = pairs[:, 0], pairs[:, 1]
    data = np.ones(2 * len(pairs), np.float32)
    adj = sp.csr_matrix((data, (np.concatenate([a, b]), np.concatenate([b, a]))), shape=(n, n))
    adj.data[:] = 1.0  # a pair listed twice stays one neighbour
    return adj


def select_views(scores: np.ndarray, adjacency: sp.csr_matrix, smoothness: float, sweeps: int = 20,
                 seed: int = 0, data_rings: int = 2) -> np.ndarray:
    """A view per face (F,) int (−1: no view sees it) minimising the Potts energy of the module docstring for the
    data ``scores`` (F, V) ≥ 0 (0: the view does not see the face) and the face ``adjacency`` (F, F). The data term
    is each face's score averaged with its neighbours' over ``data_rings`` rings where the view sees them (one
    point's sharpness is noisy; the texturers' gradient integral is over an area)."""
    if scores.ndim != 2 or adjacency.shape != (len(scores), len(scores)):
        raise ValueError(f"select_views: scores {scores.shape} must be (F, V) and adjacency {adjacency.shape} (F, F)")
    if not np.isfinite(scores).all() or (scores < 0).any():
        raise ValueError("select_views: scores must be finite and non-negative")
    if smoothness < 0:
        raise ValueError(f"select_views: smoothness must be >= 0, got {smoothness}")
    n, v = scores.shape
    scores = _ring_mean(scores, adjacency, data_rings)
    best = scores.max(1, initial=0.0)
    seen = best > 0
    with np.errstate(divide="ignore"):
        cost = np.where(scores > 0, -np.log(scores / np.where(seen, best, 1.0)[:, None]), np.inf)
    labels = np.where(seen, scores.argmax(1) if v else 0, -1)
    if smoothness == 0 or v < 2:
        return labels
    rng = np.random.default_rng(seed)
    rows = np.flatnonzero(seen)
    for _ in range(sweeps):
        onehot = sp.csr_matrix((np.ones(len(rows)), (rows, labels[rows])), shape=(n, v))
        agree = np.asarray((adjacency @ onehot).todense())  # neighbours already on each view
        new = np.where(seen, (cost - smoothness * agree).argmin(1), -1)
        move = (new != labels) & (rng.random(n) < 0.5)
        if not move.any():
            break
        labels[move] = new[move]
    return labels


def _with_self(adjacency: sp.csr_matrix, dtype) -> sp.csr_matrix:
    """``adjacency`` + I (every face also its own neighbour: one ring of averaging), the identity in ``dtype``."""
    return (adjacency + sp.identity(adjacency.shape[0], dtype, format="csr")).tocsr()


def _ring_mean(scores: np.ndarray, adjacency: sp.csr_matrix, rings: int) -> np.ndarray:
    """``scores`` (F, V) averaged ``rings`` times over each face and its neighbours, each view over the faces it sees
    (0 stays 0: a view that does not see a face is not made to)."""
    seen = (scores > 0).astype(np.float64)
    step = _with_self(adjacency, np.float64)
    count = np.maximum(np.asarray(step @ seen), 1.0)
    out = scores.astype(np.float64)
    for _ in range(rings):
        out = np.asarray(step @ (out * seen)) / count
    return out * seen


def chart_weights(labels: np.ndarray, n_views: int, adjacency: sp.csr_matrix, rings: int,
                  floor: float) -> np.ndarray:
    """Per face and view the factor (F, V) float32 on the bake's weights: the face's label one-hot, averaged
    ``rings`` times over itself and its neighbours (labelled faces only), times 1 − ``floor``, plus ``floor``;
    1 for every view where no face near it has a label (the plain blend)."""
    if labels.ndim != 1 or adjacency.shape != (len(labels), len(labels)):
        raise ValueError(f"chart_weights: labels {labels.shape} must be (F,) and adjacency {adjacency.shape} (F, F)")
    if not 0.0 <= floor <= 1.0 or rings < 0:
        raise ValueError(f"chart_weights: floor must be in [0, 1] and rings >= 0, got {floor}, {rings}")
    n = len(labels)
    rows = np.flatnonzero(labels >= 0)
    soft = np.zeros((n, n_views), np.float32)
    soft[rows, labels[rows]] = 1.0
    step = _with_self(adjacency, np.float32)
    for _ in range(rings):
        soft = np.asarray(step @ soft, np.float32)
        soft /= np.maximum(soft.sum(1, keepdims=True), 1e-12)  # the labels' share among the faces near each face
    soft = np.where(soft.sum(1, keepdims=True) > 0, soft, 1.0)
    return (floor + (1.0 - floor) * soft).astype(np.float32)
