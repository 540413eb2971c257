"""Stage ``mesh``: isosurface of the trained occupancy → ``mesh/raw.ply``; cleaned → ``mesh/clean.ply``."""

from __future__ import annotations

import shutil
from dataclasses import replace

import numpy as np
import torch
import trimesh

from dvr.atomic import export_mesh
from dvr.cameras import transform_points
from dvr.device import resolve_device
from dvr.extract import extract_mesh
from dvr.fields import evaluate_in_chunks
from pipeline.errors import StageError
from pipeline.mesh.config import MeshConfig
from pipeline.mesh.levels import budget, level_folder, parse_levels
from pipeline.mesh.visibility import (
    boundary_loops,
    seen_part,
)
from pipeline.readers import load_mesh_file, mesh_units, read_model
from pipeline.workspace import Done, Job


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


SAME_POSITION = 1e-6
"""Vertices closer than this fraction of the mesh's diagonal stand at one position (what a loader that merges
vertices by position joins): :func:`_make_closed` merges them, :func:`pinches_apart` finds the copies a split left."""


def _make_closed(ms) -> None:
    """Merge the vertices at one position (:data:`SAME_POSITION`: what a loader that merges vertices by position
    does), split non-manifold edges and vertices, then close the small holes that leaves (and any others)."""
    import pymeshlab

    ms.meshing_merge_close_vertices(threshold=pymeshlab.PercentageValue(100 * SAME_POSITION))
    ms.meshing_remove_null_faces()
    ms.meshing_remove_duplicate_faces()
    ms.meshing_repair_non_manifold_edges()
    ms.meshing_repair_non_manifold_vertices()
    # close_holes needs an edge-manifold mesh and up-to-date adjacency, which the repairs leave stale (on stale
    # adjacency it can end the process with SIGSEGV, as on DTU scan24's decimated mesh of the quality preset);
    # measuring the topology rebuilds the adjacency
    if ms.get_topological_measures()["non_two_manifold_edges"] == 0:
        try:
            ms.meshing_close_holes(maxholesize=30)
        except pymeshlab.PyMeshLabException:  # leave the holes where it cannot close them
            pass
    ms.set_selection_none()  # close_holes selects its new faces, and later filters would act on those only
    ms.meshing_remove_unreferenced_vertices()


PINCH_APART = 1e-3
"""Vertices that share a position move this fraction of the mesh's mean edge length apart (:func:`pinches_apart`)."""


def pinches_apart(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``verts`` with the vertices that share a position (:data:`SAME_POSITION`) moved into the mesh along their own
    normals by :data:`PINCH_APART` of the mean edge length. Splitting a non-manifold edge (two sheets an edge
    collapse pinched together) leaves two copies of its vertices at one place: closed as stored, but every tool that
    merges vertices by position (trimesh's loader, a slicer) joins them again into an edge of four faces, an open
    mesh."""
    from scipy.spatial import cKDTree

    if len(faces) == 0:
        return verts
    diagonal = float(np.linalg.norm(np.ptp(verts, axis=0)))
    pairs = cKDTree(verts).query_pairs(SAME_POSITION * diagonal, output_type="ndarray")
    if len(pairs) == 0:  # the edge lengths and normals serve only to move copies
        return verts
    mesh = trimesh.Trimesh(verts, faces, process=False)
    moved = np.unique(pairs)
    out = verts.copy()
    out[moved] -= PINCH_APART * float(mesh.edges_unique_length.mean()) * mesh.vertex_normals[moved]
    return out


def clean_mesh(verts: np.ndarray, faces: np.ndarray, cfg: MeshConfig,
               points: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, list[dict]]:
    """Small components, duplicates, degenerate faces, non-manifold edges, small holes, smoothing
    (:func:`repaired_mesh`), decimation, small components again (the repairs can split some off), then the pieces
    that none of the SfM ``points`` (mesh frame; None: none known) lies on (:func:`floaters`), and the split vertices
    moved apart (:func:`pinches_apart`) (:func:`finished_mesh`). Returns (vertices, faces, the dropped floaters)."""
    return finished_mesh(*repaired_mesh(verts, faces, cfg), cfg, points)


def repaired_mesh(verts: np.ndarray, faces: np.ndarray, cfg: MeshConfig) -> tuple[np.ndarray, np.ndarray]:
    """The first part of :func:`clean_mesh`, before the decimation: (vertices, faces)."""
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
    m = ms.current_mesh()
    return m.vertex_matrix(), m.face_matrix()


def finished_mesh(verts: np.ndarray, faces: np.ndarray, cfg: MeshConfig,
                  points: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, list[dict]]:
    """The rest of :func:`clean_mesh`, from a :func:`repaired_mesh`: (vertices, faces, the dropped floaters)."""
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=verts, face_matrix=faces.astype(np.int32)))
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
    return pinches_apart(np.asarray(m.vertices), np.asarray(m.faces)), np.asarray(m.faces), dropped


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


def _export(path, verts, faces, colors, scale_mat, to_normalized, frame):
    m = trimesh.Trimesh(verts, faces, vertex_colors=colors, process=False)
    m.apply_transform(scale_mat if frame == "sfm" else to_normalized)
    export_mesh(path, m)  # whole or absent (dvr.atomic)


def run(job: Job) -> Done:
    """Stage ``mesh`` (called by :func:`pipeline.stages.run_stage`): the trained occupancy's isosurface →
    mesh/raw.ply; cleaned, decimated and coloured by the texture field → mesh/clean.ply."""
    ws, cfg = job.ws, job.cfg
    parse_levels(cfg.detail)  # a misspelt level stops here, not after the extraction
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
    points = sfm_points(ws.root / "points.ply", scale_mat)
    repaired = repaired_mesh(v, f, cfg)
    cv, cf, dropped = finished_mesh(*repaired, cfg, points)
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
    _export(clean, cv, cf, vertex_colours(field, cv, dev), scale_mat, to_norm, cfg.frame)
    units = mesh_units(ws.root, cfg.frame)  # {} unless a printed board put cameras.npz in metres
    print(f"mesh: {len(f)} raw faces, {len(cf)} clean faces{' (metres)' if units else ''} → {clean}")
    levels = write_levels(ws, repaired, points, cfg, field, dev, scale_mat, to_norm)
    return Done({"raw_faces": int(len(f)), "clean_faces": int(len(cf)), "unseen_faces": unseen, "frame": cfg.frame,
                 "footprint": cfg.footprint,
                 **({"open_loops": loops, "open_length": round(length, 3)} if cfg.drop_unseen else {}),
                 "floaters": dropped, **({"levels": levels} if levels else {}),
                 **units})


def vertex_colours(field, verts: np.ndarray, dev) -> np.ndarray:
    """(N, 3) uint8: the texture field's colour at each vertex (normalized frame)."""
    with torch.no_grad():
        pts = torch.from_numpy(verts).float().to(dev)
        cc = evaluate_in_chunks(field.texture, pts, 65536, trailing_shape=(3,))
    return (cc.clamp(0, 1) * 255).round().byte().cpu().numpy()


def write_levels(ws, repaired: tuple[np.ndarray, np.ndarray], points: np.ndarray | None, cfg: MeshConfig, field,
                 dev, scale_mat: np.ndarray, to_norm: np.ndarray) -> dict:
    """The detail levels of ``cfg.detail`` (:mod:`pipeline.mesh.levels`), heaviest first, each cleaned as the clean
    mesh is (its floaters judged by the SfM ``points``) with its face budget from the level before it (the first
    finished from the default mesh's ``repaired`` mesh, :func:`repaired_mesh`: a chain of decimations
    (:func:`finished_mesh`), each from fewer faces than the raw mesh's) → ``mesh/levels/<level>/clean.ply``.
    Returns the faces of each level, in the order asked. Levels not asked for are removed (a stale one would be
    textured and shown as current)."""
    asked = parse_levels(cfg.detail)
    for old in sorted((ws.mesh / "levels").glob("*")) if (ws.mesh / "levels").is_dir() else []:
        if old.name not in asked:
            shutil.rmtree(old, ignore_errors=True)
    out = {}
    verts, faces = None, None
    for level in sorted(asked, key=budget, reverse=True):
        level_cfg = replace(cfg, max_faces=budget(level))
        # the level above is repaired already (finished_mesh repairs after its decimation): only its decimation
        verts, faces, _ = finished_mesh(*(repaired if verts is None else (verts, faces)), level_cfg, points)
        lv, lf = verts, faces
        if cfg.drop_unseen:
            lv, lf, _ = _drop_unseen(ws, lv, lf, scale_mat, cfg)
        folder = level_folder(ws.mesh, level)
        folder.mkdir(parents=True, exist_ok=True)
        _export(folder / "clean.ply", lv, lf, vertex_colours(field, lv, dev), scale_mat, to_norm, cfg.frame)
        print(f"mesh: detail level {level}: {len(lf)} faces → {folder / 'clean.ply'}")
        out[level] = int(len(lf))
    return {level: out[level] for level in asked}
