"""The normal and occlusion maps in the files people open (pipeline/texture/export.py, usdz.py): the GLB's material,
normals and tangents, the glTF validator, the MTL's lines, the USDZ's material, and a rerun without maps leaving
none behind (tests/bench/test_bench_normals.py shades the GLB as a viewer does)."""

import json
import shutil
import struct
import subprocess
import zipfile

import numpy as np
import pytest
from pxr import Usd, UsdShade, UsdValidation

from pipeline.texture.atlas import rasterize_atlas
from pipeline.texture.export import MAP_FILES, export_textured
from pipeline.texture.surface_maps import SurfaceField, bake_surface_maps
from pipeline.texture.usdz import export_usdz
from tests.pipeline.texture.test_surface_maps import CELL, _flat_icosphere, sphere_logit


@pytest.fixture(scope="module")
def sphere_maps():
    """The flat-shaded 80-face icosphere with its maps baked from the sphere's field (occlusion too)."""
    verts, faces, uvs, normals, side = _flat_icosphere()
    fid = rasterize_atlas(uvs, faces, side)
    maps = bake_surface_maps(SurfaceField(sphere_logit, CELL), verts, faces, uvs, normals, fid, True, 0.2, 4)
    return verts, faces, uvs, normals, maps


def _tree(glb):
    data = glb.read_bytes()
    return json.loads(data[20:20 + struct.unpack("<I", data[12:16])[0]])


def test_the_glb_carries_the_maps_normals_and_tangents(sphere_maps, tmp_path):
    verts, faces, uvs, normals, maps = sphere_maps
    export_textured(tmp_path, verts, faces, uvs, np.full((8, 8, 3), 0.5), None, normals, maps)
    tree = _tree(tmp_path / "textured.glb")
    attributes = tree["meshes"][0]["primitives"][0]["attributes"]
    assert {"POSITION", "NORMAL", "TANGENT", "TEXCOORD_0"} <= set(attributes) and "_tangent" not in attributes
    material = tree["materials"][0]
    assert {"normalTexture", "occlusionTexture"} <= set(material)
    mtl = (tmp_path / "textured.mtl").read_text()
    assert f"norm {MAP_FILES['normal']}" in mtl and f"map_ao {MAP_FILES['occlusion']}" in mtl
    assert all((tmp_path / name).exists() for name in MAP_FILES.values())


def test_the_gltf_validator_accepts_the_maps(sphere_maps, tmp_path):
    from tests.conftest import ROOT

    node, js = shutil.which("node"), ROOT / "node_modules" / "gltf-validator"
    if node is None or not js.exists():
        pytest.skip("node or the npm gltf-validator is not installed (make setup-web installs it)")
    verts, faces, uvs, normals, maps = sphere_maps
    export_textured(tmp_path, verts, faces, uvs, np.full((8, 8, 3), 0.5), np.eye(4), normals, maps)
    script = ("const v=require('gltf-validator');const fs=require('fs');"
              f"v.validateBytes(new Uint8Array(fs.readFileSync('{tmp_path / 'textured.glb'}')))"
              ".then(r=>{console.log(JSON.stringify(r.issues));"
              "process.exit(r.issues.numErrors+r.issues.numWarnings>0?1:0)})"
              ".catch(e=>{console.error(e);process.exit(2)})")
    out = subprocess.run([node, "-e", script], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 0, out.stdout + out.stderr


def test_a_rerun_without_maps_leaves_none_behind(sphere_maps, tmp_path):
    verts, faces, uvs, normals, maps = sphere_maps
    export_textured(tmp_path, verts, faces, uvs, np.full((8, 8, 3), 0.5), None, normals, maps)
    export_textured(tmp_path, verts, faces, uvs, np.full((8, 8, 3), 0.5), None, normals, None)
    assert not any((tmp_path / name).exists() for name in MAP_FILES.values())
    assert "norm" not in (tmp_path / "textured.mtl").read_text().replace("normal", "")
    material = _tree(tmp_path / "textured.glb")["materials"][0]
    assert "normalTexture" not in material and "occlusionTexture" not in material


def test_the_usdz_material_reads_the_maps_and_validates(sphere_maps, tmp_path):
    verts, faces, uvs, normals, maps = sphere_maps
    export_textured(tmp_path, verts, faces, uvs, np.full((8, 8, 3), 0.5), None, normals, maps)
    out = tmp_path / "textured.usdz"
    export_usdz(out, verts, faces, uvs, tmp_path / "textured.png", np.eye(4), normals)
    stage = Usd.Stage.Open(str(out))
    errors = UsdValidation.ValidationContext(UsdValidation.ValidationRegistry().GetOrLoadAllValidators()) \
        .Validate(stage)
    assert list(errors) == [], [e.GetMessage() for e in errors]
    surface = UsdShade.Shader(stage.GetPrimAtPath("/object/material/surface"))
    for name, source in (("normal", "/object/material/normal"), ("occlusion", "/object/material/occlusion")):
        connected = surface.GetInput(name).GetConnectedSources()[0]
        assert connected and str(connected[0].source.GetPath()) == source
    assert {"textured.png", *MAP_FILES.values()} <= set(zipfile.ZipFile(out).namelist())
