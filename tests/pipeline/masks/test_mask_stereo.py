"""pipeline.masks.stereo: plane-sweep object/background evidence for the automatic masks (smoke, bad input,
shapes, the guard, and the case it exists for: an object printed like its backdrop)."""

import cv2
import numpy as np
import pytest
import torch

from dvr.cameras import Cameras, load_cameras
from dvr.data import list_images
from pipeline.config import Config
from pipeline.masks.stage import background_depths
from pipeline.masks.stereo import (
    BACKGROUND,
    OBJECT,
    UNDECIDED,
    box_sums,
    neighbours,
    stereo_costs,
    stereo_labels,
    stereo_seed_labels,
)
from pipeline.stages import run_stage
from synth import scene_from_dict, write_scene
from tests.conftest import ROOT

# a plate on a ball, both with the backdrop's own noise texture: colour cannot tell them apart, depth can
CAMO = {"name": "camouflage",
        "shape": {"kind": "union", "parts": [{"kind": "sphere", "radius": 0.35, "center": [0.0, 0.0, -0.2]},
                                             {"kind": "box", "size": [0.6, 0.02, 0.35], "center": [0.0, 0.0, 0.3]}]},
        "albedo": {"kind": "noise", "scale": 2.0},
        "background": {"kind": "backdrop", "radius": 3.5, "scale": 3.0, "saturation": 0.6},
        "lighting": {"kind": "lambertian"},
        "cameras": {"n_views": 16, "width": 200, "height": 150, "radius": 2.6, "fov_deg": 45, "elevation": [10, 40],
                    "rings": 2}}


@pytest.fixture(scope="module")
def camo(tmp_path_factory):
    syn = tmp_path_factory.mktemp("camo") / "synthetic"
    write_scene(scene_from_dict(CAMO, ROOT), syn)
    names = [p.stem for p in list_images(syn / "images")]
    imgs = [cv2.imread(str(syn / "images" / f"{n}.png")) for n in names]
    gt = np.stack([cv2.imread(str(syn / "masks" / f"{n}.png"), 0) > 127 for n in names])
    return syn, load_cameras(syn / "cameras.npz"), imgs, gt


def test_labels_agree_with_ground_truth(camo):
    _, cams, imgs, gt = camo
    lab = np.stack(stereo_seed_labels(imgs, cams, background_depths(cams, None, None, [""] * len(imgs))))
    assert lab.shape == gt.shape and lab.dtype == np.uint8
    obj, bg = lab == OBJECT, lab == BACKGROUND
    assert (obj & gt).sum() / obj.sum() >= 0.98  # object labels lie on the object
    assert (bg & ~gt).sum() / bg.sum() >= 0.98  # background labels on the background
    assert (obj & gt).sum() / gt.sum() >= 0.3  # and they cover a good part of it


def test_masks_stage_separates_object_printed_like_its_backdrop(camo, tmp_path):
    syn, _, _, gt = camo

    def iou(ws):
        m = np.stack([cv2.imread(str(p), 0) > 127 for p in sorted((ws / "masks").glob("*.png"))])
        return ((m & gt).sum((1, 2)) / (m | gt).sum((1, 2))).mean()

    ious = {}
    for stereo in (True, False):
        ws = tmp_path / f"stereo={stereo}"
        cfg = Config()
        cfg.cameras.triangulate_given = False  # the seeds alone: no SfM tracks to help
        cfg.masks.stereo = stereo
        run_stage("cameras", ws, cfg, images=syn / "images", given_cameras=syn / "cameras.npz")
        run_stage("masks", ws, cfg)
        ious[stereo] = iou(ws)
    print(ious)
    assert ious[True] >= 0.95
    assert ious[False] < ious[True] - 0.05  # the stereo seeds make the difference


def test_costs_shapes_and_smoke():
    cams = _ring(4)
    imgs = torch.rand(4, 12, 16, 3)
    c_in, c_out = stereo_costs(imgs, cams, np.full(4, 6.0), n_depths=8, n_neighbors=2)
    assert c_in.shape == c_out.shape == (4, 12, 16)
    assert not torch.isnan(c_in).any() and not torch.isnan(c_out).any()
    assert neighbours(cams.centers, 2).shape == (4, 2)


def test_box_sums_match_the_average_pool_times_the_window_at_every_pixel():
    """The summed-area table gives each clipped window's sum: ``avg_pool2d`` without the padding, times the pixels
    the window holds (the borders' windows hold fewer), to float32 rounding."""
    torch.manual_seed(0)
    x = torch.rand(3, 2, 17, 23)
    for p in (1, 3, 5):
        mean = torch.nn.functional.avg_pool2d(x, p, 1, p // 2, count_include_pad=False)
        count = torch.nn.functional.avg_pool2d(torch.ones(1, 1, 17, 23), p, 1, p // 2, count_include_pad=True,
                                               divisor_override=1)
        assert box_sums(x, p).shape == x.shape
        assert torch.allclose(box_sums(x, p), mean * count, atol=1e-5)
    with pytest.raises(ValueError, match="odd"):
        box_sums(x, 4)


def test_bad_input():
    cams = _ring(4)
    with pytest.raises(ValueError, match="must agree"):
        stereo_costs(torch.rand(3, 8, 8, 3), cams, np.full(4, 6.0))
    with pytest.raises(ValueError, match="must agree"):
        stereo_costs(torch.rand(4, 8, 8, 3), cams, np.full(3, 6.0))
    with pytest.raises(ValueError, match="at least 2"):
        stereo_costs(torch.rand(1, 8, 8, 3), _ring(1), np.full(1, 6.0))


def test_unscored_side_decides_nothing():
    """Guard: where no neighbour sees a hypothesis (cost inf) the other side's low cost is no evidence."""
    c_in = torch.tensor([[[0.01, 0.01, 0.2, 0.01]]]).expand(1, 5, 4).contiguous()
    c_out = torch.tensor([[[float("inf"), 0.2, 0.01, 0.011]]]).expand(1, 5, 4).contiguous()
    lab = stereo_labels(c_in, c_out, erode_px=0)[0, 0]
    assert lab.tolist() == [UNDECIDED, OBJECT, BACKGROUND, UNDECIDED]


def _ring(n):
    K, R, t = [], [], []
    for a in np.linspace(0, 2 * np.pi, n, endpoint=False):
        c = np.array([3 * np.cos(a), 0.5, 3 * np.sin(a)])
        z = -c / np.linalg.norm(c)
        x = np.cross([0, 1, 0], z)
        x /= np.linalg.norm(x)
        Rm = np.stack([x, np.cross(z, x), z])
        K.append([[20.0, 0, 8], [0, 20.0, 6], [0, 0, 1]]), R.append(Rm), t.append(-Rm @ c)
    return Cameras(np.array(K), np.array(R), np.array(t), np.eye(4))


def test_grabcut_on_all_cores_is_deterministic(camo):
    """GrabCut's k-means draws from the calling thread's RNG: each call seeds it, so the pool's scheduling (and
    the order of the views) cannot change a mask."""
    from pipeline.masks.stage import grabcut_all

    _, _, imgs, gt = camo
    labs = []
    for g in gt:  # a loose band around the truth: GrabCut must decide it
        lab = np.full(g.shape, cv2.GC_BGD, np.uint8)
        lab[cv2.dilate(g.astype(np.uint8), np.ones((15, 15), np.uint8)) > 0] = cv2.GC_PR_BGD
        lab[g] = cv2.GC_PR_FGD
        lab[cv2.erode(g.astype(np.uint8), np.ones((15, 15), np.uint8)) > 0] = cv2.GC_FGD
        labs.append(lab)
    a = grabcut_all(imgs, labs, 3)
    b = grabcut_all(imgs[::-1], labs[::-1], 3)[::-1]
    assert all(np.array_equal(x, y) for x, y in zip(a, b))


def test_grabcut_runs_on_the_box_of_the_uncertain_pixels(camo, monkeypatch):
    """With a margin, GrabCut sees only the bounding box of the pixels not fixed as background, widened by the
    margin (clipped to the image), and its mask agrees with the whole image's run; the fixed background outside the
    box stays background."""
    from pipeline.masks import stage as M

    _, _, imgs, gt = camo
    g = gt[0]
    lab = np.full(g.shape, cv2.GC_BGD, np.uint8)
    lab[cv2.dilate(g.astype(np.uint8), np.ones((15, 15), np.uint8)) > 0] = cv2.GC_PR_BGD
    lab[g] = cv2.GC_PR_FGD
    lab[cv2.erode(g.astype(np.uint8), np.ones((15, 15), np.uint8)) > 0] = cv2.GC_FGD
    seen, real = [], cv2.grabCut
    monkeypatch.setattr(M.cv2, "grabCut", lambda img, m, *a: (seen.append(img.shape[:2]), real(img, m, *a))[1])
    whole = M.grabcut(imgs[0], lab, 3)
    boxed = M.grabcut(imgs[0], lab, 3, margin=0.05)
    ys, xs = np.nonzero(lab != cv2.GC_BGD)
    pad = round(0.05 * max(g.shape))
    want = (min(g.shape[0], ys.max() + 1 + pad) - max(0, ys.min() - pad),
            min(g.shape[1], xs.max() + 1 + pad) - max(0, xs.min() - pad))
    assert seen == [g.shape, want] and want[0] * want[1] < g.size
    assert not boxed[lab == cv2.GC_BGD].any()
    iou = lambda a, b: (a & b).sum() / (a | b).sum()  # noqa: E731
    assert iou(boxed, whole) > 0.98 and iou(boxed, g) > iou(whole, g) - 0.01


def test_photos_evened_out_before_stereo_where_exposure_changes(tmp_path):
    """The camouflage scene photographed with exposure ±25 % and white balance ±8 %: the stereo compares colours
    across views, so from the photos as taken it finds a third less of the object than from the photos evened out
    by their gains (``exposure.json``, :func:`pipeline.masks.stage.evened_out`) — which find as much as the scene
    without the effect; without the record, the photos go in as they are."""
    import copy
    import json

    from pipeline.masks.stage import evened_out
    from pipeline.scene.exposure import ExposureEstimate, write_exposure
    from pipeline.workspace import Workspace

    spec = copy.deepcopy(CAMO)
    spec["effects"] = [{"kind": "exposure", "amount": 0.25, "white_balance": 0.08}]
    syn = tmp_path / "synthetic"
    write_scene(scene_from_dict(spec, ROOT), syn)
    names = [p.stem for p in list_images(syn / "images")]
    imgs = [cv2.imread(str(syn / "images" / f"{n}.png")) for n in names]
    gt = np.stack([cv2.imread(str(syn / "masks" / f"{n}.png"), 0) > 127 for n in names])
    cams = load_cameras(syn / "cameras.npz")
    ws = Workspace(tmp_path / "ws")
    ws.root.mkdir()
    assert evened_out(ws, names, imgs) is imgs  # no record: as taken
    truth = json.loads((syn / "gt" / "exposure.json").read_text())["images"]
    log_g = np.log([truth[n] for n in names])
    write_exposure(ws.exposure, ExposureEstimate(names, np.exp(log_g - log_g.mean(0)), np.full(len(names), 50)))
    cover = {}
    for evened in (False, True):
        lab = np.stack(stereo_seed_labels(evened_out(ws, names, imgs) if evened else imgs, cams,
                                          background_depths(cams, None, None, [""] * len(imgs))))
        obj = lab == OBJECT
        assert (obj & gt).sum() / obj.sum() >= 0.98
        cover[evened] = (obj & gt).sum() / gt.sum()
    print(cover)
    assert cover[True] >= 0.35 and cover[False] < cover[True] - 0.08
