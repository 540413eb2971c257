"""Synthetic scenes: only the listed effects are computed; the workspace layout and ground truth are right."""

import json

import cv2
import numpy as np
import pytest
import trimesh

from synth import load_scene_file, scene_from_dict, write_scene
from tests.conftest import ROOT, SHARED, small_scene


def _img(ws, i=0):
    return cv2.cvtColor(cv2.imread(str(ws / "images" / f"{i:06d}.png")), cv2.COLOR_BGR2RGB) / 255.0


def test_only_listed_passes_and_albedo_only(tmp_path):
    meta = write_scene(small_scene(albedo={"kind": "constant", "color": [0.2, 0.6, 0.4]}), tmp_path)
    assert meta["passes"] == ["geometry", "albedo:constant"]
    img = _img(tmp_path)
    m = cv2.imread(str(tmp_path / "masks" / "000000.png"), 0) > 127
    assert m.any() and (~m).any()
    assert np.allclose(img[m], [0.2, 0.6, 0.4], atol=1 / 255)  # no lighting: the albedo itself
    assert np.all(img[~m] == 0)  # background none


def test_listed_effects_are_rendered(tmp_path):
    sc = small_scene(lighting={"kind": "lambertian"}, background={"kind": "backdrop"},
                     effects=[{"kind": "noise", "sigma": 0.02}, {"kind": "specular", "amount": 0.3},
                              {"kind": "exposure", "amount": 0.2}, {"kind": "blur", "sigma": 0.7},
                              {"kind": "distortion", "k1": -0.1}])
    meta = write_scene(sc, tmp_path)
    assert meta["passes"] == ["geometry", "albedo:checker", "normals", "lighting:lambertian", "background:backdrop",
                              "effect:noise", "effect:specular", "effect:exposure", "effect:blur",
                              "effect:distortion"]
    img = _img(tmp_path)
    m = cv2.imread(str(tmp_path / "masks" / "000000.png"), 0) > 127
    assert img[~m].std() > 0.05  # textured backdrop


def test_exposure_and_white_balance_are_recorded_per_view(tmp_path):
    """The exposure effect scales each view's colours by per-channel gains (exposure × white balance), different
    from view to view, and writes them to gt/exposure.json: the photos divided by them are the plain renders."""
    base = {"albedo": {"kind": "constant", "color": [0.5, 0.4, 0.3]}, "background": {"kind": "none"}}
    plain, lit = tmp_path / "plain", tmp_path / "exposed"
    write_scene(small_scene(**base), plain)
    assert not (plain / "gt" / "exposure.json").exists()
    write_scene(small_scene(**base, effects=[{"kind": "exposure", "amount": 0.3, "white_balance": 0.1}]), lit)
    gains = json.loads((lit / "gt" / "exposure.json").read_text())["images"]
    g = np.array([gains[f"{i:06d}"] for i in range(8)])
    assert g.shape == (8, 3) and g.std(0).min() > 0.02  # gains vary between views
    assert np.abs(g / g[:, 1:2] - 1).max() > 0.02  # and between channels (white balance)
    m = cv2.imread(str(plain / "masks" / "000000.png"), 0) > 127
    for i in range(8):
        a, b = _img(plain, i)[m], _img(lit, i)[m]
        assert np.allclose(b, np.clip(a * g[i], 0, 1), atol=1.5 / 255)


def test_layout_and_ground_truth(small_ws):
    for p in ["images/000000.png", "masks/000007.png", "cameras.npz", "gt/mesh.ply", "gt/depth/000000.npy",
              "depth/000000.npz", "gt/scene.json"]:
        assert (small_ws / p).exists(), p
    gt = trimesh.load(small_ws / "gt" / "mesh.ply")
    assert gt.is_watertight and gt.volume > 0
    torus_volume = 2 * np.pi ** 2 * 0.5 * 0.2 ** 2
    assert gt.volume == pytest.approx(torus_volume, rel=0.01)
    meta = json.loads((small_ws / "gt" / "scene.json").read_text())
    assert meta["n_views"] == 8 and "sparse_depth" in meta["passes"]


def test_sparse_depth_lies_on_the_surface(small_ws):
    import torch

    from dvr.data import load_scene
    from synth.render import sdf

    data = load_scene(small_ws, torch.device("cpu"))
    o, d = data.rays(data.depth_views, data.depth_uv)
    p = (o + data.depth_val[:, None] * d).double()
    shape = small_scene().shape
    assert sdf(shape, p).abs().max() < 1e-3


def test_mesh_scene_with_texture(tmp_path):
    sc = scene_from_dict({"shape": {"kind": "mesh", "path": str(SHARED / "meshes/cow/cow.obj")},
                          "albedo": {"kind": "texture"},
                          "cameras": {"n_views": 2, "width": 48, "height": 48}})
    meta = write_scene(sc, tmp_path)
    assert meta["passes"] == ["geometry", "albedo:texture"]
    gt = trimesh.load(tmp_path / "gt" / "mesh.ply")
    assert gt.is_watertight
    img = _img(tmp_path)
    m = cv2.imread(str(tmp_path / "masks" / "000000.png"), 0) > 127
    assert m.sum() > 100 and img[m].std() > 0.02


def test_bad_scene(tmp_path):
    with pytest.raises(ValueError, match="unknown Shape keys"):
        scene_from_dict({"shape": {"kind": "torus", "radios": 1}})
    with pytest.raises(ValueError, match="unknown analytic shape"):
        write_scene(scene_from_dict({"shape": {"kind": "blob"}, "cameras": {"n_views": 1, "width": 8,
                                                                           "height": 8}}), tmp_path)
    with pytest.raises(ValueError, match="world_scale"):
        write_scene(small_scene(world_scale=0.0), tmp_path)


def test_bad_scene_file_is_one_line_naming_it(tmp_path):
    """A scene file's YAML error is one line naming the file (not PyYAML's five lines), and so is an unknown key."""
    broken, unknown = tmp_path / "broken.yaml", tmp_path / "unknown.yaml"
    broken.write_text("shape: {kind: torus\n")
    unknown.write_text("shape: {kind: torus, radios: 1}\n")
    for path, said in ((broken, "broken.yaml: not valid YAML (line 2, column 1:"),
                       (unknown, "unknown.yaml: unknown Shape keys: ['radios']")):
        with pytest.raises(ValueError) as info:
            load_scene_file(path)
        assert str(info.value).startswith(str(tmp_path)) and said in str(info.value)
        assert len(str(info.value).splitlines()) == 1


def test_torus_axis_and_difference_shapes():
    """A mug's parts: a torus turned about y holds the points of its ring in the xz plane, and a difference keeps
    the first part less the others (the cup's wall, not its inside)."""
    import torch

    from synth.render import sdf
    from synth.scene import Shape

    ring = Shape(kind="torus", axis="y", radius=0.5, minor=0.1, center=[0.2, 0.0, 0.0])
    on_ring = torch.tensor([[0.7, 0.0, 0.0], [0.2, 0.0, 0.5], [-0.3, 0.0, 0.0], [0.2, 0.0, -0.5]])
    assert torch.allclose(sdf(ring, on_ring), torch.full((4,), -0.1), atol=1e-6)
    assert sdf(ring, torch.tensor([[0.2, 0.5, 0.0]])).item() > 0.3  # where the z-axis torus would be
    flat = Shape(kind="torus", radius=0.5, minor=0.1)
    assert sdf(flat, torch.tensor([[0.0, 0.5, 0.0]])).item() == pytest.approx(-0.1)
    tube = Shape(kind="cylinder", axis="x", radius=0.3, minor=0.0, size=[0, 0, 0.6])
    assert sdf(tube, torch.tensor([[0.5, 0.0, 0.0]])).item() < 0 < sdf(tube, torch.tensor([[0.0, 0.0, 0.5]])).item()
    cup = Shape(kind="difference", parts=[{"kind": "sphere", "radius": 0.5}, {"kind": "sphere", "radius": 0.4}])
    d = sdf(cup, torch.tensor([[0.0, 0.0, 0.0], [0.45, 0.0, 0.0], [0.0, 0.0, 0.6]]))
    assert d[0] == pytest.approx(0.4) and d[1] == pytest.approx(-0.05) and d[2] == pytest.approx(0.1)
    with pytest.raises(ValueError, match="two or more parts"):
        sdf(Shape(kind="difference", parts=[{"kind": "sphere"}]), on_ring)
    with pytest.raises(ValueError, match="axis must be"):
        sdf(Shape(kind="torus", axis="w"), on_ring)


def test_repo_scene_files_load():
    for f in (ROOT / "configs" / "scenes").glob("*.yaml"):
        load_scene_file(f)


def test_supersampling_is_listed_and_antialiases(tmp_path):
    """supersample: 3 box-filters 3×3 samples per pixel: silhouette pixels blend object and background,
    while masks and depth stay those of the pixel-centre ray (the same as without it)."""
    plain = write_scene(small_scene(albedo={"kind": "constant", "color": [1.0, 1.0, 1.0]}), tmp_path / "a")
    meta = write_scene(small_scene(albedo={"kind": "constant", "color": [1.0, 1.0, 1.0]},
                                   cameras={"supersample": 3}), tmp_path / "b")
    assert "supersample:3" in meta["passes"] and not any(p.startswith("supersample") for p in plain["passes"])
    a, b = _img(tmp_path / "a"), _img(tmp_path / "b")
    assert set(np.unique(a.round(3))) <= {0.0, 1.0}  # point sampling: hard edges
    assert ((b > 0.05) & (b < 0.95)).any()  # anti-aliased edges
    for f in ("masks/000000.png", "gt/depth/000000.npy"):
        x, y = tmp_path / "a" / f, tmp_path / "b" / f
        ra = np.load(x) if f.endswith(".npy") else cv2.imread(str(x), 0)
        rb = np.load(y) if f.endswith(".npy") else cv2.imread(str(y), 0)
        assert np.array_equal(ra, rb), f
    with pytest.raises(ValueError, match="supersample"):
        write_scene(small_scene(cameras={"supersample": 2}), tmp_path / "c")


def test_photo_scale_stores_larger_photos_of_the_same_views(tmp_path):
    """photo_scale: 3 stores the photos at 3 × the size (training and held-out, as a phone's sensor), and the ground
    truth stays at the working size: a photo shrunk by 3 × 3 box means is the scene rendered with supersample 3
    (to 8-bit rounding), masks and depth are the same, and the held-out reference is the shrunk photo."""
    over = {"albedo": {"kind": "checker", "scale": 4.0}, "cameras": {"supersample": 3, "heldout": 1}}
    ref = write_scene(small_scene(**over), tmp_path / "ref")
    big = write_scene(small_scene(**{**over, "cameras": {"heldout": 1, "photo_scale": 3}}), tmp_path / "big")
    assert "photo_scale:3" in big["passes"] and not any(p.startswith("photo_scale") for p in ref["passes"])
    photo, want = _img(tmp_path / "big"), _img(tmp_path / "ref")
    assert photo.shape == (192, 192, 3) and want.shape == (64, 64, 3)
    assert np.abs(photo.reshape(64, 3, 64, 3, 3).mean(axis=(1, 3)) - want).max() <= 1.01 / 255
    for f in ("masks/000000.png", "gt/depth/000000.npy", "gt/heldout/masks/000000.png"):
        x, y = tmp_path / "ref" / f, tmp_path / "big" / f
        assert np.array_equal(*(np.load(z) if f.endswith(".npy") else cv2.imread(str(z), 0) for z in (x, y))), f
    held = cv2.imread(str(tmp_path / "big" / "gt" / "heldout" / "photos" / "000000.png")) / 255.0
    held_gt = cv2.imread(str(tmp_path / "big" / "gt" / "heldout" / "images" / "000000.png")) / 255.0
    assert held.shape == (192, 192, 3) and held_gt.shape == (64, 64, 3)
    assert np.abs(held.reshape(64, 3, 64, 3, 3).mean(axis=(1, 3)) - held_gt).max() <= 1.01 / 255
    with pytest.raises(ValueError, match="photo_scale must be an odd"):
        write_scene(small_scene(cameras={"photo_scale": 2}), tmp_path / "even")
    with pytest.raises(ValueError, match="photo_scale > 1 does not go with the distortion"):
        write_scene(small_scene(cameras={"photo_scale": 3}, effects=[{"kind": "distortion", "k1": 0.1}]),
                    tmp_path / "dist")


def test_heldout_views_lie_between_training_views(tmp_path):
    from synth.render import camera_rig

    for rig in ({"rings": 0}, {"rings": 2, "elevation": [10, 40]}, {"rings": 3}):
        sc = small_scene(cameras={"n_views": 24, "heldout": 4, **rig})
        _, _, C = camera_rig(sc)
        _, _, Ch = camera_rig(sc, heldout=True)
        assert len(Ch) == 4
        d = np.linalg.norm(Ch[:, None] - C[None], axis=-1).min(1)
        spacing = np.linalg.norm(C[:, None] - C[None], axis=-1)
        spacing = np.sort(spacing, axis=1)[:, 1].min()  # closest pair of training cameras
        assert d.min() > 0.3 * spacing, rig  # no held-out view repeats (or nearly repeats) a training view


def test_mesh_up_axis(tmp_path):
    from synth.render import MeshShape
    from synth.scene import Shape

    z = MeshShape(Shape(kind="mesh", path=str(SHARED / "meshes/cow/cow.obj")), ".").mesh
    y = MeshShape(Shape(kind="mesh", path=str(SHARED / "meshes/cow/cow.obj"), up="y"), ".").mesh
    ez, ey = z.bounds[1] - z.bounds[0], y.bounds[1] - y.bounds[0]
    assert np.allclose(ey, ez[[0, 2, 1]], atol=1e-6)  # y and z extents swap
    with pytest.raises(ValueError, match="up"):
        MeshShape(Shape(kind="mesh", path=str(SHARED / "meshes/cow/cow.obj"), up="x"), ".")


# ----------------------------------------------------------------------------- the ground effect
def test_ground_effect_object_rests_on_a_plane_masks_and_mesh_object_only(tmp_path):
    ball = {"kind": "sphere", "radius": 0.5}
    base = dict(shape=ball, lighting={"kind": "lambertian"}, background={"kind": "constant", "color": [0, 0, 1]},
                cameras={"elevation": [20, 40]})
    meta = write_scene(small_scene(**base, effects=[{"kind": "ground", "pattern": "checker", "scale": 4.0}]),
                       tmp_path / "g")
    assert "effect:ground" in meta["passes"] and "ground_shadows" in meta["passes"]
    n, d = np.array(meta["ground_plane"][:3]), meta["ground_plane"][3]
    assert np.allclose(n, [0, 0, 1]) and -d == pytest.approx(-0.5 + 0.004, abs=0.003)  # touches the ball's bottom
    # the GT cameras carry the plane (SfM frame), as the cameras stage's do; a floating scene's carry none
    assert np.allclose(np.load(tmp_path / "g" / "cameras.npz")["ground_plane"], meta["ground_plane"])
    write_scene(small_scene(**base), tmp_path / "f")
    for i in range(8):
        mg = cv2.imread(str(tmp_path / "g" / "masks" / f"{i:06d}.png"), 0) > 127
        mf = cv2.imread(str(tmp_path / "f" / "masks" / f"{i:06d}.png"), 0) > 127
        assert (mg != mf).sum() <= 2  # the object alone (all but the sliver sunk into the plane)
        img = _img(tmp_path / "g", i)
        ground = ~mg & (np.abs(img - [0, 0, 1]).sum(-1) > 0.05)  # neither object nor the blue backdrop
        assert ground.mean() > 0.2  # the plane runs under and around the object
    assert "ground_plane" not in np.load(tmp_path / "f" / "cameras.npz").files
    gt = trimesh.load(tmp_path / "g" / "gt" / "mesh.ply")
    assert np.linalg.norm(gt.vertices, axis=1).max() < 0.51  # the object alone
    unlit = {**base, "lighting": {"kind": "none"}}
    ground_only = write_scene(small_scene(**unlit, effects=[{"kind": "ground", "pattern": "wood"}]), tmp_path / "n")
    assert "ground_shadows" not in ground_only["passes"]  # no lighting: no shadows computed


def test_ground_effect_as_a_wall_behind_the_object_seen_from_the_front(tmp_path):
    """``normal: [1, 0, 0]``: the plane is a wall at the object's back (its smallest x), touching it, facing the
    cameras, which ``azimuth`` keeps in front of it: every view sees the wall around the object, the masks hold the
    object alone, and the GT cameras carry the wall as the support plane."""
    from dvr.cameras import load_cameras

    ball = {"kind": "sphere", "radius": 0.5}
    base = dict(shape=ball, lighting={"kind": "lambertian"}, background={"kind": "constant", "color": [0, 0, 1]},
                cameras={"elevation": [-10, 30], "azimuth": [-60, 60]})
    wall = {"kind": "ground", "normal": [1, 0, 0], "pattern": "checker", "scale": 4.0}
    meta = write_scene(small_scene(**base, effects=[wall]), tmp_path / "w")
    n, d = np.array(meta["ground_plane"][:3]), meta["ground_plane"][3]
    assert np.allclose(n, [1, 0, 0]) and -d == pytest.approx(-0.5 + 0.004, abs=0.003)  # touches the ball's back
    cams = np.load(tmp_path / "w" / "cameras.npz")
    assert np.allclose(cams["ground_plane"], meta["ground_plane"])
    write_scene(small_scene(**base), tmp_path / "f")
    for i in range(8):
        mw = cv2.imread(str(tmp_path / "w" / "masks" / f"{i:06d}.png"), 0) > 127
        mf = cv2.imread(str(tmp_path / "f" / "masks" / f"{i:06d}.png"), 0) > 127
        assert (mw != mf).sum() <= 2  # the object alone
        img = _img(tmp_path / "w", i)
        on_wall = ~mw & (np.abs(img - [0, 0, 1]).sum(-1) > 0.05)
        assert on_wall.mean() > 0.5  # the wall behind and around the object
    centres = load_cameras(tmp_path / "w" / "cameras.npz").centers  # the canonical frame (world_scale 1)
    az = np.degrees(np.arctan2(centres[:, 1], centres[:, 0]))
    assert az.min() >= -60 - 1e-6 and az.max() < 60 and az.max() - az.min() > 90  # the arc in front of the wall


def test_ground_patterns_and_soft_contact_shadow():
    from synth.ground import ground_albedo, ground_shading
    from synth.scene import Effect

    xy = np.random.default_rng(0).uniform(-2, 2, (5000, 2))
    for pattern in ("wood", "tiles", "checker", "noise"):
        a = ground_albedo(xy, Effect(kind="ground", pattern=pattern))
        assert a.shape == (5000, 3) and a.min() >= 0 and a.max() <= 1 and a.std() > 0.03, pattern
    with pytest.raises(ValueError, match="pattern"):
        ground_albedo(xy, Effect(kind="ground", pattern="marble"))
    e = Effect(kind="ground", shadow=0.6, softness=0.1)
    centre, r = np.array([0.0, 0.0, 0.5]), 0.5  # a ball resting on z = 0

    def occluded(o, d):
        oc = o - centre
        b = (oc * d).sum(1)
        disc = b * b - ((oc * oc).sum(1) - r * r)
        return (disc > 0) & (-b + np.sqrt(np.clip(disc, 0, None)) > 0)

    def distance(p):
        return np.linalg.norm(p - centre, axis=1) - r

    pts = np.array([[0.05, 0.0, 0.0], [0.3, 0.0, 0.0], [3.0, 0.0, 0.0], [0.0, 0.0 + 0.9, 0.0]])
    light = [[0.0, -1.0, 1.0, 0.8]]  # from −y, 45° up: the ball's shadow falls towards +y
    s = ground_shading(pts, light, 0.4, e, occluded, distance)
    assert s[0] < s[1] < s[2]  # darker towards the contact point
    assert s[3] < s[2] - 0.3  # inside the cast shadow
    assert s[2] == pytest.approx(0.4 + 0.8 / np.sqrt(2), abs=1e-3)  # far away: ambient + cos · intensity


def test_the_stool_scene_mesh_is_one_closed_solid():
    """configs/scenes/meshes/stool.obj is what its generator (stool.py beside it) writes: one closed solid, a seat on
    four legs, with the volume and area of its boxes."""
    from configs.scenes.meshes.stool import LEGS, SEAT, boxes_surface

    mesh = trimesh.load(ROOT / "configs" / "scenes" / "meshes" / "stool.obj")
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.body_count == 1
    seat_w, seat_d, seat_h = (hi - lo for lo, hi in SEAT)
    leg_w, leg_d, leg_h = (hi - lo for lo, hi in LEGS[0])
    assert mesh.volume == pytest.approx(seat_w * seat_d * seat_h + 4 * leg_w * leg_d * leg_h)

    def box_area(w, d, h):
        return 2 * (w * d + w * h + d * h)

    boxes = box_area(seat_w, seat_d, seat_h) + 4 * box_area(leg_w, leg_d, leg_h)
    assert mesh.area == pytest.approx(boxes - 2 * 4 * leg_w * leg_d)  # less the legs' tops and the seat's underside
    v, f = boxes_surface([SEAT, *LEGS])
    assert trimesh.Trimesh(v, f).area == pytest.approx(mesh.area)  # the committed file is the generator's


def test_a_relief_raises_bumps_that_sphere_tracing_meets_first():
    """A sphere with bumps: the distance less the bumps' height, and rays stop at the first crossing of that
    surface (found by dense sampling), not beyond a bump they stepped over."""
    import torch

    from synth.render import sdf, sphere_trace
    from synth.scene import Shape

    ball = Shape(kind="sphere", radius=0.5, relief=0.05, relief_scale=6.0)
    p = torch.tensor([[0.5, 0.0, 0.0], [0.5 / 3**0.5] * 3], dtype=torch.float64)
    bumps = 0.05 * torch.sin(2 * torch.pi * 6.0 * p).prod(dim=-1)
    assert torch.allclose(sdf(ball, p), -bumps)
    torch.manual_seed(0)
    o = torch.randn(400, 3, dtype=torch.float64)
    o = 0.99 * o / o.norm(dim=1, keepdim=True)  # from the bounding sphere, towards points near the ball's edge
    aim = 0.45 * torch.randn(400, 3, dtype=torch.float64).clamp(-1, 1)
    d = (aim - o) / (aim - o).norm(dim=1, keepdim=True)
    hit, t = sphere_trace(ball, o, d)
    steps = torch.linspace(0, 2, 4001, dtype=torch.float64)
    along = sdf(ball, (o[:, None] + steps[None, :, None] * d[:, None]).reshape(-1, 3)).view(400, -1)
    inside = along < 0
    first = torch.where(inside.any(1), steps[inside.int().argmax(1)], torch.inf)
    assert hit.sum() > 100 and torch.equal(hit, torch.isfinite(first))
    assert (t[hit] - first[hit]).abs().max() < 1e-3
