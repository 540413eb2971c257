"""Stage ``texture``: UV atlas + texture baked from the PHOTOS → ``mesh/textured.{obj,mtl,png,glb}``.

1. xatlas charts the clean mesh; every face is rasterised into the atlas (OpenCV polygon fill with
   sub-texel precision, one call per face — no per-texel loop over faces), giving each texel its face,
   barycentrics, 3-D point and normal.
2. Every view renders a depth map of the mesh (the ray depth at every pixel centre, ray-cast by
   pipeline/render/raycast.py); a texel is visible in a view when its projection's depth agrees with that map.
3. Colour (:mod:`pipeline.texture.blend`) = weighted mean of the visible views' bilinear samples, weight =
   cos(angle)^p / distance² × a feather towards the image border; the weights are sharpened so the best views
   dominate. Colours come from 3-D points, so texels on both sides of a UV seam (same 3-D point) get the same
   colour: seams match.
4. Texels no photo sees take the trained texture field's colour; a gutter is dilated around every chart so
   mip-maps do not bleed background into the surface.
5. From the trained occupancy field: a tangent-space normal map of its own normals and an ambient-occlusion map
   (:mod:`pipeline.texture.surface_maps`), written beside the texture and into the GLB, MTL and USDZ.
6. Each detail level gets an atlas of its own and takes its colours, normals and occlusion from the default mesh's
   texture and maps (:mod:`pipeline.texture.transfer`), textured two at a time beside the default mesh.
"""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Callable

import numpy as np
import torch
import trimesh

from dvr.cameras import Cameras, load_cameras, project_points, to_normalized, to_sfm, transform_points
from dvr.data import list_images
from dvr.device import resolve_device
from dvr.fields import Field, evaluate_in_chunks
from pipeline.errors import StageError
from pipeline.mesh.levels import level_folder
from pipeline.messages import heartbeat, say_now, size_in_words
from pipeline.readers import load_mesh_file, mesh_units, read_model
from pipeline.render.raycast import MeshCaster
from pipeline.texture.appearance import photos_for_bake
from pipeline.texture.atlas import (
    dilate_gutter,
    filling_density,
    make_atlas,
    rasterize_atlas,
    texel_geometry,
)
from pipeline.texture.blend import TexelSurface, bake
from pipeline.texture.config import TextureConfig
from pipeline.texture.export import export_textured
from pipeline.texture.surface_maps import SurfaceField, bake_surface_maps, surface_field
from pipeline.texture.transfer import BakedMesh, carried, carried_uvs
from pipeline.texture.usdz import export_usdz
from pipeline.workspace import Done, Job

CARRY_REACH = 2 / 128
"""How far (working-sphere radii) a detail level's surface may lie from the default mesh's where it takes its colour
when no trained field gives the grid's cell."""

BAKES_AT_ONCE = 2
"""Detail levels textured at once, beside the default mesh (one bake keeps two cores busy only part of its time:
xatlas's packing, the PNG encoding and much of the bookkeeping run on one)."""


def depth_maps(mesh: trimesh.Trimesh, cams: Cameras, sizes: list[tuple[int, int]]) -> list[np.ndarray]:
    """Per view, the ray depth of the first mesh hit at every pixel centre (inf where none)
    (:meth:`pipeline.render.raycast.MeshCaster.depth_map`)."""
    caster = MeshCaster(mesh)
    return [caster.depth_map(cams.K[i], cams.R[i], cams.centers[i], w, h) for i, (w, h) in enumerate(sizes)]


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


@dataclass
class Carry:
    """What a detail level takes from the default mesh's texture instead of baking the photos again
    (:mod:`pipeline.texture.transfer`)."""

    source: Callable[[], BakedMesh]
    """The default mesh textured (the call may wait for its bake)."""
    texels_per_unit: float
    """The default mesh's atlas density (:func:`texels_per_unit`): the same surface seen by the same photos."""
    reach: float
    """How far apart the two surfaces may lie (:func:`pipeline.texture.transfer.carried_uvs`)."""


def texture_mesh(verts_n: np.ndarray, faces: np.ndarray, images: list[np.ndarray], cams: Cameras, cfg: TextureConfig,
                 field: Field | None = None, field_frame: np.ndarray | None = None,
                 field_gain: np.ndarray | None = None, clipped: list[np.ndarray] | None = None,
                 occupancy: SurfaceField | None = None, carry: Carry | None = None):
    """Normalized-frame mesh → (new verts, new faces, uvs, texture (side, side, 3) float, stats); the side follows
    the photos' resolution on the object (:func:`texels_per_unit`). ``field_gain``: see :func:`fill_unseen`;
    ``clipped``: the photos' over-exposed pixels (:func:`pipeline.texture.blend.clipped_pixels` of the photos as taken,
    before :func:`undo_appearance`), down-weighted by ``clipped_weight``; default: none. ``stats["normals"]``: the new
    vertices' unit normals; with the trained ``occupancy``, ``stats["maps"]``: its normal and occlusion
    maps (:func:`pipeline.texture.surface_maps.bake_surface_maps`, as ``cfg`` asks). With ``carry``, the colours
    and the surface maps' normals and occlusion are carried from another textured mesh of the same surface instead of
    baked (texels it does not reach take the texture field's colour and the field's own normals and occlusion);
    ``stats["carried"]``: the share it coloured."""
    images = [np.asarray(im, np.float32) for im in images]  # the bake's dtype: the extremes of float64 photos would
    # not round-trip through the float32 statistics of the photo-consistency pass
    base = trimesh.Trimesh(verts_n, faces, process=False)
    sizes = [(im.shape[1], im.shape[0]) for im in images]
    tpu = carry.texels_per_unit if carry is not None else texels_per_unit(base, cams, sizes, cfg)
    with ThreadPoolExecutor(1) as pool:  # the depth maps beside the atlas (xatlas releases the GIL), on a mesh of
        # their own (trimesh's caches are not thread-safe)
        deps = None if carry is not None else pool.submit(
            depth_maps, trimesh.Trimesh(verts_n, faces, process=False), cams, sizes)
        vmap, nf, uvs, side = make_atlas(verts_n, faces, tpu, cfg.padding, cfg.size)
        nv = verts_n[vmap]
        normals = base.vertex_normals[vmap]
        fid = rasterize_atlas(uvs, nf, side)
        r, c, pts, nrm, face, bary = texel_geometry(fid, uvs, nf, nv, normals, with_bary=True)
        deps = None if deps is None else deps.result()
    extra, known = {}, {}
    if carry is not None:
        source = carry.source()
        at = carried_uvs(source, pts, nrm, carry.reach)
        col, found = carried(source.texture, *at, len(pts))
        unseen = fallback = ~found
        extra["carried"] = float(found.mean()) if len(found) else 1.0
        if source.normals is not None:  # the normal map's texels are these texels
            known["known_normals"] = carried(source.normals, *at, len(pts))
        if source.occlusion is not None:  # at these texels, for the occlusion map's coarser ones to look up
            values, got = carried(source.occlusion[..., None], *at, len(pts))
            known["known_occlusion"] = np.full((side, side), np.nan, np.float32)
            known["known_occlusion"][r[got], c[got]] = values[got, 0]
    else:
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
             "faces": int(len(nf)), "faces_with_texels": int(len(covered_faces)), "filled": filled, "normals": normals,
             **extra}
    if occupancy is not None and (cfg.normal_map or cfg.occlusion_reach > 0):
        stats["maps"] = bake_surface_maps(occupancy, nv, nf, uvs, normals, fid, cfg.normal_map, cfg.occlusion_reach,
                                          cfg.gutter, **known)
    return nv, nf, uvs, tex, stats


def upright(cams: Cameras, frame: str) -> tuple[np.ndarray, str]:
    """(T, source): T the 4×4 rigid transform from the mesh's ``frame`` ('sfm' or 'normalized') to glTF's display
    frame, ``source`` where its up came from ('support plane' or 'cameras'). +Y is up — the support plane's normal
    (a printed board's z) when it is a floor (within 45° of the capture's up line: the up's sign is unsure when
    portrait and landscape photos mix, their −y axes cancelling), else (floating, or hung on a wall) the capture's
    up (:func:`pipeline.scene.support.capture_up`); +Z points level at the first photo's camera (a
    viewer's default view then looks from there); the origin is the object's sphere centre, dropped onto the floor
    when there is one. SfM's frame has no up of its own (COLMAP's is its first camera's, y down), and viewers put
    glTF's +Y up, so without this the object opened upside down or tilted."""
    from pipeline.scene.support import capture_up

    normal = None if cams.ground is None else np.asarray(cams.ground[:3], float)
    if normal is not None and abs(normal @ capture_up(cams.R)) >= np.cos(np.pi / 4) * np.linalg.norm(normal):
        up, source = normal, "support plane"
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


def turned(directions: np.ndarray, similarity: np.ndarray) -> np.ndarray:
    """Unit ``directions`` (N, 3) turned by the rotation of the 4×4 ``similarity``."""
    d = np.asarray(directions, np.float64) @ np.asarray(similarity, np.float64)[:3, :3].T
    return d / np.linalg.norm(d, axis=1, keepdims=True).clip(1e-12)


def object_size(verts: np.ndarray, display: np.ndarray) -> dict:
    """The box of the mesh ``verts`` in the GLB's display frame (``display``: :func:`upright`; +Y up, +Z towards the
    first photo's camera), in the mesh's units: ``height`` (along Y), ``width`` (X), ``depth`` (Z)."""
    ext = np.ptp(transform_points(display, np.asarray(verts, np.float64)), axis=0)
    return {"height": float(ext[1]), "width": float(ext[0]), "depth": float(ext[2])}


def fine_mesh(path: Path, mesh_stamp: dict, cams: Cameras) -> tuple[np.ndarray, np.ndarray] | None:
    """The mesh stage's full-resolution mesh (``raw.ply``) in the normalized frame: its vertices and unit vertex
    normals (the normal map's where the field is unsure); None when it is missing or unreadable (the simplified
    mesh's normals stand in)."""
    try:
        raw = trimesh.load(path, file_type="ply", process=False)
    except Exception:  # noqa: BLE001 - a missing or damaged file: only the fallback of a few texels is lost
        return None
    if not isinstance(raw, trimesh.Trimesh) or len(raw.faces) == 0:
        return None
    verts = np.asarray(raw.vertices, np.float64)
    if mesh_stamp.get("frame", "sfm") == "sfm":
        verts = to_normalized(verts, cams.scale_mat)
    normals = trimesh.Trimesh(verts, np.asarray(raw.faces), process=False).vertex_normals
    return verts, np.asarray(normals, np.float64)


def read_clean_mesh(path: Path) -> trimesh.Trimesh:
    """The mesh stage's ``clean.ply`` (StageError naming it: unreadable, no triangles, empty)."""
    m = load_mesh_file(path, "ply", "mesh", "rerun the mesh stage (mesh --force)")
    if not isinstance(m, trimesh.Trimesh):
        raise StageError(f"{path}: holds no triangles ({type(m).__name__}); rerun the mesh stage (mesh --force)")
    if len(m.faces) == 0:
        raise StageError(f"{path}: empty mesh; retrain (train --force) or check the masks")
    return m


def bake_beside(default: Callable[[], dict], levels: dict[str, Callable[[], dict]]) -> tuple[dict, dict]:
    """``default()`` in this thread and the ``levels``' bakes (in their order) :data:`BAKES_AT_ONCE` at a time
    beside it: (its result, each level's). A failure of any of them (a full disk, Ctrl-C) stops the levels not
    started yet."""
    stop = threading.Event()

    def unless_stopped(bake: Callable[[], dict]) -> dict | None:
        if stop.is_set():
            return None
        try:
            return bake()
        except BaseException:
            stop.set()
            raise

    with ThreadPoolExecutor(BAKES_AT_ONCE) as pool:
        pending = {name: pool.submit(unless_stopped, bake) for name, bake in levels.items()}
        try:
            return default(), {name: future.result() for name, future in pending.items()}
        except BaseException:
            stop.set()
            raise


def run(job: Job) -> Done:
    """Stage ``texture`` (called by :func:`pipeline.stages.run_stage`): the clean mesh UV-unwrapped and baked from
    the photos (the texture field for texels no photo sees) → mesh/textured.obj/.mtl/.png, mesh/textured.glb and
    mesh/textured.usdz; likewise each detail level the mesh stage wrote (``mesh/levels/<level>/``)."""
    ws, cfg = job.ws, job.cfg
    final = ws.model / "final.pt"
    looks = ws.model / "appearance.json"  # per-view exposure and white balance fitted in training
    paths = list_images(ws.images)
    cams = load_cameras(ws.cameras, n_views=len(paths))
    mesh_stamp = ws.stamp("mesh") or {}
    images, field_gain, clipped = photos_for_bake(paths, looks, cfg)
    field, _, field_frame = read_model(final, resolve_device(cfg.device)) if final.exists() else (None, None, None)
    fine = fine_mesh(ws.mesh / "raw.ply", mesh_stamp, cams) if field is not None and cfg.normal_map else None
    occupancy = None if field is None else surface_field(field, field_frame, mesh_stamp.get("footprint", 0.0), fine)
    reach = occupancy.cell if occupancy is not None else CARRY_REACH  # how far two meshes of the field may part
    display, up_from = upright(cams, cfg.frame)
    metric = bool(mesh_units(ws.root, cfg.frame))  # a printed board put the SfM frame in metres

    baked: dict[str, BakedMesh] = {}
    asked = mesh_stamp.get("levels", {})
    carrying = bool(asked) and not cfg.levels_from_photos

    def clean_normalized(folder: Path) -> trimesh.Trimesh:
        m = read_clean_mesh(folder / "clean.ply")
        if mesh_stamp.get("frame", "sfm") == "sfm":
            m.vertices = to_normalized(np.asarray(m.vertices, np.float64), cams.scale_mat)
        return m

    def bake_to(folder: Path, carry: Carry | None = None) -> dict:
        """The clean mesh of ``folder`` textured into that folder (its colours carried from the default mesh's with
        ``carry``); its stats. The default mesh's texture is kept in ``baked``."""
        m = clean_normalized(folder)
        nv, nf, uvs, tex, stats = texture_mesh(np.asarray(m.vertices, np.float64), np.asarray(m.faces), images, cams,
                                               cfg, field, field_frame, field_gain, clipped, occupancy, carry)
        normals, maps = stats.pop("normals"), stats.pop("maps", None)
        if folder == ws.mesh and carrying:  # the normals grown around the charts, as the colours are
            image = None if maps is None else maps.object_normals()
            grown = None if image is None else dilate_gutter(image, (image[..., :3] != 0).any(-1), cfg.gutter)[0]
            baked["default"] = BakedMesh(nv, nf, uvs, tex, None if maps is None else maps.occlusion, grown)
        out_v = to_sfm(nv, cams.scale_mat) if cfg.frame == "sfm" else nv
        if cfg.frame == "sfm":  # directions turn with the frame (a similarity: scale, rotation, shift)
            normals = turned(normals, cams.scale_mat)
            if maps is not None:
                maps.tangents[:, :3] = turned(maps.tangents[:, :3], cams.scale_mat)
        export_textured(folder, out_v, nf, uvs, tex, display, normals, maps)
        export_usdz(folder / "textured.usdz", out_v, nf, uvs, folder / "textured.png", display, normals)
        stats.pop("filled")
        if maps is not None:
            stats["normal_map_sure"] = round(maps.sure, 4)
        stats["object_size"] = {**object_size(out_v, display), "units": "metres" if metric else "arbitrary"}
        stats["glb_bytes"] = (folder / "textured.glb").stat().st_size
        return stats

    def bake_level(level: str) -> dict:
        """The detail level's mesh textured into its folder; the stats the report shows, printed."""
        folder = level_folder(ws.mesh, level)
        carry = None if not carrying else Carry(
            lambda: default_done.wait() and baked["default"], density, reach)
        with heartbeat(f"texture: detail level {level}"):
            got = {k: v for k, v in bake_to(folder, carry).items() if k in ("faces", "size", "glb_bytes", "carried")}
        say_now(f"texture: detail level {level}: {got['faces']} faces, {got['size']}² atlas, "
                f"{got['glb_bytes'] / 1e6:.1f} MB → {folder / 'textured.glb'}")
        return got

    def bake_default() -> dict:
        """The default mesh textured (the levels waiting for its colours go on once it is done or has failed)."""
        try:
            with heartbeat("texture: baking the photos into the atlas"):
                stats = bake_to(ws.mesh)
        finally:
            default_done.set()
        stats["glb_up"] = {"from": up_from, "node_matrix": np.round(display, 9).tolist()}
        print(f"texture: {stats['size']}² atlas, {100 * (1 - stats['unseen_frac']):.1f} % of texels from photos → "
              f"{ws.mesh / 'textured.glb'}; {size_in_words(stats['object_size'], metric)}")
        return stats

    if carrying:  # the levels' atlases take the default mesh's density
        density = texels_per_unit(clean_normalized(ws.mesh), cams, [(im.shape[1], im.shape[0]) for im in images], cfg)
    default_done = threading.Event()
    heaviest = sorted(asked, key=lambda lv: -(asked[lv] if isinstance(asked[lv], int) else 0))
    stats, baked_levels = bake_beside(bake_default, {level: partial(bake_level, level) for level in heaviest})
    levels = {level: baked_levels[level] for level in asked}
    if levels:
        stats["levels"] = levels
    return Done(stats)
