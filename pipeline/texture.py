"""Stage ``texture``: UV atlas + texture baked from the PHOTOS → ``mesh/textured.{obj,mtl,png,glb}``.

1. xatlas charts the clean mesh; every face is rasterised into the atlas (OpenCV polygon fill with
   sub-texel precision, one call per face — no per-texel loop over faces), giving each texel its face,
   barycentrics, 3-D point and normal.
2. Every view renders a depth map of the mesh by ray casting (trimesh, Embree when installed); a texel is
   visible in a view when its projection's depth agrees with that map.
3. Colour = weighted mean of the visible views' bilinear samples, weight = cos(angle)^p / distance² × a
   feather towards the image border; the weights are sharpened so the best views dominate. Colours come from
   3-D points, so texels on both sides of a UV seam (same 3-D point) get the same colour: seams match.
4. Texels no photo sees take the trained texture field's colour; a gutter is dilated around every chart so
   mip-maps do not bleed background into the surface.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import cv2
import numpy as np
import torch
import trimesh
import xatlas

from dvr.cameras import load_cameras
from dvr.data import list_images
from dvr.device import resolve_device
from dvr.trainer import load_model

from .cameras_config import TextureConfig
from .config import config_hash
from .raycast import mesh_intersector, pixel_center_rays
from .workspace import StageError, Workspace


def make_atlas(verts: np.ndarray, faces: np.ndarray, size: int, padding: int):
    """xatlas: (vmapping, faces into the new vertices, uvs in [0, 1])."""
    atlas = xatlas.Atlas()
    atlas.add_mesh(verts.astype(np.float32), faces.astype(np.uint32))
    po = xatlas.PackOptions()
    po.resolution = size
    po.padding = padding
    po.bilinear = True
    co = xatlas.ChartOptions()
    co.max_iterations = 1  # 2-4× faster than the default 4; charts are slightly less round
    # charts grow in superlinear time on large flat regions (a 40 k-face book: 41 s); bounding their boundary
    # length to half the surface's scale takes 1-2 s, for ~20 % less atlas utilisation
    co.max_boundary_length = 0.5 * float(np.sqrt(trimesh.Trimesh(verts, faces, process=False).area))
    atlas.generate(co, po)
    vmap, idx, uvs = atlas[0]
    return vmap, idx.astype(np.int64), uvs.astype(np.float64)


def rasterize_atlas(uvs: np.ndarray, faces: np.ndarray, size: int) -> np.ndarray:
    """(size, size) int32 face index per texel (−1: empty). Row 0 is v = 1 (image convention)."""
    shift = 4
    scale = float(1 << shift)
    xy = np.stack([uvs[:, 0] * size - 0.5, (1.0 - uvs[:, 1]) * size - 0.5], 1)
    tri = np.round(xy[faces] * scale).astype(np.int32)  # (F, 3, 2) fixed point
    ids = np.full((size, size, 3), 255, np.uint8)
    for f in range(len(faces)):
        c = ((f >> 16) & 255, (f >> 8) & 255, f & 255)
        cv2.fillConvexPoly(ids, tri[f], c, lineType=cv2.LINE_8, shift=shift)
    fid = (ids[..., 0].astype(np.int64) << 16) | (ids[..., 1].astype(np.int64) << 8) | ids[..., 2]
    fid[fid == 0xFFFFFF] = -1
    return fid.astype(np.int32)


def texel_geometry(fid: np.ndarray, uvs: np.ndarray, faces: np.ndarray, verts: np.ndarray, normals: np.ndarray):
    """Texel rows/cols, their 3-D points and (interpolated) normals."""
    size = fid.shape[0]
    r, c = np.nonzero(fid >= 0)
    f = fid[r, c]
    p = np.stack([(c + 0.5) / size, 1.0 - (r + 0.5) / size], 1)
    a, b, d = uvs[faces[f, 0]], uvs[faces[f, 1]], uvs[faces[f, 2]]
    v0, v1, v2 = b - a, d - a, p - a
    den = v0[:, 0] * v1[:, 1] - v1[:, 0] * v0[:, 1]
    den = np.where(np.abs(den) < 1e-20, 1e-20, den)
    w1 = (v2[:, 0] * v1[:, 1] - v1[:, 0] * v2[:, 1]) / den
    w2 = (v0[:, 0] * v2[:, 1] - v2[:, 0] * v0[:, 1]) / den
    bary = np.clip(np.stack([1 - w1 - w2, w1, w2], 1), 0, 1)
    bary /= bary.sum(1, keepdims=True)
    pts = (verts[faces[f]] * bary[:, :, None]).sum(1)
    nrm = (normals[faces[f]] * bary[:, :, None]).sum(1)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True).clip(1e-12)
    return r, c, pts, nrm


def depth_maps(mesh: trimesh.Trimesh, cams, sizes: list[tuple[int, int]]) -> list[np.ndarray]:
    """Per view, the ray depth of the first mesh hit at every pixel centre (inf where none)."""
    inter = mesh_intersector(mesh)
    out = []
    for i, (w, h) in enumerate(sizes):
        o, d = pixel_center_rays(cams.K[i], cams.R[i], cams.centers[i], w, h)
        loc, ir, _ = inter.intersects_location(o, d, multiple_hits=False)
        dep = np.full(len(d), np.inf)
        if len(ir):
            dist = np.linalg.norm(loc - o[ir], axis=1)
            np.minimum.at(dep, ir, dist)
        out.append(dep.reshape(h, w))
    return out


def depth_edges(depth: np.ndarray, tol: float, px: int) -> np.ndarray:
    """Pixels within ``px`` of a depth discontinuity (> 10 × tol) or of the silhouette."""
    d = np.where(np.isfinite(depth), depth, 1e6).astype(np.float32)
    k = np.ones((3, 3), np.uint8)
    jump = (cv2.dilate(d, k) - cv2.erode(d, k)) > 10 * tol
    if px > 0:
        jump = cv2.dilate(jump.astype(np.uint8), np.ones((2 * px + 1,) * 2, np.uint8)) > 0
    return jump


def sample_bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear lookup at continuous (x, y) where integer coordinates are pixel centres (edges clamped)."""
    h, w = img.shape[:2]
    x = x.clip(0, w - 1)
    y = y.clip(0, h - 1)
    x0, y0 = np.floor(x).astype(int).clip(0, w - 2), np.floor(y).astype(int).clip(0, h - 2)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    return ((img[y0, x0] * (1 - fx) + img[y0, x0 + 1] * fx) * (1 - fy)
            + (img[y0 + 1, x0] * (1 - fx) + img[y0 + 1, x0 + 1] * fx) * fy)


def sample_visible(img: np.ndarray, depth: np.ndarray, edges: np.ndarray, x: np.ndarray, y: np.ndarray,
                   dist: np.ndarray, tol: np.ndarray):
    """Depth-aware bilinear lookup at continuous (x, y) (integer = pixel centre).

    Of the four pixels around (x, y), only those whose rendered depth agrees with the texel's depth ``dist``
    (within ``tol``) contribute: a pixel of an occluder, or of the background beside a silhouette, never
    mixes in. Returns colours (M, C), the support (sum of the bilinear weights used; 0 = not visible) and
    whether an edge pixel was used.
    """
    h, w = depth.shape
    x0 = np.floor(x).astype(int).clip(0, w - 2)
    y0 = np.floor(y).astype(int).clip(0, h - 2)
    fx, fy = (x - x0).clip(0, 1), (y - y0).clip(0, 1)
    col = np.zeros((len(x), img.shape[2]))
    sup = np.zeros(len(x))
    edge = np.zeros(len(x), bool)
    for dy, dx, wt in ((0, 0, (1 - fx) * (1 - fy)), (0, 1, fx * (1 - fy)), (1, 0, (1 - fx) * fy), (1, 1, fx * fy)):
        yy, xx = y0 + dy, x0 + dx
        ok = np.abs(depth[yy, xx] - dist) < tol  # inf (no surface there) never agrees
        wk = np.where(ok, wt, 0.0)
        col += wk[:, None] * img[yy, xx]
        sup += wk
        edge |= ok & (wt > 0) & edges[yy, xx]
    col /= np.maximum(sup, 1e-12)[:, None]
    return col, sup, edge


def bake(pts: np.ndarray, nrm: np.ndarray, images: list[np.ndarray], cams, depths: list[np.ndarray],
         cfg: TextureConfig) -> tuple[np.ndarray, np.ndarray]:
    """Colours (M, 3) in [0, 1] and total weights (M,) of texel points seen by the photos.

    Per view: texels in front of the camera, inside the image and facing it (cos > ``min_cos``) are sampled
    with :func:`sample_visible` (the depth test against the ray-cast depth map, with a tolerance that grows
    with the pixel footprint on slanted surfaces). Weight = cos^p / distance² × a feather towards the image
    border × the support; samples that touch a depth discontinuity or silhouette (where real photos blend
    foreground and background) are down-weighted by ``edge_weight``, so they only count where nothing better
    sees the texel.
    """
    acc = np.zeros((len(pts), 3))
    wsum = np.zeros(len(pts))
    edges = [depth_edges(d, cfg.depth_tolerance, cfg.edge_px) for d in depths]
    for i, img in enumerate(images):
        h, w = img.shape[:2]
        c = cams.centers[i]
        x = (cams.P[i] @ np.concatenate([pts, np.ones((len(pts), 1))], 1).T).T
        z = x[:, 2]
        front = z > 1e-9
        uv = np.where(front[:, None], x[:, :2] / np.where(front, z, 1.0)[:, None], -1.0)
        inside = front & (uv[:, 0] >= 0.5) & (uv[:, 0] <= w - 0.5) & (uv[:, 1] >= 0.5) & (uv[:, 1] <= h - 0.5)
        view = c - pts
        dist = np.linalg.norm(view, axis=1)
        cos = (nrm * view).sum(1) / dist.clip(1e-12)
        ok = inside & (cos > cfg.min_cos)
        if not ok.any():
            continue
        idx = np.nonzero(ok)[0]
        # depth change across one pixel on a surface tilted by θ: (dist / f) · tan θ
        cs = cos[idx]
        tol = cfg.depth_tolerance + 1.5 * dist[idx] / cams.K[i][0, 0] * np.sqrt(1 - cs ** 2) / cs
        col, sup, edge = sample_visible(img, depths[i], edges[i], uv[idx, 0] - 0.5, uv[idx, 1] - 0.5, dist[idx], tol)
        keep = sup > 0.05
        idx, col, sup, edge, cs = idx[keep], col[keep], sup[keep], edge[keep], cs[keep]
        if not len(idx):
            continue
        border = np.minimum.reduce([uv[idx, 0], w - uv[idx, 0], uv[idx, 1], h - uv[idx, 1]])
        feather = np.clip(border / (0.05 * max(w, h)), 0.05, 1.0)
        wt = cs ** cfg.angle_power / dist[idx] ** 2 * feather * sup * np.where(edge, cfg.edge_weight, 1.0)
        acc[idx] += wt[:, None] * col
        wsum[idx] += wt
    seen = wsum > 0
    acc[seen] /= wsum[seen, None]
    return acc, wsum


def dilate_gutter(tex: np.ndarray, valid: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Grow colours ``n`` texels outwards from valid texels (mean of valid neighbours)."""
    tex = tex.copy()
    valid = valid.copy()
    k = np.ones((3, 3), np.float32)
    for _ in range(n):
        m = valid.astype(np.float32)
        s = cv2.filter2D(tex * m[..., None], -1, k, borderType=cv2.BORDER_CONSTANT)
        cnt = cv2.filter2D(m, -1, k, borderType=cv2.BORDER_CONSTANT)
        grow = (~valid) & (cnt > 0)
        if not grow.any():
            break
        tex[grow] = s[grow] / cnt[grow, None]
        valid |= grow
    return tex, valid


def fill_unseen(pts: np.ndarray, col: np.ndarray, unseen: np.ndarray, field=None,
                field_frame: np.ndarray | None = None) -> np.ndarray:
    """Colours of the texels no photo sees: the trained texture field's when there is one (``field_frame``:
    4×4 map of the field's frame to the frame of ``pts``), else the colour of the nearest seen texel in 3-D
    (never black)."""
    if field is not None:
        dev = next(field.parameters()).device
        q = pts[unseen]
        if field_frame is not None:
            inv = np.linalg.inv(field_frame)
            q = q @ inv[:3, :3].T + inv[:3, 3]
        with torch.no_grad():
            q = torch.from_numpy(q).float().to(dev)
            return torch.cat([field.texture(q[s : s + 65536]) for s in range(0, len(q), 65536)]).cpu().numpy()
    if unseen.all():
        return np.full((int(unseen.sum()), 3), 0.5)
    from scipy.spatial import cKDTree

    _, nn = cKDTree(pts[~unseen]).query(pts[unseen], k=1)
    return col[~unseen][nn]


def photo_texel_density(mesh: trimesh.Trimesh, cams, sizes: list[tuple[int, int]], min_cos: float = 0.3) -> float:
    """Photo pixels per unit length on the surface where the photos see it best: per face, the largest
    focal / distance over the views that see it from the front (cos > ``min_cos``) inside the image; the
    area-weighted median over faces (0 when no view sees any face)."""
    cen, nrm, area = mesh.triangles_center, mesh.face_normals, mesh.area_faces
    best = np.zeros(len(cen))
    hom = np.concatenate([cen, np.ones((len(cen), 1))], 1)
    for i, (w, h) in enumerate(sizes):
        view = cams.centers[i] - cen
        dist = np.linalg.norm(view, axis=1).clip(1e-12)
        x = hom @ cams.P[i].T
        z = np.where(np.abs(x[:, 2]) < 1e-12, 1e-12, x[:, 2])
        u, v = x[:, 0] / z, x[:, 1] / z
        ok = (x[:, 2] > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h) & ((nrm * view).sum(1) / dist > min_cos)
        best = np.maximum(best, np.where(ok, cams.K[i][0, 0] / dist, 0.0))
    seen = best > 0
    if not seen.any():
        return 0.0
    order = np.argsort(best[seen])
    cum = np.cumsum(area[seen][order])
    return float(best[seen][order][np.searchsorted(cum, 0.5 * cum[-1])])


def atlas_size(mesh: trimesh.Trimesh, cams, sizes: list[tuple[int, int]], cfg: TextureConfig,
               utilisation: float = 0.6) -> int:
    """Side of the texture: about ``cfg.texel_density`` texels per photo pixel on the object (the surface area at
    :func:`photo_texel_density`, over xatlas' typical utilisation), a multiple of 128 in [256, ``cfg.size``];
    ``cfg.size`` when ``texel_density`` is 0."""
    if cfg.texel_density <= 0:
        return cfg.size
    tpu = cfg.texel_density * photo_texel_density(mesh, cams, sizes)
    side = np.sqrt(mesh.area * tpu * tpu / utilisation)
    return int(min(cfg.size, max(256, 128 * np.ceil(side / 128))))


def texture_mesh(verts_n: np.ndarray, faces: np.ndarray, images: list[np.ndarray], cams, cfg: TextureConfig,
                 field=None, field_frame: np.ndarray | None = None):
    """Normalized-frame mesh → (new verts, new faces, uvs, texture (side, side, 3) float, stats); the side follows
    the photos' resolution on the object (:func:`atlas_size`)."""
    base = trimesh.Trimesh(verts_n, faces, process=False)
    sizes = [(im.shape[1], im.shape[0]) for im in images]
    side = atlas_size(base, cams, sizes, cfg)
    vmap, nf, uvs = make_atlas(verts_n, faces, side, cfg.padding)
    nv = verts_n[vmap]
    normals = base.vertex_normals[vmap]
    fid = rasterize_atlas(uvs, nf, side)
    r, c, pts, nrm = texel_geometry(fid, uvs, nf, nv, normals)
    deps = depth_maps(base, cams, sizes)
    col, wsum = bake(pts, nrm, images, cams, deps, cfg)
    unseen = wsum <= 0
    if unseen.any():
        col[unseen] = fill_unseen(pts, col, unseen, field, field_frame)
    tex = np.zeros((side, side, 3), np.float32)
    tex[r, c] = col
    valid = fid >= 0
    tex, filled = dilate_gutter(tex, valid, cfg.gutter)
    covered_faces = np.unique(fid[valid])
    stats = {"size": side, "texels": int(valid.sum()), "unseen_frac": float(unseen.mean()) if len(unseen) else 0.0,
             "faces": int(len(nf)), "faces_with_texels": int(len(covered_faces)), "filled": filled}
    return nv, nf, uvs, tex, stats


def render_textured(verts: np.ndarray, faces: np.ndarray, uvs: np.ndarray, tex: np.ndarray, K: np.ndarray,
                    R: np.ndarray, center: np.ndarray, w: int, h: int) -> tuple[np.ndarray, np.ndarray]:
    """Ray-cast a UV-textured mesh (same frame as the camera): image (h, w, 3) and hit mask (h, w)."""
    mesh = trimesh.Trimesh(verts, faces, process=False)
    o, d = pixel_center_rays(K, R, center, w, h)
    loc, ir, it = mesh_intersector(mesh).intersects_location(o, d, multiple_hits=False)
    img = np.zeros((h * w, 3))
    hit = np.zeros(h * w, bool)
    if len(ir):
        bary = trimesh.triangles.points_to_barycentric(mesh.triangles[it], loc)
        uv = (uvs[faces[it]] * bary[:, :, None]).sum(1)
        S = tex.shape[0]
        img[ir] = sample_bilinear(tex, uv[:, 0] * S - 0.5, (1 - uv[:, 1]) * S - 0.5)
        hit[ir] = True
    return img.reshape(h, w, 3), hit.reshape(h, w)


def export_textured(out_dir: Path, verts: np.ndarray, faces: np.ndarray, uvs: np.ndarray, tex: np.ndarray) -> None:
    from PIL import Image

    img = Image.fromarray((tex.clip(0, 1) * 255).round().astype(np.uint8))
    mat = trimesh.visual.material.PBRMaterial(baseColorTexture=img, metallicFactor=0.0, roughnessFactor=1.0)
    mesh = trimesh.Trimesh(verts, faces, visual=trimesh.visual.TextureVisuals(uv=uvs, material=mat), process=False)
    mesh.export(out_dir / "textured.glb")
    simple = trimesh.visual.material.SimpleMaterial(image=img, name="textured", diffuse=(255, 255, 255, 255),
                                                    ambient=(255, 255, 255, 255), specular=(0, 0, 0, 255))
    mesh_obj = trimesh.Trimesh(verts, faces, visual=trimesh.visual.TextureVisuals(uv=uvs, material=simple),
                               process=False)
    text, files = trimesh.exchange.obj.export_obj(mesh_obj, include_texture=True, return_texture=True,
                                                  mtl_name="textured.mtl")
    for name, data in files.items():  # the MTL and its texture, renamed to the contract's textured.png
        if name.endswith(".mtl"):
            mtl = data.decode()
            for other in files:
                if not other.endswith(".mtl"):
                    mtl = mtl.replace(other, "textured.png")
            (out_dir / "textured.mtl").write_text(mtl)
    (out_dir / "textured.obj").write_text(text)
    img.save(out_dir / "textured.png")


def undo_appearance(images: list[np.ndarray], names: list[str], looks: dict) -> list[np.ndarray]:
    """Each photo mapped back to the shared colour of the texture field: ``photo / gain`` with the view's
    fitted transform (``model/appearance.json``), so views of different exposure agree before they are blended."""
    out = []
    for img, name in zip(images, names):
        t = looks.get(name)
        if t is None:
            out.append(img)
            continue
        out.append(np.clip(img / np.maximum(np.asarray(t["gain"], np.float32), 1e-3), 0.0, 1.0))
    return out


def run(ws: Workspace, cfg: TextureConfig, force: bool = False) -> bool:
    clean = ws.mesh / "clean.ply"
    final = ws.model / "final.pt"
    ws.require(clean, hint="run the mesh stage first")
    ws.require(ws.images, ws.cameras, hint="run the cameras stage first")
    h = config_hash(cfg)
    outs = [ws.mesh / f"textured.{e}" for e in ("obj", "mtl", "png", "glb")]
    looks = ws.model / "appearance.json"  # per-view exposure and white balance fitted in training
    ins = [clean, ws.images, ws.cameras] + [p for p in (final, looks) if p.exists()]
    if not force and ws.up_to_date("texture", h, ins, outs):
        print(f"texture: up to date ({outs[-1]})")
        return False
    ws.clear("texture")
    t0 = time.perf_counter()
    paths = list_images(ws.images)
    cams = load_cameras(ws.cameras, n_views=len(paths))
    S = cams.scale_mat
    m = trimesh.load(clean, process=False)
    if len(m.faces) == 0:
        raise StageError(f"{clean}: empty mesh; retrain (train --force) or check the masks")
    try:
        mesh_frame = json.loads((ws.stages / "mesh.json").read_text()).get("frame", "sfm")
    except (OSError, ValueError):
        mesh_frame = "sfm"
    verts_n = np.asarray(m.vertices, np.float64)
    if mesh_frame == "sfm":
        verts_n = (verts_n - S[:3, 3]) @ np.linalg.inv(S[:3, :3]).T
    images = [cv2.cvtColor(cv2.imread(str(p), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0
              for p in paths]
    if looks.exists():
        images = undo_appearance(images, [p.stem for p in paths], json.loads(looks.read_text()))
    field, _, field_frame = load_model(final, resolve_device(cfg.device)) if final.exists() else (None, None, None)
    nv, nf, uvs, tex, stats = texture_mesh(verts_n, np.asarray(m.faces), images, cams, cfg, field, field_frame)
    out_v = nv @ S[:3, :3].T + S[:3, 3] if cfg.frame == "sfm" else nv
    export_textured(ws.mesh, out_v, nf, uvs, tex)
    stats.pop("filled")
    ws.mark_done("texture", h, time.perf_counter() - t0, stats)
    print(f"texture: {tex.shape[0]}² atlas, {100 * (1 - stats['unseen_frac']):.1f} % of texels from photos → "
          f"{ws.mesh / 'textured.glb'}")
    return True
