"""A prototype outside the pipeline (README, "What holds DTU's texture"): photometric refinement of DTU's clean mesh
-- per-vertex offsets along the normal, fitted so that 5x5 patches of each training view agree (ZNCC) with their
reprojection through the mesh into one of its 4 nearest views; photos blurred coarse to fine, one blur per round,
the hits ray-cast again each round; a Laplacian smoothness on the offsets -- then the texture stage again and DTU's
held-out and training-view PSNR (bench/evaluate.py run_dtu's protocol):

    python bench/dtu_arm.py                                   # leaves its workspace in bench/runs/work/dtu_arm/ws
    python bench/refine_probe.py '{"rounds": 3, "iters": 400}'  # a copy refined in bench/runs/work/refine_probe
    python bench/refine_probe.py '{"rounds": 0}'                # the same copy unrefined: the dtu_arm figures
"""
from __future__ import annotations

import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
import trimesh

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import evaluate as ev  # noqa: E402
from dvr.cameras import load_cameras, to_normalized, to_sfm  # noqa: E402
from dvr.data import list_images  # noqa: E402
from pipeline.render.raycast import mesh_intersector, pixel_center_rays  # noqa: E402
from pipeline.texture.appearance import photos_for_bake  # noqa: E402
from pipeline.texture.config import TextureConfig  # noqa: E402
from pipeline.texture.stage import depth_maps  # noqa: E402


def neighbours(cams, k):
    """(V, k): each view's k nearest views by the angle of their centres about the sphere's centre."""
    c = cams.centers
    d = c / np.linalg.norm(c, axis=1, keepdims=True)
    cos = d @ d.T
    np.fill_diagonal(cos, -2)
    return np.argsort(-cos, axis=1)[:, :k]


def blur(img, sigma):
    """``img`` under a Gaussian blur of ``sigma`` pixels (none at 0)."""
    import cv2

    if sigma <= 0:
        return img
    return cv2.GaussianBlur(img, (0, 0), sigma)


def sample(imgs_t, view, x, y):
    """Bilinear samples (N, C) of the images (V, C, H, W) at pixel positions x, y (pixel centres at j + 0.5, as
    grid_sample's align_corners=False places them) of each sample's ``view``."""
    out = torch.zeros(len(x), imgs_t.shape[1], dtype=x.dtype)
    _, _, H, W = imgs_t.shape
    for v in torch.unique(view).tolist():
        m = view == v
        g = torch.stack([2 * x[m] / W - 1, 2 * y[m] / H - 1], -1)[None, None]
        out[m] = F.grid_sample(imgs_t[v:v + 1], g, align_corners=False, padding_mode="border")[0, :, 0].T
    return out


def hit_pixels(mesh, masks, cams, half: int):
    """Per view, the mask's pixels (a patch's half-width from the border) whose centre's ray meets ``mesh``: their
    views, pixel centres (x + 0.5, y + 0.5) and hit faces, concatenated over the views."""
    inter = mesh_intersector(mesh)
    views, xy, hit = [], [], []
    for i, mask in enumerate(masks):
        H, W = mask.shape
        ys, xs = np.nonzero(mask[half:-half, half:-half])
        ys, xs = ys + half, xs + half
        o, d = pixel_center_rays(cams.K[i], cams.R[i], cams.centers[i], W, H)
        tri = inter.intersects_first(o[ys * W + xs], d[ys * W + xs])
        ok = tri >= 0
        views.append(np.full(ok.sum(), i))
        xy.append(np.stack([xs[ok], ys[ok]], 1) + 0.5)
        hit.append(tri[ok])
    return (torch.as_tensor(np.concatenate(views)), torch.as_tensor(np.concatenate(xy)),
            torch.as_tensor(np.concatenate(hit)))


def on_face_planes(tri, xy, K, R, t):
    """(B, P, 3): where the rays through the pixels ``xy`` (B, P, 2) of cameras (K, R, t) (B, …) meet the planes of
    the triangles ``tri`` (B, 3, 3): differentiable in the corners, each point moving along its own ray."""
    n = torch.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=1)
    hom = torch.cat([xy, torch.ones_like(xy[..., :1])], -1)
    dirs = hom @ torch.linalg.inv(K).transpose(1, 2) @ R  # world directions R^T K^-1 x
    c = -(R.transpose(1, 2) @ t[:, :, None])[:, :, 0]
    den = (dirs * n[:, None]).sum(-1)
    depth = ((tri[:, 0] - c) * n).sum(-1, keepdim=True) / torch.where(den.abs() < 1e-12, 1e-12, den)
    return c[:, None] + depth[..., None] * dirs


def seen_at(X, K, R, t, depths, view, W: int, H: int):
    """Pixel x, y (B, P) of the points ``X`` in cameras (K, R, t) (B, …), and whether each patch's centre is seen
    there (in the frame, in front, within 1 % of the mesh's depth in ``depths`` (V, H, W) of its ``view``)."""
    Xc = X @ R.transpose(1, 2) + t[:, None]
    z = Xc[..., 2]
    pix = Xc @ K.transpose(1, 2)
    x, y = pix[..., 0] / z.clamp(min=1e-6), pix[..., 1] / z.clamp(min=1e-6)
    with torch.no_grad():
        mid = X.shape[1] // 2
        cx, cy = x[:, mid], y[:, mid]
        inside = (cx > 1) & (cx < W - 1) & (cy > 1) & (cy < H - 1) & (z[:, mid] > 0)
        col, row = cx.long().clamp(0, W - 1), cy.long().clamp(0, H - 1)
        dist = (X[:, mid] + (R.transpose(1, 2) @ t[:, :, None])[:, :, 0]).norm(dim=-1)
        mesh_depth = depths[view, row, col]
        seen = inside & ((dist - mesh_depth).abs() < 0.01 * dist)
    return x, y, seen


def zncc(a, b):
    """Zero-mean normalised cross-correlation of grey patches (B, P) and whether ``a`` has texture."""
    a0, b0 = a - a.mean(1, keepdim=True), b - b.mean(1, keepdim=True)
    va, vb = (a0 ** 2).mean(1), (b0 ** 2).mean(1)
    return (a0 * b0).mean(1) / torch.sqrt(va * vb + 1e-8), va > 1e-4


def laplacian(s, edges, degree):
    """Umbrella Laplacian of per-vertex values ``s`` over the mesh's unique ``edges`` (E, 2)."""
    total = torch.zeros_like(s).index_add(0, edges[:, 0], s[edges[:, 1]]).index_add(0, edges[:, 1], s[edges[:, 0]])
    return s - total / degree


def refine(verts, faces, images, masks, cams, rounds=3, iters=150, batch=2048, k=4, half=2, lr=2e-3,
           smooth=1.0, sigmas=(2.0, 1.0, 0.5), max_step=0.03, seed=0):
    """``verts`` (normalized frame) moved along their normals so that neighbouring views' patches agree."""
    gen = torch.Generator().manual_seed(seed)
    n_views, (H, W) = len(cams), images[0].shape[:2]
    near = torch.as_tensor(neighbours(cams, k))
    faces_t = torch.as_tensor(faces, dtype=torch.int64)
    edges = torch.as_tensor(np.unique(np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]],
                                                              faces[:, [2, 0]]]), 1), axis=0))
    degree = torch.bincount(edges.flatten(), minlength=len(verts)).double().clamp(min=1)
    K, R, t = (torch.as_tensor(a) for a in (cams.K, cams.R, cams.t))
    offs = torch.stack(torch.meshgrid(torch.arange(-half, half + 1), torch.arange(-half, half + 1), indexing="ij"),
                       -1).reshape(-1, 2).double()
    cur = np.asarray(verts, np.float64).copy()
    for rnd in range(rounds):
        sigma = sigmas[min(rnd, len(sigmas) - 1)]
        grey = torch.as_tensor(np.stack([blur(im, sigma).mean(-1) for im in images]))[:, None].double()
        mesh = trimesh.Trimesh(cur, faces, process=False)
        normals, base = torch.tensor(np.array(mesh.vertex_normals)), torch.as_tensor(cur)
        depths = torch.as_tensor(np.stack(depth_maps(mesh, cams, [(W, H)] * n_views)))
        pix_view, pix_xy, pix_face = hit_pixels(mesh, masks, cams, half)
        s = torch.zeros(len(cur), dtype=torch.float64, requires_grad=True)
        opt = torch.optim.Adam([s], lr=lr)
        t0 = time.time()
        for it in range(iters):
            pick = torch.randint(len(pix_view), (batch,), generator=gen)
            vi = pix_view[pick]
            vj = near[vi, torch.randint(k, (batch,), generator=gen)]
            xy = pix_xy[pick][:, None, :] + offs[None]  # (B, P, 2) patch pixels around each picked pixel
            tri = (base + normals * s[:, None])[faces_t[pix_face[pick]]]
            X = on_face_planes(tri, xy, K[vi], R[vi], t[vi])
            xj, yj, seen = seen_at(X, K[vj], R[vj], t[vj], depths, vj, W, H)
            a = sample(grey, vi.repeat_interleave(len(offs)), xy[..., 0].flatten(), xy[..., 1].flatten())
            b = sample(grey, vj.repeat_interleave(len(offs)), xj.flatten(), yj.flatten())
            ncc, textured = zncc(a.reshape(batch, -1), b.reshape(batch, -1))
            used = (textured & seen).double()
            data = ((1 - ncc) * used).sum() / used.sum().clamp(min=1)
            lap = laplacian(s, edges, degree)
            loss = data + smooth * (lap ** 2).mean() * 1e4
            opt.zero_grad()
            loss.backward()
            opt.step()
            with torch.no_grad():
                s.clamp_(-max_step, max_step)
            if it % 50 == 0 or it == iters - 1:
                print(f"round {rnd} it {it} 1-zncc {data.item():.4f} |offset| {s.abs().mean().item():.4f} "
                      f"patches {int(used.sum())} {time.time() - t0:.1f} s", flush=True)
        cur = (base + normals * s[:, None]).detach().numpy()
    return cur


def main():
    """Refine a copy of bench/dtu_arm.py's workspace with the JSON options of :func:`refine`, bake it, measure."""
    src, out = ev.RUNS / "work" / "dtu_arm" / "ws", ev.RUNS / "work" / "refine_probe"
    opts = json.loads(sys.argv[1]) if len(sys.argv) > 1 else {}
    full = ev.RUNS / "dtu_all"
    shutil.rmtree(out, ignore_errors=True)
    shutil.copytree(src, out, symlinks=True)
    paths = list_images(out / "images")
    cams = load_cameras(out / "cameras.npz", n_views=len(paths))
    m = trimesh.load(out / "mesh" / "clean.ply", process=False)
    vn = to_normalized(np.asarray(m.vertices, np.float64), cams.scale_mat)
    images, _, _ = photos_for_bake(paths, out / "model" / "appearance.json", TextureConfig())
    masks = [ev._read_mask(out / "masks" / f"{p.stem}.png") for p in paths]
    t0 = time.time()
    if opts.get("rounds", 1) > 0:
        vn = refine(vn, np.asarray(m.faces), images, masks, cams, **opts)
    print("refine s", time.time() - t0)
    trimesh.Trimesh(to_sfm(vn, cams.scale_mat), m.faces, process=False).export(out / "mesh" / "clean.ply")
    (out / ".stages" / "texture.json").unlink(missing_ok=True)
    ev.stages(("texture",), out, ev.config(None))
    print(json.dumps(metrics(full, out)))


def metrics(full, ws):
    """Mean PSNR of the workspace's textured mesh at DTU's held-out and training views (bench/evaluate.py run_dtu)."""
    from pipeline.render.textured import render_textured

    tm, tex = ev.textured(ws)
    paths_all = list_images(full / "images")
    names = [p.stem for p in paths_all]
    cams = load_cameras(full / "cameras.npz")
    held = ev.dtu_heldout(len(names))
    tr, ho = [], []
    for i in range(len(names)):
        photo = ev._read_rgb(paths_all[i])
        h, w = photo.shape[:2]
        img, hit = render_textured(tm.vertices, tm.faces, tm.visual.uv, tex, cams.K[i], cams.R[i],
                                   cams.sfm_centers[i], w, h)
        mask = ev._read_mask(full / "masks" / f"{names[i]}.png")
        (ho if i in held else tr).append(ev.image_psnr(img, hit, photo, mask))
    return {"psnr": float(np.mean(ho)), "psnr_train": float(np.mean(tr))}


if __name__ == "__main__":
    main()
