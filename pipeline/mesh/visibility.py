"""Which faces of a mesh the photos see (``--mesh.drop-unseen``): pixel rays and face-centre rays, the seen part
tidied to one clean open edge."""

from __future__ import annotations

import numpy as np
import trimesh

from pipeline.mesh.config import MeshConfig


def seen_faces(verts: np.ndarray, faces: np.ndarray, K: np.ndarray, R: np.ndarray, centres: np.ndarray,
               sizes: list[tuple[int, int]], max_rays: int = 1 << 20) -> np.ndarray:
    """(F,) bool: the faces some view sees first through a pixel centre; ``K``, ``R``, ``centres`` (N, …) in the
    frame of ``verts``, ``sizes`` each view's (height, width). A view of more than ``max_rays`` pixels casts through
    the centres of a coarser grid of them (every s-th pixel's neighbourhood: a 12 MP photo through 1 M rays)."""
    from pipeline.render.raycast import MeshCaster, pixel_center_rays

    if len(K) != len(sizes) or len(R) != len(K) or len(centres) != len(K):
        raise ValueError(f"seen_faces: {len(K)} K, {len(R)} R, {len(centres)} centres and {len(sizes)} sizes differ")
    caster = MeshCaster(trimesh.Trimesh(verts, faces, process=False))
    seen = np.zeros(len(faces), bool)
    for k, (h, w) in enumerate(sizes):
        s = max(1.0, float(np.sqrt(h * w / max_rays)))
        coarse = np.diag([1.0 / s, 1.0 / s, 1.0]) @ K[k]
        first = caster.first_faces(*pixel_center_rays(coarse, R[k], centres[k], int(w / s), int(h / s)))
        seen[first[first >= 0]] = True
    return seen


def centre_seen_faces(verts: np.ndarray, faces: np.ndarray, K: np.ndarray, R: np.ndarray, centres: np.ndarray,
                      sizes: list[tuple[int, int]], min_cos: float = 0.2) -> np.ndarray:
    """(F,) bool: the faces whose centre some view sees: turned towards the camera (the cosine of the angle between
    its normal and the way to the camera above ``min_cos``: not at a grazing angle), projected inside its image,
    and first along the ray from the camera to it. Unlike :func:`seen_faces` it does not depend on a face covering a
    pixel centre: faces smaller than a pixel, which pixel rays hit only here and there, count as seen throughout."""
    from dvr.cameras import project_points
    from pipeline.render.raycast import MeshCaster

    if len(K) != len(sizes) or len(R) != len(K) or len(centres) != len(K):
        raise ValueError(f"centre_seen_faces: {len(K)} K, {len(R)} R, {len(centres)} centres and {len(sizes)} sizes "
                         f"differ")
    mesh = trimesh.Trimesh(verts, faces, process=False)
    caster = MeshCaster(mesh)
    mid, normal = mesh.triangles_center, mesh.face_normals
    seen = np.zeros(len(faces), bool)
    for k, (h, w) in enumerate(sizes):
        c = np.asarray(centres[k], float)
        uv, z = project_points(K[k] @ np.concatenate([R[k], -R[k] @ c[:, None]], 1), mid)
        to_cam = c - mid
        facing = (to_cam * normal).sum(1) > min_cos * np.linalg.norm(to_cam, axis=1)
        ask = np.flatnonzero(facing)
        ask = ask[(z[ask] > 0) & (uv[ask, 0] >= 0) & (uv[ask, 0] <= w) & (uv[ask, 1] >= 0) & (uv[ask, 1] <= h)]
        if len(ask) == 0:
            continue
        d = mid[ask] - c
        first = caster.first_faces(np.broadcast_to(c, d.shape), d / np.linalg.norm(d, axis=1, keepdims=True))
        seen[ask[first == ask]] = True
    return seen


def face_neighbours(faces: np.ndarray):
    """(F, F) sparse matrix (CSR) with a 1 where two faces share an edge."""
    from scipy.sparse import coo_matrix

    pairs = trimesh.graph.face_adjacency(faces=faces)
    n = len(faces)
    return coo_matrix((np.ones(2 * len(pairs)), (np.r_[pairs[:, 0], pairs[:, 1]], np.r_[pairs[:, 1], pairs[:, 0]])),
                      shape=(n, n)).tocsr()


def _patches(neighbours, within: np.ndarray) -> np.ndarray:
    """(F,) component label of each face in ``within`` over the edge adjacency ``neighbours``; −1 outside it."""
    from scipy.sparse.csgraph import connected_components

    idx = np.flatnonzero(within)
    label = np.full(len(within), -1)
    label[idx] = connected_components(neighbours[idx][:, idx], directed=False)[1]
    return label


def tidy_seen(faces: np.ndarray, seen: np.ndarray, hole_ratio: float, rings: int) -> np.ndarray:
    """(F,) bool: the faces ``--mesh.drop-unseen`` keeps, given those some photo sees (``seen``, (F,) bool). Unseen
    patches of fewer than ``hole_ratio`` × F faces are put back (holes in the seen surface); then the set is opened
    by ``rings`` rings of faces: eroded (a face with a neighbour outside goes) ``rings`` times, then grown back
    ``rings`` times within itself, which removes strips, fringes and specks narrower than 2 × ``rings`` faces. Holes
    first, or the erosion would widen every pinhole (on DTU's stop-56 mesh the open edge came out a third shorter
    this way than the other)."""
    if len(faces) != len(seen):
        raise ValueError(f"tidy_seen: {len(faces)} faces and {len(seen)} seen flags differ")
    near = face_neighbours(faces)
    whole = np.asarray(seen, bool).copy()
    holes = _patches(near, ~whole)
    if (holes >= 0).any():
        size = np.bincount(holes[holes >= 0])
        whole |= (holes >= 0) & (size[np.maximum(holes, 0)] < hole_ratio * len(faces))
    keep = whole.copy()
    for _ in range(rings):
        keep &= ~(near @ (~keep).astype(np.float64) > 0)
    for _ in range(rings):
        keep = whole & (keep | (near @ keep.astype(np.float64) > 0))
    return keep


def boundary_loops(mesh: trimesh.Trimesh) -> tuple[int, float]:
    """(how many closed chains the edges of one face each form, their total length): a mesh's openings."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    edges, count = np.unique(mesh.edges_sorted, axis=0, return_counts=True)
    rim = edges[count == 1]
    if len(rim) == 0:
        return 0, 0.0
    n = len(mesh.vertices)
    label = connected_components(coo_matrix((np.ones(len(rim)), (rim[:, 0], rim[:, 1])), shape=(n, n)),
                                 directed=False)[1]
    length = np.linalg.norm(mesh.vertices[rim[:, 0]] - mesh.vertices[rim[:, 1]], axis=1).sum()
    return len(np.unique(label[rim[:, 0]])), float(length)


def seen_part(verts: np.ndarray, faces: np.ndarray, K: np.ndarray, R: np.ndarray, centres: np.ndarray,
              sizes: list[tuple[int, int]], cfg: MeshConfig) -> np.ndarray:
    """(F,) bool: the faces ``--mesh.drop-unseen`` keeps (``verts`` in the cameras' frame): seen through a pixel
    centre (:func:`seen_faces`) or at their centre (:func:`centre_seen_faces`), tidied (:func:`tidy_seen`)."""
    seen = seen_faces(verts, faces, K, R, centres, sizes) | centre_seen_faces(verts, faces, K, R, centres, sizes)
    return tidy_seen(faces, seen, cfg.unseen_hole_ratio, cfg.unseen_rings)
