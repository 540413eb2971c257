"""Maps baked from the trained occupancy field into the atlas: a tangent-space normal map and an ambient-occlusion map.

The normal map carries the field's own surface normal −∇f/|∇f| (at the level set nearest each texel's point on the
possibly simplified mesh) in the mesh's tangent frame, so a light mesh shades like the full-resolution surface. The
tangent frame is glTF's: per-vertex tangents (xyz, handedness w) written into the GLB, bitangent = cross(N, T)·w,
and a viewer's normal = normalize(T·x + B·y + N·z) with the normal, tangent and bitangent interpolated over the face
from its corners. The occlusion map holds, per texel, the share of its hemisphere the field leaves open within a
reach (1: open, 0: closed in).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from dvr.extract import footprint_occupancy, refine_vertices
from dvr.fields import Field, central_difference_gradient, evaluate_in_chunks
from pipeline.texture.atlas import dilate_gutter, rasterize_atlas, texel_geometry

LogitFn = Callable[[torch.Tensor], torch.Tensor]

FLAT_NORMAL = np.array([0.5, 0.5, 1.0], np.float32)
"""A normal map's colour for "the mesh's own normal": tangent-space (0, 0, 1)."""


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True).clip(1e-12)


def vertex_tangents(verts: np.ndarray, faces: np.ndarray, uvs: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(V, 4) glTF tangents of a UV-mapped mesh: xyz the unit direction of increasing u, orthogonal to the vertex's
    normal (``normals`` (V, 3) unit), w = ±1 the handedness (+1 when cross(N, T) points along increasing v). Each
    face's UV-gradient directions are summed over a vertex's faces weighted by the face's area; a vertex whose faces
    give no u direction takes any direction orthogonal to its normal."""
    verts, uvs, normals = (np.asarray(a, np.float64) for a in (verts, uvs, normals))
    faces = np.asarray(faces, np.int64)
    if verts.ndim != 2 or verts.shape[1] != 3 or normals.shape != verts.shape or uvs.shape != (len(verts), 2):
        raise ValueError(f"expected verts (V, 3), uvs (V, 2), normals (V, 3); got {verts.shape}, {uvs.shape}, "
                         f"{normals.shape}")
    p, t = verts[faces], uvs[faces]
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    d1, d2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    area = 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1)
    sign = np.sign(det)[:, None]
    tan_f = _unit((e1 * d2[:, 1:] - e2 * d1[:, 1:]) * sign) * area[:, None]  # ∂p/∂u's direction
    bit_f = _unit((e2 * d1[:, :1] - e1 * d2[:, :1]) * sign) * area[:, None]  # ∂p/∂v's direction
    corners = faces.reshape(-1)
    tan, bit = (np.stack([np.bincount(corners, np.repeat(v[:, j], 3), len(verts)) for j in range(3)], 1)
                for v in (tan_f, bit_f))
    tan -= normals * (tan * normals).sum(1, keepdims=True)
    weak = np.linalg.norm(tan, axis=1) < 1e-12
    if weak.any():  # any direction orthogonal to the normal
        axis = np.eye(3)[np.argmin(np.abs(normals[weak]), axis=1)]
        tan[weak] = np.cross(normals[weak], axis)
    tan = _unit(tan)
    w = np.where((np.cross(normals, tan) * bit).sum(1) < 0, -1.0, 1.0)
    return np.concatenate([tan, w[:, None]], axis=1)


def texel_frames(faces: np.ndarray, face: np.ndarray, bary: np.ndarray, normals: np.ndarray,
                 tangents: np.ndarray) -> np.ndarray:
    """(M, 3, 3) tangent frames [T, B, N] (rows) at texels of faces ``face`` (M,) with barycentrics ``bary`` (M, 3), as
    a glTF viewer shades them: the corners' normals, tangents and bitangents cross(N, T)·w interpolated and each
    normalised (not re-orthogonalised). Interpolated coordinate by coordinate (1-D gathers are several × faster
    than gathers of rows)."""
    corner = [np.ascontiguousarray(faces[:, k]).take(face) for k in range(3)]
    weight = np.ascontiguousarray(np.asarray(bary, np.float64).T)
    bitangents = np.cross(normals, tangents[:, :3]) * tangents[:, 3:]
    out = np.empty((3, 3, len(face)))
    for row, vectors in enumerate((tangents[:, :3], bitangents, normals)):
        for j in range(3):
            x = np.ascontiguousarray(vectors[:, j])
            out[row, j] = x.take(corner[0]) * weight[0] + x.take(corner[1]) * weight[1] + x.take(corner[2]) * weight[2]
        out[row] /= np.sqrt((out[row] ** 2).sum(0)).clip(1e-12)
    return np.ascontiguousarray(out.transpose(2, 0, 1))


def to_tangent_space(frames: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Unit tangent-space vectors (M, 3) whose shading normal normalize(T·x + B·y + N·z) is ``normals`` (M, 3):
    x = [T B N]⁻¹ n by Cramer's rule, normalised (the frames need not be orthogonal; a degenerate one gives
    (0, 0, 1))."""
    t, b, n = frames[:, 0], frames[:, 1], frames[:, 2]
    bn, nt, tb = np.cross(b, n), np.cross(n, t), np.cross(t, b)
    det = (t * bn).sum(1)
    x = np.stack([(bn * normals).sum(1), (nt * normals).sum(1), (tb * normals).sum(1)], 1)
    ok = np.abs(det) > 1e-9
    x = np.where(ok[:, None], x / np.where(ok, det, 1.0)[:, None], [0.0, 0.0, 1.0])
    return _unit(x)


def shading_normals(frames: np.ndarray, tangent_normals: np.ndarray) -> np.ndarray:
    """The viewer's shading normals (M, 3) of tangent-space normals (M, 3) in ``frames`` (M, 3, 3)."""
    return _unit(np.einsum("mij,mi->mj", frames, tangent_normals))


def encode_normals(tangent_normals: np.ndarray) -> np.ndarray:
    """Tangent-space unit normals → normal-map colours in [0, 1] (x, y, z → R, G, B as 0.5 + 0.5·value)."""
    return (0.5 + 0.5 * np.asarray(tangent_normals, np.float32)).clip(0.0, 1.0)


def decode_normals(colours: np.ndarray) -> np.ndarray:
    """Normal-map colours in [0, 1] → unit tangent-space normals."""
    return _unit(2.0 * np.asarray(colours, np.float64) - 1.0)


def field_normals(logit_fn: LogitFn, points: np.ndarray, mesh_normals: np.ndarray, cell: float,
                  steps: int = 3, chunk: int = 1 << 17) -> tuple[np.ndarray, np.ndarray]:
    """The occupancy field's outward unit normals at the level set nearest ``points`` (M, 3) (a simplified mesh's
    surface points; ``mesh_normals`` its unit normals there), and where they can be trusted (M,) bool.

    Each point takes ``steps`` Newton steps onto f = 0 (each at most one ``cell``, the field's grid spacing), then
    −∇f/|∇f| by central differences a cell either side (the trilinear grid's gradient jumps at every cell face;
    differences across two cells average the jumps out). Trusted where the point landed within two cells of where
    it started, on the level set (|f| below a tenth of the logit change across a cell) with a gradient, and facing
    within 75° of the mesh's normal; elsewhere the field is unsure (a thin part, a hole the mesh closed) and
    ``mesh_normals`` stand (:func:`bake_normal_map` puts the full-resolution mesh's there)."""
    if points.shape != mesh_normals.shape or points.ndim != 2 or points.shape[1:] != (3,):
        raise ValueError(f"expected points and mesh_normals (M, 3); got {points.shape}, {mesh_normals.shape}")
    p = torch.from_numpy(np.ascontiguousarray(points, np.float32))
    moved = refine_vertices(logit_fn, p, steps, cell)
    with torch.no_grad():
        g = evaluate_in_chunks(lambda q: central_difference_gradient(logit_fn, q, cell), moved, chunk, (3,))
        f = evaluate_in_chunks(logit_fn, moved, chunk)
    g, f = g.double().numpy(), f.double().numpy()
    slope = np.linalg.norm(g, axis=1)
    n = -g / slope.clip(1e-12)[:, None]
    dist = np.linalg.norm(moved.double().numpy() - points, axis=1)
    sure = (np.isfinite(n).all(1) & (dist <= 2 * cell) & (slope > 1e-6) & (np.abs(f) <= 0.1 * slope * cell)
            & ((n * mesh_normals).sum(1) >= np.cos(np.radians(75))))
    return np.where(sure[:, None], n, mesh_normals), sure


def hemisphere_directions(n: int) -> np.ndarray:
    """``n`` unit directions (n, 3) over the +z hemisphere, cosine-distributed (a Fibonacci spiral on the disc
    lifted to the hemisphere): their plain mean estimates a cosine-weighted integral."""
    k = np.arange(n) + 0.5
    r = np.sqrt(k / n)
    phi = k * np.pi * (3.0 - np.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(1.0 - r * r)], axis=1)


def ambient_occlusion(logit_fn: LogitFn, points: np.ndarray, normals: np.ndarray, reach: float, lift: float,
                      directions: int = 12, samples: int = 4, chunk: int = 1 << 15) -> np.ndarray:
    """Ambient occlusion (M,) in [0, 1] at surface ``points`` with outward unit ``normals`` (M, 3): the
    cosine-weighted share of the hemisphere where the field stays empty up to ``reach`` (1: fully open). Each
    direction is occluded by the largest occupancy probability sigmoid(f) among ``samples`` points spaced evenly
    over (reach / samples, reach], from the point lifted by ``lift`` along its normal (two grid cells: the grazing
    rays of a flat surface would otherwise run through the soft edge of its own level set); the direction set is
    turned about the normal by a per-texel angle so its pattern does not print into the map."""
    if points.shape != normals.shape or points.ndim != 2 or points.shape[1:] != (3,):
        raise ValueError(f"expected points and normals (M, 3); got {points.shape}, {normals.shape}")
    dirs = torch.from_numpy(hemisphere_directions(directions)).float()
    steps = torch.arange(1, samples + 1, dtype=torch.float32) * (reach / samples)
    pts = torch.from_numpy(np.ascontiguousarray(points, np.float32))
    nrm = torch.from_numpy(np.ascontiguousarray(normals, np.float32))
    spin = torch.from_numpy((np.arange(len(points)) * 0.6180339887 % 1.0 * 2 * np.pi).astype(np.float32))

    def occlusion(rows: torch.Tensor) -> torch.Tensor:
        p, n, a = rows[:, :3], rows[:, 3:6], rows[:, 6]
        axis = torch.where(n[:, :1].abs() < 0.9, torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.0, 1.0, 0.0]))
        t = torch.nn.functional.normalize(torch.cross(n, axis, dim=1), dim=1)
        b = torch.cross(n, t, dim=1)
        c, s = torch.cos(a)[:, None], torch.sin(a)[:, None]
        t, b = c * t + s * b, c * b - s * t
        d = dirs[None, :, :1] * t[:, None] + dirs[None, :, 1:2] * b[:, None] + dirs[None, :, 2:] * n[:, None]
        start = p + lift * n
        q = start[:, None, None] + d[:, :, None] * steps[None, None, :, None]  # (m, directions, samples, 3)
        prob = torch.sigmoid(logit_fn(q.reshape(-1, 3))).view(len(p), directions, samples)
        return 1.0 - prob.amax(dim=2).mean(dim=1)

    with torch.no_grad():
        ao = evaluate_in_chunks(occlusion, torch.cat([pts, nrm, spin[:, None]], 1), chunk)
    return ao.double().numpy().clip(0.0, 1.0)


KnownNormals = tuple[np.ndarray, np.ndarray]
"""Normals known elsewhere at M texel points: (x, y, z, sure) (M, 4) and where they were found (M,) bool."""


def object_normals(surface: SurfaceField, points: np.ndarray, mesh_normals: np.ndarray,
                   known: KnownNormals | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (M, 3) of the field at surface ``points`` (M, 3) and whether the field was sure there (M,):
    :func:`field_normals`; where the field is unsure, the normal of the nearest vertex of the full-resolution mesh
    (``surface.fine``), else the mesh's own (``mesh_normals``). ``known``: those found there are taken, the field is
    asked for the rest."""
    normals, sure = np.array(mesh_normals, np.float64), np.zeros(len(points), bool)
    todo = np.ones(len(points), bool)
    if known is not None:
        values, found = known
        if len(found) != len(points):
            raise ValueError(f"known normals of {len(found)} points for {len(points)} points")
        normals[found], sure[found] = _unit(values[found, :3].astype(np.float64)), values[found, 3] > 0.5
        todo = ~found
    if todo.any():
        normals[todo], sure[todo] = field_normals(surface.logit, points[todo], mesh_normals[todo], surface.cell)
        unsure = np.flatnonzero(todo & ~sure)
        if surface.fine is not None and len(unsure):
            from scipy.spatial import cKDTree

            fine_points, fine_normals = surface.fine
            _, nearest = cKDTree(fine_points).query(points[unsure], k=1)
            normals[unsure] = fine_normals[nearest]
    return normals, sure


def bake_normal_map(surface: SurfaceField, side: int, rows: np.ndarray, cols: np.ndarray, points: np.ndarray,
                    frames: np.ndarray, known: KnownNormals | None = None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(side, side, 3) normal-map colours of the texels at (``rows``, ``cols``) with surface ``points`` (M, 3) and
    tangent ``frames`` (M, 3, 3) (:func:`texel_frames`): the field's normal (:func:`object_normals`, ``known``: see
    there) in tangent space; other texels flat. Also those normals (M, 3) and where the field was sure (M,)."""
    normals, sure = object_normals(surface, points, frames[:, 2], known)
    out = np.tile(FLAT_NORMAL, (side, side, 1))
    out[rows, cols] = encode_normals(to_tangent_space(frames, normals))
    return out, normals, sure


def bake_occlusion_map(logit_fn: LogitFn, side: int, rows: np.ndarray, cols: np.ndarray, points: np.ndarray,
                       normals: np.ndarray, reach: float, lift: float, known: np.ndarray | None = None
                       ) -> np.ndarray:
    """(side, side) occlusion of the texels at (``rows``, ``cols``) (:func:`ambient_occlusion`; where ``known``, the
    occlusion known elsewhere at an atlas of any side (NaN: not known), holds a value at the texel's centre, that
    value); others 1."""
    out = np.ones((side, side), np.float32)
    todo = np.ones(len(rows), bool)
    if known is not None:
        scale = known.shape[0] / side  # the known atlas's texel under each texel's centre
        at_r = np.minimum(((rows + 0.5) * scale).astype(np.intp), known.shape[0] - 1)
        at_c = np.minimum(((cols + 0.5) * scale).astype(np.intp), known.shape[1] - 1)
        values = known[at_r, at_c]
        todo = ~np.isfinite(values)
        out[rows[~todo], cols[~todo]] = values[~todo]
    if todo.any():
        out[rows[todo], cols[todo]] = ambient_occlusion(logit_fn, points[todo], normals[todo], reach, lift)
    return out


@dataclass
class SurfaceField:
    """The trained occupancy as the texture stage sees it: ``logit`` at points of the mesh's frame (M, 3) → (M,),
    ``cell`` its grid spacing in that frame."""

    logit: LogitFn
    cell: float
    fine: tuple[np.ndarray, np.ndarray] | None = None
    """The full-resolution mesh's vertices (V, 3) and unit normals (V, 3) in the mesh's frame, whose normals stand
    where the field is unsure; None: the simplified mesh's own normals stand there."""


def surface_field(field: Field, field_frame: np.ndarray | None, footprint: float = 0.0,
                  fine: tuple[np.ndarray, np.ndarray] | None = None) -> SurfaceField:
    """The occupancy the mesh stage extracted (``footprint``: its band above the support plane extruded,
    :func:`dvr.extract.footprint_occupancy`) read at points of the mesh's frame (``field_frame``: 4×4 map of the
    field's frame to that one, a similarity; None: the same frame). The points may be on any device: the field
    reads them on its own. ``fine``: see :class:`SurfaceField`."""
    occupancy = footprint_occupancy(field, footprint)
    frame = np.eye(4) if field_frame is None else np.asarray(field_frame, np.float64)
    inv = torch.from_numpy(np.linalg.inv(frame)).float()
    scale = abs(float(np.linalg.det(frame[:3, :3]))) ** (1.0 / 3.0)
    res = getattr(field, "grid_resolution", None) or 256
    device = next(field.parameters()).device
    m = inv.to(device)

    def logit(p: torch.Tensor) -> torch.Tensor:
        """The logits at points ``p`` of the mesh's frame, computed on the field's device, returned on ``p``'s."""
        q = p.to(device=device, dtype=torch.float32)
        return occupancy(q @ m[:3, :3].T + m[:3, 3]).to(p.device)

    return SurfaceField(logit, 2.0 / res * scale, fine)


@dataclass
class SurfaceMaps:
    """What :func:`bake_surface_maps` gives: the normal map's colours (side, side, 3) and the occlusion map
    (side/2, side/2) (either None when not asked for), the glTF vertex tangents (V, 4) and the share of the normal
    map's texels where the field was sure."""

    normal: np.ndarray | None
    occlusion: np.ndarray | None
    tangents: np.ndarray
    sure: float
    texel_normals: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
    """The normal map's texels (rows (M,), cols (M,)), their normals in the mesh's frame (M, 3) and where the field
    was sure (M,) (:func:`bake_normal_map`); None without a normal map."""

    def object_normals(self) -> np.ndarray | None:
        """:attr:`texel_normals` as a (side, side, 4) image (x, y, z, sure; 0 off the texels); None without them."""
        if self.texel_normals is None:
            return None
        rows, cols, normals, sure = self.texel_normals
        image = np.zeros((*self.normal.shape[:2], 4), np.float32)
        image[rows, cols] = np.concatenate([normals, sure[:, None]], 1)
        return image


def bake_surface_maps(surface: SurfaceField, verts: np.ndarray, faces: np.ndarray, uvs: np.ndarray,
                      normals: np.ndarray, fid: np.ndarray, normal_map: bool, occlusion_reach: float,
                      gutter: int, known_normals: KnownNormals | None = None,
                      known_occlusion: np.ndarray | None = None) -> SurfaceMaps:
    """The normal map at the atlas's resolution (``fid``: :func:`rasterize_atlas`'s face per texel) and the occlusion
    map at half of it (``occlusion_reach`` > 0; it varies slowly), each grown ``gutter`` texels around the charts,
    for the UV-mapped mesh ``verts``, ``faces``, ``uvs`` with unit vertex ``normals``. ``known_normals``: at the
    atlas's texels in ``np.nonzero(fid >= 0)``'s order (:func:`object_normals`); ``known_occlusion``: see
    :func:`bake_occlusion_map`."""
    tangents = vertex_tangents(verts, faces, uvs, normals)
    normal, sure, occlusion, texel_normals = None, 1.0, None, None
    if normal_map:
        r, c, pts, _, face, bary = texel_geometry(fid, uvs, faces, verts, normals, with_bary=True)
        frames = texel_frames(faces, face, bary, normals, tangents)
        normal, field_normal, field_sure = bake_normal_map(surface, fid.shape[0], r, c, pts, frames, known_normals)
        normal = dilate_gutter(normal, fid >= 0, gutter)[0]
        sure = float(field_sure.mean()) if len(field_sure) else 1.0
        texel_normals = (r, c, field_normal, field_sure)
    if occlusion_reach > 0:
        half = max(fid.shape[0] // 2, 1)
        coarse = rasterize_atlas(uvs, faces, half)
        r, c, pts, nrm = texel_geometry(coarse, uvs, faces, verts, normals)
        occlusion = bake_occlusion_map(surface.logit, half, r, c, pts, nrm, occlusion_reach, 2 * surface.cell,
                                       known_occlusion)
        occlusion = dilate_gutter(occlusion[..., None], coarse >= 0, max(gutter // 2, 1))[0][..., 0]
    return SurfaceMaps(normal, occlusion, tangents, sure, texel_normals)
