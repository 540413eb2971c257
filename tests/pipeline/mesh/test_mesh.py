"""Stage mesh: cleaning (small components, holes, decimation to the face budget)."""

import numpy as np
import pytest
import trimesh

from pipeline.mesh.config import MeshConfig
from pipeline.mesh.stage import clean_mesh, floaters, keep_large_components


def _holed_sphere_and_speck():
    big = trimesh.creation.icosphere(subdivisions=5, radius=0.5)  # 20480 faces
    big.update_faces(np.arange(len(big.faces)) > 3)  # a small hole: close_holes has work to do
    big.remove_unreferenced_vertices()
    speck = trimesh.creation.icosphere(subdivisions=1, radius=0.02)
    speck.apply_translation([0.8, 0, 0])
    m = trimesh.util.concatenate([big, speck])
    return np.asarray(m.vertices), np.asarray(m.faces), len(big.faces)


def test_small_components_dropped():
    v, f, n_big = _holed_sphere_and_speck()
    kept = keep_large_components(v, f, 0.02)
    assert len(kept) == n_big
    assert len(keep_large_components(v, f, 0.0)) == len(f)
    assert len(keep_large_components(v, f[:0], 0.5)) == 0


def test_decimation_reaches_the_budget_after_hole_filling():
    """close_holes selects the faces it adds; without clearing that selection the decimation acts on those
    few faces only and the budget is silently missed (seen on DTU: 682 k faces for a 40 k budget)."""
    v, f, _ = _holed_sphere_and_speck()
    cv, cf, _ = clean_mesh(v, f, MeshConfig(max_faces=5000))
    assert 4000 <= len(cf) <= 5000
    m = trimesh.Trimesh(cv, cf)
    assert len(m.split(only_watertight=False)) == 1  # the speck is gone
    assert np.allclose(np.linalg.norm(cv, axis=1), 0.5, atol=0.02)


def test_make_closed_splits_an_edge_shared_by_four_faces():
    """Two boxes meeting along one edge (what a decimation's edge collapse can make, as on the e2e phone scene: 1 edge
    of 40 k faces shared by 4 faces, and the mesh is not watertight): after _make_closed every edge has 2 faces."""
    import pymeshlab

    from pipeline.mesh.stage import _make_closed

    a = trimesh.creation.box(bounds=[[0, 0, 0], [1, 1, 1]])
    b = trimesh.creation.box(bounds=[[1, 1, 0], [2, 2, 1]])
    m = trimesh.util.concatenate([a, b])
    m.merge_vertices()
    assert not m.is_watertight  # the shared edge has four faces
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.asarray(m.vertices, float), face_matrix=np.asarray(m.faces, np.int32)))
    _make_closed(ms)
    c = ms.current_mesh()
    out = trimesh.Trimesh(c.vertex_matrix(), c.face_matrix(), process=False)
    assert out.is_watertight and len(out.faces) >= 24


def test_split_vertices_move_apart_so_a_merging_loader_sees_a_closed_mesh():
    """The two boxes split apart along their shared edge keep two copies of its vertices at one place: a loader that
    merges vertices by position (trimesh's default, as a slicer's) joins them into an edge of four faces again.
    pinches_apart moves only those copies, a thousandth of an edge into their own box; a mesh without them comes
    back as it was."""
    from pipeline.mesh.stage import PINCH_APART, pinches_apart

    a = trimesh.creation.box(bounds=[[0, 0, 0], [1, 1, 1]])
    b = trimesh.creation.box(bounds=[[1, 1, 0], [2, 2, 1]])
    split = trimesh.util.concatenate([a, b])  # closed as stored, four vertices at the two ends of the shared edge
    assert split.is_watertight and not trimesh.Trimesh(split.vertices, split.faces).is_watertight
    v = pinches_apart(np.asarray(split.vertices), np.asarray(split.faces))
    assert trimesh.Trimesh(v, split.faces).is_watertight  # merged on loading: still closed
    moved = np.linalg.norm(v - split.vertices, axis=1)
    assert (moved > 0).sum() == 4 and moved.max() <= 2 * PINCH_APART  # the copies, and no more than a hair
    assert trimesh.Trimesh(v[:8], split.faces[:12]).contains([[0.5, 0.5, 0.5]])[0]  # still a box round its centre
    assert a.contains(v[:8][moved[:8] > 0]).all()  # moved into their own box
    assert np.array_equal(pinches_apart(np.asarray(a.vertices), np.asarray(a.faces)), a.vertices)


def _house_and_slab(n_points=2000, slab_density=0.0, seed=0):
    """A sphere of radius 0.5 (the object) with ``n_points`` points on its surface, and a disc-like slab of radius
    0.2 floating above it carrying ``slab_density`` × the sphere's density of points."""
    rng = np.random.default_rng(seed)
    body = trimesh.creation.icosphere(subdivisions=4, radius=0.5)
    slab = trimesh.creation.cylinder(radius=0.2, height=0.04, sections=32)
    slab.apply_translation([0, 0, 0.8])
    pts = [trimesh.sample.sample_surface(body, n_points, seed=1)[0]]
    n_slab = int(round(slab_density * n_points * slab.area / body.area))
    if n_slab:
        pts.append(trimesh.sample.sample_surface(slab, n_slab, seed=2)[0])
    pts = np.concatenate(pts) + rng.normal(0, 0.003, (sum(len(p) for p in pts), 3))  # SfM's noise
    m = trimesh.util.concatenate([body, slab])
    return np.asarray(m.vertices), np.asarray(m.faces), pts, len(body.faces)


def test_a_piece_no_point_lies_on_is_dropped():
    """The slab would carry ≈ 190 points at the object's density and carries none: a floater (DTU's roof slab)."""
    v, f, pts, n_body = _house_and_slab()
    keep, dropped = floaters(v, f, pts, 0.1, 0.02)
    assert keep.sum() == n_body and keep[:n_body].all()
    assert len(dropped) == 1 and dropped[0]["points"] == 0 and 170 < dropped[0]["expected"] < 215
    assert dropped[0]["faces"] == len(f) - n_body
    cv, cf, dropped = clean_mesh(v, f, MeshConfig(), pts)
    assert len(trimesh.Trimesh(cv, cf).split(only_watertight=False)) == 1 and len(dropped) == 1
    assert np.allclose(np.linalg.norm(cv, axis=1), 0.5, atol=0.02)  # what is left is the object
    assert floaters(v, f, pts, 0.0, 0.02)[0].all()  # 0: off


def test_a_piece_with_its_own_points_is_kept():
    """A second part seen and matched like the object (full density, or a third of it) stays; so does every piece
    when no points are known, and a piece too small to judge (fewer than 10 points expected)."""
    for density in (1.0, 0.3):
        v, f, pts, _ = _house_and_slab(slab_density=density)
        keep, dropped = floaters(v, f, pts, 0.1, 0.02)
        assert keep.all() and dropped == []
    v, f, pts, _ = _house_and_slab()
    assert floaters(v, f, pts[:0], 0.1, 0.02)[0].all()
    assert len(clean_mesh(v, f, MeshConfig(), None)[1]) == len(clean_mesh(v, f, MeshConfig(), pts)[1]) + 128
    v, f, pts, _ = _house_and_slab(n_points=80)  # 7.6 points expected on the slab (at 150: 14, dropped)
    assert floaters(v, f, pts, 0.1, 0.02)[0].all()


def test_the_mesh_stage_drops_a_floater_from_the_points_in_the_sfm_frame(small_ws, tmp_path, monkeypatch, capsys):
    """The stage reads points.ply in the SfM frame (cameras.npz's), maps it into the field's frame (the trained
    field's own sphere here, not cameras.npz's normalized frame), drops the piece no point lies on and records it in
    its stamp; without points.ply both pieces stay."""
    import json
    import shutil

    import torch

    from dvr.cameras import load_cameras, transform_points
    from dvr.checkpoint import load_model
    from pipeline.cameras.export import write_points
    from pipeline.config import Config
    from pipeline.mesh import stage as mesh_stage
    from pipeline.stages import run_stage
    from tests.conftest import tiny_training

    ws = tmp_path / "ws"
    shutil.copytree(small_ws, ws)
    cfg = tiny_training(Config(), iterations=5, batch_rays=128)
    cfg.train.carve_min_views = 1  # 8 views of 64 px: the two-view hull nearly fills the sphere (no frame of its own)
    run_stage("train", ws, cfg)
    v, f, pts, n_body = _house_and_slab()
    monkeypatch.setattr(mesh_stage, "extract_mesh", lambda *a, **k: (v, f, np.full((len(v), 3), 0.5)))
    scale_mat = load_model(ws / "model" / "final.pt", torch.device("cpu"))[1]  # the field's frame → SfM
    assert not np.allclose(scale_mat, load_cameras(ws / "cameras.npz").scale_mat)  # a frame of its own
    run_stage("mesh", ws, cfg)
    both = trimesh.load(ws / "mesh" / "clean.ply")
    assert len(both.split(only_watertight=False)) == 2  # no points.ply: nothing to judge by
    write_points(ws / "points.ply", transform_points(scale_mat, pts), np.zeros((len(pts), 3), np.uint8))
    capsys.readouterr()
    run_stage("mesh", ws, cfg, force=True)
    assert "dropped a floating piece of 128 faces: 0 SfM points lie on it" in capsys.readouterr().out
    one = trimesh.load(ws / "mesh" / "clean.ply")
    assert len(one.split(only_watertight=False)) == 1
    assert np.allclose(np.linalg.norm(transform_points(np.linalg.inv(scale_mat), one.vertices), axis=1), 0.5,
                       atol=0.02)
    stamp = json.loads((ws / ".stages" / "mesh.json").read_text())
    assert [p["faces"] for p in stamp["floaters"]] == [len(f) - n_body]


def test_a_speck_split_off_by_the_repairs_is_dropped():
    """A small piece that touches the object at one vertex is one component until the non-manifold repair splits
    that vertex; the small components go again after the repairs (DTU: an 18-face speck far from the house made a
    viewer frame the house off-centre)."""
    body = trimesh.creation.icosphere(subdivisions=4, radius=0.5)
    speck = trimesh.creation.icosphere(subdivisions=0, radius=0.03)
    tip = body.vertices[np.argmax(body.vertices[:, 0])]
    speck.apply_translation(tip - speck.vertices[np.argmin(speck.vertices[:, 0])])  # its leftmost corner on the tip
    m = trimesh.util.concatenate([body, speck])
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    merged = trimesh.Trimesh(v, f)  # the shared corner merged, as the cleaning's first step does
    assert len(keep_large_components(merged.vertices, merged.faces, 0.02)) == len(f)  # one piece before the repairs
    cv, cf, _ = clean_mesh(v, f, MeshConfig())
    assert len(trimesh.Trimesh(cv, cf).split(only_watertight=False)) == 1
    assert np.allclose(np.linalg.norm(cv, axis=1), 0.5, atol=0.02)


def test_unreadable_points_are_a_clear_error(tmp_path):
    """A damaged points.ply stops the mesh stage with one line naming it and the fix, not a parser's traceback."""
    import pytest

    from pipeline.errors import StageError
    from pipeline.mesh.stage import sfm_points

    bad = tmp_path / "points.ply"
    bad.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 5\nproperty float x\nend_header\n\x00")
    with pytest.raises(StageError, match="points.ply: unreadable SfM points .*rerun the cameras stage"):
        sfm_points(bad, np.eye(4))
    assert sfm_points(tmp_path / "none.ply", np.eye(4)) is None


def _camera_at(centre, target=(0.0, 0.0, 0.0), f=60.0, size=64):
    """K, world→camera R and the centre of a pinhole camera at ``centre`` looking at ``target`` (y down)."""
    c, t = np.asarray(centre, float), np.asarray(target, float)
    z = (t - c) / np.linalg.norm(t - c)
    x = np.cross(z, [0.0, 1.0, 0.0] if abs(z[1]) < 0.9 else [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    K = np.array([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1.0]])
    return K, R, c


def test_seen_faces_are_the_ones_facing_a_camera_and_never_the_far_side():
    from pipeline.mesh.visibility import seen_faces

    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    K, R, C = _camera_at([0.0, 0.0, 3.0])
    seen = seen_faces(ball.vertices, ball.faces, K[None], R[None], C[None], [(64, 64)])
    facing = ((C - ball.triangles_center) * ball.face_normals).sum(1) > 0
    assert seen.any() and not (seen & ~facing).any()  # nothing behind the ball's outline
    assert seen.sum() > 0.5 * facing.sum()  # most of the near half, at 64 px
    with pytest.raises(ValueError, match="differ"):
        seen_faces(ball.vertices, ball.faces, K[None], R[None], C[None], [(64, 64), (64, 64)])


def test_the_mesh_stage_drops_what_no_photo_sees_only_when_asked(small_ws, tmp_path, monkeypatch):
    """--mesh.drop-unseen: of a ball holding a second, smaller ball inside (a closed cavity, as an isosurface can
    have), the inner one goes, since no photo of the small scene sees it, and the outer one stays whole; by default
    both stay."""
    import json
    import shutil

    from pipeline.config import Config
    from pipeline.mesh import stage as mesh_stage
    from pipeline.stages import run_stage
    from tests.conftest import tiny_training

    ws = tmp_path / "ws"
    shutil.copytree(small_ws, ws)
    cfg = tiny_training(Config(), iterations=5, batch_rays=128)
    run_stage("train", ws, cfg)
    outer = trimesh.creation.icosphere(subdivisions=3, radius=0.4)
    inner = trimesh.creation.icosphere(subdivisions=3, radius=0.2)
    both = trimesh.util.concatenate([outer, inner])
    monkeypatch.setattr(mesh_stage, "extract_mesh",
                        lambda *a, **k: (both.vertices, both.faces, np.full((len(both.vertices), 3), 0.5)))
    run_stage("mesh", ws, cfg)
    assert len(trimesh.load(ws / "mesh" / "clean.ply").faces) == len(both.faces)
    cfg.mesh.drop_unseen = True
    run_stage("mesh", ws, cfg)
    kept = trimesh.load(ws / "mesh" / "clean.ply")
    stamp = json.loads((ws / ".stages" / "mesh.json").read_text())
    assert stamp["unseen_faces"] == len(inner.faces) and len(kept.faces) == len(outer.faces)
    assert kept.is_watertight and stamp["open_loops"] == 0 and stamp["open_length"] == 0


def _ball_and_cameras(n_cameras: int, size: int, subdivisions: int = 4):
    """A ball of radius 0.5 and ``n_cameras`` cameras at distance 3 on the +z side of it, spread 50° around z."""
    ball = trimesh.creation.icosphere(subdivisions=subdivisions, radius=0.5)
    tilts = [(0.0, 0.0)] + [(np.radians(50), 2 * np.pi * i / (n_cameras - 1)) for i in range(n_cameras - 1)]
    cams = [_camera_at([3 * np.sin(a) * np.cos(b), 3 * np.sin(a) * np.sin(b), 3 * np.cos(a)], f=size * 1.2, size=size)
            for a, b in tilts]
    K, R, C = (np.stack(x) for x in zip(*cams))
    return ball, K, R, C, [(size, size)] * n_cameras


def test_centre_seen_faces_counts_faces_smaller_than_a_pixel_and_never_the_far_side():
    from pipeline.mesh.visibility import centre_seen_faces, seen_faces

    ball, K, R, C, sizes = _ball_and_cameras(1, 24)  # 5120 faces, the ball about 12 px across
    to_cam = C[0] - ball.triangles_center
    cos = (to_cam * ball.face_normals).sum(1) / np.linalg.norm(to_cam, axis=1)
    centre = centre_seen_faces(ball.vertices, ball.faces, K, R, C, sizes)
    pixel = seen_faces(ball.vertices, ball.faces, K, R, C, sizes)
    assert centre[cos > 0.25].all() and not centre[cos < 0.2].any()
    assert pixel[cos > 0.25].mean() < 0.2  # pixel centres hit few of them
    with pytest.raises(ValueError, match="differ"):
        centre_seen_faces(ball.vertices, ball.faces, K, R, C, sizes * 2)


def _plane_grid(n: int):
    """A flat n × n grid of squares, two triangles each: vertices, faces, each face's row and column."""
    ii, jj = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
    verts = np.stack([jj.ravel(), ii.ravel(), np.zeros(ii.size)], 1).astype(float)
    a = (np.arange(n)[:, None] * (n + 1) + np.arange(n)[None]).ravel()
    faces = np.stack([np.stack([a, a + 1, a + n + 2], 1), np.stack([a, a + n + 2, a + n + 1], 1)], 1).reshape(-1, 3)
    cell = np.repeat(np.arange(n * n), 2)
    return verts, faces, cell // n, cell % n


def test_tidy_seen_fills_a_pinhole_and_drops_a_shred():
    """The left half of a grid seen, with a one-square hole in it and a one-square-wide strip reaching into the
    unseen half (a glimpse at a grazing angle): the tidy keeps exactly the left half; without the opening the strip
    stays, without the hole filling the hole does."""
    from pipeline.mesh.visibility import tidy_seen

    _, faces, row, col = _plane_grid(20)
    half = col < 10
    seen = half.copy()
    seen[(row == 5) & (col >= 10)] = True
    seen[(row == 12) & (col == 4)] = False
    assert np.array_equal(tidy_seen(faces, seen, 0.01, 2), half)
    assert tidy_seen(faces, seen, 0.01, 0)[(row == 5) & (col >= 10)].all()
    assert not tidy_seen(faces, seen, 0.0, 2)[(row == 12) & (col == 4)].any()
    with pytest.raises(ValueError, match="differ"):
        tidy_seen(faces, seen[:-1], 0.01, 2)


def test_a_ball_photographed_from_one_side_opens_along_one_clean_edge():
    """Five cameras on one side of a ball: the part drop-unseen keeps is one piece with one open edge, all that the
    cameras see well and nothing on the far side."""
    from pipeline.mesh.config import MeshConfig
    from pipeline.mesh.visibility import boundary_loops, seen_part

    ball, K, R, C, sizes = _ball_and_cameras(5, 48)
    keep = seen_part(ball.vertices, ball.faces, K, R, C, sizes, MeshConfig())
    kept = trimesh.Trimesh(ball.vertices, ball.faces[keep])
    assert boundary_loops(kept)[0] == 1 and len(kept.split(only_watertight=False)) == 1
    away = ((C[:, None] - ball.triangles_center[None]) * ball.face_normals[None]).sum(2).max(0) < 0
    assert away.sum() > 1000 and not keep[away].any()
    to_cam = C[:, None] - ball.triangles_center[None]
    cos = ((to_cam * ball.face_normals[None]).sum(2) / np.linalg.norm(to_cam, axis=2)).max(0)
    assert keep[cos > 0.3].all()  # the opening ate nothing from what the cameras see well


def test_a_large_photo_casts_through_a_coarser_grid_and_still_sees_what_faces_it():
    """Above max_rays a view casts through a coarser grid: it sees no face the full grid does not, and still every
    face turned towards it (only faces at grazing angles, a pixel or two wide, can fall between its rays)."""
    from pipeline.mesh.visibility import seen_faces

    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    K, R, C = _camera_at([0.0, 0.0, 3.0], f=240.0, size=256)
    full = seen_faces(ball.vertices, ball.faces, K[None], R[None], C[None], [(256, 256)])
    coarse = seen_faces(ball.vertices, ball.faces, K[None], R[None], C[None], [(256, 256)], max_rays=64 * 64)
    to_cam = C - ball.triangles_center
    cos = (to_cam * ball.face_normals).sum(1) / np.linalg.norm(to_cam, axis=1)
    assert not (coarse & ~full).any() and (full & ~coarse).any()  # the coarse grid was used
    assert coarse[cos > 0.5].all() and full[cos > 0.5].all() and (cos > 0.5).sum() > 50


def test_holes_are_closed_after_the_adjacency_is_measured_and_only_on_an_edge_manifold_mesh():
    """The repairs leave pymeshlab's adjacency stale, and closing holes on it can end the process (SIGSEGV; DTU
    scan24's decimated mesh of the quality preset does): _make_closed measures the topology (which rebuilds the
    adjacency) before it closes holes, and leaves them open where an edge still has more than two faces."""
    import pymeshlab

    from pipeline.mesh.stage import _make_closed

    class Recorded:
        """A MeshSet whose calls are recorded; ``edges``: the non-manifold edges its measures report."""

        def __init__(self, edges: int | None = None):
            self.ms, self.calls, self.edges = pymeshlab.MeshSet(), [], edges

        def __getattr__(self, name):
            call = getattr(self.ms, name)

            def recorded(*args, **kwargs):
                self.calls.append(name)
                out = call(*args, **kwargs)
                return {**out, "non_two_manifold_edges": self.edges} if self.edges is not None and \
                    name == "get_topological_measures" else out
            return recorded

    v, f, _ = _holed_sphere_and_speck()
    for edges, closes in ((None, True), (1, False)):
        ms = Recorded(edges)
        ms.add_mesh(pymeshlab.Mesh(vertex_matrix=v, face_matrix=f.astype(np.int32)))
        _make_closed(ms)
        repairs = max(ms.calls.index(n) for n in ("meshing_repair_non_manifold_edges",
                                                    "meshing_repair_non_manifold_vertices"))
        assert repairs < ms.calls.index("get_topological_measures")
        assert ("meshing_close_holes" in ms.calls) == closes
        if closes:
            assert ms.calls.index("get_topological_measures") < ms.calls.index("meshing_close_holes")
            assert ms.ms.current_mesh().face_number() > len(f)  # the hole's faces were added
