"""Synthetic scenes: only the listed effects are computed; the workspace layout and ground truth are right."""

import json

import cv2
import numpy as np
import pytest
import trimesh

from pipeline.synth import load_scene_file, scene_from_dict, write_scene
from tests.conftest import ROOT, SHARED, small_scene


def _img(ws, i=0):
    return cv2.cvtColor(cv2.imread(str(ws / "images" / f"{i:06d}.png")), cv2.COLOR_BGR2RGB) / 255.0


def test_only_listed_passes_and_albedo_only(tmp_path):
    meta = write_scene(small_scene(albedo={"kind": "constant", "color": [0.2, 0.6, 0.4]}), tmp_path)
    assert meta["passes"] == ["geometry", "albedo:constant"]
    img = _img(tmp_path)
    m = cv2.imread(str(tmp_path / "masks" / "000000.png"), 0) > 127
    assert m.any() and (~m).any()
    assert np.allclose(img[m], [0.2, 0.6, 0.4], atol=1 / 255)  # no lighting: the albedo itself
    assert np.all(img[~m] == 0)  # background none


def test_listed_effects_are_rendered(tmp_path):
    sc = small_scene(lighting={"kind": "lambertian"}, background={"kind": "backdrop"},
                     effects=[{"kind": "noise", "sigma": 0.02}, {"kind": "specular", "amount": 0.3},
                              {"kind": "exposure", "amount": 0.2}, {"kind": "blur", "sigma": 0.7},
                              {"kind": "distortion", "k1": -0.1}])
    meta = write_scene(sc, tmp_path)
    assert meta["passes"] == ["geometry", "albedo:checker", "normals", "lighting:lambertian", "background:backdrop",
                              "effect:noise", "effect:specular", "effect:exposure", "effect:blur",
                              "effect:distortion"]
    img = _img(tmp_path)
    m = cv2.imread(str(tmp_path / "masks" / "000000.png"), 0) > 127
    assert img[~m].std() > 0.05  # textured backdrop


def test_layout_and_ground_truth(small_ws):
    for p in ["images/000000.png", "masks/000007.png", "cameras.npz", "gt/mesh.ply", "gt/depth/000000.npy",
              "depth/000000.npz", "gt/scene.json"]:
        assert (small_ws / p).exists(), p
    gt = trimesh.load(small_ws / "gt" / "mesh.ply")
    assert gt.is_watertight and gt.volume > 0
    torus_volume = 2 * np.pi ** 2 * 0.5 * 0.2 ** 2
    assert gt.volume == pytest.approx(torus_volume, rel=0.01)
    meta = json.loads((small_ws / "gt" / "scene.json").read_text())
    assert meta["n_views"] == 8 and "sparse_depth" in meta["passes"]


def test_sparse_depth_lies_on_the_surface(small_ws):
    import torch

    from dvr.data import load_scene
    from pipeline.synth.render import sdf

    data = load_scene(small_ws, torch.device("cpu"))
    o, d = data.rays(data.depth_views, data.depth_uv)
    p = (o + data.depth_val[:, None] * d).double()
    shape = small_scene().shape
    assert sdf(shape, p).abs().max() < 1e-3


def test_mesh_scene_with_texture(tmp_path):
    sc = scene_from_dict({"shape": {"kind": "mesh", "path": str(SHARED / "meshes/cow/cow.obj")},
                          "albedo": {"kind": "texture"},
                          "cameras": {"n_views": 2, "width": 48, "height": 48}})
    meta = write_scene(sc, tmp_path)
    assert meta["passes"] == ["geometry", "albedo:texture"]
    gt = trimesh.load(tmp_path / "gt" / "mesh.ply")
    assert gt.is_watertight
    img = _img(tmp_path)
    m = cv2.imread(str(tmp_path / "masks" / "000000.png"), 0) > 127
    assert m.sum() > 100 and img[m].std() > 0.02


def test_bad_scene(tmp_path):
    with pytest.raises(ValueError, match="unknown Shape keys"):
        scene_from_dict({"shape": {"kind": "torus", "radios": 1}})
    with pytest.raises(ValueError, match="unknown analytic shape"):
        write_scene(scene_from_dict({"shape": {"kind": "blob"}, "cameras": {"n_views": 1, "width": 8,
                                                                           "height": 8}}), tmp_path)
    with pytest.raises(ValueError, match="world_scale"):
        write_scene(small_scene(world_scale=0.0), tmp_path)


def test_repo_scene_files_load():
    for f in (ROOT / "configs" / "scenes").glob("*.yaml"):
        load_scene_file(f)
