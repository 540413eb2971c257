"""Stage ``mesh``: isosurface of the trained occupancy → ``mesh/raw.ply``; cleaned → ``mesh/clean.ply``."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch
import trimesh

from dvr.cameras import transform_points
from dvr.checkpoint import load_model
from dvr.device import resolve_device
from dvr.extract import extract_mesh
from dvr.fields import evaluate_in_chunks

from .board import mesh_units
from .workspace import Done, Job, StageError


@dataclass
class MeshConfig:
    """Isosurface extraction and cleaning (stage ``mesh``)."""

    resolution: int = 256
    """Marching-cubes cells per axis over [-1, 1] (fine level)."""
    coarse_factor: int = 4
    """The coarse level is resolution / coarse_factor; only cells near the surface are refined."""
    refine_steps: int = 2
    """Newton steps moving vertices onto the level set (0: off)."""
    min_component_ratio: float = 0.02
    """Drop connected components with fewer faces than this fraction of the largest."""
    floater_support: float = 0.1
    """Drop a connected piece other than the largest as a floater when fewer SfM points (``points.ply``) lie on
    it than this fraction of what the largest piece's density of points (per unit area) would put there, where that
    is at least 10 points. A real part of the object is seen and matched as the rest of it is; a piece no point lies
    on explains some views' colours at a depth where nothing is (DTU: a 6000-face slab of roof hung above the house
    with 0 of the 270–330 points its area would carry, and a piece of wall at the sphere's edge with 0 of about 40,
    while the house carries 2018 of the 2179 points in the sphere). 0: off; no effect without points."""
    floater_distance: float = 0.02
    """A point lies on the mesh within this distance of its surface (working-sphere radii)."""
    footprint: float = 0.03
    """Height above the support plane (working-sphere radii) below which the mesh is the vertical extrusion of its
    cross-section at that height: the object meets its floor or table with the footprint of what stands just above,
    where automatic masks lose the lowest strip to the contact shadow (the lying book from photos: 23.4 → 24.3 dB
    held-out; cow, jar and DTU within ±0.03 dB). 0: off; no effect without a support plane."""
    smooth_iterations: int = 0
    """Taubin smoothing iterations of the clean mesh (0: off)."""
    max_faces: int = 40000
    """Decimate the clean mesh to at most this many faces (quadric edge collapse)."""
    drop_unseen: bool = False
    """Remove the faces that no pixel centre of any photo sees first (ray-cast through every pixel of every view in
    cameras.npz): the back of an object photographed from one side, which otherwise closes along the working sphere
    and takes the texture field's guessed colours, and the underside where it stands. The mesh is then open, as
    photogrammetry's is; off: one closed surface."""
    unseen_hole_ratio: float = 0.01
    """With ``drop_unseen``: a patch of unseen faces with fewer faces than this fraction of the mesh's stays (a pit
    or a face between two pixels' rays inside what the photos see: a hole there is a tear, not the open back)."""
    unseen_rings: int = 2
    """With ``drop_unseen``: the seen faces are opened by this many rings of faces (eroded, then grown back within
    what is seen), so strips narrower than twice that, glimpsed at grazing angles beyond the outline, go with the
    unseen side instead of hanging off the edge as shreds (DTU: 67 open loops 31.8 working-sphere radii long → 2, 12.3).
    0: every seen face stays."""
    frame: Literal["sfm", "normalized"] = "sfm"
    """Frame of the written meshes: 'sfm' (the frame of cameras.npz) or 'normalized' (unit sphere)."""
    device: str = "auto"
    """'auto' (CUDA when present), 'cpu' or 'cuda'."""


def face_components(n_verts: int, faces: np.ndarray) -> np.ndarray:
    """Connected-component label of each face (vertex connectivity through a sparse graph: linear memory, unlike a
    face-adjacency split)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]])
    g = coo_matrix((np.ones(len(e), np.int8), (e[:, 0], e[:, 1])), shape=(n_verts, n_verts))
    return connected_components(g, directed=False)[1][faces[:, 0]]


def keep_large_components(verts: np.ndarray, faces: np.ndarray, min_ratio: float) -> np.ndarray:
    """Faces of the connected components with at least ``min_ratio`` × the faces of the largest."""
    if len(faces) == 0:
        return faces
    fl = face_components(len(verts), faces)
    count = np.bincount(fl)
    return faces[count[fl] >= min_ratio * count.max()]


def floaters(verts: np.ndarray, faces: np.ndarray, points: np.ndarray, ratio: float, distance: float,
             min_expected: float = 10.0) -> tuple[np.ndarray, list[dict]]:
    """The pieces of a mesh that no SfM point supports (``MeshConfig.floater_support``): (boolean mask of the faces
    to keep, one dict per dropped piece: faces, area, points on it, points expected there). ``points`` (M, 3) in the
    mesh's frame; a point lies on the piece of its nearest face when within ``distance``. The piece with the most
    faces sets the density of points per unit area; another piece is dropped when its area would carry at least
    ``min_expected`` points at that density and fewer than ``ratio`` × that many lie on it."""
    keep = np.ones(len(faces), bool)
    if ratio <= 0 or len(points) == 0 or len(faces) == 0:
        return keep, []
    label = face_components(len(verts), faces)
    n = label.max() + 1
    if n == 1:
        return keep, []
    mesh = trimesh.Trimesh(verts, faces, process=False)
    reach = np.linalg.norm(points - verts.mean(0), axis=1) <= np.linalg.norm(verts - verts.mean(0), axis=1).max() \
        + distance  # only points near the mesh can lie on it (closest_point costs per point)
    _, dist, tri = trimesh.proximity.closest_point(mesh, points[reach])
    on = np.bincount(label[tri[dist <= distance]], minlength=n)
    area = np.bincount(label, weights=mesh.area_faces, minlength=n)
    ref = np.bincount(label, minlength=n).argmax()
    expected = area * on[ref] / max(area[ref], 1e-12)
    drop = (np.arange(n) != ref) & (expected >= min_expected) & (on < ratio * expected)
    keep = ~drop[label]
    return keep, [{"faces": int((label == c).sum()), "area": round(float(area[c]), 4), "points": int(on[c]),
                   "expected": round(float(expected[c]), 1)} for c in np.flatnonzero(drop)]


def _make_closed(ms) -> None:
    """Split non-manifold edges and vertices, then close the small holes that leaves (and any others)."""
    import pymeshlab

    ms.meshing_repair_non_manifold_edges()
    ms.meshing_repair_non_manifold_vertices()
    try:
        ms.meshing_close_holes(maxholesize=30)
    except pymeshlab.PyMeshLabException:  # needs an edge-manifold mesh; leave the holes otherwise
        pass
    ms.set_selection_none()  # close_holes selects its new faces, and later filters would act on those only
    ms.meshing_remove_unreferenced_vertices()


def clean_mesh(verts: np.ndarray, faces: np.ndarray, cfg: MeshConfig,
               points: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, list[dict]]:
    """Small components, duplicates, degenerate faces, non-manifold edges, small holes, smoothing, decimation, small
    components again (the repairs can split some off), then the pieces that none of the SfM ``points`` (mesh frame;
    None: none known) lies on (:func:`floaters`). Returns (vertices, faces, the dropped floaters)."""
    import pymeshlab  # here, not at the top: the config tree (and a GPU machine's train stage) imports this module

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=verts.astype(np.float64), face_matrix=faces.astype(np.int32)))
    ms.meshing_remove_duplicate_vertices()
    ms.meshing_remove_duplicate_faces()
    ms.meshing_remove_null_faces()
    ms.meshing_repair_non_manifold_edges()
    ms.meshing_remove_unreferenced_vertices()
    m = ms.current_mesh()
    v, f = m.vertex_matrix(), keep_large_components(m.vertex_matrix(), m.face_matrix(), cfg.min_component_ratio)
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=v, face_matrix=f.astype(np.int32)))
    ms.meshing_remove_unreferenced_vertices()
    _make_closed(ms)
    if cfg.smooth_iterations > 0:
        ms.apply_coord_taubin_smoothing(stepsmoothnum=cfg.smooth_iterations)
    if ms.current_mesh().face_number() > cfg.max_faces:
        ms.meshing_decimation_quadric_edge_collapse(targetfacenum=cfg.max_faces, preservenormal=True)
        _make_closed(ms)  # an edge collapse can pinch two sheets into one edge shared by four faces
    ms.meshing_remove_unreferenced_vertices()
    m = ms.current_mesh()
    v = m.vertex_matrix()
    # the repairs split pieces joined by a vertex: DTU's decimated mesh got an 18-face speck that a viewer frames
    f = keep_large_components(v, m.face_matrix(), cfg.min_component_ratio)
    dropped = []
    if points is not None:
        keep, dropped = floaters(v, f, points, cfg.floater_support, cfg.floater_distance)
        f = f[keep]
    m = trimesh.Trimesh(v, f, process=False)
    m.remove_unreferenced_vertices()
    return np.asarray(m.vertices), np.asarray(m.faces), dropped


def seen_faces(verts: np.ndarray, faces: np.ndarray, K: np.ndarray, R: np.ndarray, centres: np.ndarray,
               sizes: list[tuple[int, int]], max_rays: int = 1 << 20) -> np.ndarray:
    """(F,) bool: the faces some view sees first through a pixel centre; ``K``, ``R``, ``centres`` (N, …) in the
    frame of ``verts``, ``sizes`` each view's (height, width). A view of more than ``max_rays`` pixels casts through
    the centres of a coarser grid of them (every s-th pixel's neighbourhood: a 12 MP photo through 1 M rays)."""
    from .raycast import mesh_intersector, pixel_center_rays

    if len(K) != len(sizes) or len(R) != len(K) or len(centres) != len(K):
        raise ValueError(f"seen_faces: {len(K)} K, {len(R)} R, {len(centres)} centres and {len(sizes)} sizes differ")
    hits = mesh_intersector(trimesh.Trimesh(verts, faces, process=False))
    seen = np.zeros(len(faces), bool)
    for k, (h, w) in enumerate(sizes):
        s = max(1.0, float(np.sqrt(h * w / max_rays)))
        coarse = np.diag([1.0 / s, 1.0 / s, 1.0]) @ K[k]
        first = hits.intersects_first(*pixel_center_rays(coarse, R[k], centres[k], int(w / s), int(h / s)))
        seen[first[first >= 0]] = True
    return seen


def centre_seen_faces(verts: np.ndarray, faces: np.ndarray, K: np.ndarray, R: np.ndarray, centres: np.ndarray,
                      sizes: list[tuple[int, int]], min_cos: float = 0.2) -> np.ndarray:
    """(F,) bool: the faces whose centre some view sees: turned towards the camera (the cosine of the angle between
    its normal and the way to the camera above ``min_cos``: not at a grazing angle), projected inside its image,
    and first along the ray from the camera to it. Unlike :func:`seen_faces` it does not depend on a face covering a
    pixel centre: faces smaller than a pixel, which pixel rays hit only here and there, count as seen throughout."""
    from dvr.cameras import project_points

    from .raycast import mesh_intersector

    if len(K) != len(sizes) or len(R) != len(K) or len(centres) != len(K):
        raise ValueError(f"centre_seen_faces: {len(K)} K, {len(R)} R, {len(centres)} centres and {len(sizes)} sizes "
                         f"differ")
    mesh = trimesh.Trimesh(verts, faces, process=False)
    hits = mesh_intersector(mesh)
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
        first = hits.intersects_first(np.broadcast_to(c, d.shape), d / np.linalg.norm(d, axis=1, keepdims=True))
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


def _drop_unseen(ws, verts: np.ndarray, faces: np.ndarray, scale_mat: np.ndarray, cfg: MeshConfig,
                 ) -> tuple[np.ndarray, np.ndarray, int]:
    """The clean mesh (normalized frame) without the faces no photo of the workspace sees (:func:`seen_part`),
    small pieces dropped again; and how many faces went."""
    from PIL import Image

    from dvr.cameras import load_cameras, to_sfm
    from dvr.data import list_images

    cams = load_cameras(ws.cameras)
    sizes = []
    for path in list_images(ws.images):
        with Image.open(path) as im:  # the header only
            sizes.append(im.size[::-1])
    kept = faces[seen_part(to_sfm(verts, scale_mat), faces, cams.K, cams.R, cams.sfm_centers, sizes, cfg)]
    kept = keep_large_components(verts, kept, cfg.min_component_ratio) if len(kept) else kept
    m = trimesh.Trimesh(verts, kept, process=False)
    m.remove_unreferenced_vertices()
    return np.asarray(m.vertices), np.asarray(m.faces), int(len(faces) - len(m.faces))


def sfm_points(path, scale_mat: np.ndarray) -> np.ndarray | None:
    """The cameras stage's sparse points (``points.ply``, SfM frame) in the field's frame (``scale_mat``: field →
    SfM); None when there is no such file (a workspace from given cameras without triangulation)."""
    if not path.exists():
        return None
    # a PLY of no points loads as an empty Scene
    loaded = load_mesh_file(path, "ply", "SfM points", "rerun the cameras stage (--force) or delete the file")
    pts = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), np.float64).reshape(-1, 3)
    return transform_points(np.linalg.inv(scale_mat), pts)


def load_mesh_file(path: Path, file_type: str, what: str, fix: str, **kwargs):
    """``trimesh.load`` of a file a stage wrote (``process=False`` unless given), or a StageError naming it, what it
    should hold and ``fix``, when it is damaged (a killed write, a disk that filled) or not what was written."""
    try:
        return trimesh.load(path, file_type=file_type, **{"process": False, **kwargs})
    except Exception as e:  # noqa: BLE001 - trimesh raises what its parser meets (ValueError, KeyError, struct.error)
        raise StageError(f"{path}: unreadable {what} ({type(e).__name__}); {fix}") from e


def read_model(path, device: torch.device):
    """The trained field of ``model/final.pt`` (:func:`dvr.checkpoint.load_model`: field, scale_mat, frame); a
    StageError naming the file and the fix when it is damaged or another version's."""
    try:
        return load_model(path, device)
    except ValueError as exc:
        raise StageError(f"{exc}; retrain (train --force)") from exc


def _export(path, verts, faces, colors, scale_mat, to_normalized, frame):
    m = trimesh.Trimesh(verts, faces, vertex_colors=colors, process=False)
    m.apply_transform(scale_mat if frame == "sfm" else to_normalized)
    m.export(path)


def run(job: Job) -> Done:
    """Stage ``mesh`` (called by :func:`pipeline.stages.run_stage`): the trained occupancy's isosurface →
    mesh/raw.ply; cleaned, decimated and coloured by the texture field → mesh/clean.ply."""
    ws, cfg = job.ws, job.cfg
    final = ws.model / "final.pt"
    raw, clean = ws.mesh / "raw.ply", ws.mesh / "clean.ply"
    dev = resolve_device(cfg.device)
    field, scale_mat, to_norm = read_model(final, dev)
    v, f, c = extract_mesh(field, cfg.resolution, cfg.coarse_factor, cfg.refine_steps, device=dev,
                           footprint=cfg.footprint)
    if len(f) == 0:
        raise StageError(f"{final}: the trained field has no surface; check masks/ and retrain (--force)")
    ws.mesh.mkdir(parents=True, exist_ok=True)
    _export(raw, v, f, c, scale_mat, to_norm, cfg.frame)
    cv, cf, dropped = clean_mesh(v, f, cfg, sfm_points(ws.root / "points.ply", scale_mat))
    for piece in dropped:
        print(f"mesh: dropped a floating piece of {piece['faces']} faces: {piece['points']} SfM points lie on it, "
              f"where the object's density of points would put {piece['expected']:.0f}")
    unseen = 0
    if cfg.drop_unseen:
        cv, cf, unseen = _drop_unseen(ws, cv, cf, scale_mat, cfg)
        loops, length = boundary_loops(trimesh.Trimesh(cv, cf, process=False))
        print(f"mesh: dropped {unseen} faces no photo sees (--mesh.drop-unseen); the mesh's open edge: {loops} "
              f"loop(s), {length:.2f} working-sphere radii long")
        if len(cf) == 0:
            raise StageError(f"{ws.cameras}: no photo sees the mesh; check the cameras, or mesh without "
                             f"--mesh.drop-unseen")
    with torch.no_grad():
        pts = torch.from_numpy(cv).float().to(dev)
        cc = evaluate_in_chunks(field.texture, pts, 65536, trailing_shape=(3,))
    _export(clean, cv, cf, (cc.clamp(0, 1) * 255).round().byte().cpu().numpy(), scale_mat, to_norm, cfg.frame)
    units = mesh_units(ws.root, cfg.frame)  # {} unless a printed board put cameras.npz in metres
    print(f"mesh: {len(f)} raw faces, {len(cf)} clean faces{' (metres)' if units else ''} → {clean}")
    return Done({"raw_faces": int(len(f)), "clean_faces": int(len(cf)), "unseen_faces": unseen, "frame": cfg.frame,
                 **({"open_loops": loops, "open_length": round(length, 3)} if cfg.drop_unseen else {}),
                 "floaters": dropped,
                 **units})
