"""Texture baking from photos: a known textured object (the cow) baked back from its renderings; seams
match across charts; every face is covered; the outputs load (GLB in trimesh, OBJ in pymeshlab). On small scenes
rendered here: a highlight one view alone sees is rejected, no background colour reaches the texture at
silhouettes, a blurred view loses to a sharp one."""

import shutil
import subprocess

import cv2
import numpy as np
import pytest
import trimesh

from dvr.cameras import Cameras, load_cameras, sphere_frame, to_sfm
from pipeline.render.textured import render_textured, sample_bilinear
from pipeline.texture.atlas import dilate_gutter, rasterize_atlas, texel_geometry
from pipeline.texture.blend import (
    ViewSampler,
    clipped_pixels,
    depth_edges,
    robust_weights,
    sample_visible,
    sharpness_map,
)
from pipeline.texture.config import TextureConfig
from pipeline.texture.export import export_textured, read_textured
from pipeline.texture.stage import depth_maps, fill_unseen, object_size, texture_mesh, upright
from synth import scene_from_dict, write_scene
from synth.render import MeshShape
from tests.conftest import ROOT, SHARED

W = 256


@pytest.fixture(scope="module")
def baked(tmp_path_factory):
    ws = tmp_path_factory.mktemp("bake")
    sc = scene_from_dict({"shape": {"kind": "mesh", "path": str(SHARED / "meshes/cow/cow.obj")},
                          "albedo": {"kind": "texture"},
                          "cameras": {"n_views": 24, "width": W, "height": W, "rings": 2, "elevation": [0, 45],
                                      "heldout": 4}})
    write_scene(sc, ws)
    shape = MeshShape(sc.shape, ".")
    cams = load_cameras(ws / "cameras.npz")
    imgs = [cv2.cvtColor(cv2.imread(str(p)), cv2.COLOR_BGR2RGB).astype(np.float32) / 255
            for p in sorted((ws / "images").glob("*.png"))]
    gt = shape.gt
    out = texture_mesh(np.asarray(gt.vertices), np.asarray(gt.faces), imgs, cams, TextureConfig(size=1024), None)
    return ws, shape, out


def _heldout_psnr(ws, nv, nf, uvs, tex):
    hc = load_cameras(ws / "gt" / "heldout" / "cameras.npz")
    out = []
    for i in range(len(hc)):
        g = cv2.cvtColor(cv2.imread(str(ws / "gt" / "heldout" / "images" / f"{i:06d}.png")), cv2.COLOR_BGR2RGB) / 255.0
        a, ha = render_textured(nv, nf, uvs, tex, hc.K[i], hc.R[i], hc.centers[i], W, W)
        out.append(-10 * np.log10(((a - g)[ha] ** 2).mean()))
    return np.array(out)


def test_baked_texture_psnr_at_heldout_views(baked):
    ws, shape, (nv, nf, uvs, tex, stats) = baked
    hc = load_cameras(ws / "gt" / "heldout" / "cameras.npz")
    ref = []
    for i in range(len(hc)):
        g = cv2.cvtColor(cv2.imread(str(ws / "gt" / "heldout" / "images" / f"{i:06d}.png")), cv2.COLOR_BGR2RGB) / 255.0
        b, hb = render_textured(shape.mesh.vertices, shape.mesh.faces, shape.uv, shape.texture, hc.K[i], hc.R[i],
                                hc.centers[i], W, W)
        ref.append(-10 * np.log10(((b - g)[hb] ** 2).mean()))
    ours = _heldout_psnr(ws, nv, nf, uvs, tex)
    print("baked PSNR", np.round(ours, 2), "original texture", np.round(ref, 2))
    assert min(ref) > 50  # the renderer reproduces the photos from the original texture
    # the cow's 1024² texture holds far more detail than 24 photos of 256 px: the bake is photo-limited
    assert np.mean(ours) >= 35.0 and min(ours) >= 30.0


def noise_cow_photos(folder):
    """The cow with a smooth 3-D noise albedo, 24 photos of 256² and 4 held out written into ``folder``: (its scene,
    true mesh, cameras, photos as float32 RGB)."""
    sc = scene_from_dict({"shape": {"kind": "mesh", "path": str(SHARED / "meshes/cow/cow.obj")},
                          "albedo": {"kind": "noise", "scale": 1.0},
                          "cameras": {"n_views": 24, "width": W, "height": W, "rings": 2, "elevation": [0, 45],
                                      "heldout": 4}})
    write_scene(sc, folder)
    imgs = [cv2.cvtColor(cv2.imread(str(p)), cv2.COLOR_BGR2RGB).astype(np.float32) / 255
            for p in sorted((folder / "images").glob("*.png"))]
    return sc, MeshShape(sc.shape, ".").gt, load_cameras(folder / "cameras.npz"), imgs


def test_smooth_texture_baked_back_near_lossless(tmp_path):
    """A texture the photos resolve (smooth 3-D noise on the cow) comes back to within ~1 grey level RMS at
    held-out views; the oracle (the true albedo written straight into the same atlas) shows the limit of the
    atlas and of 8-bit images."""
    from synth.render import albedo_of

    sc, gt, cams, imgs = noise_cow_photos(tmp_path)
    cfg = TextureConfig(size=1024)
    nv, nf, uvs, tex, stats = texture_mesh(np.asarray(gt.vertices), np.asarray(gt.faces), imgs, cams, cfg, None)
    fid = rasterize_atlas(uvs, nf, tex.shape[0])
    r, c, pts, _ = texel_geometry(fid, uvs, nf, nv, np.ones_like(nv))
    oracle = np.zeros_like(tex)
    oracle[r, c] = albedo_of(sc, pts, None, None)
    oracle, _ = dilate_gutter(oracle, fid >= 0, cfg.gutter)
    ours, best = _heldout_psnr(tmp_path, nv, nf, uvs, tex), _heldout_psnr(tmp_path, nv, nf, uvs, oracle)
    print("smooth texture: baked", ours.round(2), "oracle atlas", best.round(2), "unseen", stats["unseen_frac"])
    assert best.min() > 50
    assert stats["unseen_frac"] < 0.03
    assert ours.mean() >= 48.0 and ours.min() >= 45.0


def test_depth_aware_sampling_never_mixes_the_occluder():
    """Texels just beside a depth step take only the pixels at their own depth (plain bilinear would blend
    in the occluder's colour: the check below fails for it)."""
    h, w = 8, 8
    depth = np.full((h, w), 2.0)
    depth[:, :4] = 1.0  # an occluder covers the left half
    img = np.zeros((h, w, 3))
    img[:, :4] = 1.0  # white occluder, black surface behind it
    edges = depth_edges(depth, 0.01, 1)
    x = np.array([3.6, 4.2, 6.5])  # between the last occluder column (3) and the first far column (4)
    y = np.full(3, 3.3)
    col, sup, edge = sample_visible(img, depth, edges, x, y, np.full(3, 2.0), np.full(3, 0.05))
    assert np.allclose(col, 0.0) and (sup > 0).all()
    assert edge[:2].all() and not edge[2]
    plain = sample_bilinear(img, x, y)
    assert plain[0].max() > 0.3  # what the depth test prevents
    col, sup, _ = sample_visible(img, depth, edges, x, y, np.full(3, 3.0), np.full(3, 0.05))
    assert (sup == 0).all()  # behind everything: not visible


def test_unseen_texels_never_black_without_field():
    pts = np.array([[0.0, 0, 0], [1.0, 0, 0], [0.1, 0, 0], [0.9, 0, 0]])
    col = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 0], [0, 0, 0]])
    unseen = np.array([False, False, True, True])
    fill = fill_unseen(pts, col, unseen, None)
    assert np.allclose(fill, [[1, 0, 0], [0, 1, 0]])


def test_every_face_covered(baked):
    _, _, (nv, nf, uvs, tex, stats) = baked
    assert stats["unseen_frac"] < 0.1
    size = tex.shape[0]
    cen = uvs[nf].mean(1)
    r = np.clip(((1 - cen[:, 1]) * size).astype(int), 0, size - 1)
    c = np.clip((cen[:, 0] * size).astype(int), 0, size - 1)
    assert stats["filled"][r, c].all()


def test_no_visible_seams(baked):
    """Mesh edges whose two faces lie in different charts: colours sampled along the edge in either chart agree."""
    _, _, (nv, nf, uvs, tex, stats) = baked
    size = tex.shape[0]
    m = trimesh.Trimesh(nv, nf, process=False)
    merged = trimesh.Trimesh(nv, nf, process=False)
    merged.merge_vertices(merge_tex=True, merge_norm=True)
    # pairs of faces sharing a 3-D edge
    adj, edges = merged.face_adjacency, merged.face_adjacency_edges
    diffs = []
    t = np.linspace(0.1, 0.9, 5)
    for (fa, fb), (ea, eb) in zip(adj, edges):
        pa, pb = merged.vertices[ea], merged.vertices[eb]

        def uv_on(face, pa=pa, pb=pb):
            vs = m.faces[face]
            ia = vs[np.argmin(np.linalg.norm(m.vertices[vs] - pa, axis=1))]
            ib = vs[np.argmin(np.linalg.norm(m.vertices[vs] - pb, axis=1))]
            return uvs[ia], uvs[ib]

        ua, ub = uv_on(fa)
        va, vb = uv_on(fb)
        if np.allclose(ua, va) and np.allclose(ub, vb):
            continue  # not a seam
        p1 = ua[None] + t[:, None] * (ub - ua)[None]
        p2 = va[None] + t[:, None] * (vb - va)[None]
        c1 = sample_bilinear(tex, p1[:, 0] * size - 0.5, (1 - p1[:, 1]) * size - 0.5)
        c2 = sample_bilinear(tex, p2[:, 0] * size - 0.5, (1 - p2[:, 1]) * size - 0.5)
        diffs.append(np.abs(c1 - c2).mean())
    assert len(diffs) > 50
    print("seam colour difference: median", np.median(diffs), "p95", np.percentile(diffs, 95))
    assert np.median(diffs) < 0.02 and np.percentile(diffs, 95) < 0.08


def _some_display() -> np.ndarray:
    """A rigid 4×4 node transform for the GLB (a turn and a shift)."""
    display = trimesh.transformations.rotation_matrix(0.7, [1, 2, 3])
    display[:3, 3] = [1, -2, 3]
    return display


def test_outputs_load(baked, tmp_path):
    import pymeshlab

    _, _, (nv, nf, uvs, tex, stats) = baked
    display = _some_display()
    export_textured(tmp_path, nv, nf, uvs, tex, display)
    for f in ("textured.obj", "textured.mtl", "textured.png", "textured.glb"):
        assert (tmp_path / f).exists(), f
    assert "textured.png" in (tmp_path / "textured.mtl").read_text()
    g, read_tex = read_textured(tmp_path / "textured.glb")  # the mesh as given: the node's transform not applied
    assert len(g.faces) == len(nf) and g.visual.uv.shape == (len(g.vertices), 2)
    np.testing.assert_allclose(g.vertices, nv, atol=1e-5)
    assert read_tex.shape == tex.shape
    seen = trimesh.load(tmp_path / "textured.glb", force="mesh")  # as a viewer places it: through the node
    np.testing.assert_allclose(seen.vertices, trimesh.transform_points(nv, display), atol=1e-5)
    ms = pymeshlab.MeshSet()
    ms.load_new_mesh(str(tmp_path / "textured.obj"))
    assert ms.current_mesh().face_number() == len(nf)
    # a GLB a killed or interrupted write left (the report reads it): one line naming it (was: numpy's "index 0 is
    # out of bounds" traceback for an empty file, json's message for a truncated one)
    from pipeline.errors import StageError

    glb = tmp_path / "textured.glb"
    whole = glb.read_bytes()
    for damaged in (b"", whole[: len(whole) // 3]):
        glb.write_bytes(damaged)
        with pytest.raises(StageError, match=r"textured.glb: unreadable GLB \(\w+\); rerun the texture stage"):
            read_textured(glb)
    assert ms.current_mesh().has_wedge_tex_coord() or ms.current_mesh().has_vertex_tex_coord()


def _level_ring(up: np.ndarray, n: int = 8, radius: float = 3.0, height: float = 1.0):
    """World → camera rotations and centres of a ring of level cameras (no roll) around the origin, looking at it,
    in a world whose up is ``up``."""
    up = up / np.linalg.norm(up)
    a = np.cross(up, [1.0, 0, 0]) if abs(up[0]) < 0.9 else np.cross(up, [0, 1.0, 0])
    a /= np.linalg.norm(a)
    b = np.cross(up, a)
    Rs, Cs = [], []
    for ang in np.linspace(0, 2 * np.pi, n, endpoint=False):
        c = radius * (np.cos(ang) * a + np.sin(ang) * b) + height * up
        z = -c / np.linalg.norm(c)
        x = np.cross(z, up)
        x /= np.linalg.norm(x)
        Rs.append(np.stack([x, np.cross(z, x), z])), Cs.append(c)
    return np.stack(Rs), np.stack(Cs)


@pytest.mark.parametrize("grounded", [True, False])
def test_upright_puts_the_glb_up_along_gltf_y(grounded):
    """The GLB's node turns the mesh's frame so that a viewer (glTF: +Y up) shows the object standing: +Y is the
    support plane's normal (else the cameras' up), the plane goes to y = 0, and the first camera lies level
    along +Z; the same display from the SfM frame as from the normalized one."""
    up = np.array([0.3, -0.8, 0.5])
    up /= np.linalg.norm(up)
    Rs, Cs = _level_ring(up)
    K = np.tile(np.array([[300.0, 0, 160], [0, 300, 120], [0, 0, 1]]), (len(Rs), 1, 1))
    ground = np.append(up, 0.6) if grounded else None  # the plane 0.6 below the sphere centre
    cams = Cameras(K, Rs, -np.einsum("nij,nj->ni", Rs, Cs), sphere_frame(np.array([2.0, -1.0, 5.0]), 4.0), ground)
    T, source = upright(cams, "normalized")
    assert source == ("support plane" if grounded else "cameras")
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
    assert np.linalg.det(T[:3, :3]) > 0
    np.testing.assert_allclose(T[:3, :3] @ up, [0, 1, 0], atol=1e-9)
    first = trimesh.transform_points(cams.centers[:1], T)[0]
    assert abs(first[0]) < 1e-9 and first[2] > 0
    on_plane = -0.6 * up + np.array([[0.0, 0, 0], [*np.cross(up, [1.0, 0, 0])]])
    heights = trimesh.transform_points(on_plane, T)[:, 1]
    np.testing.assert_allclose(heights, [0, 0] if grounded else [-0.6, -0.6], atol=1e-9)
    T_sfm, _ = upright(cams, "sfm")  # the same turn, in SfM's units: the display is the normalized one × radius
    points = np.random.default_rng(0).normal(size=(5, 3))
    np.testing.assert_allclose(trimesh.transform_points(to_sfm(points, cams.scale_mat), T_sfm),
                               4.0 * trimesh.transform_points(points, T), atol=1e-9)


def test_object_size_is_measured_upright():
    """object_size: the box of the mesh in the GLB's display frame, so height is along its up whatever the SfM frame
    (a box 0.1 × 0.3 × 0.2 along SfM x, y, z, shown with SfM z up: 0.2 high)."""
    box = trimesh.creation.box((0.1, 0.3, 0.2))
    z_up = np.eye(4)
    z_up[:3, :3] = [[1, 0, 0], [0, 0, 1], [0, -1, 0]]  # display y = SfM z, display z = −SfM y
    size = object_size(np.asarray(box.vertices) + 5.0, z_up)
    assert np.allclose([size["height"], size["width"], size["depth"]], [0.2, 0.1, 0.3])


def test_upright_of_an_object_on_a_wall_keeps_the_cameras_up():
    """An object hung on a wall: the support plane's normal is level (towards the cameras), so +Y is the capture's
    up, not the wall's normal (the object would open lying on its back), and +Z still points at the first camera."""
    up = np.array([0.0, 0.0, 1.0])
    Rs, Cs = _level_ring(up)
    K = np.tile(np.array([[300.0, 0, 160], [0, 300, 120], [0, 0, 1]]), (len(Rs), 1, 1))
    wall = np.array([1.0, 0.0, 0.0, 0.6])  # the plane x = −0.6, facing +x
    cams = Cameras(K, Rs, -np.einsum("nij,nj->ni", Rs, Cs), np.eye(4), wall)
    T, source = upright(cams, "normalized")
    assert source == "cameras"
    np.testing.assert_allclose(T[:3, :3] @ up, [0, 1, 0], atol=1e-9)
    first = trimesh.transform_points(cams.centers[:1], T)[0]
    assert abs(first[0]) < 1e-9 and first[2] > 0


def test_gltf_validator(baked, tmp_path):
    from tests.conftest import ROOT

    node = shutil.which("node")
    js = ROOT / "node_modules" / "gltf-validator"
    if node is None or not js.exists():
        pytest.skip("node or the npm gltf-validator is not installed (make setup-web installs it)")
    _, _, (nv, nf, uvs, tex, stats) = baked
    display = _some_display()
    export_textured(tmp_path, nv, nf, uvs, tex, display)  # with the upright node, as the stage writes it
    script = ("const v=require('gltf-validator');const fs=require('fs');"
              f"v.validateBytes(new Uint8Array(fs.readFileSync('{tmp_path / 'textured.glb'}')))"
              ".then(r=>{console.log(JSON.stringify(r.issues));process.exit(r.issues.numErrors>0?1:0)})"
              ".catch(e=>{console.error(e);process.exit(2)})")
    out = subprocess.run([node, "-e", script], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 0, out.stdout + out.stderr


def test_glb_textures_clamp_to_edge(tmp_path):
    """The GLB's texture samples clamped to the edge (glTF's default REPEAT would blend the atlas's opposite border
    into charts that reach it), with mip-mapped linear filtering."""
    import json
    import struct

    box = trimesh.creation.box()
    uvs = np.random.default_rng(0).random((len(box.vertices), 2))
    export_textured(tmp_path, box.vertices, box.faces, uvs, np.full((8, 8, 3), 0.5))
    data = (tmp_path / "textured.glb").read_bytes()
    tree = json.loads(data[20:20 + struct.unpack("<I", data[12:16])[0]])
    assert tree["textures"]
    for texture in tree["textures"]:
        sampler = tree["samplers"][texture["sampler"]]
        assert sampler["wrapS"] == sampler["wrapT"] == 33071  # CLAMP_TO_EDGE
        assert sampler["minFilter"] == 9987 and sampler["magFilter"] == 9729


def test_a_full_disk_while_the_png_is_written_stops_the_export(tmp_path, monkeypatch):
    """textured.png's failure to be written (a full disk) is the export's: no warning, no OBJ without its texture."""
    import errno

    from dvr import atomic

    real = atomic.os.replace

    def replace(src, dst):
        if str(dst).endswith("textured.png"):
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(src, dst)

    monkeypatch.setattr(atomic.os, "replace", replace)
    box = trimesh.creation.box()
    uvs = np.random.default_rng(0).random((len(box.vertices), 2))
    with pytest.raises(atomic.DiskFull, match="textured.png"):
        export_textured(tmp_path, box.vertices, box.faces, uvs, np.full((8, 8, 3), 0.5))
    assert not (tmp_path / "textured.png").exists()


# ---- synthetic scenes rendered here (a few small views; the bake's robustness features) ----

def look_at_camera(center, target, f: float, size: int, down=(0.0, 0.0, -1.0)):
    """(K, R, t) of a pinhole camera at ``center`` looking at ``target`` (x right, y down in the image)."""
    center, target = np.asarray(center, float), np.asarray(target, float)
    z = target - center
    z /= np.linalg.norm(z)
    x = np.cross(down, z)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    K = np.array([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1.0]])
    return K, R, -R @ center


def make_cameras(centers, target, f: float, size: int, down=(0.0, 0.0, -1.0)):
    """Cameras (normalized frame = world) at ``centers`` looking at ``target``, square images of ``size`` px."""
    from dvr.cameras import Cameras

    Ks, Rs, ts = zip(*[look_at_camera(c, target, f, size, down) for c in centers])
    return Cameras(np.stack(Ks), np.stack(Rs), np.stack(ts), np.eye(4))


def render_mesh(mesh, colour_of, cams, size: int, background=(0.0, 0.0, 0.0), supersample: int = 3):
    """Ray-cast photos (float32, anti-aliased by ``supersample``²): ``colour_of(points) -> (N, 3)`` on the mesh,
    ``background`` elsewhere."""
    from pipeline.render.raycast import MeshCaster, pixel_center_rays

    caster = MeshCaster(mesh)
    s = supersample
    out = []
    for i in range(len(cams)):
        K = np.diag([s, s, 1.0]) @ cams.K[i]
        o, d = pixel_center_rays(K, cams.R[i], cams.centers[i], size * s, size * s)
        ray, _, loc = caster.first_hits(o, d)
        img = np.tile(np.asarray(background, np.float64), (len(d), 1))
        img[ray] = colour_of(loc)
        img = img.reshape(size * s, size * s, 3).astype(np.float32)
        out.append(cv2.resize(img, (size, size), interpolation=cv2.INTER_AREA))
    return out


def plane_mesh(n: int = 21, half: float = 1.0) -> trimesh.Trimesh:
    """An n × n vertex grid over [−half, half]² at z = 0, normals +z."""
    g = np.linspace(-half, half, n)
    xx, yy = np.meshgrid(g, g)
    verts = np.stack([xx.ravel(), yy.ravel(), np.zeros(n * n)], 1)
    i = np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None]
    a, b, c, d = i.ravel(), i.ravel() + 1, i.ravel() + n, i.ravel() + n + 1
    faces = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    return trimesh.Trimesh(verts, faces, process=False)


def smooth_colour(p: np.ndarray) -> np.ndarray:
    """A smooth, non-green RGB pattern on 3-D points."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    return np.stack([0.55 + 0.15 * np.sin(3 * x + z), 0.35 + 0.1 * np.cos(2 * y), 0.45 + 0.1 * np.sin(2 * z + x)], 1)


def bake_texels(mesh, imgs, cams, cfg, clipped=None):
    """texture_mesh on a synthetic mesh: the baked colour and the true colour of every texel, and its 3-D point."""
    nv, nf, uvs, tex, _ = texture_mesh(np.asarray(mesh.vertices), np.asarray(mesh.faces), imgs, cams, cfg, None,
                                       clipped=clipped)
    fid = rasterize_atlas(uvs, nf, tex.shape[0])
    r, c, pts, _ = texel_geometry(fid, uvs, nf, nv, np.ones_like(nv))
    return tex[r, c].astype(np.float64), smooth_colour(pts), pts


SYNTH = dict(size=256, texel_density=0, sharpness_power=0.0)


@pytest.fixture(scope="module")
def plane_views():
    """Four views of a smoothly coloured plane (64 px); a white highlight drawn into view 0 only."""
    mesh = plane_mesh()
    cams = make_cameras([(-0.7, -0.7, 2.2), (0.7, -0.7, 2.2), (-0.7, 0.7, 2.2), (0.7, 0.7, 2.2)], (0, 0, 0), 50.0,
                        64, down=(0.0, -1.0, 0.0))
    imgs = render_mesh(mesh, smooth_colour, cams, 64)
    spot = np.array([0.15, 0.1, 0.0])
    uvw = cams.K[0] @ (cams.R[0] @ spot + cams.t[0])
    cv2.circle(imgs[0], (int(round(uvw[0] / uvw[2])), int(round(uvw[1] / uvw[2]))), 4, (1.0, 1.0, 1.0), -1)
    return mesh, cams, imgs, spot


def test_highlight_in_one_view_does_not_reach_texture(plane_views):
    """A white blob in one of four views: the photo-consistency pass drops it (without it, it shows)."""
    mesh, cams, imgs, spot = plane_views
    near = None
    err = {}
    for thr in (0.1, 0.0):
        baked, true, pts = bake_texels(mesh, imgs, cams, TextureConfig(**SYNTH, outlier_threshold=thr))
        near = np.linalg.norm(pts - spot, axis=1) < 0.12
        err[thr] = np.abs(baked - true)[near].max()
    print("max error at the highlight: robust", err[0.1], "plain", err[0.0])
    assert near.sum() > 50
    assert err[0.1] < 0.03
    assert err[0.0] > 0.1  # what the robust pass prevents


def test_float64_photos_bake_as_float32_photos(plane_views):
    """Photos read as float64 (8-bit values / 255, not representable in float32) bake to the texture of the same
    photos in float32; before texture_mesh cast them, the photo-consistency pass's extremes (float32) never equalled
    a float64 sample and indexed past the samples (IndexError)."""
    mesh, cams, imgs, _ = plane_views
    photos = [np.round(im.astype(np.float64) * 255) / 255 for im in imgs]
    got, _, _ = bake_texels(mesh, photos, cams, TextureConfig(**SYNTH))
    want, _, _ = bake_texels(mesh, [p.astype(np.float32) for p in photos], cams, TextureConfig(**SYNTH))
    assert np.array_equal(got, want)


def test_an_over_exposed_view_does_not_darken_the_texture(plane_views):
    """One of four views photographed 3× brighter (a dark backdrop fooling auto exposure), clipped at 1 as a camera
    clips, then divided by its gain (as the bake undoes a fitted exposure): its clipped pixels say only "at least
    this bright", and the bake keeps them out where the other views see the surface unclipped (without that they
    darken the texture)."""
    mesh, cams, _, _ = plane_views
    true = render_mesh(mesh, smooth_colour, cams, 64)
    gain = 3.0
    taken = [np.clip(true[0] * gain, 0.0, 1.0), *true[1:]]
    undone = [taken[0] / gain, *taken[1:]]
    clipped = [clipped_pixels(im, 0.98) for im in taken]
    assert clipped[0].mean() > 0.1 and not any(c.any() for c in clipped[1:])
    err = {}
    for name, level in (("kept out", 0.98), ("off", 2.0)):
        baked, colour, _ = bake_texels(mesh, undone, cams, TextureConfig(**SYNTH, clipped_level=level),
                                       clipped=[clipped_pixels(im, level) for im in taken])
        over = (colour * gain >= 1.0).any(1)  # texels the bright view saw clipped
        err[name] = float(np.abs(baked - colour)[over].mean())
    print("mean error of the texels the bright view saw clipped:", err)
    assert err["kept out"] < 0.01
    assert err["off"] > 2 * err["kept out"]  # what keeping clipped pixels out prevents


def test_clipped_pixels_values_and_bad_input():
    img = np.zeros((8, 8, 3), np.float32)
    img[4, 4, 1] = 1.0
    out = clipped_pixels(img, 0.98)
    assert out.shape == (8, 8) and out.dtype == bool
    assert out[3:6, 3:6].all() and out.sum() == 9  # the pixel and its neighbours (bilinear lookups blend them)
    assert not clipped_pixels(img, 1.5).any()
    with pytest.raises(ValueError, match="clipped_pixels"):
        clipped_pixels(np.zeros((8, 8)), 0.98)
    cams = make_cameras([(0, 0, 2.0)], (0, 0, 0), 50.0, 16, down=(0.0, -1.0, 0.0))
    with pytest.raises(ValueError, match="clipped"):
        ViewSampler(np.zeros((5, 3)), np.zeros((5, 3)), [np.zeros((16, 16, 3))], cams, [np.ones((16, 16))],
                    TextureConfig(), clipped=[np.zeros((8, 8), bool)])


def test_no_background_in_silhouette_band():
    """An object in front of pure green, baked on a slightly too large mesh (as reconstructions are): texels that
    project within 2 px of a silhouette hold no green (sampling the silhouette pixels, they do)."""
    truth = trimesh.creation.icosphere(subdivisions=3, radius=0.8)
    ring = [(2.5 * np.cos(a), 2.5 * np.sin(a), h) for a, h in zip(np.linspace(0, 2 * np.pi, 8, endpoint=False),
                                                                   [0.0, 1.0, 0.0, -1.0] * 2)]
    cams = make_cameras(ring, (0, 0, 0), 70.0, 80)
    imgs = render_mesh(truth, smooth_colour, cams, 80, background=(0.0, 1.0, 0.0))
    mesh = trimesh.Trimesh(truth.vertices * 1.03, truth.faces, process=False)
    depths = depth_maps(mesh, cams, [(80, 80)] * len(cams))
    green = {}
    for robust in (True, False):
        cfg = TextureConfig(**SYNTH, silhouette_px=1 if robust else 0)
        baked, true, pts = bake_texels(mesh, imgs, cams, cfg)
        band = np.zeros(len(pts), bool)
        for i, d in enumerate(depths):
            sil = depth_edges(d, 0.01, 2)
            x = (cams.P[i] @ np.concatenate([pts, np.ones((len(pts), 1))], 1).T).T
            u, v = (x[:, 0] / x[:, 2]).astype(int).clip(0, 79), (x[:, 1] / x[:, 2]).astype(int).clip(0, 79)
            seen = np.abs(d[v, u] - np.linalg.norm(pts - cams.centers[i], axis=1)) < 0.05
            band |= seen & sil[v, u]
        diff = baked - true
        green[robust] = diff[band, 1] - 0.5 * (diff[band, 0] + diff[band, 2])  # ≈ 1.2 × the green fraction
    print("green in the silhouette band (p99, max): ", {k: (np.percentile(g, 99), g.max()) for k, g in green.items()})
    assert len(green[True]) > 500
    assert np.percentile(green[True], 99) < 0.02 and green[True].max() < 0.06  # < 5 % green anywhere in the band
    assert green[False].max() > 0.1  # what leaving out the silhouette pixels prevents


def fine_pattern(p: np.ndarray) -> np.ndarray:
    """A fine grey checker-like pattern on the z = 0 plane."""
    return np.repeat((0.5 + 0.3 * np.sin(12 * p[:, :1]) * np.sin(12 * p[:, 1:2])), 3, 1)


def sharp_and_blurred_views():
    """Two equally placed views (96 px) of the finely patterned plane, the second defocused (σ = 2 px)."""
    mesh = plane_mesh()
    cams = make_cameras([(-0.5, 0.0, 2.2), (0.5, 0.0, 2.2)], (0, 0, 0), 60.0, 96, down=(0.0, -1.0, 0.0))
    imgs = render_mesh(mesh, fine_pattern, cams, 96)
    imgs[1] = cv2.GaussianBlur(imgs[1], (0, 0), 2.0)
    return mesh, cams, imgs


def inner_rms_error(mesh, imgs, cams, cfg) -> float:
    """RMS error of the baked texture against :func:`fine_pattern` over the plane's inner |x|, |y| < 0.7."""
    nv, nf, uvs, tex, _ = texture_mesh(mesh.vertices, mesh.faces, imgs, cams, cfg, None)
    fid = rasterize_atlas(uvs, nf, tex.shape[0])
    r, c, pts, _ = texel_geometry(fid, uvs, nf, nv, np.ones_like(nv))
    inner = (np.abs(pts[:, :2]) < 0.7).all(1)
    return float(np.sqrt(((tex[r, c] - fine_pattern(pts))[inner] ** 2).mean()))


def test_blurred_view_loses_to_sharp_view():
    """Two equally placed views of a finely patterned plane, one defocused: with the sharpness term the texture
    follows the sharp view."""
    mesh, cams, imgs = sharp_and_blurred_views()
    err = {power: inner_rms_error(mesh, imgs, cams, TextureConfig(**{**SYNTH, "sharpness_power": power},
                                                                  seam_levelling=False, outlier_threshold=0.0))
           for power in (1.0, 0.0)}
    print("RMS error with / without the sharpness term", err)
    assert err[1.0] < 0.9 * err[0.0]  # modest by design: the sharp view weighs about twice the blurred one


def test_robust_and_sharpness_helpers_reject_bad_shapes():
    with pytest.raises(ValueError, match="robust_weights"):
        robust_weights(np.zeros((4, 3)), np.zeros((4, 2)), np.zeros(4), 0.1, 3.0)
    with pytest.raises(ValueError, match="threshold"):
        robust_weights(np.zeros((4, 3)), np.zeros((4, 3)), np.zeros(4), 0.0, 3.0)
    with pytest.raises(ValueError, match="sharpness_map"):
        sharpness_map(np.zeros((8, 8)))
    with pytest.raises(ValueError, match="exclude"):
        sharpness_map(np.zeros((8, 8, 3)), np.zeros((4, 4), bool))
    cams = make_cameras([(0, 0, 2.0)], (0, 0, 0), 50.0, 16, down=(0.0, -1.0, 0.0))
    with pytest.raises(ValueError, match="ViewSampler"):
        ViewSampler(np.zeros((5, 3)), np.zeros((5, 2)), [np.zeros((16, 16, 3))], cams, [np.ones((16, 16))],
                    TextureConfig())
    with pytest.raises(ValueError, match="ViewSampler"):
        ViewSampler(np.zeros((5, 3)), np.zeros((5, 3)), [np.zeros((16, 16, 3))] * 2, cams, [np.ones((16, 16))],
                    TextureConfig())


def test_robust_weights_values():
    ref = np.full((3, 3), 0.5)
    col = np.array([[0.5, 0.5, 0.5], [0.6, 0.6, 0.6], [1.0, 1.0, 1.0]])
    w = robust_weights(col, ref, np.array([3, 3, 2]), 0.1, 3.0)
    assert np.allclose(w[:2], [1.0, 0.5], atol=1e-6)
    assert 0 < w[2] < 0.05  # far, but only 2 views: down-weighted, not dropped
    assert robust_weights(col, ref, np.array([3, 3, 3]), 0.1, 3.0)[2] == 0.0


# ---- fast paths against their simple references ----

def _reference_accumulate(n, views, extremes):
    """The blend sums one view at a time, as the bake first computed them; the extremes per tier."""
    acc, weight = np.zeros((3, n, 3)), np.zeros((3, n))
    count = np.zeros(n, np.int32)
    hi, lo = np.full((3, n, 3), -np.inf, np.float32), np.full((3, n, 3), np.inf, np.float32)
    hi_w, lo_w = np.zeros((3, n, 3), np.float32), np.zeros((3, n, 3), np.float32)
    for idx, col, w, tier in views:
        for k in range(3):
            s = tier == k
            acc[k][idx[s]] += w[s, None] * col[s]
            weight[k][idx[s]] += w[s]
            if extremes:
                i, c, wt = idx[s], col[s], np.broadcast_to(w[s, None], col[s].shape)
                for val, vw, better in ((hi[k], hi_w[k], np.greater), (lo[k], lo_w[k], np.less)):
                    cur = val[i]
                    up = better(c, cur)
                    val[i] = np.where(up, c, cur)
                    vw[i] = np.where(up, wt, vw[i])
        count[idx] += 1
    return acc, weight, count, hi, lo, hi_w, lo_w


def test_blend_accumulator_all_views_at_once_equals_view_by_view():
    """One add() of all views' samples (bincount sums, extremes by ufunc.at) gives bit for bit the sums, counts and
    extremes of adding the views one by one — ties (equal colours in two views) included: the first view wins."""
    from pipeline.texture.blend import BlendAccumulator

    rng = np.random.default_rng(3)
    n, views = 40, []
    for _ in range(6):
        idx = np.sort(rng.choice(n, 25, replace=False))
        col = (rng.integers(0, 5, (25, 3)) / 4).astype(np.float32)  # few levels: many ties
        views.append((idx, col, rng.random(25).astype(np.float32), rng.choice([0, 0, 0, 1, 2], 25).astype(np.int8)))
    acc, weight, count, hi, lo, hi_w, lo_w = _reference_accumulate(n, views, True)
    out = BlendAccumulator(n, extremes=True)
    out.add(*(np.concatenate(a) for a in zip(*views)))
    assert np.array_equal(out.count, count)
    for k in range(3):
        assert np.array_equal(out.acc[k], acc[k]) and np.array_equal(out.weight[k], weight[k])
    for got, want in ((out.hi, hi), (out.lo, lo), (out.hi_w, hi_w), (out.lo_w, lo_w)):
        assert np.array_equal(got.transpose(0, 2, 1), want)
    one_by_one = BlendAccumulator(n, extremes=True)
    for v in views:
        one_by_one.add(*v)
    for mode in (True, False):
        assert np.array_equal(out.reference(mode), one_by_one.reference(mode))
        assert np.array_equal(out.blend(mode)[0], one_by_one.blend(mode)[0])


def test_an_edge_sample_never_trims_a_clean_one():
    """The robust pass of a texel seen cleanly by some views judges them by THEIR trimmed mean: an edge sample (down-
    weighted, maybe background) neither counts as a view nor stands in for an extreme. Two clean views (0.5, 0.9)
    and a black edge sample: both clean views stay (0.7; counting the edge sample made it three views, trimmed the
    0.9 away and rejected it: 0.5). Three clean views and a white edge sample: the clean median is the reference, so
    the clean outlier is rejected."""
    from pipeline.texture.blend import blend_views

    cfg = TextureConfig(edge_weight=0.02, outlier_threshold=0.05, edge_fallback_only=True)
    for clean, edge, want in (([0.5, 0.9], 0.0, 0.7), ([0.5, 0.52, 0.95], 1.0, 0.51)):
        k = len(clean) + 1
        col = np.repeat(np.array(clean + [edge], np.float32)[:, None], 3, 1)
        weight = np.array([1.0] * len(clean) + [cfg.edge_weight], np.float32)
        samples = (np.zeros(k, np.intp), col, weight, np.array([0] * len(clean) + [1], np.int8))
        first = blend_views(samples, 1, cfg, extremes=True)
        assert first.tier_count(True)[0] == len(clean) and first.count[0] == k
        reference, count = first.reference(True), first.tier_count(True)
        got = blend_views(samples, 1, cfg, reference=reference, count=count).blend(True)[0][0]
        assert np.allclose(got, want, atol=2e-3), (clean, edge, got)


def test_sharpness_map_matches_kornia():
    """The OpenCV sharpness map is kornia's Sobel magnitude and Gaussian blur, to float rounding."""
    import kornia
    import torch

    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.random((40, 52, 3)).astype(np.float32), (0, 0), 1.0)
    exclude = rng.random((40, 52)) < 0.1
    grey = torch.from_numpy(img.mean(2))[None, None]
    grad = kornia.filters.sobel(grey, eps=0.0) * torch.from_numpy(~exclude)[None, None].float()
    want = kornia.filters.gaussian_blur2d(grad, (11, 11), (2.0, 2.0))[0, 0].numpy()
    got = sharpness_map(img, exclude)
    assert got.dtype == np.float32 and np.allclose(got, want, rtol=1e-5, atol=1e-7)


def test_texel_geometry_matches_row_formula():
    """Coordinate by coordinate, the texel points, normals and barycentrics are those of the (M, 3) row formula."""
    mesh = trimesh.creation.icosphere(subdivisions=2)
    from pipeline.texture.atlas import make_atlas

    vmap, nf, uvs, _ = make_atlas(mesh.vertices, mesh.faces, 30.0, 2, 128, 128)
    nv, normals = mesh.vertices[vmap], mesh.vertex_normals[vmap]
    fid = rasterize_atlas(uvs, nf, 128)
    r, c, pts, nrm, f, bary = texel_geometry(fid, uvs, nf, nv, normals, with_bary=True)
    rr, cc = np.nonzero(fid >= 0)
    p = np.stack([(cc + 0.5) / 128, 1.0 - (rr + 0.5) / 128], 1)
    a, b, d = uvs[nf[f, 0]], uvs[nf[f, 1]], uvs[nf[f, 2]]
    v0, v1, v2 = b - a, d - a, p - a
    den = v0[:, 0] * v1[:, 1] - v1[:, 0] * v0[:, 1]
    w1 = (v2[:, 0] * v1[:, 1] - v1[:, 0] * v2[:, 1]) / den
    w2 = (v0[:, 0] * v2[:, 1] - v2[:, 0] * v0[:, 1]) / den
    want = np.clip(np.stack([1 - w1 - w2, w1, w2], 1), 0, 1)
    want /= want.sum(1, keepdims=True)
    want_n = (normals[nf[f]] * want[:, :, None]).sum(1)
    assert np.array_equal(r, rr) and np.array_equal(c, cc) and np.array_equal(bary, want)
    assert np.array_equal(pts, (nv[nf[f]] * want[:, :, None]).sum(1))
    assert np.array_equal(nrm, want_n / np.linalg.norm(want_n, axis=1, keepdims=True))


def test_dilate_gutter_matches_filter_reference():
    """The ring-by-ring gutter is the full-image 3×3 mean filter of valid neighbours, step by step; texels it never
    reaches keep their values."""
    rng = np.random.default_rng(1)
    valid = cv2.dilate((rng.random((60, 70)) < 0.01).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    tex = rng.random((60, 70, 3)).astype(np.float32)
    want_tex, want_valid = tex.copy(), valid.copy()
    k = np.ones((3, 3), np.float32)
    for _ in range(3):
        m = want_valid.astype(np.float32)
        s = cv2.filter2D(want_tex * m[..., None], -1, k, borderType=cv2.BORDER_CONSTANT)
        cnt = cv2.filter2D(m, -1, k, borderType=cv2.BORDER_CONSTANT)
        grow = ~want_valid & (cnt > 0)
        want_tex[grow] = s[grow] / cnt[grow, None]
        want_valid |= grow
    got_tex, got_valid = dilate_gutter(tex, valid, 3)
    assert np.array_equal(got_valid, want_valid)
    assert np.allclose(got_tex, want_tex, rtol=1e-6, atol=1e-7)
    assert np.array_equal(got_tex[~want_valid], tex[~want_valid])


def test_bake_chunks_and_threads_do_not_change_the_texture(plane_views, monkeypatch):
    """Texels are baked in chunks, in threads: tiny chunks over several threads give the same texture, bit for bit."""
    from pipeline.texture import blend

    mesh, cams, imgs, _ = plane_views
    cfg = TextureConfig(**SYNTH)
    ref = texture_mesh(np.asarray(mesh.vertices), np.asarray(mesh.faces), imgs, cams, cfg, None)[3]
    monkeypatch.setattr(blend, "BAKE_CHUNK", 997)
    monkeypatch.setattr(blend, "BAKE_THREADS", 3)
    tiny = texture_mesh(np.asarray(mesh.vertices), np.asarray(mesh.faces), imgs, cams, cfg, None)[3]
    assert np.array_equal(ref, tiny)


def test_a_head_on_texel_whose_cosine_rounds_above_one_is_sampled():
    """A texel seen head-on whose normal rounds a hair above unit length (as float32 normalising gives): cos θ =
    1 + 2e-7, and sqrt(1 − cos²) was NaN, the depth tolerance NaN and the sample silently dropped."""
    import warnings

    cams = make_cameras([(0.0, 0.0, 2.0)], (0.0, 0.0, 0.0), 50.0, 64, down=(0.0, -1.0, 0.0))
    pts, nrm = np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0000002]])
    depth = np.full((64, 64), 2.0)
    sampler = ViewSampler(pts, nrm, [np.full((64, 64, 3), 0.5, np.float32)], cams, [depth], TextureConfig(**SYNTH))
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        idx, col, weight, _ = sampler.samples(0)
    assert list(idx) == [0] and np.isfinite(weight).all() and weight[0] > 0
    assert np.allclose(col, 0.5)


SHARPNESS_REPEATS = """
import sys
import numpy as np
from pipeline.texture.blend import sharpness_map
rng = np.random.default_rng(0)
img = rng.random((301, 403, 3)).astype(np.float32)
ref, held, differ = sharpness_map(img), [], 0
for _ in range(40):
    held.append(np.empty(int(rng.integers(1, 5000)), np.uint8))  # moves where numpy puts the next arrays
    out = sharpness_map(img)  # (the last result stays alive during the next call: another allocation pattern)
    differ += not np.array_equal(out, ref)
print(differ)
"""


def test_sharpness_map_is_the_same_on_every_call():
    """OpenCV's vectorised Sobel and blur round the last bit by where a buffer starts in memory: the same photo
    must give the same sharpness map wherever numpy happens to put the intermediate arrays (before the aligned
    buffers, 28 of these 40 calls differed; in a fresh interpreter, whose allocator state this depends on)."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", SHARPNESS_REPEATS], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "0"


def _texels_per_length(uvs: np.ndarray, nf: np.ndarray, verts: np.ndarray, side: int) -> float:
    """Area-weighted median of sqrt(texel area / surface area) over the faces: texels per unit length."""
    t = uvs[nf] * side
    uv_area = 0.5 * np.abs(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]))
    area = trimesh.triangles.area(verts[nf])
    ratio = np.sqrt(uv_area / area)
    order = np.argsort(ratio)
    cum = np.cumsum(area[order])
    return float(ratio[order][np.searchsorted(cum, 0.5 * cum[-1])])


def test_atlas_texels_are_texture_texels():
    """The texture holds the density asked for: xatlas's atlas is not square and not the side it was asked for,
    and squeezing it onto a square of the asked side gave 0.77× the density on DTU's mesh. Above the cap the
    atlas is re-charted at a lower density, never squeezed past it."""
    from pipeline.texture.atlas import make_atlas

    mesh = trimesh.creation.icosphere(subdivisions=3)
    vmap, nf, uvs, side = make_atlas(mesh.vertices, mesh.faces, 40.0, 4, 1024)
    assert 256 <= side <= 1024 and uvs.min() >= 0 and uvs.max() <= 1
    assert _texels_per_length(uvs, nf, mesh.vertices[vmap], side) == pytest.approx(40.0, rel=0.03)
    fid = rasterize_atlas(uvs, nf, side)
    assert len(np.unique(fid[fid >= 0])) == len(nf)  # every face has texels at this density

    vmap, nf, uvs, side = make_atlas(mesh.vertices, mesh.faces, 400.0, 4, 512)  # would need ~2400 texels
    assert 0.9 * 512 <= side <= 512 and uvs.max() <= 1
    assert _texels_per_length(uvs, nf, mesh.vertices[vmap], side) < 0.25 * 400


def test_a_large_mesh_past_the_cap_is_charted_once_and_scaled_onto_it(monkeypatch):
    """An atlas past the largest side is charted again at a lower density, unless the mesh has more than
    ``RECHART_FACES`` faces (charting again costs as much as the first time): then it is charted once and scaled
    onto the side, its uvs within it."""
    import xatlas

    from pipeline.texture import atlas

    calls = []

    class Counted(xatlas.Atlas):
        def generate(self, *args, **kwargs):
            calls.append(1)
            return super().generate(*args, **kwargs)

    monkeypatch.setattr(xatlas, "Atlas", Counted)
    monkeypatch.setattr(atlas, "ATLAS_UTILISATION", 0.95)  # the first try's density overshoots the cap
    mesh = trimesh.creation.icosphere(subdivisions=3)
    atlas.make_atlas(mesh.vertices, mesh.faces, 400.0, 4, 512)
    assert len(calls) > 1
    calls.clear()
    monkeypatch.setattr(atlas, "RECHART_FACES", len(mesh.faces) - 1)
    vmap, nf, uvs, side = atlas.make_atlas(mesh.vertices, mesh.faces, 400.0, 4, 512)
    assert len(calls) == 1 and side == 512 and 0 <= uvs.min() and uvs.max() <= 1
    fid = rasterize_atlas(uvs, nf, side)
    assert len(np.unique(fid[fid >= 0])) > 0.95 * len(nf)


def test_a_mesh_charted_in_pieces_is_one_atlas_of_the_same_faces(monkeypatch):
    """A mesh of more than twice ``PIECE_FACES`` faces is charted as pieces (boxes of space of equal face counts): one
    atlas, each face at its own corners in its own place in the faces' order, no two faces on one texel, the density
    asked for."""
    from pipeline.texture import atlas

    mesh = trimesh.creation.icosphere(subdivisions=4)  # 5120 faces
    pieces = atlas.split_faces(mesh.vertices, mesh.faces, 5)
    assert len(pieces) == 5 and np.array_equal(np.sort(np.concatenate(pieces)), np.arange(len(mesh.faces)))
    assert max(map(len, pieces)) - min(map(len, pieces)) <= 1
    monkeypatch.setattr(atlas, "PIECE_FACES", 1000)
    charted = []
    real_joined = atlas._joined
    monkeypatch.setattr(atlas, "_joined", lambda at, local, p: charted.append(len(p)) or real_joined(at, local, p))
    # charts bounded by a piece's scale are a few dozen texels across here (xatlas rounds smaller ones up)
    vmap, nf, uvs, side = atlas.make_atlas(mesh.vertices, mesh.faces, 160.0, 4, 2048)
    assert charted == [5]
    assert np.allclose(mesh.vertices[vmap][nf], mesh.vertices[mesh.faces])  # the same faces, in the same order
    assert uvs.min() >= 0 and uvs.max() <= 1
    assert _texels_per_length(uvs, nf, mesh.vertices[vmap], side) == pytest.approx(160.0, rel=0.03)
    fid = rasterize_atlas(uvs, nf, side)
    assert (np.bincount(fid[fid >= 0], minlength=len(nf)) > 0).all()
    assert _most_faces_on_a_texel(uvs * side, nf, side) == 1  # no two charts overlap


def _most_faces_on_a_texel(xy: np.ndarray, faces: np.ndarray, side: int) -> int:
    """The most UV triangles (``xy`` in texels) whose inside holds one texel centre."""
    count = np.zeros((side, side), np.int32)
    for tri in xy[faces]:
        (x0, y0), (x1, y1) = np.floor(tri.min(0)).astype(int), np.ceil(tri.max(0)).astype(int)
        px, py = np.meshgrid(np.arange(x0, x1) + 0.5, np.arange(y0, y1) + 0.5)
        a, b, c = tri
        den = (b[0] - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (b[1] - a[1])
        w1 = ((px - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (py - a[1])) / den
        w2 = ((b[0] - a[0]) * (py - a[1]) - (px - a[0]) * (b[1] - a[1])) / den
        inside = (w1 > 1e-6) & (w2 > 1e-6) & (w1 + w2 < 1 - 1e-6)
        count[y0:y1, x0:x1][inside] += 1
    return int(count.max())


def test_unreadable_clean_mesh_is_one_line(tmp_path):
    """clean.ply is the texture stage's input, and a user may edit it: a points-only PLY was an AttributeError
    traceback ('PointCloud' object has no attribute 'faces'), a damaged one trimesh's own message."""
    from pipeline.errors import StageError
    from pipeline.texture.stage import read_clean_mesh

    path = tmp_path / "clean.ply"
    trimesh.PointCloud(np.random.default_rng(0).normal(size=(10, 3))).export(path)
    with pytest.raises(StageError, match=r"clean.ply: holds no triangles \(PointCloud\); rerun the mesh stage"):
        read_clean_mesh(path)
    path.write_bytes(b"not a ply at all")
    with pytest.raises(StageError, match="clean.ply: unreadable mesh"):
        read_clean_mesh(path)
    box = trimesh.creation.box()
    box.export(path)
    assert len(read_clean_mesh(path).faces) == 12


def test_textured_caster_box_casts_only_its_pixels():
    """TexturedCaster.render with a box: the full render inside the box, nothing outside it."""
    from pipeline.render.textured import TexturedCaster

    ball = trimesh.creation.icosphere(subdivisions=3)
    uv = (ball.vertices[:, :2] + 1) / 2
    tex = np.random.default_rng(0).random((32, 32, 3))
    K = np.array([[120.0, 0, 40], [0, 120.0, 30], [0, 0, 1]])
    caster = TexturedCaster(ball.vertices, ball.faces, uv, tex)
    full, hit = caster.render(K, np.eye(3), np.array([0.0, 0, -4]), 80, 60)
    part, phit = caster.render(K, np.eye(3), np.array([0.0, 0, -4]), 80, 60, box=(10, 35, 20, 50))
    assert hit[10:35, 20:50].any() and hit.sum() > phit.sum()
    assert np.array_equal(phit[10:35, 20:50], hit[10:35, 20:50]) and not phit[:10].any() and not phit[:, 50:].any()
    assert np.array_equal(part[10:35, 20:50], full[10:35, 20:50]) and not part[35:].any()
    ref, ref_hit = render_textured(ball.vertices, ball.faces, uv, tex, K, np.eye(3), np.array([0.0, 0, -4]), 80, 60)
    assert np.array_equal(ref, full) and np.array_equal(ref_hit, hit)
