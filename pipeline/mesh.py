"""Stage ``mesh``: isosurface of the trained occupancy → ``mesh/raw.ply``; cleaned → ``mesh/clean.ply``."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch
import trimesh

from dvr.device import resolve_device
from dvr.extract import extract_mesh
from dvr.fields import evaluate_in_chunks
from dvr.trainer import load_model

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
    footprint: float = 0.03
    """Height above the support plane (working-sphere radii) below which the mesh is the vertical extrusion of its
    cross-section at that height: the object meets its floor or table with the footprint of what stands just above,
    where automatic masks lose the lowest strip to the contact shadow (the lying book from photos: 23.4 → 24.3 dB
    held-out; cow, jar and DTU within ±0.03 dB). 0: off; no effect without a support plane."""
    smooth_iterations: int = 0
    """Taubin smoothing iterations of the clean mesh (0: off)."""
    max_faces: int = 40000
    """Decimate the clean mesh to at most this many faces (quadric edge collapse)."""
    frame: Literal["sfm", "normalized"] = "sfm"
    """Frame of the written meshes: 'sfm' (the frame of cameras.npz) or 'normalized' (unit sphere)."""
    device: str = "auto"
    """'auto' (CUDA when present), 'cpu' or 'cuda'."""


def keep_large_components(verts: np.ndarray, faces: np.ndarray, min_ratio: float) -> np.ndarray:
    """Faces of the connected components with at least ``min_ratio`` × the faces of the largest (vertex
    connectivity through a sparse graph: linear memory, unlike a face-adjacency split)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    if len(faces) == 0:
        return faces
    n = len(verts)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]])
    g = coo_matrix((np.ones(len(e), np.int8), (e[:, 0], e[:, 1])), shape=(n, n))
    _, label = connected_components(g, directed=False)
    fl = label[faces[:, 0]]
    count = np.bincount(fl)
    return faces[count[fl] >= min_ratio * count.max()]


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


def clean_mesh(verts: np.ndarray, faces: np.ndarray, cfg: MeshConfig) -> tuple[np.ndarray, np.ndarray]:
    """Small components, duplicates, degenerate faces, non-manifold edges, small holes, smoothing, decimation."""
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
    return m.vertex_matrix(), m.face_matrix()


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
    field, scale_mat, to_norm = load_model(final, dev)
    v, f, c = extract_mesh(field, cfg.resolution, cfg.coarse_factor, cfg.refine_steps, device=dev,
                           footprint=cfg.footprint)
    if len(f) == 0:
        raise StageError(f"{final}: the trained field has no surface; check masks/ and retrain (--force)")
    ws.mesh.mkdir(parents=True, exist_ok=True)
    _export(raw, v, f, c, scale_mat, to_norm, cfg.frame)
    cv, cf = clean_mesh(v, f, cfg)
    with torch.no_grad():
        pts = torch.from_numpy(cv).float().to(dev)
        cc = evaluate_in_chunks(field.texture, pts, 65536, trailing_shape=(3,))
    _export(clean, cv, cf, (cc.clamp(0, 1) * 255).round().byte().cpu().numpy(), scale_mat, to_norm, cfg.frame)
    units = mesh_units(ws.root, cfg.frame)  # {} unless a printed board put cameras.npz in metres
    print(f"mesh: {len(f)} raw faces, {len(cf)} clean faces{' (metres)' if units else ''} → {clean}")
    return Done({"raw_faces": int(len(f)), "clean_faces": int(len(cf)), "frame": cfg.frame, **units})
