"""Textures carried from one textured mesh onto another of the same surface (pipeline/texture/transfer.py): the
bilinear lookup against grid_sample, the rays' reach and sides, bad input; a detail level carried from the baked cow
looks as the cow baked from its photos does, without the photos."""

import numpy as np
import pytest
import torch
import trimesh

from pipeline.render.textured import sample_uv
from pipeline.texture import stage as texture_stage
from pipeline.texture.config import TextureConfig
from pipeline.texture.stage import Carry, texels_per_unit, texture_mesh
from pipeline.texture.transfer import BakedMesh, carried, carried_uvs
from tests.pipeline.texture.test_texture import W, _heldout_psnr, noise_cow_photos


def test_bilinear_is_grid_samples():
    """The texture lookup is ``grid_sample``'s (align_corners=False, border padding) at the same uvs, in and out."""
    rng = np.random.default_rng(0)
    tex = rng.random((16, 16, 3)).astype(np.float32)
    uv = rng.uniform(-0.1, 1.1, (500, 2))
    grid = torch.from_numpy(np.stack([2 * uv[:, 0] - 1, 1 - 2 * uv[:, 1]], 1)).float()[None, None]
    want = torch.nn.functional.grid_sample(torch.from_numpy(tex).permute(2, 0, 1)[None], grid, mode="bilinear",
                                           padding_mode="border", align_corners=False)[0, :, 0].T.numpy()
    assert np.allclose(sample_uv(tex, uv), want, atol=1e-5)


def _two_sided_slab(thickness: float) -> BakedMesh:
    """A 2 × 2 slab of ``thickness`` (top at z = 0) whose texture is red on the top face and blue elsewhere."""
    slab = trimesh.creation.box((2.0, 2.0, thickness))
    slab.apply_translation((0, 0, -thickness / 2))
    top = slab.face_normals[:, 2] > 0.5
    # every face on corners of its own, so that a face's uvs are all its own side's
    verts, faces = slab.vertices[slab.faces].reshape(-1, 3), np.arange(3 * len(slab.faces)).reshape(-1, 3)
    uvs = np.where(np.repeat(top, 3), 0.25, 0.75)[:, None].repeat(2, 1)
    tex = np.zeros((8, 8, 3), np.float32)
    tex[4:, :4] = (1, 0, 0)  # uv (0.25, 0.25): rows of v < 0.5 are the lower half
    tex[:4, 4:] = (0, 0, 1)
    return BakedMesh(verts, faces, uvs, tex)


def test_the_nearest_side_within_reach_is_carried():
    """Points just above and below the top of a thick slab take its red, a point near its bottom facing down the
    bottom's blue; a point beyond the reach is not found. On a slab thinner than the reach, whose underside the ray
    from below meets first, the ray from above finds the top: the side a point faces, never the far side's."""
    thick = _two_sided_slab(0.5)
    pts = np.array([[0.1, 0.2, 0.01], [-0.3, 0.4, -0.01], [0.0, 0.0, 0.5], [0.2, 0.2, -0.46]])
    nrm = np.array([[0, 0, 1.0], [0, 0, 1.0], [0, 0, 1.0], [0, 0, -1.0]])
    col, found = carried(thick.texture, *carried_uvs(thick, pts, nrm, reach=0.1), len(pts))
    assert found.tolist() == [True, True, False, True]
    assert np.allclose(col[:2], (1, 0, 0)) and np.allclose(col[3], (0, 0, 1)) and np.allclose(col[2], 0)
    thin = _two_sided_slab(0.05)
    on_top = np.array([[0.1, 0.2, 0.0], [0.1, 0.2, 0.0]])
    col, found = carried(thin.texture, *carried_uvs(thin, on_top, np.array([[0, 0, 1.0], [0, 0, -1.0]]), 0.1), 2)
    assert found.all() and np.allclose(col, [(1, 0, 0), (0, 0, 1)])


def test_bad_input_is_a_value_error():
    slab = _two_sided_slab(0.05)
    with pytest.raises(ValueError, match="points and normals"):
        carried_uvs(slab, np.zeros((3, 3)), np.zeros((2, 3)), 0.1)
    with pytest.raises(ValueError, match="reach"):
        carried_uvs(slab, np.zeros((3, 3)), np.zeros((3, 3)), 0.0)
    rows, uv = carried_uvs(slab, np.zeros((0, 3)), np.zeros((0, 3)), 0.1)
    assert rows.shape == (0,) and uv.shape == (0, 2)


def test_a_level_carried_from_the_baked_cow_looks_as_one_baked_from_the_photos(tmp_path, monkeypatch):
    """The cow (smooth noise albedo) baked from 24 photos; a finer mesh of it (each face cut in four) textured by
    carrying that texture, with no depth map cast: every texel found, its held-out PSNR within 1.5 dB (at 48 dB: 0.2
    grey levels RMS; the texture resampled once more) of the same finer mesh baked from the photos."""
    _, gt, cams, imgs = noise_cow_photos(tmp_path)
    cfg = TextureConfig(size=1024)
    nv, nf, uvs, tex, _ = texture_mesh(np.asarray(gt.vertices), np.asarray(gt.faces), imgs, cams, cfg)
    fine_v, fine_f = trimesh.remesh.subdivide(np.asarray(gt.vertices), np.asarray(gt.faces))
    from_photos = texture_mesh(fine_v, fine_f, imgs, cams, cfg)

    def no_depth_maps(*args):
        raise AssertionError("a carried level casts no depth maps")

    monkeypatch.setattr(texture_stage, "depth_maps", no_depth_maps)
    density = texels_per_unit(gt, cams, [(W, W)] * len(imgs), cfg)
    carry = Carry(lambda: BakedMesh(nv, nf, uvs, tex), density, reach=0.01)
    lv, lf, luv, ltex, lstats = texture_mesh(fine_v, fine_f, imgs, cams, cfg, carry=carry)
    assert lstats["carried"] > 0.999 and len(lf) == 4 * len(gt.faces)
    carried_psnr = _heldout_psnr(tmp_path, lv, lf, luv, ltex).mean()
    photos_psnr = _heldout_psnr(tmp_path, *from_photos[:4]).mean()
    print(f"carried {carried_psnr:.2f} dB, baked from the photos {photos_psnr:.2f} dB")
    assert carried_psnr > photos_psnr - 1.5


def test_a_failure_stops_the_levels_not_started(monkeypatch):
    """The default mesh baked in this thread, the levels beside it one at a time here: a level that fails, or the
    default mesh failing, stops the levels still waiting; the running one finishes."""
    import threading
    import time

    monkeypatch.setattr(texture_stage, "BAKES_AT_ONCE", 1)
    started = []

    def level(name: str, fail: bool = False, wait: float = 0.0):
        def bake():
            started.append(name)
            time.sleep(wait)
            if fail:
                raise OSError(f"{name}: no room")
            return {"name": name}
        return bake

    stats, levels = texture_stage.bake_beside(lambda: {"default": 1}, {"a": level("a"), "b": level("b")})
    assert stats == {"default": 1} and levels == {"a": {"name": "a"}, "b": {"name": "b"}}
    started.clear()
    with pytest.raises(OSError, match="a: no room"):
        texture_stage.bake_beside(lambda: {}, {"a": level("a", fail=True), "b": level("b"), "c": level("c")})
    assert started == ["a"]
    started.clear()
    running = threading.Event()

    def failing_default():
        running.wait(5)
        raise KeyboardInterrupt

    first = level("a", wait=0.2)
    with pytest.raises(KeyboardInterrupt):
        texture_stage.bake_beside(failing_default, {"a": lambda: running.set() or first(), "b": level("b")})
    assert started == ["a"]
