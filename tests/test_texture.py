"""Texture baking from photos: a known textured object (the cow) baked back from its renderings; seams
match across charts; every face is covered; the outputs load (GLB in trimesh, OBJ in pymeshlab)."""

import shutil
import subprocess

import cv2
import numpy as np
import pytest
import trimesh

from dvr.cameras import load_cameras
from pipeline.cameras_config import TextureConfig
from pipeline.synth import scene_from_dict, write_scene
from pipeline.synth.render import MeshShape
from pipeline.texture import export_textured, render_textured, sample_bilinear, texture_mesh
from tests.conftest import SHARED

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


def test_baked_texture_psnr_at_heldout_views(baked):
    ws, shape, (nv, nf, uvs, tex, stats) = baked
    hc = load_cameras(ws / "gt" / "heldout" / "cameras.npz")
    ours, ref = [], []
    for i in range(len(hc)):
        g = cv2.cvtColor(cv2.imread(str(ws / "gt" / "heldout" / "images" / f"{i:06d}.png")), cv2.COLOR_BGR2RGB) / 255.0
        a, ha = render_textured(nv, nf, uvs, tex, hc.K[i], hc.R[i], hc.centers[i], W, W)
        b, hb = render_textured(shape.mesh.vertices, shape.mesh.faces, shape.uv, shape.texture, hc.K[i], hc.R[i],
                                hc.centers[i], W, W)
        m = ha | hb
        ours.append(-10 * np.log10(((a - g)[m] ** 2).mean()))
        ref.append(-10 * np.log10(((b - g)[m] ** 2).mean()))
    print("baked PSNR", np.round(ours, 2), "original texture", np.round(ref, 2))
    assert min(ref) > 50  # the renderer reproduces the photos from the original texture
    assert np.mean(ours) >= 30.0  # baked from 24 photos of 256 px


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

        def uv_on(face):
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


def test_outputs_load(baked, tmp_path):
    import pymeshlab

    _, _, (nv, nf, uvs, tex, stats) = baked
    export_textured(tmp_path, nv, nf, uvs, tex)
    for f in ("textured.obj", "textured.mtl", "textured.png", "textured.glb"):
        assert (tmp_path / f).exists(), f
    assert "textured.png" in (tmp_path / "textured.mtl").read_text()
    g = trimesh.load(tmp_path / "textured.glb", force="mesh")
    assert len(g.faces) == len(nf) and g.visual.uv.shape == (len(g.vertices), 2)
    ms = pymeshlab.MeshSet()
    ms.load_new_mesh(str(tmp_path / "textured.obj"))
    assert ms.current_mesh().face_number() == len(nf)
    assert ms.current_mesh().has_wedge_tex_coord() or ms.current_mesh().has_vertex_tex_coord()


def test_gltf_validator(baked, tmp_path):
    from tests.conftest import ROOT

    node = shutil.which("node")
    js = ROOT / "node_modules" / "gltf-validator"
    if node is None or not js.exists():
        pytest.skip("node or the npm gltf-validator is not installed (make setup-web installs it)")
    _, _, (nv, nf, uvs, tex, stats) = baked
    export_textured(tmp_path, nv, nf, uvs, tex)
    script = ("const v=require('gltf-validator');const fs=require('fs');"
              f"v.validateBytes(new Uint8Array(fs.readFileSync('{tmp_path / 'textured.glb'}')))"
              ".then(r=>{console.log(JSON.stringify(r.issues));process.exit(r.issues.numErrors>0?1:0)})"
              ".catch(e=>{console.error(e);process.exit(2)})")
    out = subprocess.run([node, "-e", script], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 0, out.stdout + out.stderr
