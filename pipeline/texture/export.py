"""The textured mesh written as OBJ + MTL + PNG and as a GLB, and read back."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import trimesh

from dvr.atomic import atomic_file, export_mesh, write_text
from pipeline.errors import StageError
from pipeline.readers import load_mesh_file


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
    in the opposite border's texels."""
    if tree.get("textures"):
        tree["samplers"] = [dict(GLTF_CLAMP_SAMPLER)]
        for texture in tree["textures"]:
            texture["sampler"] = 0


def export_textured(out_dir: Path, verts: np.ndarray, faces: np.ndarray, uvs: np.ndarray, tex: np.ndarray,
                    display: np.ndarray | None = None) -> None:
    """``textured.glb`` (PBR material), ``textured.obj`` / ``.mtl`` and their texture ``textured.png`` in ``out_dir``.
    ``display``: the GLB's node transform (:func:`upright`; its vertices stay those given). The PNG is encoded once
    for the OBJ (in a thread: the encoder releases the GIL) while the GLB encodes its own."""
    from PIL import Image

    img = Image.fromarray((tex.clip(0, 1) * 255).round().astype(np.uint8))
    png_error: list[BaseException] = []

    def write_png():
        try:
            with atomic_file(out_dir / "textured.png") as f:
                img.save(f, format="PNG")
        except BaseException as exc:  # noqa: BLE001 - raised below, in the caller's thread (a full disk)
            png_error.append(exc)

    png = threading.Thread(target=write_png)
    png.start()
    try:
        mat = trimesh.visual.material.PBRMaterial(baseColorTexture=img, metallicFactor=0.0, roughnessFactor=1.0)
        mesh = trimesh.Trimesh(verts, faces, visual=trimesh.visual.TextureVisuals(uv=uvs, material=mat),
                               process=False)
        scene = trimesh.Scene()
        scene.add_geometry(mesh, node_name="object", geom_name="textured",
                           transform=np.eye(4) if display is None else display)
        export_mesh(out_dir / "textured.glb", scene, tree_postprocessor=clamped_textures)
        simple = trimesh.visual.material.SimpleMaterial(name="textured", diffuse=(255, 255, 255, 255),
                                                        ambient=(255, 255, 255, 255), specular=(0, 0, 0, 255))
        mesh_obj = trimesh.Trimesh(verts, faces, visual=trimesh.visual.TextureVisuals(uv=uvs, material=simple),
                                   process=False)
        text, files = trimesh.exchange.obj.export_obj(mesh_obj, include_texture=True, return_texture=True,
                                                      mtl_name="textured.mtl")
        mtl = next(data.decode() for name, data in files.items() if name.endswith(".mtl"))
        write_text(out_dir / "textured.mtl", mtl + "\nmap_Kd textured.png")  # the material's texture: textured.png
        write_text(out_dir / "textured.obj", text)
    finally:
        png.join()
    if png_error:
        raise png_error[0]
