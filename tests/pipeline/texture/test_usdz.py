"""The USDZ export (pipeline/texture/usdz.py): USD's own validators pass, the mesh stands as the GLB does, and its
material reads the texture packaged with it."""

import zipfile

import cv2
import numpy as np
import pytest
import trimesh
from pxr import Usd, UsdGeom, UsdShade, UsdValidation

from pipeline.texture.usdz import export_usdz


def _box_usdz(tmp_path, display):
    box = trimesh.creation.box((0.1, 0.3, 0.2))
    verts, faces = np.asarray(box.vertices), np.asarray(box.faces)
    uvs = (verts[:, :2] - verts[:, :2].min(0)) / np.ptp(verts[:, :2], axis=0)
    png = tmp_path / "textured.png"
    cv2.imwrite(str(png), np.full((16, 16, 3), (40, 120, 200), np.uint8))
    out = tmp_path / "textured.usdz"
    export_usdz(out, verts + 5.0, faces, uvs, png, display)
    return out, len(faces)


def test_usdz_passes_usds_validators_and_stands_upright(tmp_path):
    """A box 0.1 × 0.3 × 0.2 along x, y, z shown with z up (the GLB's node): 0.2 high in the USDZ's Y-up world, every
    one of USD's validators (the USDZ package's among them) silent, the texture inside the package."""
    z_up = np.eye(4)
    z_up[:3, :3] = [[1, 0, 0], [0, 0, 1], [0, -1, 0]]
    out, n_faces = _box_usdz(tmp_path, z_up)
    stage = Usd.Stage.Open(str(out))
    errors = UsdValidation.ValidationContext(UsdValidation.ValidationRegistry().GetOrLoadAllValidators()) \
        .Validate(stage)
    assert list(errors) == [], [e.GetMessage() for e in errors]
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/object/mesh"))
    assert len(mesh.GetFaceVertexCountsAttr().Get()) == n_faces
    box = UsdGeom.BBoxCache(Usd.TimeCode.Default(), [UsdGeom.Tokens.default_]).ComputeWorldBound(mesh.GetPrim())
    size = box.ComputeAlignedRange().GetSize()
    assert np.allclose([size[0], size[1], size[2]], [0.1, 0.2, 0.3], atol=1e-6)
    material, _ = UsdShade.MaterialBindingAPI(mesh.GetPrim()).ComputeBoundMaterial()
    assert material and stage.GetPrimAtPath("/object/material/texture").IsValid()
    assert any(n.endswith("textured.png") for n in zipfile.ZipFile(out).namelist())


def test_usdz_is_written_whole_or_not_at_all(tmp_path):
    """A failure while packaging (a texture that cannot be read) leaves no .usdz (and no temporary folder) behind."""
    box = trimesh.creation.box()
    with pytest.raises(OSError, match="could not package"):
        export_usdz(tmp_path / "textured.usdz", box.vertices, box.faces, np.zeros((8, 2)), tmp_path / "textured.png")
    assert list(tmp_path.iterdir()) == []
