"""Render a synthetic scene into the workspace layout, with ground truth beside it.

Only what the scene lists is computed: normals only for lighting or specular highlights, a background
only when one is listed, each effect only when listed. The list of computed passes is returned and written
to ``gt/scene.json`` so tests can check it.

Written (docs/design.md, "Workspace"): ``images/``, ``masks/`` (unless ``write_masks: false``), ``cameras.npz``
(world_mat_i in the world = "SfM" frame, scale_mat: canonical/normalized → world), ``depth/`` when
``sparse_depth`` > 0, and ``gt/``: ``mesh.ply`` (world frame), ``depth/*.npy`` (ray depth, normalized
frame, 0 on background), ``heldout/`` views, ``scene.json``, ``board.json`` (a ground effect's printed board).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict
from pathlib import Path

import cv2
import numpy as np
import torch
import trimesh
from skimage import measure

from dvr.cameras import save_cameras, sphere_bounds, sphere_frame
from pipeline.render.raycast import MeshCaster
from synth.ground import board_spec_of, ground_albedo, ground_shading, plane_coords, plane_hits, plane_normal
from synth.noise import procedural_noise
from synth.scene import Effect, Scene, Shape


# ----------------------------------------------------------------------------- shapes
def sdf(shape: Shape, p: torch.Tensor) -> torch.Tensor:
    """Signed distance (negative inside) of an analytic shape at points (M, 3); with a relief, the distance less
    the bumps' height (no longer a true distance: :func:`lipschitz` bounds its slope)."""
    d = _plain_sdf(shape, p)
    if shape.relief:
        w = 2 * math.pi * shape.relief_scale
        d = d - shape.relief * torch.sin(w * p).prod(dim=-1)
    return d


def lipschitz(shape: Shape) -> float:
    """An upper bound on the slope of :func:`sdf` (1 for a true distance; a union's or difference's the largest of
    its parts'): sphere tracing steps by the distance over it, so that bumps are not stepped through."""
    parts = max([1.0] + [lipschitz(Shape(**d)) for d in shape.parts])
    return parts + abs(shape.relief) * 2 * math.pi * shape.relief_scale * math.sqrt(3)


def _plain_sdf(shape: Shape, p: torch.Tensor) -> torch.Tensor:
    """Signed distance of the shape without its relief."""
    c = torch.tensor(shape.center, dtype=p.dtype)
    q = p - c
    k = shape.kind
    if k in ("torus", "cylinder") and shape.axis != "z":  # turn the frame so that the axis becomes z
        if shape.axis not in ("x", "y"):
            raise ValueError(f"shape axis must be 'x', 'y' or 'z', got '{shape.axis}'")
        q = q[:, [1, 2, 0]] if shape.axis == "x" else q[:, [2, 0, 1]]
    if k == "sphere":
        return q.norm(dim=-1) - shape.radius
    if k == "box":
        b = torch.tensor(shape.size, dtype=p.dtype)
        d = q.abs() - b
        return d.clamp_min(0).norm(dim=-1) + d.max(dim=-1).values.clamp_max(0)
    if k == "torus":
        xy = q[:, :2].norm(dim=-1) - shape.radius
        return torch.stack([xy, q[:, 2]], -1).norm(dim=-1) - shape.minor
    if k == "cylinder":  # upright, radius, half height size[2], edges rounded by minor
        r = shape.minor
        dd = torch.stack([q[:, :2].norm(dim=-1) - (shape.radius - r), q[:, 2].abs() - (shape.size[2] - r)], -1)
        return dd.max(dim=-1).values.clamp_max(0) + dd.clamp_min(0).norm(dim=-1) - r
    if k == "shell":
        return (q.norm(dim=-1) - (shape.radius - shape.minor / 2)).abs() - shape.minor / 2
    if k == "union":
        if not shape.parts:
            raise ValueError("union shape needs parts")
        return _union_sdf(shape.parts, p)
    if k == "difference":
        if len(shape.parts) < 2:
            raise ValueError("difference shape needs two or more parts (the solid, then what is cut from it)")
        return torch.maximum(sdf(Shape(**shape.parts[0]), p), -_union_sdf(shape.parts[1:], p))
    raise ValueError(f"unknown analytic shape '{k}' (sphere, box, torus, cylinder, shell, union, difference, mesh)")


def _union_sdf(parts: list[dict], p: torch.Tensor) -> torch.Tensor:
    """Signed distance of the union of the Shape dicts ``parts`` at points (M, 3)."""
    return torch.stack([sdf(Shape(**d), p) for d in parts]).min(dim=0).values


class MeshShape:
    """A textured mesh scaled into the unit sphere; ray casting with trimesh (Embree when installed)."""

    def __init__(self, shape: Shape, base_dir: str):
        if shape.relief:
            raise ValueError("shape.relief is for analytic shapes; a mesh carries its own relief")
        path = Path(shape.path)
        if not path.is_absolute():
            path = Path(base_dir) / path
        if not path.exists():
            raise FileNotFoundError(f"{path}: mesh file of the scene not found; fix shape.path")
        m = trimesh.load(str(path), process=False, force="mesh")
        if shape.up == "y":
            m.apply_transform(np.array([[1.0, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]]))
        elif shape.up != "z":
            raise ValueError(f"shape.up must be 'z' or 'y', got '{shape.up}'")
        center = 0.5 * (m.bounds[0] + m.bounds[1])
        radius = np.linalg.norm(m.vertices - center, axis=1).max()
        m.apply_translation(-center)
        m.apply_scale(shape.fit_radius / radius)
        self.mesh = m
        self.uv = getattr(m.visual, "uv", None)
        mat = getattr(m.visual, "material", None)
        img = getattr(mat, "image", None) if mat is not None else None
        if img is None and mat is not None and hasattr(mat, "baseColorTexture"):
            img = mat.baseColorTexture
        self.texture = None if img is None else np.asarray(img.convert("RGB"), dtype=np.float32) / 255.0
        # closed surface for ground truth: merge vertices ignoring UVs
        gt = trimesh.Trimesh(m.vertices.copy(), m.faces.copy(), process=True)
        gt.merge_vertices(merge_tex=True, merge_norm=True)
        self.gt = gt
        self.caster = MeshCaster(m)

    def cast(self, o: np.ndarray, d: np.ndarray):
        """First hits: (hit mask, depth, point, normal, uv or None)."""
        n = o.shape[0]
        ir, it, loc = self.caster.first_hits(o, d)
        hit = np.zeros(n, bool)
        depth = np.zeros(n)
        pts = np.zeros((n, 3))
        nrm = np.zeros((n, 3))
        uv = np.zeros((n, 2)) if self.uv is not None else None
        if len(ir):
            hit[ir], depth[ir], pts[ir] = True, ((loc - o[ir]) * d[ir]).sum(1), loc
            tri = self.mesh.triangles[it]
            bary = trimesh.triangles.points_to_barycentric(tri, loc)
            vn = self.mesh.vertex_normals[self.mesh.faces[it]]
            nn = (vn * bary[:, :, None]).sum(1)
            nrm[ir] = nn / np.linalg.norm(nn, axis=1, keepdims=True).clip(1e-12)
            if uv is not None:
                uv[ir] = (self.uv[self.mesh.faces[it]] * bary[:, :, None]).sum(1)
        return hit, depth, pts, nrm, uv


def sphere_trace(shape: Shape, o: torch.Tensor, d: torch.Tensor, iters: int = 256, eps: float = 1e-5):
    """Sphere tracing of the shape's SDF along rays inside the unit sphere: hit (M,) bool and ray depth t (M,)."""
    near, far, valid = sphere_bounds(o, d, 1.0)
    slope = lipschitz(shape)
    t = near.clone()
    alive = valid.clone()
    hit = torch.zeros_like(valid)
    for _ in range(math.ceil(iters * slope)):
        idx = alive.nonzero().view(-1)
        if idx.numel() == 0:
            break
        s = sdf(shape, o[idx] + t[idx, None] * d[idx]) / slope
        t[idx] += s
        h = s.abs() < eps
        hit[idx[h]] = True
        gone = h | (t[idx] > far[idx])
        alive[idx[gone]] = False
    return hit, t


def sdf_normals(shape: Shape, p: torch.Tensor, h: float = 1e-4) -> torch.Tensor:
    """Unit normals (M, 3) of the shape's SDF at points p (central differences of step ``h``)."""
    e = torch.eye(3, dtype=p.dtype) * h
    g = torch.stack([sdf(shape, p + e[i]) - sdf(shape, p - e[i]) for i in range(3)], -1)
    return g / g.norm(dim=-1, keepdim=True).clamp_min(1e-12)


# ----------------------------------------------------------------------------- textures


def albedo_of(scene: Scene, pts: np.ndarray, uv: np.ndarray | None, tex: np.ndarray | None) -> np.ndarray:
    """Albedo (M, 3) of the scene's object at surface points ``pts`` (and their ``uv`` in the mesh texture ``tex``)."""
    a = scene.albedo
    if a.kind == "constant":
        return np.broadcast_to(np.asarray(a.color, float), pts.shape).copy()
    if a.kind == "checker":
        k = np.floor(pts * a.scale).sum(1).astype(int) % 2
        return np.where(k[:, None] == 0, np.asarray(a.color), np.asarray(a.color2))
    if a.kind == "noise":
        c = np.asarray(a.color, float)
        return c + a.contrast * (procedural_noise(pts, a.scale, a.seed, a.levels) - c)
    if a.kind == "texture":
        if uv is None or tex is None:
            raise ValueError("albedo 'texture' needs a mesh shape with UVs and a texture image")
        h, w = tex.shape[:2]
        x = (uv[:, 0] % 1.0) * w - 0.5
        y = (1 - uv[:, 1] % 1.0) * h - 0.5
        out = np.zeros((len(x), tex.shape[2] if tex.ndim == 3 else 1))
        for s in range(0, len(x), 32000):  # cv2.remap takes at most 32767 columns
            m = cv2.remap(tex, x[s : s + 32000].astype(np.float32)[None], y[s : s + 32000].astype(np.float32)[None],
                          cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
            out[s : s + 32000] = m[0].reshape(-1, out.shape[1])
        return out
    raise ValueError(f"unknown albedo '{a.kind}' (constant, checker, noise, texture)")


# ----------------------------------------------------------------------------- cameras
def camera_rig(scene: Scene, heldout: bool = False):
    """K (N,3,3), R (N,3,3), centres (N,3) in the canonical frame; views looking at the origin.

    Training views lie on a spiral (``rings: 0``), on ``rings`` rings, or on a video's path (``orbit_turns``).
    Held-out views use the same layout at fractional positions halfway between training views, so no held-out view
    repeats a training camera.
    """
    rig = scene.cameras
    n = rig.heldout if heldout else rig.n_views
    if n <= 0:
        return np.zeros((0, 3, 3)), np.zeros((0, 3, 3)), np.zeros((0, 3))
    f = 0.5 * rig.width / math.tan(math.radians(rig.fov_deg) / 2)
    K = np.array([[f, 0, rig.width / 2], [0, f, rig.height / 2], [0, 0, 1.0]])
    Ks, Rs, Cs = [], [], []
    lo, hi = rig.elevation
    nt = max(1, rig.n_views)
    for i in range(n):
        if rig.orbit_turns > 0:  # a video's frames: one path, held-out views halfway between two frames
            x = math.floor((i + 0.5) * nt / n) + 0.5 if heldout else float(i)
            az = 2 * math.pi * rig.orbit_turns * x / nt
            el = math.radians(lo + (hi - lo) * x / max(1, nt - 1))
        elif rig.rings > 0:  # k rings, views spread evenly around each
            ring = i % rig.rings
            per = math.ceil(nt / rig.rings)
            slot = float(i // rig.rings)
            if heldout:  # spread over the ring, then halfway between two training slots
                slot = math.floor((slot + 0.5) * per / math.ceil(n / rig.rings)) + 0.5
            az = 2 * math.pi * (slot + 0.5 * ring) / per
            el = math.radians(lo + (hi - lo) * ring / max(1, rig.rings - 1))
        else:
            x = float(i)
            if heldout:  # fractional spiral index halfway between two training views
                x = math.floor((i + 0.5) * nt / n) + 0.5
            az = 2 * math.pi * x / nt
            el = math.radians(lo + (hi - lo) * ((x * 0.618034) % 1.0))
        lo_az, hi_az = rig.azimuth
        if (lo_az, hi_az) != (0.0, 360.0):  # part of a turn: the full orbit's layout squeezed onto [lo, hi)
            az = math.radians(lo_az + (hi_az - lo_az) * ((az / (2 * math.pi)) % 1.0))
        c = rig.radius * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        fwd = -c / np.linalg.norm(c)
        right = np.cross(fwd, [0, 0, 1.0])
        right /= np.linalg.norm(right)
        down = np.cross(fwd, right)
        Rs.append(np.stack([right, down, fwd]))
        Ks.append(K.copy())
        Cs.append(c)
    return np.stack(Ks), np.stack(Rs), np.stack(Cs)


# ----------------------------------------------------------------------------- rendering
def object_tracer(scene: Scene, mesh_shape: MeshShape | None, need_normals: bool):
    """``trace(o, d)`` → first object hits (hit, depth, point, normal or None, uv or None) of rays (M, 3)."""
    def trace(o: np.ndarray, d: np.ndarray):
        """First hits of rays ``o`` + t ``d`` on the mesh or, without one, the SDF."""
        if mesh_shape is not None:
            return mesh_shape.cast(o, d)
        hit_t, t = sphere_trace(scene.shape, torch.from_numpy(o), torch.from_numpy(d))
        hit, depth = hit_t.numpy(), t.numpy()
        pts = o + depth[:, None] * d
        nrm = None
        if need_normals:
            nrm = np.zeros_like(pts)
            nrm[hit] = sdf_normals(scene.shape, torch.from_numpy(pts[hit])).numpy()
        return hit, depth, pts, nrm, None

    return trace


def object_occlusion(scene: Scene, mesh_shape: MeshShape | None):
    """(occluded(o, d) → bool (M,), distance(p) → (M,)) of the object, for the ground's shadows."""
    if mesh_shape is not None:
        from scipy.spatial import cKDTree

        tree = cKDTree(trimesh.sample.sample_surface(mesh_shape.gt, 60000, seed=0)[0])
        # beyond 6 radii the contact shadow is < 0.3 %: far queries (slow in a KD-tree) stop there
        reach = 6 * max(e.softness for e in scene.effects if e.kind == "ground")
        return mesh_shape.caster.any_hit, lambda p: tree.query(p, distance_upper_bound=reach, workers=-1)[0]
    return (lambda o, d: sphere_trace(scene.shape, torch.from_numpy(o), torch.from_numpy(d))[0].numpy(),
            lambda p: sdf(scene.shape, torch.from_numpy(p)).numpy())


def shade_object(scene: Scene, listed: dict, col: np.ndarray, nrm: np.ndarray | None, d: np.ndarray) -> np.ndarray:
    """Albedo ``col`` (M, 3) of object points lit by the scene's lights (and specular highlights when listed)."""
    if scene.lighting.kind == "lambertian":
        shade = np.full(len(col), scene.lighting.ambient)
        for lx, ly, lz, li in scene.lighting.lights:
            ldir = np.array([lx, ly, lz]) / np.linalg.norm([lx, ly, lz])
            shade += li * np.clip(nrm @ ldir, 0, None)
        col = col * shade[:, None]
    elif scene.lighting.kind != "none":
        raise ValueError(f"unknown lighting '{scene.lighting.kind}' (none, lambertian)")
    if "specular" in listed:
        e = listed["specular"]
        for lx, ly, lz, li in (scene.lighting.lights or [[0.4, 0.5, 0.8, 1.0]]):
            ldir = np.array([lx, ly, lz]) / np.linalg.norm([lx, ly, lz])
            hv = ldir - d
            hv /= np.linalg.norm(hv, axis=1, keepdims=True)
            col = col + e.amount * li * np.clip((nrm * hv).sum(1), 0, None)[:, None] ** e.shininess
    return col


def background_colour(scene: Scene, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Colour (M, 3) of rays that see neither the object nor the ground."""
    bg = scene.background
    if bg.kind == "none":
        return np.zeros_like(o)
    if bg.kind == "constant":
        return np.broadcast_to(np.asarray(bg.color, float), o.shape).copy()
    if bg.kind == "backdrop":
        b = (o * d).sum(1)
        c2 = (o * o).sum(1) - bg.radius ** 2
        t = -b + np.sqrt(np.clip(b * b - c2, 0, None))
        col = procedural_noise((o + t[:, None] * d) / bg.radius, bg.scale, bg.seed, bg.levels)
        gray = col.mean(1, keepdims=True)
        return (gray + bg.saturation * (col - gray)) * 0.9
    raise ValueError(f"unknown background '{bg.kind}' (none, constant, backdrop)")


def ground_colour(scene: Scene, ground: Effect, pts: np.ndarray, occlusion) -> np.ndarray:
    """Colour (M, 3) of ground points: the pattern, lit (with soft shadows) when the scene has lighting."""
    col = ground_albedo(plane_coords(pts, plane_normal(ground)), ground)
    if scene.lighting.kind == "none":
        return col
    return col * ground_shading(pts, scene.lighting.lights, scene.lighting.ambient, ground, *occlusion)[:, None]


def pixel_samples(H: int, W: int, ss: int) -> tuple[np.ndarray, np.ndarray]:
    """Homogeneous pixel coordinates of ss × ss samples per pixel (H·ss·W·ss, 3), and which sample is the
    pixel centre (masks and depth come from it)."""
    if ss < 1 or ss % 2 == 0:
        raise ValueError(f"cameras.supersample × cameras.photo_scale must be an odd number ≥ 1, got {ss}")
    sub = (np.arange(ss) + 0.5) / ss
    jj = (np.arange(W)[None, None, :, None] + sub[None, None, None, :]) * np.ones((H, ss, W, ss))
    ii = (np.arange(H)[:, None, None, None] + sub[None, :, None, None]) * np.ones((H, ss, W, ss))
    pix = np.stack([jj, ii, np.ones_like(jj)], -1).reshape(-1, 3)
    centre = np.zeros((H, ss, W, ss), bool)
    centre[:, ss // 2, :, ss // 2] = True
    return pix, centre.reshape(-1)


def exposure_gains(e: Effect, rng: np.random.Generator) -> np.ndarray:
    """Per-channel gains (3,) of one view: an exposure gain 1 ± ``amount`` times a white balance 1 ± ``white_balance``
    per channel (linear RGB, as the renderer's colours)."""
    gain = 1 + rng.uniform(-1, 1) * e.amount
    return gain * (1 + rng.uniform(-1, 1, 3) * e.white_balance) if e.white_balance > 0 else np.full(3, gain)


def image_effects(img: np.ndarray, listed: dict, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Per-view camera effects on an (H, W, 3) image: exposure and white balance, blur, sensor noise (only those
    listed); returns the image and its per-channel exposure gains (ones without the effect)."""
    gains = exposure_gains(listed["exposure"], rng) if "exposure" in listed else np.ones(3)
    img = img * gains
    if "blur" in listed:
        img = cv2.GaussianBlur(img, (0, 0), listed["blur"].sigma)
    if "noise" in listed:
        img = img + rng.normal(0, listed["noise"].sigma, img.shape)
    return np.clip(img, 0, 1), gains


def render_views(scene: Scene, K, R, C, mesh_shape: MeshShape | None, passes: list[str], view_seed: int = 0,
                 ground_z: float | None = None):
    """Render views: images (N,H,W,3) float, masks (N,H,W) bool, depth (N,H,W) canonical ray depth, exposure gains
    (N,3); the images at ``cameras.photo_scale`` × (H, W) (each of their pixels ``supersample``² samples).

    With a ``ground`` effect, ``ground_z`` is the height of its plane along its normal (canonical frame): rays that
    reach it before the object see the ground, and masks and depth are the object's alone."""
    rig = scene.cameras
    H, W, ss, ps = rig.height, rig.width, int(rig.supersample), int(rig.photo_scale)
    pix, centre = pixel_samples(H, W, ss * ps)
    rng = np.random.default_rng(scene.cameras.seed + 1000 * view_seed)
    listed = {e.kind: e for e in scene.effects}
    ground = listed.get("ground")
    if ground is not None and ground_z is None:
        raise ValueError("a ground effect needs the plane's height (ground_z)")
    need_normals = scene.lighting.kind != "none" or "specular" in listed
    trace = object_tracer(scene, mesh_shape, need_normals)
    occlusion = object_occlusion(scene, mesh_shape) if ground is not None and scene.lighting.kind != "none" else None
    imgs, masks, depths, gains = [], [], [], []
    for v in range(len(K)):
        d = pix @ np.linalg.inv(K[v]).T @ R[v]
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        o = np.broadcast_to(C[v], d.shape).copy()
        hit, depth, pts, nrm, uv = trace(o, d)
        on_ground = np.zeros(len(d), bool)
        if ground is not None:
            on_ground, t_ground = plane_hits(o, d, ground_z, plane_normal(ground))
            hit &= ~(on_ground & (t_ground < depth))  # what of the object lies below the plane is hidden
            on_ground &= ~hit
        img = np.zeros((len(pix), 3))
        if hit.any():
            col = albedo_of(scene, pts[hit], None if uv is None else uv[hit],
                            mesh_shape.texture if mesh_shape else None)
            img[hit] = shade_object(scene, listed, col, None if nrm is None else nrm[hit], d[hit])
        if on_ground.any():
            img[on_ground] = ground_colour(scene, ground, o[on_ground] + t_ground[on_ground, None] * d[on_ground],
                                           occlusion)
        rest = ~hit & ~on_ground
        img[rest] = background_colour(scene, o[rest], d[rest])
        img = img.reshape(H * ps, ss, W * ps, ss, 3).mean(axis=(1, 3))  # box filter over the photo's pixel
        hit, depth = hit[centre], depth[centre]
        img, g = image_effects(img, listed, rng)
        imgs.append(img)
        gains.append(g)
        masks.append(hit.reshape(H, W))
        depths.append(np.where(hit, depth, 0.0).reshape(H, W))
    _list_passes(scene, passes, ss, need_normals)
    return np.stack(imgs), np.stack(masks), np.stack(depths), np.stack(gains)


EFFECTS = ("noise", "exposure", "distortion", "blur", "specular", "ground")


def _list_passes(scene: Scene, passes: list[str], ss: int, need_normals: bool) -> None:
    """Append the passes a scene computed (what tests check: nothing it does not list)."""
    light = scene.lighting.kind != "none"
    for name, on in [(f"supersample:{ss}", ss > 1), (f"photo_scale:{scene.cameras.photo_scale}",
                                                       scene.cameras.photo_scale > 1), ("normals", need_normals),
                     (f"lighting:{scene.lighting.kind}", light),
                     (f"background:{scene.background.kind}", scene.background.kind != "none")]:
        if on and name not in passes:
            passes.append(name)
    for e in scene.effects:
        if e.kind not in EFFECTS:
            raise ValueError(f"unknown effect '{e.kind}' ({', '.join(EFFECTS)})")
        for name in [f"effect:{e.kind}"] + (["ground_shadows"] if e.kind == "ground" and light else []):
            if name not in passes:
                passes.append(name)


def distort(images: np.ndarray, masks: np.ndarray, K: np.ndarray, k1: float):
    """Apply radial distortion x_d = x_u (1 + k1 r_u²) to images and masks (pinhole K)."""
    H, W = images.shape[1:3]
    jj, ii = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    xd, yd = (jj - K[0, 2]) / K[0, 0], (ii - K[1, 2]) / K[1, 1]
    xu, yu = xd.copy(), yd.copy()
    for _ in range(20):  # invert the distortion by fixed point
        r2 = xu * xu + yu * yu
        xu, yu = xd / (1 + k1 * r2), yd / (1 + k1 * r2)
    mx = (xu * K[0, 0] + K[0, 2] - 0.5).astype(np.float32)
    my = (yu * K[1, 1] + K[1, 2] - 0.5).astype(np.float32)
    out_i = np.stack([cv2.remap(im.astype(np.float32), mx, my, cv2.INTER_LINEAR) for im in images])
    out_m = np.stack([cv2.remap(m.astype(np.float32), mx, my, cv2.INTER_LINEAR) > 0.5 for m in masks])
    return out_i, out_m


def _write_png(path: Path, img: np.ndarray) -> None:
    if img.ndim == 3:
        img = cv2.cvtColor((img * 255).round().clip(0, 255).astype(np.uint8), cv2.COLOR_RGB2BGR)
    cv2.imwrite(str(path), img)


def _write_views(imgs, masks, depths, img_dir: Path | None, mask_dir: Path | None, depth_dir: Path | None) -> None:
    """View i as ``<i:06d>.png`` in ``img_dir``, its mask in ``mask_dir`` and its depth (``.npy``, float32) in
    ``depth_dir`` (each folder only when given)."""
    for i in range(len(imgs)):
        name = f"{i:06d}"
        if img_dir is not None:
            _write_png(img_dir / f"{name}.png", imgs[i])
        if mask_dir is not None:
            _write_png(mask_dir / f"{name}.png", (masks[i] * 255).astype(np.uint8))
        if depth_dir is not None:
            np.save(depth_dir / f"{name}.npy", depths[i].astype(np.float32))


def _write_sparse_depth(folder: Path, masks, depths, per_view: int, seed: int) -> None:
    """``depth/<i:06d>.npz`` per view: ``per_view`` pixels of the mask drawn at random (``seed``), their centres' ray
    depths from the GT depth maps, confidence 1."""
    folder.mkdir(exist_ok=True)
    rng = np.random.default_rng(seed)
    for i in range(len(masks)):
        ii, jj = np.nonzero(masks[i])
        sel = rng.choice(len(ii), size=min(per_view, len(ii)), replace=False) if len(ii) else []
        uv = np.stack([jj[sel] + 0.5, ii[sel] + 0.5], 1).astype(np.float32) if len(ii) else np.zeros((0, 2))
        d = depths[i][ii[sel], jj[sel]].astype(np.float32) if len(ii) else np.zeros(0)
        np.savez(folder / f"{i:06d}.npz", uv=uv, depth=d, confidence=np.ones_like(d))


def _ground_plane(ground: Effect | None, mesh, s: float, off: np.ndarray):
    """With a ground effect: its height along its normal in the canonical frame (the GT mesh's lowest point along
    it + ``sink``) and the support plane n·x + d = 0 in the world frame (the SfM frame of the GT cameras), n towards
    the object and the cameras — part of the ground truth the GT cameras carry, as SfM's cameras carry the plane it
    finds; (None, None) without one."""
    if ground is None:
        return None, None
    n = plane_normal(ground)
    ground_z = float((mesh.vertices @ n).min()) + ground.sink
    return ground_z, [*(float(x) for x in n), -float(s * ground_z + n @ off)]


def gt_mesh(scene: Scene, mesh_shape: MeshShape | None, res: int = 256) -> trimesh.Trimesh:
    """Ground-truth surface in the canonical frame."""
    if mesh_shape is not None:
        return mesh_shape.gt.copy()
    lin = torch.linspace(-1, 1, res + 1, dtype=torch.float64)
    g = torch.stack(torch.meshgrid(lin, lin, lin, indexing="ij"), -1).view(-1, 3)
    vol = torch.cat([sdf(scene.shape, g[s : s + 500000]) for s in range(0, g.shape[0], 500000)])
    v, f, _, _ = measure.marching_cubes(vol.view(res + 1, res + 1, res + 1).numpy(), 0.0, spacing=(2 / res,) * 3)
    m = trimesh.Trimesh(v - 1.0, f, process=True)
    if m.volume < 0:
        m.invert()
    return m


def write_scene(scene: Scene, out: str | Path) -> dict:
    """Render ``scene`` into workspace ``out``; returns the metadata written to gt/scene.json."""
    t0 = time.perf_counter()
    out = Path(out)
    passes: list[str] = ["geometry", f"albedo:{scene.albedo.kind}"]
    mesh_shape = MeshShape(scene.shape, scene.base_dir) if scene.shape.kind == "mesh" else None
    s, off = float(scene.world_scale), np.asarray(scene.world_offset, float)
    if not (s > 0 and np.isfinite(s)):
        raise ValueError(f"world_scale must be a positive finite number, got {scene.world_scale}")
    scale_mat = sphere_frame(off, s)  # canonical → world
    for sub in ["images", "masks", "gt/depth", "gt/heldout/images", "gt/heldout/masks"]:
        (out / sub).mkdir(parents=True, exist_ok=True)
    listed = {e.kind: e for e in scene.effects}
    dist = listed.get("distortion")
    ps = int(scene.cameras.photo_scale)
    if ps > 1 and dist is not None and dist.k1 != 0.0:
        raise ValueError("cameras.photo_scale > 1 does not go with the distortion effect (its masks are distorted at "
                         "the photos' size); use one of them")
    mesh = gt_mesh(scene, mesh_shape)
    ground = listed.get("ground")
    ground_z, plane = _ground_plane(ground, mesh, s, off)

    exposure: dict[str, dict] = {}  # per image folder, per view: the exposure gains the photo was rendered with

    def one_set(K, R, C, img_dir: Path, mask_dir: Path | None, cam_path: Path, depth_dir: Path | None, seed: int,
                photo_dir: Path | None = None):
        """Render, distort and write one set of views (training or held-out) with its cameras; with a photo_scale
        > 1 the photos go to ``photo_dir`` (``img_dir`` when None) and ``img_dir`` gets them box-filtered to the
        ground truth's size when that differs."""
        imgs, masks, depths, gains = render_views(scene, K, R, C, mesh_shape, passes, seed, ground_z)
        if ps > 1:
            photo_dir = photo_dir or img_dir
            photo_dir.mkdir(parents=True, exist_ok=True)
            _write_views(imgs, masks, depths, photo_dir, None, None)
            n, h, w = masks.shape
            imgs = imgs.reshape(n, h, ps, w, ps, 3).mean(axis=(2, 4))
        exposure[img_dir.relative_to(out).as_posix()] = {f"{i:06d}": [round(float(x), 6) for x in g]
                                                         for i, g in enumerate(gains)}
        if dist is not None and dist.k1 != 0.0:
            imgs, masks = distort(imgs, masks, K[0], dist.k1)
        save_cameras(cam_path, K, R, -np.einsum("nij,nj->ni", R, s * C + off), scale_mat, plane)  # world frame
        _write_views(imgs, masks, depths, None if img_dir == photo_dir else img_dir, mask_dir, depth_dir)
        return imgs, masks, depths

    K, R, C = camera_rig(scene)
    imgs, masks, depths = one_set(K, R, C, out / "images", out / "masks" if scene.write_masks else None,
                                  out / "cameras.npz", out / "gt" / "depth", 0)
    (out / "gt" / "masks").mkdir(exist_ok=True)
    for i in range(len(K)):
        _write_png(out / "gt" / "masks" / f"{i:06d}.png", (masks[i] * 255).astype(np.uint8))
    if not scene.write_masks:
        (out / "masks").rmdir() if not any((out / "masks").iterdir()) else None
    np.savez(out / "gt" / "cameras.npz", **dict(np.load(out / "cameras.npz")))
    if scene.sparse_depth > 0:
        _write_sparse_depth(out / "depth", masks, depths, scene.sparse_depth, scene.cameras.seed + 7)
        passes.append("sparse_depth")
    Kh, Rh, Ch = camera_rig(scene, heldout=True)
    if len(Kh):
        one_set(Kh, Rh, Ch, out / "gt/heldout/images", out / "gt/heldout/masks", out / "gt/heldout/cameras.npz",
                None, 1, out / "gt/heldout/photos")
    mesh.apply_transform(scale_mat)
    mesh.export(out / "gt" / "mesh.ply")
    meta = {"scene": asdict(scene), "passes": passes, "seconds": round(time.perf_counter() - t0, 3),
            "n_views": int(len(K)), "n_heldout": int(len(Kh))}
    if plane is not None:
        meta["ground_plane"] = plane
    (out / "gt" / "scene.json").write_text(json.dumps(meta, indent=1))
    if "exposure" in listed:
        (out / "gt" / "exposure.json").write_text(json.dumps(exposure, indent=1))
    if ground is not None and ground.board:
        (out / "gt" / "board.json").write_text(json.dumps(board_truth(ground, s, off, ground_z), indent=1))
    return meta


def board_truth(ground: Effect, s: float, off: np.ndarray, ground_z: float) -> dict:
    """Ground truth of a scene's printed board: its definition, metres per world (GT camera) unit, and the world →
    board frame similarity (metres, origin at the board's centre, z up; as ``pipeline/cameras/board.py`` recovers
    it)."""
    spec = board_spec_of(ground)
    k = ground.metres_per_unit / s
    T = np.eye(4)
    T[:3, :3] *= k
    T[:3, 3] = -k * off - np.array([0.0, 0.0, ground.metres_per_unit * ground_z])
    return {**spec.info(), "metres_per_unit": ground.metres_per_unit, "metres_per_world_unit": k,
            "world_to_board": T.tolist()}
