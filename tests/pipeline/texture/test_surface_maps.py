"""The normal and occlusion maps baked from the occupancy field (pipeline/texture/surface_maps.py): tangents in glTF's
convention, the tangent-space round trip, a coarse sphere shading like the true sphere through its normal map, the
field's unsure places, and ambient occlusion in the open and in a pit."""

import numpy as np
import pytest
import torch
import trimesh

from pipeline.texture.atlas import make_atlas, rasterize_atlas, texel_geometry
from pipeline.texture.surface_maps import (
    SurfaceField,
    ambient_occlusion,
    bake_surface_maps,
    decode_normals,
    encode_normals,
    field_normals,
    hemisphere_directions,
    shading_normals,
    texel_frames,
    to_tangent_space,
    vertex_tangents,
)

RADIUS = 0.5
CELL = 2.0 / 96


def sphere_logit(p: torch.Tensor) -> torch.Tensor:
    """An occupancy logit whose level set is the sphere of radius 0.5 (> 0 inside)."""
    return 40.0 * (RADIUS - p.norm(dim=1))


def _angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos((a * b).sum(1).clip(-1, 1)))


def viewer_frames(faces, face, bary, normals, tangents):
    """The glTF Sample Viewer's tangent frame at a fragment, row by row: its vertex shader makes each corner's
    bitangent cross(N, T)·w, the rasteriser interpolates T, B and N, the fragment shader normalises each."""
    frames = []
    for f, w in zip(face, bary):
        corner_b = [np.cross(normals[v], tangents[v, :3]) * tangents[v, 3] for v in faces[f]]
        t = sum(wk * tangents[v, :3] for wk, v in zip(w, faces[f]))
        b = sum(wk * bk for wk, bk in zip(w, corner_b))
        n = sum(wk * normals[v] for wk, v in zip(w, faces[f]))
        frames.append([x / np.linalg.norm(x) for x in (t, b, n)])
    return np.array(frames)


def _flat_icosphere():
    """An 80-face icosphere of radius 0.5 with one vertex per face corner and the faces' normals (shaded flat, as a
    heavily simplified mesh is): UV-mapped by xatlas."""
    ico = trimesh.creation.icosphere(1, RADIUS)
    verts = ico.vertices[ico.faces].reshape(-1, 3)
    faces = np.arange(len(verts)).reshape(-1, 3)
    normals = np.repeat(ico.face_normals, 3, axis=0)
    vmap, nf, uvs, side = make_atlas(verts, faces, 300.0, 4, 512)
    return verts[vmap], nf, uvs, normals[vmap], side


def test_tangents_follow_u_and_their_sign_follows_v():
    """A square in z = 0 (normal +z) mapped u = x: tangent +x; v = y gives handedness +1 (cross(N, T) = +y is
    increasing v), v = −y gives −1."""
    verts = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    normals = np.tile([0.0, 0.0, 1.0], (4, 1))
    up = vertex_tangents(verts, faces, verts[:, :2], normals)
    np.testing.assert_allclose(up, np.tile([1.0, 0, 0, 1], (4, 1)), atol=1e-12)
    mirrored = vertex_tangents(verts, faces, verts[:, :2] * [1, -1], normals)
    np.testing.assert_allclose(mirrored, np.tile([1.0, 0, 0, -1], (4, 1)), atol=1e-12)


def test_tangents_are_unit_orthogonal_and_reject_bad_shapes():
    verts, faces, uvs, normals, _ = _flat_icosphere()
    tan = vertex_tangents(verts, faces, uvs, normals)
    assert tan.shape == (len(verts), 4) and np.isfinite(tan).all()
    np.testing.assert_allclose(np.linalg.norm(tan[:, :3], axis=1), 1.0, atol=1e-9)
    assert np.abs((tan[:, :3] * normals).sum(1)).max() < 1e-9 and set(np.unique(tan[:, 3])) <= {-1.0, 1.0}
    with pytest.raises(ValueError, match="expected verts"):
        vertex_tangents(verts, faces, uvs[:, :1], normals)


def test_a_vertex_without_a_u_direction_gets_a_tangent_all_the_same():
    """Degenerate UVs (every corner at one point): still unit tangents orthogonal to the normals, no NaN."""
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float)
    normals = np.tile([0.0, 0.0, 1.0], (3, 1))
    tan = vertex_tangents(verts, np.array([[0, 1, 2]]), np.zeros((3, 2)), normals)
    assert np.isfinite(tan).all() and np.allclose(np.linalg.norm(tan[:, :3], axis=1), 1.0)
    assert np.abs(tan[:, 2]).max() < 1e-12


def test_tangent_space_round_trip_in_skewed_frames():
    """For frames that are not orthogonal (interpolated T, B, N each normalised), the tangent-space vector gives back
    the normal it was made from, through the 8-bit colours to within half a degree."""
    rng = np.random.default_rng(0)
    frames = np.eye(3)[None] + 0.1 * rng.normal(size=(500, 3, 3))
    frames /= np.linalg.norm(frames, axis=2, keepdims=True)
    target = frames[:, 2] + 0.5 * rng.normal(size=(500, 3))
    target /= np.linalg.norm(target, axis=1, keepdims=True)
    ts = to_tangent_space(frames, target)
    np.testing.assert_allclose(np.linalg.norm(ts, axis=1), 1.0, atol=1e-12)
    assert _angles(shading_normals(frames, ts), target).max() < 1e-4
    colours = np.round(encode_normals(ts) * 255) / 255
    assert _angles(shading_normals(frames, decode_normals(colours)), target).max() < 1.5
    assert np.isfinite(to_tangent_space(np.zeros((2, 3, 3)), target[:2])).all()


def test_a_flat_shaded_sphere_shades_like_the_sphere_through_its_normal_map():
    """80 flat faces: the faces' normals are up to 20° off the sphere's; with the baked map, the shading normal
    at every texel (frames interpolated as a glTF viewer does, the map's 8-bit colours) is within 1° of it."""
    verts, faces, uvs, normals, side = _flat_icosphere()
    fid = rasterize_atlas(uvs, faces, side)
    maps = bake_surface_maps(SurfaceField(sphere_logit, CELL), verts, faces, uvs, normals, fid, True, 0.0, 4)
    assert maps.occlusion is None and maps.sure == 1.0 and maps.normal.shape == (side, side, 3)
    r, c, pts, nrm, face, bary = texel_geometry(fid, uvs, faces, verts, normals, with_bary=True)
    frames = texel_frames(faces, face, bary, normals, maps.tangents)
    some = np.arange(0, len(face), 97)
    np.testing.assert_allclose(frames[some], viewer_frames(faces, face[some], bary[some], normals, maps.tangents),
                               atol=1e-9)
    colours = np.round(maps.normal[r, c] * 255) / 255
    truth = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    shaded = np.einsum("mij,mi->mj", viewer_frames(faces, face[some], bary[some], normals, maps.tangents),
                       decode_normals(colours[some]))  # the viewer's normalize(T·x + B·y + N·z)
    mapped = _angles(shaded / np.linalg.norm(shaded, axis=1, keepdims=True), truth[some])
    assert mapped.mean() < 0.5 and np.percentile(mapped, 99) < 1.0, (mapped.mean(), mapped.max())
    assert _angles(nrm, truth).mean() > 5.0


def test_field_normals_fall_back_to_the_mesh_where_the_field_is_flat():
    """A field with no gradient (a constant) or far from the points: the mesh's normals, marked unsure, no NaN."""
    pts = np.array([[0.0, 0.0, 0.5], [0.0, 0.0, 0.9]])
    mesh_n = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
    n, sure = field_normals(lambda p: 0.0 * p.sum(1), pts, mesh_n, CELL)
    assert not sure.any() and np.array_equal(n, mesh_n)
    n, sure = field_normals(sphere_logit, pts, mesh_n, CELL)
    assert sure.tolist() == [True, False] and np.isfinite(n).all()
    np.testing.assert_allclose(n[0], [0, 0, 1], atol=1e-6)
    with pytest.raises(ValueError, match="expected points"):
        field_normals(sphere_logit, pts, mesh_n[:1], CELL)


def test_hemisphere_directions_are_cosine_distributed():
    d = hemisphere_directions(4096)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    assert (d[:, 2] > 0).all() and abs(d[:, 2].mean() - 2 / 3) < 0.01  # E[cos θ] under a cosine density


def test_ambient_occlusion_open_on_a_floor_and_dark_in_a_pit():
    """On top of a slab (everything below z = 0 occupied) the hemisphere is open; at the bottom of a narrow pit
    (a 0.04-wide shaft 0.5 deep in the slab) almost closed; half-way up a wall beside a tall block, about half."""
    def slab(p):
        return 60.0 * -p[:, 2]

    def pit(p):
        outside_shaft = torch.maximum(p[:, 0].abs(), p[:, 1].abs()) - 0.02
        return 60.0 * torch.minimum(-p[:, 2], torch.maximum(outside_shaft, -(p[:, 2] + 0.5)))

    def wall(p):
        return 60.0 * -p[:, 0]  # occupied where x < 0: a vertical wall; the point looks along +x

    up = np.array([[0.0, 0.0, 1.0]])
    assert ambient_occlusion(slab, np.zeros((1, 3)), up, 0.2, 2 * CELL)[0] > 0.97
    assert ambient_occlusion(pit, np.array([[0.0, 0.0, -0.5]]), up, 0.2, 2 * CELL)[0] < 0.1
    floor_by_wall = ambient_occlusion(lambda p: torch.maximum(slab(p), wall(p)), np.array([[0.01, 0.0, 0.0]]),
                                      up, 0.2, 2 * CELL, directions=64)[0]
    assert 0.35 < floor_by_wall < 0.75
    with pytest.raises(ValueError, match="expected points"):
        ambient_occlusion(slab, np.zeros((2, 3)), up, 0.2, 2 * CELL)


def test_surface_field_reads_the_field_in_the_meshs_frame():
    """A trained-field stand-in (a grid field set to a sphere's logits) seen through a similarity of scale 2 and a
    shift: the logit at a mesh-frame point is the field's at the point mapped back, and the cell is the grid's
    spacing scaled by 2; the footprint band is the mesh stage's (none without a support plane)."""
    from dvr.config import FieldConfig
    from dvr.fields import make_field
    from pipeline.texture.surface_maps import surface_field

    field = make_field(FieldConfig(base_res=32))
    axis = torch.linspace(-1, 1, 33)
    grid = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1)
    field.init_occupancy(sphere_logit(grid.reshape(-1, 3)).reshape(33, 33, 33))
    frame = np.diag([2.0, 2.0, 2.0, 1.0])
    frame[:3, 3] = [1.0, -2.0, 0.5]
    surface = surface_field(field, frame, footprint=0.03)
    assert surface.cell == pytest.approx(2.0 / 32 * 2.0)
    pts = torch.tensor([[0.3, 0.1, -0.2], [0.0, 0.9, 0.1]])
    mesh_pts = pts * 2.0 + torch.tensor([1.0, -2.0, 0.5])
    with torch.no_grad():
        np.testing.assert_allclose(surface.logit(mesh_pts).numpy(), field.occupancy(pts).numpy(), atol=1e-5)


def test_where_the_field_is_unsure_the_full_resolution_mesh_gives_the_normal():
    """A field with no gradient anywhere: every texel unsure. With the full-resolution mesh (a fine icosphere) its
    nearest vertex's normal is baked (the coarse sphere then shades within 1.5° of the true one); without it, the
    coarse faces' own normals (several degrees off)."""
    verts, faces, uvs, normals, side = _flat_icosphere()
    fid = rasterize_atlas(uvs, faces, side)
    fine = trimesh.creation.icosphere(5, RADIUS)
    flat = lambda p: 0.0 * p.sum(1)  # noqa: E731
    r, c, pts, _, face, bary = texel_geometry(fid, uvs, faces, verts, normals, with_bary=True)
    truth = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    errors = []
    for surface in (SurfaceField(flat, CELL, (fine.vertices, fine.vertex_normals)), SurfaceField(flat, CELL)):
        maps = bake_surface_maps(surface, verts, faces, uvs, normals, fid, True, 0.0, 4)
        assert maps.sure == 0.0
        frames = texel_frames(faces, face, bary, normals, maps.tangents)
        errors.append(_angles(shading_normals(frames, decode_normals(maps.normal[r, c])), truth).mean())
    assert errors[0] < 1.5 < 5.0 < errors[1], errors


def test_the_full_resolution_mesh_is_read_in_the_normalized_frame_or_not_at_all(tmp_path):
    from dvr.cameras import Cameras
    from pipeline.texture.stage import fine_mesh

    scale = np.diag([2.0, 2.0, 2.0, 1.0])
    scale[:3, 3] = [1.0, 0.0, 0.0]
    cams = Cameras(K=np.eye(3)[None], R=np.eye(3)[None], t=np.zeros((1, 3)), scale_mat=scale)
    sphere = trimesh.creation.icosphere(2, RADIUS)
    sphere.apply_transform(scale)  # in the SfM frame
    sphere.export(tmp_path / "raw.ply")
    verts, normals = fine_mesh(tmp_path / "raw.ply", {"frame": "sfm"}, cams)
    np.testing.assert_allclose(np.linalg.norm(verts, axis=1), RADIUS, atol=1e-6)
    np.testing.assert_allclose((verts / RADIUS * normals).sum(1), 1.0, atol=0.02)
    assert fine_mesh(tmp_path / "missing.ply", {}, cams) is None
    (tmp_path / "bad.ply").write_bytes(b"ply\ngarbage")
    assert fine_mesh(tmp_path / "bad.ply", {}, cams) is None


def test_known_normals_and_occlusion_are_taken_where_found_and_the_field_asked_elsewhere():
    """Normals and occlusion known elsewhere (another mesh's maps carried over) stand where they were found; the
    field gives the rest, as it would alone; known normals of another number of points are a ValueError."""
    from pipeline.texture.surface_maps import bake_occlusion_map, object_normals

    rng = np.random.default_rng(0)
    directions = rng.normal(size=(50, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    points, mesh_normals = RADIUS * directions, directions
    surface = SurfaceField(sphere_logit, CELL)
    alone, alone_sure = object_normals(surface, points, mesh_normals)
    found = np.arange(50) % 3 == 0
    known = np.zeros((50, 4))
    known[:, 2], known[:, 3] = 2.0, 1.0  # +z, 2 long (made unit), sure
    normals, sure = object_normals(surface, points, mesh_normals, (known, found))
    assert np.allclose(normals[found], [0, 0, 1]) and sure[found].all()
    assert np.allclose(normals[~found], alone[~found]) and (sure[~found] == alone_sure[~found]).all()
    with pytest.raises(ValueError, match="known normals of 49 points for 50 points"):
        object_normals(surface, points, mesh_normals, (known[:49], found[:49]))

    rows, cols = np.arange(50) // 10, np.arange(50) % 10  # texels of a 10² map; occlusion known on a 21² one
    field_only = bake_occlusion_map(sphere_logit, 10, rows, cols, points, mesh_normals, 0.2, 2 * CELL)
    fine = np.full((21, 21), np.nan, np.float32)
    fine[(rows[found] * 2.1 + 1.05).astype(int), (cols[found] * 2.1 + 1.05).astype(int)] = 0.25  # under the centres
    known_ao = bake_occlusion_map(sphere_logit, 10, rows, cols, points, mesh_normals, 0.2, 2 * CELL, fine)
    assert np.allclose(known_ao[rows[found], cols[found]], 0.25)
    assert np.allclose(known_ao[rows[~found], cols[~found]], field_only[rows[~found], cols[~found]])
