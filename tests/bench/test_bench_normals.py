"""bench/normals.py: the GLB read back as a viewer reads it (its tangents, v-flipped UVs and PNG normal map) shades
the coarse sphere as the true sphere; the level table against a known truth."""

import numpy as np
import pytest
import trimesh

from bench.normals import normal_errors, read_glb, shaded_normals
from pipeline.render.raycast import MeshCaster
from pipeline.render.textured import sample_uv
from pipeline.texture.export import export_textured
from tests.pipeline.texture.test_export_maps import sphere_maps  # noqa: F401 - a fixture


def _rays(n: int = 40):
    grid = np.stack(np.meshgrid(np.linspace(-0.45, 0.45, n), np.linspace(-0.45, 0.45, n)), -1).reshape(-1, 2)
    origins = np.concatenate([grid, np.full((len(grid), 1), 2.0)], 1)
    return origins, np.tile([0.0, 0.0, -1.0], (len(grid), 1))


def test_the_glb_read_back_holds_what_was_written(sphere_maps, tmp_path):  # noqa: F811
    verts, faces, uvs, normals, maps = sphere_maps
    export_textured(tmp_path, verts, faces, uvs, np.full((8, 8, 3), 0.5), None, normals, maps)
    glb = read_glb(tmp_path / "textured.glb")
    np.testing.assert_allclose(glb["tangents"], maps.tangents, atol=1e-6)
    np.testing.assert_allclose(glb["normals"], normals, atol=1e-6)
    np.testing.assert_allclose(glb["uvs"], uvs, atol=1e-6)
    assert np.abs(glb["normal_map"] - maps.normal).max() <= 0.5 / 255 + 1e-6


def test_the_glb_as_a_viewer_shades_it_is_the_sphere(sphere_maps, tmp_path):  # noqa: F811
    """Rays from a camera at the GLB read back (its tangents, v-flipped UVs and PNG normal map): the shading normal
    is within a degree of the true sphere's at the pixels, the faces' own normals are not."""
    verts, faces, uvs, normals, maps = sphere_maps
    export_textured(tmp_path, verts, faces, uvs, np.full((8, 8, 3), 0.5), None, normals, maps)
    glb = read_glb(tmp_path / "textured.glb")
    caster = MeshCaster(trimesh.Trimesh(glb["verts"], glb["faces"], process=False))
    origins, dirs = _rays()
    for mapped, bound in ((True, 1.0), (False, None)):
        ray, depth, n = shaded_normals(glb, caster, origins, dirs, mapped)
        hit = origins[ray] + depth[:, None] * dirs[ray]
        truth = hit / np.linalg.norm(hit, axis=1, keepdims=True)
        angle = np.degrees(np.arccos((n * truth).sum(1).clip(-1, 1)))
        if bound:
            assert len(ray) > 900 and angle.mean() < 0.6 and np.percentile(angle, 99) < bound, angle.max()
        else:
            assert angle.mean() > 5.0




def test_bilinear_samples_texel_centres_and_clamps():
    image = np.arange(12, dtype=float).reshape(3, 4, 1)
    centre = np.array([[(1 + 0.5) / 4, 1 - (2 + 0.5) / 3]])  # texel (row 2, col 1)
    assert sample_uv(image, centre)[0, 0] == pytest.approx(9.0)
    assert sample_uv(image, np.array([[-1.0, 2.0]]))[0, 0] == pytest.approx(0.0)


def test_the_level_table_against_a_truth(sphere_maps, tmp_path):  # noqa: F811
    """The coarse sphere against the true sphere (a fine icosphere) at one camera: the map brings the mean angle
    from about 10° to 3° (what remains: a pixel meets the two spheres at points up to 3 % of the radius apart,
    whose normals differ by up to 3.4°)."""
    from dvr.cameras import Cameras

    verts, faces, uvs, normals, maps = sphere_maps
    export_textured(tmp_path, verts, faces, uvs, np.full((8, 8, 3), 0.5), None, normals, maps)
    fine = trimesh.creation.icosphere(5, 0.5)
    K = np.array([[200.0, 0, 50], [0, 200.0, 50], [0, 0, 1]])
    R = np.diag([1.0, -1.0, -1.0])  # looking down −z from +z
    cams = Cameras(K=K[None], R=R[None], t=(-R @ np.array([0, 0, 3.0]))[None], scale_mat=np.eye(4))
    rows = normal_errors({"coarse": read_glb(tmp_path / "textured.glb")},
                         (fine, lambda face, bary: fine.face_normals[face]), cams, (100, 100), [0], 10.0)
    row = rows["coarse"]
    assert row["faces"] == len(faces) and row["pixels"] > 3000
    assert row["without_map_deg"] > 8.0 and row["with_map_deg"] < 3.5
