"""The textured mesh as USDZ (Apple's AR Quick Look, usdview, Blender): one mesh with its UVs, a UsdPreviewSurface
material reading the same texture PNGs as the OBJ (colour, and the normal and occlusion maps when they were baked),
standing upright as the GLB does; metres per unit 1, as glTF's."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from dvr.atomic import write_bytes
from pipeline.texture.export import MAP_FILES


def export_usdz(path: Path, verts: np.ndarray, faces: np.ndarray, uvs: np.ndarray, texture_png: Path,
                display: np.ndarray | None = None, normals: np.ndarray | None = None) -> None:
    """``path`` (a .usdz): the mesh ``verts`` (N, 3), ``faces`` (F, 3), per-vertex ``uvs`` (N, 2; v up, as the OBJ's)
    textured with ``texture_png`` (and the normal and occlusion maps of :data:`MAP_FILES` found beside it), unit
    vertex ``normals`` (N, 3) when given, under a transform ``display`` (4×4; the GLB's upright node,
    :func:`upright`), Y up, 1 metre per unit (the SfM frame's units: metres with a printed board). Written whole or
    not at all."""
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade, Vt

    maps = {k: texture_png.parent / name for k, name in MAP_FILES.items() if (texture_png.parent / name).exists()}

    with tempfile.TemporaryDirectory(dir=path.parent) as tmp:
        layer = Path(tmp) / "textured.usdc"
        stage = Usd.Stage.CreateNew(str(layer))
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
        UsdGeom.SetStageMetersPerUnit(stage, 1.0)
        root = UsdGeom.Xform.Define(stage, "/object")
        stage.SetDefaultPrim(root.GetPrim())
        matrix = np.eye(4) if display is None else np.asarray(display, float)
        root.AddTransformOp().Set(Gf.Matrix4d(matrix.T.tolist()))  # USD's matrices act on row vectors
        mesh = UsdGeom.Mesh.Define(stage, "/object/mesh")
        mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.asarray(verts, np.float32)))
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, np.int32)))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.asarray(faces, np.int32).reshape(-1)))
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        lo, hi = np.asarray(verts).min(0), np.asarray(verts).max(0)
        mesh.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))]))
        st = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray,
                                                     UsdGeom.Tokens.vertex)
        st.Set(Vt.Vec2fArray.FromNumpy(np.asarray(uvs, np.float32)))
        if normals is not None:
            mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(np.asarray(normals, np.float32)))
            mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)

        material = UsdShade.Material.Define(stage, "/object/material")
        surface = UsdShade.Shader.Define(stage, "/object/material/surface")
        surface.CreateIdAttr("UsdPreviewSurface")
        surface.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(1.0)
        surface.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(0.0)
        reader = UsdShade.Shader.Define(stage, "/object/material/st")
        reader.CreateIdAttr("UsdPrimvarReader_float2")
        reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")

        def texture(name: str, png: Path, colour_space: str):
            image = UsdShade.Shader.Define(stage, f"/object/material/{name}")
            image.CreateIdAttr("UsdUVTexture")
            image.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(png.name)
            image.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set(colour_space)
            image.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(reader.ConnectableAPI(), "result")
            return image

        rgb = texture("texture", texture_png, "sRGB").CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
        surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(rgb)
        if "normal" in maps:  # colours 0-1 to tangent-space -1-1
            image = texture("normal", maps["normal"], "raw")
            image.CreateInput("scale", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(2, 2, 2, 1))
            image.CreateInput("bias", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(-1, -1, -1, 0))
            surface.CreateInput("normal", Sdf.ValueTypeNames.Normal3f).ConnectToSource(
                image.CreateOutput("rgb", Sdf.ValueTypeNames.Float3))
        if "occlusion" in maps:
            image = texture("occlusion", maps["occlusion"], "raw")
            surface.CreateInput("occlusion", Sdf.ValueTypeNames.Float).ConnectToSource(
                image.CreateOutput("r", Sdf.ValueTypeNames.Float))
        material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
        UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)
        stage.GetRootLayer().Save()

        packed = Path(tmp) / "textured.usdz"
        try:  # the layer first (the package's default layer), the textures under the names the layer gives them
            zip_writer = Sdf.ZipFileWriter.CreateNew(str(packed))
            zip_writer.AddFile(str(layer), layer.name)
            for png in (texture_png, *maps.values()):
                zip_writer.AddFile(str(png), png.name)
            saved = zip_writer.Save()
        except Exception as exc:  # noqa: BLE001 - USD raises its own Tf.ErrorException (a file it cannot read)
            raise OSError(f"{path}: USD could not package the mesh ({type(exc).__name__})") from exc
        if not saved:
            raise OSError(f"{path}: USD could not package the mesh")
        write_bytes(path, packed.read_bytes())
