"""The textured mesh written as OBJ + MTL + PNG and as a GLB, and read back."""

from __future__ import annotations

import io
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import trimesh

from dvr.atomic import export_mesh, write_bytes, write_text
from pipeline.errors import StageError
from pipeline.readers import load_mesh_file
from pipeline.texture.surface_maps import SurfaceMaps


def read_textured(path: Path) -> tuple[trimesh.Trimesh, np.ndarray]:
    """The textured mesh of a ``textured.glb`` in the mesh stage's frame (its node's upright transform not applied)
    and its texture (float RGB); StageError naming it when it is damaged (a killed or interrupted write) or not ours."""
    scene = load_mesh_file(path, "glb", "GLB", "rerun the texture stage (texture --force)", process=True)
    try:
        geoms = list(scene.geometry.values()) if isinstance(scene, trimesh.Scene) else [scene]
        texture = geoms[0].visual.material.baseColorTexture.convert("RGB") if len(geoms) == 1 else None
    except Exception as e:  # noqa: BLE001 - trimesh and PIL raise what they meet (IndexError, JSON, struct errors)
        raise StageError(f"{path}: unreadable GLB ({type(e).__name__}); rerun the texture stage (texture --force)") \
            from e
    if texture is None:
        raise StageError(f"{path}: expected one textured mesh, found {len(geoms)} meshes; rerun the texture stage "
                         "(texture --force)")
    return geoms[0], np.asarray(texture, np.float32) / 255.0


GLTF_CLAMP_SAMPLER = {"magFilter": 9729, "minFilter": 9987, "wrapS": 33071, "wrapT": 33071}
"""Linear filtering with mip-maps, clamped to the edge (glTF's default wrap is REPEAT)."""


def clamped_textures(tree: dict) -> None:
    """Every texture of a glTF ``tree`` samples with :data:`GLTF_CLAMP_SAMPLER`: the atlas's charts reach to within
    a texel of its border, and with the default REPEAT wrap a viewer's bilinear and mip-map filtering there blends
    in the opposite border's texels. A vertex attribute ``_tangent`` (trimesh writes its own attributes with a
    leading underscore) becomes glTF's ``TANGENT``."""
    if tree.get("textures"):
        tree["samplers"] = [dict(GLTF_CLAMP_SAMPLER)]
        for texture in tree["textures"]:
            texture["sampler"] = 0
    for mesh in tree.get("meshes", []):
        for primitive in mesh["primitives"]:
            if "_tangent" in primitive["attributes"]:
                primitive["attributes"]["TANGENT"] = primitive["attributes"].pop("_tangent")


MAP_FILES = {"normal": "textured_normal.png", "occlusion": "textured_occlusion.png"}
"""The files of the surface maps beside ``textured.png``."""


def _image(values: np.ndarray):
    from PIL import Image

    return Image.fromarray((np.asarray(values).clip(0, 1) * 255).round().astype(np.uint8))


class _EncodedPNG:
    """A PIL image whose PNG bytes are already made: what trimesh's glTF writer asks of it (its ``format`` and its
    ``save``) without encoding it again; every other attribute is the image's."""

    format = "PNG"

    def __init__(self, image, data: bytes):
        self._image, self.data = image, data

    def save(self, f, format=None) -> None:  # noqa: A002 - PIL's keyword
        f.write(self.data)

    def __getattr__(self, name: str):
        return getattr(self._image, name)


PNG_COMPRESSION = 4
"""zlib level of the PNGs: 2.4 × faster to encode than PIL's default 6, for files 2-4 % larger (DTU's maps)."""


def _png_bytes(image) -> bytes:
    buffer = io.BytesIO()
    image.save(buffer, format="PNG", compress_level=PNG_COMPRESSION)
    return buffer.getvalue()


def export_textured(out_dir: Path, verts: np.ndarray, faces: np.ndarray, uvs: np.ndarray, tex: np.ndarray,
                    display: np.ndarray | None = None, normals: np.ndarray | None = None,
                    maps: SurfaceMaps | None = None) -> None:
    """``textured.glb`` (PBR material), ``textured.obj`` / ``.mtl`` and their texture ``textured.png`` in ``out_dir``.
    ``display``: the GLB's node transform (:func:`upright`; its vertices stay those given); ``normals``: unit vertex
    normals for smooth shading (else a viewer shades faces flat); ``maps``: the normal and occlusion maps
    (:data:`MAP_FILES`, in the GLB's material and the MTL; the GLB then carries the tangents they were baked in). The
    PNGs are encoded once, side by side (the encoder releases the GIL), for the files and the GLB."""
    extra = {} if maps is None else {k: v for k, v in (("normal", maps.normal), ("occlusion", maps.occlusion))
                                     if v is not None}
    pixels = {"textured.png": _image(tex), **{MAP_FILES[k]: _image(v) for k, v in extra.items()}}
    with ThreadPoolExecutor(len(pixels)) as pool:
        images = dict(zip(pixels, pool.map(lambda im: _EncodedPNG(im, _png_bytes(im)), pixels.values())))
    for name, image in images.items():
        write_bytes(out_dir / name, image.data)
    for key, name in MAP_FILES.items():  # a map not baked this time is not left from an earlier run
        if key not in extra:
            (out_dir / name).unlink(missing_ok=True)
    img = images["textured.png"]
    mat = trimesh.visual.material.PBRMaterial(
        baseColorTexture=img, metallicFactor=0.0, roughnessFactor=1.0,
        normalTexture=images.get(MAP_FILES["normal"]), occlusionTexture=images.get(MAP_FILES["occlusion"]))
    mesh = trimesh.Trimesh(verts, faces, visual=trimesh.visual.TextureVisuals(uv=uvs, material=mat),
                           vertex_normals=normals, process=False)
    if maps is not None and "normal" in extra:
        mesh.vertex_attributes["tangent"] = np.asarray(maps.tangents, np.float32)
    scene = trimesh.Scene()
    scene.add_geometry(mesh, node_name="object", geom_name="textured",
                       transform=np.eye(4) if display is None else display)
    export_mesh(out_dir / "textured.glb", scene, tree_postprocessor=clamped_textures,
                include_normals=normals is not None)
    simple = trimesh.visual.material.SimpleMaterial(name="textured", diffuse=(255, 255, 255, 255),
                                                    ambient=(255, 255, 255, 255), specular=(0, 0, 0, 255))
    mesh_obj = trimesh.Trimesh(verts, faces, visual=trimesh.visual.TextureVisuals(uv=uvs, material=simple),
                               vertex_normals=normals, process=False)
    text, files = trimesh.exchange.obj.export_obj(mesh_obj, include_normals=normals is not None,
                                                  include_texture=True, return_texture=True,
                                                  mtl_name="textured.mtl")
    mtl = next(data.decode() for name, data in files.items() if name.endswith(".mtl"))
    lines = ["map_Kd textured.png"]  # the material's texture: textured.png
    if "normal" in extra:  # the PBR extension of MTL (three.js's MTLLoader and tinyobjloader read it)
        lines.append(f"norm {MAP_FILES['normal']}")
    if "occlusion" in extra:
        lines.append(f"map_ao {MAP_FILES['occlusion']}")
    write_text(out_dir / "textured.mtl", mtl + "\n" + "\n".join(lines))
    write_text(out_dir / "textured.obj", text)
