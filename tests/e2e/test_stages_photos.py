"""Stages cameras, masks, depth on a synthetic textured object on a textured backdrop (COLMAP must register it),
plus their bad inputs."""

import hashlib
import shutil

import cv2
import numpy as np
import pytest
from PIL import Image

from dvr.cameras import load_cameras
from dvr.metrics import pose_errors, umeyama
from pipeline.cameras.export import normalization
from pipeline.cli import main
from pipeline.inputs.photos import list_photos, read_upright
from pipeline.stages import run_stage
from synth import load_scene_file, write_scene
from tests.conftest import ROOT

N_VIEWS = 24


def _tree_hash(folder):
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*")):
        if p.is_file():
            h.update(p.name.encode() + p.read_bytes() + str(p.stat().st_mtime_ns).encode())
    return h.hexdigest()


@pytest.fixture(scope="module")
def photo_ws(tmp_path_factory):
    """Synthetic photos (no masks, no cameras given) → cameras → masks → depth."""
    root = tmp_path_factory.mktemp("photos")
    syn = root / "synthetic"
    write_scene(load_scene_file(ROOT / "configs" / "scenes" / "torus_backdrop.yaml"), syn)
    before = _tree_hash(syn / "images")
    ws = root / "ws"
    run_stage("cameras", ws, images=syn / "images")
    run_stage("masks", ws)
    run_stage("depth", ws)
    assert _tree_hash(syn / "images") == before  # inputs untouched
    return syn, ws


def _centres_sfm(c):
    return c.centers @ c.scale_mat[:3, :3].T + c.scale_mat[:3, 3]


def test_all_registered_and_poses_within_1pct(photo_ws):
    syn, ws = photo_ws
    est, gt = load_cameras(ws / "cameras.npz"), load_cameras(syn / "cameras.npz")
    assert len(est) == N_VIEWS  # every view registered
    err = pose_errors(_centres_sfm(est), est.R, _centres_sfm(gt), gt.R)
    assert err["center_err_rel_max"] <= 0.01, err
    assert err["rot_err_deg_max"] < 1.0, err
    for p in ("sfm/database.db", "sfm/sparse/best/cameras.bin", "points.ply", "images/000000.png"):
        assert (ws / p).exists(), p


def test_object_inside_unit_sphere(photo_ws):
    import trimesh

    syn, ws = photo_ws
    est, gt = load_cameras(ws / "cameras.npz"), load_cameras(syn / "cameras.npz")
    s, R, t = umeyama(_centres_sfm(gt), _centres_sfm(est))  # GT world → SfM frame
    v = trimesh.load(syn / "gt" / "mesh.ply").vertices
    v_sfm = s * v @ R.T + t
    v_n = (v_sfm - est.scale_mat[:3, 3]) / est.scale_mat[0, 0]
    r = np.linalg.norm(v_n, axis=1)
    assert r.max() < 1.0 and r.max() > 0.5  # inside, and not lost in a huge sphere


def test_auto_masks_iou(photo_ws):
    syn, ws = photo_ws
    ious = []
    for i in range(N_VIEWS):
        a = cv2.imread(str(ws / "masks" / f"{i:06d}.png"), 0) > 127
        b = cv2.imread(str(syn / "gt" / "masks" / f"{i:06d}.png"), 0) > 127
        b = b[: a.shape[0], : a.shape[1]]  # undistortion crops ≤ 1 px at the right/bottom
        ious.append((a & b).sum() / (a | b).sum())
    assert np.mean(ious) >= 0.95, np.round(ious, 3)
    assert (ws / "masks" / "overlays" / "000000.jpg").exists() and (ws / "masks" / "confidence.json").exists()


def test_mask_seeds_skip_observations_off_their_point(photo_ws, tmp_path):
    """A wrong match makes a view "observe" a point its ray does not meet (a backdrop point behind the object); the
    masks' seeds keep only observations that reproject within ``seed_max_error`` × the mean error: the moved
    observations go, nearly all others stay, and 0 keeps every one."""
    import pycolmap

    from pipeline.masks.stage import _tracks
    from pipeline.workspace import Workspace

    _, ws = photo_ws
    rec = pycolmap.Reconstruction(ws / "sfm" / "undistorted" / "sparse")
    names = sorted(rec.image(i).name.rsplit(".", 1)[0] for i in rec.reg_image_ids())
    moved = {}
    for i in sorted(rec.reg_image_ids())[:4]:  # one observation per view 6 px off its point
        im = rec.image(i)
        p = next(p for p in im.points2D if p.has_point3D())
        p.xy = p.xy + np.array([6.0, 0.0])
        moved[im.name.rsplit(".", 1)[0]] = p.point3D_id
    copy = Workspace(tmp_path / "ws")
    (copy.root / "sfm" / "undistorted" / "sparse").mkdir(parents=True)
    rec.write(copy.root / "sfm" / "undistorted" / "sparse")
    ids = list(rec.points3D.keys())
    _, every = _tracks(copy, names, 0.0)
    _, kept = _tracks(copy, names, 1.0)
    for name, pid in moved.items():
        assert ids.index(pid) in every[name] and ids.index(pid) not in kept[name]
    total = sum(len(v) for v in every.values())
    assert total == rec.compute_num_observations()
    assert sum(len(v) for v in kept.values()) >= 0.5 * total


def test_sparse_depth_matches_gt(photo_ws):
    syn, ws = photo_ws
    est, gt = load_cameras(ws / "cameras.npz"), load_cameras(syn / "cameras.npz")
    s, _, _ = umeyama(_centres_sfm(est), _centres_sfm(gt))
    rel = []
    for i in range(N_VIEWS):
        z = np.load(ws / "depth" / f"{i:06d}.npz")
        g = np.load(syn / "gt" / "depth" / f"{i:06d}.npy")
        ij = np.floor(z["uv"]).astype(int)
        gv = g[ij[:, 1], ij[:, 0]]
        d = z["depth"] * est.scale_mat[0, 0] * s
        ok = gv > 0
        rel.append(np.abs(d[ok] - gv[ok]) / gv[ok])
        assert np.all((z["confidence"] > 0) & (z["confidence"] <= 1))
    rel = np.concatenate(rel)
    assert len(rel) > 200 and np.median(rel) <= 0.01


def test_photos_of_one_exposure_measure_no_spread(photo_ws):
    """The cameras stage's exposure record (pipeline/scene/exposure.py) of photos the generator took at one exposure:
    every view measured, all within 1 % of the average (so ``--train.appearance auto`` stays off)."""
    from pipeline.scene.exposure import read_exposure

    est = read_exposure(photo_ws[1] / "exposure.json")
    assert len(est.names) == N_VIEWS and (est.points >= 20).all()
    assert est.spread() < 0.01 and np.abs(np.log(est.gains)).max() < 0.02, est.gains


def test_exposure_record_is_a_cameras_output(photo_ws):
    """exposure.json is one of the cameras stage's outputs (with an SfM model): a workspace that lost it is not up to
    date, and a failed run that rewrote it is not rolled back as if nothing changed."""
    from pipeline.stages import stage_named
    from pipeline.workspace import Workspace

    ws = Workspace(photo_ws[1])
    assert ws.exposure.exists() and ws.exposure in stage_named("cameras").outputs(ws)


def test_stages_are_idempotent(photo_ws, capsys):
    syn, ws = photo_ws
    assert main(["cameras", str(ws), "--images", str(syn / "images")]) == 0
    assert main(["masks", str(ws)]) == 0
    out = capsys.readouterr().out
    assert "cameras: up to date" in out and "masks: up to date" in out


# ----------------------------------------------------------------------------- bad input
def test_too_few_images(tmp_path, capsys):
    (tmp_path / "p").mkdir()
    for i in range(2):
        cv2.imwrite(str(tmp_path / "p" / f"{i}.png"), np.zeros((20, 20, 3), np.uint8))
    rc = main(["cameras", str(tmp_path / "ws"), "--images", str(tmp_path / "p")])
    err = capsys.readouterr().err
    assert rc == 2 and "at least 3" in err


def test_unreadable_and_non_images_skipped_with_warning(tmp_path):
    (tmp_path / "a.png").write_bytes(b"not a png")
    (tmp_path / "notes.txt").write_text("hi")
    cv2.imwrite(str(tmp_path / "b.png"), np.zeros((8, 8, 3), np.uint8))
    ok, skipped = list_photos(tmp_path)
    assert [p.name for p in ok] == ["b.png"]
    assert any("a.png" in s and "unreadable" in s for s in skipped)
    assert any("notes.txt" in s for s in skipped)


def test_workspace_inside_photos_refused(tmp_path, capsys):
    rc = main(["cameras", str(tmp_path / "ws"), "--images", str(tmp_path)])
    assert rc == 2 and "must not be" in capsys.readouterr().err


def test_unregistered_images_named(photo_ws, tmp_path, capsys):
    syn, _ = photo_ws
    d = tmp_path / "mixed"
    d.mkdir()
    for i in (0, 2, 4, 6, 8):  # neighbours on the lower ring
        shutil.copy(syn / "images" / f"{i:06d}.png", d / f"good{i}.png")
    rng = np.random.default_rng(0)
    for i in range(6):
        cv2.imwrite(str(d / f"noise{i}.png"), cv2.GaussianBlur(rng.integers(0, 255, (240, 320, 3), np.uint8),
                                                              (0, 0), 3))
    rc = main(["cameras", str(tmp_path / "ws"), "--images", str(d)])
    err = capsys.readouterr().err
    assert rc == 2
    import re

    assert re.search(r"only \d/11 photos registered", err), err
    # more than five names become a count and the first three, grouped by why they were left out
    assert "6 photos (noise0, noise1, noise2, …) (no verified match" in err and "likely" in err, err


# ----------------------------------------------------------------------------- EXIF, given cameras, masks
def _exif_jpeg(path, w, h, orientation):
    img = Image.new("RGB", (w, h))
    img.paste((255, 0, 0), (0, 0, w // 2, h))  # left half red in stored pixels
    exif = Image.Exif()
    exif[0x0112] = orientation
    img.save(path, exif=exif.tobytes())


def test_exif_orientation_applied_for_sfm_and_training(tmp_path):
    _exif_jpeg(tmp_path / "a.jpg", 40, 20, 6)  # 6: rotate 90° clockwise to display
    _exif_jpeg(tmp_path / "b.jpg", 40, 20, 1)
    a, b = read_upright(tmp_path / "a.jpg", 1000), read_upright(tmp_path / "b.jpg", 1000)
    assert a.shape[:2] == (40, 20) and b.shape[:2] == (20, 40)
    assert a[2, 10, 2] > 200 and a[-3, 10, 2] < 50  # stored left half (red) is now the top


def test_given_cameras_skip_sfm(photo_ws, tmp_path):
    """Given cameras are kept as given (no mapping); features are triangulated at their poses, so sparse depth
    exists as after SfM, and the depths agree with the GT depth maps; without triangulation: no points, no depth."""
    syn, _ = photo_ws
    ws = tmp_path / "given"
    run_stage("cameras", ws, images=syn / "images", given_cameras=syn / "cameras.npz")
    a, b = load_cameras(ws / "cameras.npz"), load_cameras(syn / "cameras.npz")
    assert np.allclose(a.centers, b.centers, atol=1e-6) and np.allclose(a.K, b.K, atol=1e-6)
    assert np.allclose(a.scale_mat, b.scale_mat)
    assert not (ws / "sfm" / "ladder").exists()  # no mapping ran
    run_stage("depth", ws)
    rel = []
    for i in range(N_VIEWS):
        z, g = np.load(ws / "depth" / f"{i:06d}.npz"), np.load(syn / "gt" / "depth" / f"{i:06d}.npy")
        ij = np.floor(z["uv"]).astype(int)
        gv = g[ij[:, 1], ij[:, 0]]
        ok = gv > 0
        rel.append(np.abs(z["depth"][ok] * a.scale_mat[0, 0] - gv[ok]) / gv[ok])
    rel = np.concatenate(rel)
    assert len(rel) > 200 and np.median(rel) <= 0.005, (len(rel), np.median(rel))
    plain = tmp_path / "plain"
    assert main(["cameras", str(plain), "--images", str(syn / "images"), "--given-cameras", str(syn / "cameras.npz"),
                 "--cameras.no-triangulate-given"]) == 0
    assert not (plain / "sfm").exists()
    run_stage("depth", plain)
    assert not (plain / "depth").exists()


def test_given_colmap_model_skips_sfm(photo_ws, tmp_path, capsys):
    syn, ws0 = photo_ws
    model = tmp_path / "model"
    shutil.copytree(ws0 / "sfm" / "sparse" / "best", model)  # a COLMAP model made from these photos
    ws = tmp_path / "given_model"
    run_stage("cameras", ws, images=syn / "images", given_cameras=model)
    a, b = load_cameras(ws / "cameras.npz"), load_cameras(ws0 / "cameras.npz")
    assert np.allclose(a.P, b.P, atol=1e-6) and np.allclose(a.scale_mat, b.scale_mat)
    assert sorted(p.name for p in (ws / "images").iterdir()) == sorted(p.name for p in (ws0 / "images").iterdir())
    run_stage("depth", ws)
    assert len(list((ws / "depth").glob("*.npz"))) > 0
    assert main(["cameras", str(tmp_path / "bad"), "--images", str(syn / "images"), "--given-cameras",
                 str(tmp_path)]) == 2  # a folder that is no model
    assert "not a COLMAP sparse model" in capsys.readouterr().err


def test_given_colmap_model_of_jpeg_photos(photo_ws, tmp_path):
    """A model made from JPEGs (a user's own COLMAP run): COLMAP's undistorter keeps each image's name, and the
    board search read ``<stem>.png`` there, so every such model failed ("unreadable; rerun the cameras stage")."""
    import pycolmap

    syn, ws0 = photo_ws
    photos = tmp_path / "jpeg"
    photos.mkdir()
    rec = pycolmap.Reconstruction(ws0 / "sfm" / "sparse" / "best")
    for i in rec.reg_image_ids():
        stem = rec.image(i).name.rsplit(".", 1)[0]
        cv2.imwrite(str(photos / f"{stem}.jpg"), cv2.imread(str(syn / "images" / f"{stem}.png")))
        rec.image(i).name = f"{stem}.jpg"
    model = tmp_path / "model"
    model.mkdir()
    rec.write(model)
    ws = tmp_path / "given_jpeg_model"
    run_stage("cameras", ws, images=photos, given_cameras=model)
    a, b = load_cameras(ws / "cameras.npz"), load_cameras(ws0 / "cameras.npz")
    assert np.allclose(a.P, b.P, atol=1e-6)
    assert sorted(p.name for p in (ws / "images").iterdir()) == sorted(p.name for p in (ws0 / "images").iterdir())


def test_normalization_ignores_background_points():
    rng = np.random.default_rng(0)
    obj = rng.normal(size=(500, 3)) * 0.2 + [1.0, 2.0, 3.0]
    bg = rng.normal(size=(300, 3)) * 20
    ang = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    centers = np.stack([np.cos(ang) * 4, np.sin(ang) * 4, np.zeros(12)], 1) + [1.0, 2.0, 3.0]
    dirs = [1.0, 2.0, 3.0] - centers
    K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
    Ps, sizes = [], []
    for c, d in zip(centers, dirs):
        z = d / np.linalg.norm(d)
        x = np.cross(z, [0, 0, 1.0])
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(z, x), z])
        Ps.append(K @ np.concatenate([R, (-R @ c)[:, None]], 1))
        sizes.append((320, 240))
    Ps, sizes = np.stack(Ps), np.asarray(sizes, float)
    S = normalization(np.concatenate([obj, bg]), Ps, sizes, centers, dirs, 1.1)
    assert np.allclose(S[:3, 3], [1.0, 2.0, 3.0], atol=0.05)
    assert 0.5 < S[0, 0] < 1.0
    # a weakly textured object: too few points of its own, the background's would set the radius; the images
    # bound it (the sphere through the image corners: 4 · sin(atan(200 / 300)) = 2.2, × 1.25)
    few = np.concatenate([obj[:10], bg])
    assert normalization(few, Ps, sizes, centers, dirs, 1.1)[0, 0] > 3.5  # up to the cameras without focals
    S = normalization(few, Ps, sizes, centers, dirs, 1.1, focals=np.full(12, 300.0))
    assert np.allclose(S[:3, 3], [1.0, 2.0, 3.0], atol=0.05)
    assert abs(S[0, 0] - 1.25 * 4 * np.sin(np.arctan(200 / 300))) < 1e-6
    assert 0.5 < normalization(np.concatenate([obj, bg]), Ps, sizes, centers, dirs, 1.1, np.full(12, 300.0))[0, 0] < 1


def test_reconstruct_names_a_missing_user_mask_before_sfm(photo_ws, tmp_path, capsys):
    """``reconstruct --masks-dir`` with a photo whose mask is missing stops at once with the masks stage's one line,
    before the cameras stage (not after SfM: on DTU 17 s later), and writes nothing."""
    syn, _ = photo_ws
    (tmp_path / "m").mkdir()
    for i in range(1, N_VIEWS):  # 000000's mask missing
        shutil.copy(syn / "gt" / "masks" / f"{i:06d}.png", tmp_path / "m" / f"{i:06d}.png")
    ws = tmp_path / "ws"
    assert main(["reconstruct", str(ws), "--images", str(syn / "images"), "--masks-dir", str(tmp_path / "m")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "m: no mask for 000000; name each mask like its photo" in err[0]
    assert not (ws / "cameras.npz").exists() and not (ws / ".stages" / "cameras.json").exists()


def test_user_masks_validated(photo_ws, tmp_path, capsys):
    syn, ws0 = photo_ws
    ws = tmp_path / "ws"
    shutil.copytree(ws0, ws, ignore=shutil.ignore_patterns("masks", ".stages"))
    assert main(["masks", str(ws), "--masks-dir", str(tmp_path / "m")]) == 2  # the fix names the real option
    assert "m: not a folder; pass --masks-dir DIR" in capsys.readouterr().err
    (tmp_path / "m").mkdir()
    assert main(["masks", str(ws), "--masks-dir", str(tmp_path / "m")]) == 2
    assert "no mask for 000000" in capsys.readouterr().err
    for i in range(N_VIEWS):
        shutil.copy(syn / "gt" / "masks" / f"{i:06d}.png", tmp_path / "m" / f"{i:06d}.png")
    cv2.imwrite(str(tmp_path / "m" / "000003.png"), np.full((240, 320), 128, np.uint8))
    assert main(["masks", str(ws), "--masks-dir", str(tmp_path / "m")]) == 2
    assert "neither black nor white" in capsys.readouterr().err
    ones = (cv2.imread(str(syn / "gt" / "masks" / "000003.png"), 0) > 127).astype(np.uint8)  # numpy's 0/1 mask
    cv2.imwrite(str(tmp_path / "m" / "000003.png"), ones)
    assert main(["masks", str(ws), "--masks-dir", str(tmp_path / "m")]) == 2  # not: every pixel background
    assert "000003.png: mask of 0 and 1; save the object as 255" in capsys.readouterr().err
    shutil.copy(syn / "gt" / "masks" / "000003.png", tmp_path / "m" / "000003.png")
    cv2.imwrite(str(tmp_path / "m" / "000003.jpg"), ones * 255)  # a second mask of the same photo
    assert main(["masks", str(ws), "--masks-dir", str(tmp_path / "m")]) == 2  # not: whichever comes last
    assert "000003.jpg and 000003.png are masks of one photo" in capsys.readouterr().err
    (tmp_path / "m" / "000003.jpg").unlink()
    (tmp_path / "m" / "000003.json").write_text("{}")  # a labelme file beside its mask is not a mask
    assert main(["masks", str(ws), "--masks-dir", str(tmp_path / "m")]) == 0
    m = cv2.imread(str(ws / "masks" / "000003.png"), 0)
    assert m.shape == cv2.imread(str(ws / "images" / "000003.png"), 0).shape
    # a rerun with a wrong folder or one bad mask loses nothing: every mask is checked before those of before go
    # (the stage emptied masks/ first, and a typo in --masks-dir left the workspace without masks); having changed
    # nothing, it leaves the masks stage done, as it was, so training may use them
    before = {p.name: p.read_bytes() for p in (ws / "masks").glob("*.png")}
    stamp = ws / ".stages" / "masks.json"
    done = stamp.read_bytes(), stamp.stat().st_mtime
    (tmp_path / "m" / "000005.png").unlink()
    for folder in (tmp_path / "typo", tmp_path / "m"):
        assert main(["masks", str(ws), "--masks-dir", str(folder), "--force"]) == 2
        assert {p.name: p.read_bytes() for p in (ws / "masks").glob("*.png")} == before
        assert (stamp.read_bytes(), stamp.stat().st_mtime) == done
        assert not (ws / ".stages" / "masks.unfinished").exists()


def _synthetic_model(k):
    import pycolmap

    o = pycolmap.SyntheticDatasetOptions()
    o.num_rigs, o.num_frames_per_rig, o.num_points3D = 1, 8, 300
    o.camera_model_id = pycolmap.CameraModelId.SIMPLE_RADIAL
    o.camera_params = [1280.0, 512.0, 384.0, k]
    o.sensor_from_rig_translation_stddev = 0.0
    o.sensor_from_rig_rotation_stddev = 0.0
    return pycolmap.synthesize_dataset(o)


def test_pinhole_replaces_distortion_that_explains_nothing_real_distortion_stays():
    from pipeline.cameras.mapping import prefer_pinhole

    rec = _synthetic_model(1e-4)  # moves the image corners by 0.02 px
    out, notes = prefer_pinhole(rec, 0.1)
    cam = next(iter(out.cameras.values()))
    assert cam.params[3] == 0.0 and notes and "pinhole" in notes[0]
    assert out.compute_mean_reprojection_error() < 0.1
    assert next(iter(rec.cameras.values())).params[3] == 1e-4  # the input model is not modified
    # a pinhole scene that SfM fitted with a spurious distortion and a long focal length: the true focal returns
    rec = _synthetic_model(0.0)
    cam = next(iter(rec.cameras.values()))
    cam.params = [1280.0 * 1.05, 512.0, 384.0, 0.02]
    rec.cameras[cam.camera_id] = cam
    assert next(iter(rec.cameras.values())).params[3] == 0.02
    out, notes = prefer_pinhole(rec, 0.1)
    cam = next(iter(out.cameras.values()))
    assert notes and "pinhole" in notes[-1]
    assert cam.params[3] == 0.0 and abs(cam.params[0] / 1280.0 - 1) < 0.005, cam.params
    rec = _synthetic_model(0.05)  # tens of pixels at the corners: a real lens, which a pinhole fits worse
    out, notes = prefer_pinhole(rec, 0.1)
    assert next(iter(out.cameras.values())).params[3] == 0.05 and "kept" in notes[0]
    out, notes = prefer_pinhole(_synthetic_model(1e-4), -1.0)  # negative disables the check
    assert next(iter(out.cameras.values())).params[3] == 1e-4 and notes == []


def _mapped_with_outliers(seed: int = 0):
    """A synthetic model as COLMAP's mapper leaves it: 0.3 px keypoint noise, 8 % of the observations 2 px off
    (inside the mapper's 4 px), bundle-adjusted with a plain squared loss. Returns (ground truth, model)."""
    import pycolmap

    pycolmap.set_random_seed(seed)  # the synthetic scene and its noise
    gt = _synthetic_model(0.0)
    rec = pycolmap.Reconstruction(gt)
    noise = pycolmap.SyntheticNoiseOptions()
    noise.point2D_stddev = 0.3
    pycolmap.synthesize_noise(noise, rec)
    rng = np.random.default_rng(seed)
    for i in rec.reg_image_ids():
        for p in rec.image(i).points2D:  # edited in place
            if p.has_point3D() and rng.random() < 0.08:
                p.xy = p.xy + rng.normal(0.0, 2.0, 2)
    opts = pycolmap.BundleAdjustmentOptions()
    opts.print_summary, opts.refine_extra_params = False, False
    pycolmap.bundle_adjustment(rec, opts)
    return gt, rec


def _rotation_error_deg(gt, rec) -> float:
    """Mean rotation error (°) of ``rec``'s views against ``gt``'s after a Sim(3) of the centres (the adjustment
    does not fix the gauge)."""
    def poses(model):
        M = np.stack([model.image(i).cam_from_world().matrix() for i in sorted(gt.reg_image_ids())])
        return -np.einsum("nji,nj->ni", M[:, :, :3], M[:, :, 3]), M[:, :, :3]

    return pose_errors(*poses(rec), *poses(gt))["rot_err_deg_mean"]


def test_final_adjustment_drops_the_tail_the_mapper_keeps():
    """Observations a few pixels off pull a squared-loss adjustment: the final passes (drop what lies above 2.5 × the
    mean error, re-adjust with a Cauchy loss) bring the rotations closer to the truth, keep the distortion at 0, and
    leave the input model as it was."""
    from pipeline.cameras.sfm import refine_model

    gt, rec = _mapped_with_outliers()
    before = _rotation_error_deg(gt, rec)
    e_in, n_in = rec.compute_mean_reprojection_error(), rec.compute_num_observations()
    out, notes = refine_model(rec, 3, 2.5)
    after = _rotation_error_deg(gt, out)
    print(f"rotation error {before:.4f}° → {after:.4f}°", notes)
    assert after < 0.6 * before
    assert out.compute_num_observations() < n_in and out.compute_mean_reprojection_error() < e_in
    assert notes and f"kept {out.compute_num_observations()}/{n_in} observations" in notes[0]
    assert next(iter(out.cameras.values())).params[3] == 0.0  # a pinhole stays a pinhole
    assert rec.compute_num_observations() == n_in and _rotation_error_deg(gt, rec) == before  # input untouched


def test_final_adjustment_off_or_too_few_points_keeps_the_mapped_model():
    from pipeline.cameras.sfm import refine_model

    _, rec = _mapped_with_outliers()
    assert refine_model(rec, 0, 2.5) == (rec, [])
    out, notes = refine_model(rec, 3, 2.5, min_points_per_view=10**6)  # every view would be short
    assert out is rec and "skipped" in notes[0]


def test_final_adjustment_through_the_cameras_stage(photo_ws, tmp_path):
    """``--cameras.final-passes 3`` on the torus photos: the stage runs the passes, says so in its stamp and the
    report, and the poses stay as good as the plain run's (the op's gain is tested above on a known model); with
    ``--cameras.final-retriangulate`` the points are triangulated afresh at the adjusted poses."""
    import json

    from pipeline.report.stage import capture_section
    from pipeline.workspace import Workspace

    syn, plain = photo_ws
    ws = tmp_path / "final"
    assert main(["cameras", str(ws), "--images", str(syn / "images"), "--cameras.final-passes", "3",
                 "--cameras.final-retriangulate"]) == 0
    stamp = json.loads((ws / ".stages" / "cameras.json").read_text())
    assert stamp["final_adjustment"][0].startswith("final adjustment: 3 passes kept")
    # the points re-triangulated at the adjusted poses: the sparse depth keeps the observations the passes dropped
    import pycolmap

    kept = {name: pycolmap.Reconstruction(w / "sfm" / "sparse" / "best").compute_num_observations()
            for name, w in (("plain", plain), ("final", ws))}
    print(kept, stamp["final_adjustment"])
    assert "re-triangulated" in stamp["final_adjustment"][1] and kept["final"] >= 0.95 * kept["plain"]
    assert "Final adjustment: 3 passes kept" in capture_section(Workspace(ws), stamp)
    assert json.loads((plain / ".stages" / "cameras.json").read_text())["final_adjustment"] == []  # off by default
    gt = load_cameras(syn / "cameras.npz")
    errs = {}
    for name, w in (("plain", plain), ("final", ws)):
        est = load_cameras(w / "cameras.npz")
        errs[name] = pose_errors(_centres_sfm(est), est.R, _centres_sfm(gt), gt.R)["rot_err_deg_mean"]
    print(errs)
    assert errs["final"] <= 1.1 * errs["plain"]


def test_the_same_photos_give_the_same_cameras(photo_ws, tmp_path):
    """COLMAP on one thread (``cameras.deterministic``, the default): a second run of the cameras stage on the
    same photos gives the first run's cameras to the last bit (on all cores they differ by ~1e-3)."""
    syn, ws = photo_ws
    again = tmp_path / "again"
    assert main(["cameras", str(again), "--images", str(syn / "images")]) == 0
    first, second = np.load(ws / "cameras.npz"), np.load(again / "cameras.npz")
    assert first.files == second.files
    for key in first.files:
        np.testing.assert_array_equal(second[key], first[key], err_msg=key)


def test_a_saved_mapping_gives_the_cameras_of_the_run_that_mapped_it(photo_ws, tmp_path, monkeypatch):
    """The benchmark's stand-in for the SfM ladder (:func:`pipeline.cameras.mapping.map_photos`) returns a
    workspace's saved model; the rest of the cameras stage (:func:`pipeline.cameras.mapping.finish_model`, the frame,
    the support plane) then gives that workspace's cameras again, without mapping, and the final passes change them."""
    import pipeline.cameras.mapping as mapping
    from bench.arms import from_mapping

    def no_mapping(*args):
        raise AssertionError("mapped again")

    syn, plain = photo_ws
    monkeypatch.setattr(mapping, "run_rung", no_mapping)
    monkeypatch.setattr(mapping, "map_photos", from_mapping(plain))
    again, passes = tmp_path / "again", tmp_path / "passes"
    assert main(["cameras", str(again), "--images", str(syn / "images")]) == 0
    assert main(["cameras", str(passes), "--images", str(syn / "images"), "--cameras.final-passes", "3"]) == 0
    a, b, c = (np.load(w / "cameras.npz") for w in (plain, again, passes))
    assert a.files == b.files
    for key in a.files:
        np.testing.assert_allclose(b[key], a[key], rtol=0, atol=1e-9, err_msg=key)
    assert not np.allclose(c["world_mat_0"], a["world_mat_0"], rtol=0, atol=1e-9)


def test_a_model_from_a_later_rung_gets_the_final_passes(photo_ws, tmp_path, monkeypatch):
    """The final adjustment's passes run by default on a model that the ladder had to climb for
    (``cameras.climbed_passes``), and not on one from the first rung; its points are re-triangulated only where the
    passes take the object's sphere below the points it needs (``cameras.climbed_retriangulate``). The torus's saved
    mapping, reported as mapped at the 'dsp' rung, gives the cameras and points of ``--cameras.final-passes 3``
    (its sphere keeps its points); with the sphere's counts stubbed (100 as mapped, 0 after the passes) those of
    ``--cameras.final-passes 3 --cameras.final-retriangulate``, but not where the sphere was short as mapped
    already (10, then 5); ``--cameras.climbed-passes 0`` gives it back as mapped."""
    import json

    import trimesh

    import pipeline.cameras.mapping as mapping
    from bench.arms import from_mapping
    from dvr.cameras import to_normalized
    from dvr.data import list_images
    from pipeline.cameras.export import SPHERE_MIN_POINTS, central_points

    syn, plain = photo_ws
    saved = from_mapping(plain)

    def climbed(*args):
        rec, inp, database, rung, tried, doubtful = saved(*args)
        assert rung == "default"
        return rec, inp, database, "dsp", tried, doubtful

    images = ["--images", str(syn / "images")]
    monkeypatch.setattr(mapping, "map_photos", saved)
    assert main(["cameras", str(tmp_path / "passes"), *images, "--cameras.final-passes", "3",
                 "--cameras.final-retriangulate"]) == 0
    assert main(["cameras", str(tmp_path / "kept"), *images, "--cameras.final-passes", "3"]) == 0
    monkeypatch.setattr(mapping, "map_photos", climbed)
    assert main(["cameras", str(tmp_path / "climbed"), *images]) == 0
    assert main(["cameras", str(tmp_path / "off"), *images, "--cameras.climbed-passes", "0"]) == 0
    for name, counts in (("short", [100, 0]), ("short_as_mapped", [10, 5])):  # sphere points as mapped, after
        told = iter(counts)
        with monkeypatch.context() as m:
            m.setattr(mapping, "sphere_points", lambda rec, cfg, told=told: next(told))
            assert main(["cameras", str(tmp_path / name), *images]) == 0
    a, passes, kept, auto, short, short_before, off = (np.load(w / "cameras.npz") for w in (plain, *(
        tmp_path / n for n in ("passes", "kept", "climbed", "short", "short_as_mapped", "off"))))
    for key in a.files:
        np.testing.assert_allclose(auto[key], kept[key], rtol=0, atol=1e-9, err_msg=key)
        np.testing.assert_allclose(short[key], passes[key], rtol=0, atol=1e-9, err_msg=key)
        np.testing.assert_allclose(short_before[key], kept[key], rtol=0, atol=1e-9, err_msg=key)  # nothing to undo
        np.testing.assert_allclose(off[key], a[key], rtol=0, atol=1e-9, err_msg=key)
    assert not np.allclose(auto["world_mat_0"], a["world_mat_0"], rtol=0, atol=1e-9)
    points = {n: trimesh.load(tmp_path / n / "points.ply").vertices for n in ("kept", "passes", "climbed", "short")}
    np.testing.assert_allclose(points["climbed"], points["kept"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(points["short"], points["passes"], rtol=0, atol=1e-9)
    assert len(points["short"]) > len(points["kept"])  # re-triangulated: the points the passes dropped are back
    notes = json.loads((tmp_path / "climbed" / ".stages" / "cameras.json").read_text())["final_adjustment"]
    left = int(notes[1].split("sphere ")[1].split(" of")[0])
    assert "points kept as adjusted" in notes[1] and left >= SPHERE_MIN_POINTS
    # the count is what the object's sphere is fitted to: the exported points inside most views
    cams = load_cameras(tmp_path / "climbed" / "cameras.npz")
    sizes = np.array([cv2.imread(str(p)).shape[1::-1] for p in list_images(tmp_path / "climbed" / "images")], float)
    in_frame = to_normalized(points["climbed"], cams.scale_mat)
    assert len(central_points(in_frame, cams.P, sizes)[1]) == left
    assert "points re-triangulated" in json.loads((tmp_path / "short" / ".stages" / "cameras.json").read_text()
                                                  )["final_adjustment"][1]


def test_floating_object_has_no_support_plane(photo_ws):
    """The torus floats in front of its backdrop: no plane carries it, and the cameras stage records none."""
    import json

    syn, ws = photo_ws
    assert "ground_plane" not in np.load(ws / "cameras.npz").files
    assert load_cameras(ws / "cameras.npz").ground is None
    assert json.loads((ws / ".stages" / "cameras.json").read_text())["support"] is None


def test_given_cameras_survive_a_failed_triangulation(small_ws, tmp_path, monkeypatch, capsys):
    """COLMAP failing on the given photos costs the sparse depth, never the given cameras: one warning line."""
    from pipeline.cameras import given as given_cameras

    def fails(*args, **kwargs):
        raise RuntimeError("no features")

    monkeypatch.setattr(given_cameras, "triangulate_at", fails)
    ws = tmp_path / "given"
    assert main(["cameras", str(ws), "--images", str(small_ws / "images"), "--given-cameras",
                 str(small_ws / "cameras.npz")]) == 0
    assert "points triangulated at the given cameras" in capsys.readouterr().err
    assert not (ws / "sfm").exists()
    a, b = load_cameras(ws / "cameras.npz"), load_cameras(small_ws / "cameras.npz")
    assert np.allclose(a.centers, b.centers) and np.allclose(a.scale_mat, b.scale_mat)


def test_given_cameras_file_checked_entry_by_entry(tmp_path, capsys):
    """A given cameras.npz with a broken entry stops the cameras stage with one line naming the file and the entry
    (not decompose_projection's message without either, or a KeyError traceback for a gap in the indices)."""
    photos = tmp_path / "photos"
    photos.mkdir()
    rng = np.random.default_rng(0)
    for i in range(3):
        cv2.imwrite(str(photos / f"{i}.png"), rng.integers(0, 255, (48, 64, 3), np.uint8))
    P = np.array([[50.0, 0, 32, 0], [0, 50, 24, 0], [0, 0, 1, 3]])
    for bad, words in ((np.zeros((3, 4)), "world_mat_1: projection matrix is singular"),
                       (np.eye(3), "world_mat_1 has shape (3, 3)")):
        np.savez(tmp_path / "cameras.npz", world_mat_0=P, world_mat_1=bad, world_mat_2=P)
        rc = main(["cameras", str(tmp_path / "ws"), "--images", str(photos), "--given-cameras",
                   str(tmp_path / "cameras.npz")])
        err = capsys.readouterr().err.strip().splitlines()
        assert rc == 2 and len(err) == 1 and str(tmp_path / "cameras.npz") in err[0] and words in err[0], err
    np.savez(tmp_path / "cameras.npz", world_mat_0=P, world_mat_2=P, world_mat_3=P)  # a photo's entry deleted
    assert main(["cameras", str(tmp_path / "ws"), "--images", str(photos), "--given-cameras",
                 str(tmp_path / "cameras.npz")]) == 2
    assert "indices must be 0..N-1 without gaps" in capsys.readouterr().err
