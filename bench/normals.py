"""How well each detail level's GLB shades: the normal a viewer computes (the mesh's interpolated normal, bent by the
normal map in the GLB's tangents) against the true surface normal, at a synthetic scene's held-out views; and
pictures of each level lit from the side.

    python bench/normals.py WS --truth SCENE [--views N]
    python bench/normals.py WS --against LEVEL [--views N]
    python bench/normals.py WS --pictures FOLDER [--view K]
    python bench/normals.py --sphere FOLDER

``WS``: a workspace whose texture stage baked detail levels (``python -m pipeline mesh WS --mesh.detail
preview,full`` then ``python -m pipeline texture WS``) in the frame of ``SCENE``'s ground truth (a workspace trained
on the scene's true cameras, as ``python bench/arms.py gt cow`` makes). Prints, per level, the mean angle (degrees)
between the true normal and the shaded normal with and without the normal map, over the pixels where the level and
the true mesh meet the ray at the same depth. ``--against``: the same with a level's own shading (its
interpolated normals, e.g. ``full``) in place of the truth, at the workspace's cameras (a real capture).
``--pictures``: each level (and the default mesh) rendered with
Lambert shading under a light from the camera's right, with and without its normal map, beside each other, and
all of them in ``levels.png``. ``--sphere``: pages that show a flat-shaded icosphere with and without the normal map
of the true sphere in model-viewer (three.js), for ``bench/glb_shot.mjs`` to photograph.
"""
from __future__ import annotations

import argparse
import json
import struct
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dvr.cameras import load_cameras  # noqa: E402
from pipeline.render.raycast import MeshCaster, pixel_center_rays  # noqa: E402
from pipeline.render.textured import sample_uv  # noqa: E402
from pipeline.texture.surface_maps import decode_normals, shading_normals, texel_frames  # noqa: E402

COMPONENTS = {5126: np.float32, 5125: np.uint32, 5123: np.uint16}
WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}


def read_glb(path: Path) -> dict:
    """The one primitive of a GLB the texture stage wrote: ``verts``, ``faces``, ``uvs`` (v up), ``normals``,
    ``tangents`` (None when absent) and ``normal_map`` (float RGB, None when absent), as a viewer reads them."""
    import io

    from PIL import Image

    data = path.read_bytes()
    json_len = struct.unpack_from("<I", data, 12)[0]
    tree = json.loads(data[20:20 + json_len])
    binary = data[20 + json_len + 8:]

    def view_bytes(index: int) -> bytes:
        view = tree["bufferViews"][index]
        return binary[view.get("byteOffset", 0):view.get("byteOffset", 0) + view["byteLength"]]

    def accessor(index: int) -> np.ndarray:
        acc = tree["accessors"][index]
        raw = np.frombuffer(view_bytes(acc["bufferView"]), COMPONENTS[acc["componentType"]],
                            acc["count"] * WIDTH[acc["type"]], acc.get("byteOffset", 0))
        return raw.reshape(acc["count"], WIDTH[acc["type"]]).astype(np.float64)

    prim = tree["meshes"][0]["primitives"][0]
    attrs = prim["attributes"]
    uvs = accessor(attrs["TEXCOORD_0"])
    uvs[:, 1] = 1.0 - uvs[:, 1]
    material = tree["materials"][prim["material"]]
    normal_map = None
    if "normalTexture" in material:
        image = tree["images"][tree["textures"][material["normalTexture"]["index"]]["source"]]
        normal_map = np.asarray(Image.open(io.BytesIO(view_bytes(image["bufferView"]))).convert("RGB"),
                                np.float64) / 255.0
    return {"verts": accessor(attrs["POSITION"]), "faces": accessor(prim["indices"]).astype(np.int64).reshape(-1, 3),
            "uvs": uvs, "normals": accessor(attrs["NORMAL"]),
            "tangents": accessor(attrs["TANGENT"]) if "TANGENT" in attrs else None, "normal_map": normal_map}


def shaded_normals(glb: dict, caster: MeshCaster, origins: np.ndarray, dirs: np.ndarray, mapped: bool):
    """(ray index, hit depth, unit shading normal) of each ray that meets the GLB's mesh: the interpolated vertex
    normal, bent by the normal map (``mapped``) in the glTF tangent frame."""
    import trimesh

    ray, face, loc = caster.first_hits(origins, dirs)
    tri = glb["verts"][glb["faces"][face]]
    bary = trimesh.triangles.points_to_barycentric(tri, loc)
    if mapped and glb["normal_map"] is not None:
        frames = texel_frames(glb["faces"], face, bary, glb["normals"], glb["tangents"])
        uv = (glb["uvs"][glb["faces"][face]] * bary[..., None]).sum(1)
        normals = shading_normals(frames, decode_normals(sample_uv(glb["normal_map"], uv)))
    else:
        normals = (glb["normals"][glb["faces"][face]] * bary[..., None]).sum(1)
        normals /= np.linalg.norm(normals, axis=1, keepdims=True).clip(1e-12)
    depth = ((loc - origins[ray]) * dirs[ray]).sum(1)
    return ray, depth, normals


def level_folders(ws: Path) -> dict[str, Path]:
    """The default mesh's folder and each detail level's, by name."""
    out = {"default": ws / "mesh"}
    for folder in sorted((ws / "mesh" / "levels").glob("*")):
        if (folder / "textured.glb").exists():
            out[folder.name] = folder
    return out


def normal_errors(levels: dict[str, dict], truth, cams, size: tuple[int, int], views: list[int],
                  scale: float) -> dict:
    """Per level (``levels``: :func:`read_glb` by name), the mean angle (degrees) between the reference normal and
    the shaded normal, without and with the normal map, at ``views`` of ``cams`` (``size``: (width, height)); the
    reference ``truth``: (trimesh mesh, function (face, barycentrics) → unit normals); pixels count where both
    meet the ray within 1 % of ``scale`` of each other."""
    import trimesh

    mesh, reference = truth
    ref_caster = MeshCaster(mesh)
    casters = {name: MeshCaster(trimesh.Trimesh(g["verts"], g["faces"], process=False)) for name, g in levels.items()}
    sums, counts = {name: np.zeros(2) for name in levels}, dict.fromkeys(levels, 0)
    for i in views:
        o, d = pixel_center_rays(cams.K[i], cams.R[i], cams.sfm_centers[i], *size)
        ray_t, face_t, loc_t = ref_caster.first_hits(o, d)
        true_n = np.full((len(d), 3), np.nan)
        true_n[ray_t] = reference(face_t, trimesh.triangles.points_to_barycentric(mesh.triangles[face_t], loc_t))
        true_d = np.full(len(d), np.nan)
        true_d[ray_t] = ((loc_t - o[ray_t]) * d[ray_t]).sum(1)
        for name, glb in levels.items():
            for k, mapped in enumerate((False, True)):
                ray, depth, n = shaded_normals(glb, casters[name], o, d, mapped)
                same = np.abs(depth - true_d[ray]) < 0.01 * scale  # NaN (the reference missed) compares False
                cos = (n[same] * true_n[ray[same]]).sum(1).clip(-1, 1)
                sums[name][k] += np.degrees(np.arccos(cos)).sum()
                counts[name] += int(same.sum()) if k == 0 else 0
    return {name: {"faces": len(levels[name]["faces"]), "pixels": counts[name],
                   "without_map_deg": float(sums[name][0] / max(counts[name], 1)),
                   "with_map_deg": float(sums[name][1] / max(counts[name], 1))} for name in levels}


def against_truth(ws: Path, scene: Path, views: int) -> dict:
    """:func:`normal_errors` of every level of ``ws`` against a synthetic ``scene``'s true mesh (its faces'
    normals) at ``views`` of its held-out cameras."""
    import trimesh
    from PIL import Image

    gt = trimesh.load(scene / "gt" / "mesh.ply", process=False)
    cams = load_cameras(scene / "gt" / "heldout" / "cameras.npz")
    size = Image.open(sorted((scene / "images").glob("*.png"))[0]).size
    picks = np.linspace(0, len(cams) - 1, min(views, len(cams))).round().astype(int).tolist()
    levels = {name: read_glb(folder / "textured.glb") for name, folder in level_folders(ws).items()}
    return normal_errors(levels, (gt, lambda face, bary: gt.face_normals[face]), cams, size, picks,
                         float(np.linalg.norm(np.ptp(gt.vertices, axis=0))))


def against_level(ws: Path, reference: str, views: int) -> dict:
    """:func:`normal_errors` of every other level of ``ws`` against level ``reference``'s shading without its map
    (its interpolated vertex normals) at ``views`` of the workspace's cameras: how far a lighter level's shading is
    from the heavier one's."""
    import trimesh
    from PIL import Image

    from dvr.data import list_images

    folders = level_folders(ws)
    ref = read_glb(folders[reference] / "textured.glb")
    mesh = trimesh.Trimesh(ref["verts"], ref["faces"], process=False)

    def smooth(face, bary):
        n = (ref["normals"][ref["faces"][face]] * bary[..., None]).sum(1)
        return n / np.linalg.norm(n, axis=1, keepdims=True).clip(1e-12)

    photos = list_images(ws / "images")
    cams = load_cameras(ws / "cameras.npz", n_views=len(photos))
    picks = np.linspace(0, len(cams) - 1, min(views, len(cams))).round().astype(int).tolist()
    levels = {name: read_glb(folder / "textured.glb") for name, folder in folders.items() if name != reference}
    return normal_errors(levels, (mesh, smooth), cams, Image.open(photos[0]).size, picks,
                         float(np.linalg.norm(np.ptp(ref["verts"], axis=0))))


def side_lit(ws: Path, out: Path, view: int) -> list[Path]:
    """Each level at camera ``view`` of the workspace, Lambert-shaded under a light from the camera's right (and a
    little from the front), without (left) and with (right) its normal map → ``out/<level>.png``."""
    import trimesh
    from PIL import Image

    from dvr.data import list_images

    cams = load_cameras(ws / "cameras.npz")
    w, h = Image.open(list_images(ws / "images")[view]).size
    o, d = pixel_center_rays(cams.K[view], cams.R[view], cams.sfm_centers[view], w, h)
    light = cams.R[view].T @ np.array([0.8, 0.0, -0.6])  # the camera's right and towards it (camera z looks away)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for name, folder in level_folders(ws).items():
        glb = read_glb(folder / "textured.glb")
        caster = MeshCaster(trimesh.Trimesh(glb["verts"], glb["faces"], process=False))
        halves = []
        for mapped in (False, True):
            ray, _, n = shaded_normals(glb, caster, o, d, mapped)
            img = np.zeros(len(d))
            img[ray] = 0.08 + 0.92 * (n @ light).clip(0, 1)
            halves.append((img.reshape(h, w) * 255).round().astype(np.uint8))
        path = out / f"{name}.png"
        Image.fromarray(np.concatenate(halves, axis=1)).save(path)
        written.append(path)
    return written


def stacked(paths: list[Path], out: Path) -> Path:
    """The pictures ``paths`` one above the other → ``out``."""
    from PIL import Image

    images = [Image.open(p) for p in paths]
    sheet = Image.new("L", (max(i.width for i in images), sum(i.height for i in images)))
    y = 0
    for image in images:
        sheet.paste(image, (0, y))
        y += image.height
    sheet.save(out)
    return out


def sphere_pages(out: Path) -> list[Path]:
    """An 80-face icosphere shaded flat (its faces' normals), with and without the normal map of the true sphere,
    as GLBs inside model-viewer pages (``out/sphere_{flat,mapped}.html``) for ``bench/glb_shot.mjs``: a viewer's own
    check of the map's tangent convention (a wrong one leaves facets or lights them from the wrong side)."""
    import torch
    import trimesh

    from pipeline.report.stage import inlined_viewer
    from pipeline.texture.atlas import make_atlas, rasterize_atlas
    from pipeline.texture.export import export_textured
    from pipeline.texture.surface_maps import SurfaceField, bake_surface_maps

    ico = trimesh.creation.icosphere(1, 0.5)
    verts, faces = ico.vertices[ico.faces].reshape(-1, 3), np.arange(3 * len(ico.faces)).reshape(-1, 3)
    vmap, nf, uvs, side = make_atlas(verts, faces, 300.0, 4, 512)
    normals = np.repeat(ico.face_normals, 3, axis=0)[vmap]
    field = SurfaceField(lambda p: 40.0 * (0.5 - torch.linalg.norm(p, dim=1)), 2.0 / 96)
    maps = bake_surface_maps(field, verts[vmap], nf, uvs, normals, rasterize_atlas(uvs, nf, side), True, 0.0, 8)
    pages = []
    for name, with_maps in (("flat", None), ("mapped", maps)):
        folder = out / f"sphere_{name}"
        folder.mkdir(parents=True, exist_ok=True)
        export_textured(folder, verts[vmap], nf, uvs, np.full((side, side, 3), 0.7, np.float32), None, normals,
                        with_maps)
        js, src = inlined_viewer(folder / "textured.glb")
        page = out / f"sphere_{name}.html"
        page.write_text(f'<html><body style="margin:0"><script type="module">{js}</script><model-viewer src="{src}" '
                        'camera-orbit="20deg 60deg 2m" environment-image="legacy" '
                        'style="width:500px;height:500px;background:#fff"></model-viewer></body></html>')
        pages.append(page)
    return pages


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("ws", type=Path, nargs="?")
    ap.add_argument("--truth", type=Path, help="the synthetic scene's folder (gt/mesh.ply, gt/heldout/)")
    ap.add_argument("--against", help="compare the other levels with this level's shading (no ground truth)")
    ap.add_argument("--views", type=int, default=8, help="held-out views measured (spread over all)")
    ap.add_argument("--pictures", type=Path, help="write side-lit pictures of every level here")
    ap.add_argument("--view", type=int, default=0, help="the workspace's photo the pictures are taken from")
    ap.add_argument("--sphere", type=Path, help="write model-viewer pages of a flat-shaded sphere with its map here")
    args = ap.parse_args(argv)
    rows = against_truth(args.ws, args.truth, args.views) if args.truth else \
        against_level(args.ws, args.against, args.views) if args.against else None
    if rows:
        print(f"{'level':10s} {'faces':>8s} {'pixels':>8s} {'without map °':>14s} {'with map °':>11s}")
        for name, r in rows.items():
            print(f"{name:10s} {r['faces']:8d} {r['pixels']:8d} {r['without_map_deg']:14.2f} {r['with_map_deg']:11.2f}")
        print(json.dumps(rows))
    if args.pictures:
        paths = side_lit(args.ws, args.pictures, args.view)
        faces = {p: len(read_glb(level_folders(args.ws)[p.stem] / "textured.glb")["faces"]) for p in paths}
        print(stacked(sorted(paths, key=faces.get), args.pictures / "levels.png"), "(lightest level on top)")
    if args.sphere:
        for page in sphere_pages(args.sphere):
            print(f"node --experimental-websocket bench/glb_shot.mjs {page} {page.with_suffix('.png')} 500 500")


if __name__ == "__main__":
    main()
