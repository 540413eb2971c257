"""pipeline/render/raycast.py, the one mesh ray-caster: pixel-centre rays (whole image or a box of it), the box a
mesh's projection can cover, the covered pixels cast only inside that box, first hits and faces, and depth maps
against a numpy z-buffer (tests/pipeline/render/zbuffer.py, the test reference)."""

import numpy as np
import pytest
import trimesh

from pipeline.render.raycast import MeshCaster, pixel_center_rays, projected_box
from tests.pipeline.render.zbuffer import ray_depth_map

W, H = 64, 48
K = np.array([[60.0, 0, W / 2], [0, 60.0, H / 2], [0, 0, 1]])


def _camera(centre):
    """World→camera rotation of a camera at ``centre`` looking at the origin (y down in the image)."""
    f = -np.asarray(centre, float) / np.linalg.norm(centre)
    r = np.cross(f, [0.0, 0.0, 1.0])
    r /= np.linalg.norm(r)
    return np.stack([r, np.cross(f, r), f]), np.asarray(centre, float)


def _all_rays_cover(caster, R, c):
    o, d = pixel_center_rays(K, R, c, W, H)
    return caster.any_hit(o, d).reshape(H, W)


def test_rays_of_a_box_are_those_of_the_whole_image():
    R, c = _camera([3.0, 0.5, 0.4])
    o, d = pixel_center_rays(K, R, c, W, H)
    ob, db = pixel_center_rays(K, R, c, W, H, (5, 20, 7, 30))
    assert ob.shape == db.shape == (15 * 23, 3)
    assert np.array_equal(db, d.reshape(H, W, 3)[5:20, 7:30].reshape(-1, 3)) and np.array_equal(ob[0], c)


@pytest.mark.parametrize("centre", [[3.0, 0.5, 0.4], [0.2, -2.5, 1.0]])
def test_covered_pixels_equal_casting_every_ray(centre):
    box = trimesh.creation.box(extents=[0.6, 0.4, 0.5])
    caster = MeshCaster(box)
    R, c = _camera(centre)
    y0, y1, x0, x1 = projected_box(box.vertices, K, R, c, W, H)
    assert 0 < y1 - y0 < H or 0 < x1 - x0 < W  # a box smaller than the image: fewer rays cast
    got = caster.covered_pixels(K, R, c, W, H)
    assert got.any() and np.array_equal(got, _all_rays_cover(caster, R, c))


def test_a_vertex_behind_the_camera_bounds_nothing_and_every_ray_is_cast():
    """A mesh reaching behind the camera projects without bound: no box, and the covered pixels are still exact."""
    R, c = _camera([3.0, 0.5, 0.4])
    slab = trimesh.creation.box(extents=[8.0, 0.3, 0.3])  # from in front of the camera to behind it
    assert projected_box(slab.vertices, K, R, c, W, H) is None
    caster = MeshCaster(slab)
    got = caster.covered_pixels(K, R, c, W, H)
    assert got.any() and np.array_equal(got, _all_rays_cover(caster, R, c))


def test_a_mesh_outside_the_image_covers_nothing():
    R, c = _camera([3.0, 0.0, 0.0])
    far_side = trimesh.creation.box(extents=[0.2, 0.2, 0.2])
    far_side.apply_translation([0.0, 5.0, 0.0])  # beside the view, in front of the camera
    y0, y1, x0, x1 = projected_box(far_side.vertices, K, R, c, W, H)
    assert y1 == y0 or x1 == x0
    assert not MeshCaster(far_side).covered_pixels(K, R, c, W, H).any()


def _scene_for_depth():
    """A sphere, a box half occluding it and a floor under both (two big triangles, behind some cameras)."""
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.6)
    box = trimesh.creation.box((0.4, 0.4, 0.4))
    box.apply_translation((0.5, -0.5, 0.3))
    floor = trimesh.Trimesh([[-2, -2, -0.7], [2, -2, -0.7], [2, 2, -0.7], [-2, 2, -0.7]], [[0, 1, 2], [0, 2, 3]])
    return trimesh.util.concatenate([sphere, box, floor])


def _off_centre_camera(centre):
    """A camera at ``centre`` looking at the origin with non-square pixels and its principal point off centre."""
    R, c = _camera(centre)
    return np.array([[60.0, 0, 31.3], [0, 55.0, 20.7], [0, 0, 1]]), R, c


def test_depth_maps_equal_the_z_buffer_reference():
    """The caster's depth at every pixel centre is the z-buffer's: silhouettes, occlusion, the box's faces seen
    edge-on, floor triangles larger than the image; a view where the floor crosses the camera plane, which the
    z-buffer declines (None), still has its depth map."""
    mesh = _scene_for_depth()
    caster = MeshCaster(mesh)
    declined = 0
    for centre in [(2.5, 0.3, 1.2), (-1.8, 1.9, 0.4), (0.2, -2.6, 2.0), (1.0, -0.8, 2.6), (1.5, 1.5, -0.2)]:
        Kc, R, c = _off_centre_camera(centre)
        got = caster.depth_map(Kc, R, c, W, H)
        want = ray_depth_map(mesh.vertices, mesh.faces, Kc, R, c, W, H)
        assert got.shape == (H, W) and np.isfinite(got).sum() > 500
        if want is None:
            declined += 1
            continue
        assert (np.isfinite(want) != np.isfinite(got)).sum() <= 2, centre  # at most a grazing ray or two
        both = np.isfinite(want) & np.isfinite(got)
        close = np.abs(want[both] - got[both]) < 1e-6 * want[both]
        assert close.mean() > 0.998, (centre, close.mean())
    assert 1 <= declined <= 2  # the views behind which the floor reaches


def test_a_small_object_casts_only_its_box_and_keeps_the_depths():
    """An object in a corner of the image: the rays of its projected box only (the rest of the image is inf) give
    the z-buffer's depths."""
    R, c = _camera([0.0, 0.1, 3.0])
    small = trimesh.creation.icosphere(subdivisions=2, radius=0.3)
    small.apply_translation((0.6, 0.4, 0.0))
    caster = MeshCaster(small)
    cast = []
    real = caster.first_hits
    caster.first_hits = lambda o, d: cast.append(len(d)) or real(o, d)
    got = caster.depth_map(K, R, c, W, H)
    want = ray_depth_map(small.vertices, small.faces, K, R, c, W, H)
    assert 0 < cast[0] < W * H / 3 and np.isfinite(got).sum() > 40
    assert (np.isfinite(want) != np.isfinite(got)).sum() <= 2
    both = np.isfinite(want) & np.isfinite(got)
    assert np.allclose(got[both], want[both], rtol=1e-6)


def test_the_z_buffer_reference_outside_the_image_and_behind_the_camera():
    R, c = _camera([0.0, 0.1, 3.0])
    far = trimesh.creation.box((0.1, 0.1, 0.1))
    far.apply_translation((40.0, 0.0, 0.0))  # outside the image
    d = ray_depth_map(far.vertices, far.faces, K, R, c, W, H)
    assert d.shape == (H, W) and np.isinf(d).all()
    assert np.isinf(MeshCaster(far).depth_map(K, R, c, W, H)).all()
    behind = trimesh.creation.box((0.1, 0.1, 0.1))
    behind.apply_translation((0.0, 0.2, 5.0))  # wholly behind the camera: skipped, not declined
    d = ray_depth_map(behind.vertices, behind.faces, K, R, c, W, H)
    assert d is not None and np.isinf(d).all()


def test_first_hits_are_the_nearest_and_agree_with_first_faces():
    """One row per ray that hits, the nearest surface of two stacked boxes; the same faces as ``first_faces`` and
    the same rays as ``any_hit``."""
    near, far = trimesh.creation.box((0.4, 0.4, 0.4)), trimesh.creation.box((0.4, 0.4, 0.4))
    far.apply_translation((-0.8, 0.0, 0.0))
    mesh = trimesh.util.concatenate([near, far])
    caster = MeshCaster(mesh)
    R, c = _camera([3.0, 0.0, 0.0])
    o, d = pixel_center_rays(K, R, c, W, H)
    ray, face, loc = caster.first_hits(o, d)
    assert len(ray) == len(np.unique(ray)) > 40
    assert np.allclose(loc[:, 0], 0.2)  # the near box's face towards the camera, never the far box
    first = caster.first_faces(o, d)
    assert np.array_equal(first[ray], face) and (first >= 0).sum() == len(ray)
    assert np.array_equal(np.flatnonzero(caster.any_hit(o, d)), np.sort(ray))


def test_barycentric_hits_are_the_first_hits_with_or_without_embree():
    """Embree's own barycentrics and distances give the points :meth:`first_hits` finds; trimesh's intersector (no
    Embree) gives the same rows."""
    near, far = trimesh.creation.box((0.4, 0.4, 0.4)), trimesh.creation.box((0.4, 0.4, 0.4))
    far.apply_translation((0.1, 0.05, -1.0))
    mesh = trimesh.util.concatenate([near, far])
    rng = np.random.default_rng(3)
    origins = np.column_stack([rng.uniform(-0.4, 0.4, (300, 2)), np.full(300, 2.0)])
    dirs = np.tile([0.0, 0.0, -1.0], (300, 1)) + rng.normal(0, 0.05, (300, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    caster = MeshCaster(mesh)
    ray, face, loc = caster.first_hits(origins, dirs)
    for c in (caster, _without_embree(mesh)):
        r, f, dist, bary = c.first_hits_barycentric(origins, dirs)
        order = np.argsort(r)
        assert np.array_equal(r[order], np.sort(ray)) and np.array_equal(f[order], face[np.argsort(ray)])
        points = np.einsum("kc,kcd->kd", bary, mesh.triangles[f])
        assert np.allclose(points[order], loc[np.argsort(ray)], atol=1e-5)
        assert np.allclose(dist, np.linalg.norm(points - origins[r], axis=1), atol=1e-5)
        assert np.allclose(bary.sum(1), 1.0) and (bary > -1e-6).all()


def _without_embree(mesh) -> MeshCaster:
    caster = MeshCaster(mesh)
    caster._inter = trimesh.ray.ray_triangle.RayMeshIntersector(mesh)
    return caster
