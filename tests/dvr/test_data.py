"""Views of different sizes (a phone's portrait and landscape photos) in one workspace: loading, sampling, hull."""

import shutil

import cv2
import numpy as np
import pytest
import torch

from dvr.cameras import load_cameras, save_cameras
from dvr.data import RaySampler, load_scene, pad_stack
from dvr.hull import outside_hull
from synth.phone import upright_roll


def _portrait_copy(src, dst):
    """``src`` with every other view turned into a portrait photo (the camera rolled 90°, pixels turned)."""
    shutil.copytree(src, dst)
    cams = load_cameras(src / "cameras.npz")
    S = cams.scale_mat
    K, R, t = cams.K.copy(), cams.R.copy(), cams.t.copy()
    for i in range(0, len(K), 2):
        for sub in ("images", "masks"):
            p = dst / sub / f"{i:06d}.png"
            cv2.imwrite(str(p), cv2.rotate(cv2.imread(str(p), cv2.IMREAD_UNCHANGED), cv2.ROTATE_90_CLOCKWISE))
        h, w = cv2.imread(str(dst / "images" / f"{i:06d}.png")).shape[:2]
        K[i][0, 2], K[i][1, 2] = w - K[i][1, 2], K[i][0, 2]  # x' = H − y, y' = x
        R[i] = upright_roll(R[i], 6)
        t[i] = upright_roll(np.eye(3), 6) @ t[i]
    # back to the SfM frame of cameras.npz (R, t above are normalized-frame; scale_mat is the identity here)
    assert np.allclose(S, np.eye(4))
    save_cameras(dst / "cameras.npz", K, R, t, S)
    return dst


def test_pad_stack_keeps_each_views_pixels():
    a, b = np.ones((3, 5)), np.full((5, 3), 2.0)
    canvas, sizes = pad_stack([a, b])
    assert canvas.shape == (2, 5, 5) and sizes.tolist() == [[5, 3], [3, 5]]
    assert (canvas[0, :3, :5] == 1).all() and (canvas[0, 3:] == 0).all() and (canvas[1, :, 3:] == 0).all()


def test_mixed_sizes_load_sample_and_carve_like_the_original(small_ws, tmp_path):
    small = small_ws
    mixed = _portrait_copy(small, tmp_path / "mixed")
    a = load_scene(small, torch.device("cpu"))
    b = load_scene(mixed, torch.device("cpu"))
    assert b.sizes[0].tolist() == [64, 64] and b.shape == a.shape  # square views: the canvas is the same
    # a portrait view's rays see what the landscape one saw: its pixel (x', y') = (H − y, x)
    o, d = b.rays(torch.tensor([0]), torch.tensor([[64 - 20.5, 10.5]]))
    o2, d2 = a.rays(torch.tensor([0]), torch.tensor([[10.5, 20.5]]))
    assert torch.allclose(d, d2, atol=1e-5) and torch.allclose(o, o2, atol=1e-5)
    pts = torch.rand(4000, 3) * 2 - 1
    assert torch.equal(outside_hull(pts, a.P, a.masks), outside_hull(pts, b.P, b.masks, sizes=b.sizes))


def test_sampler_stays_inside_each_views_own_pixels(small_ws, tmp_path):
    ws = tmp_path / "ws"
    shutil.copytree(small_ws, ws)
    for i in range(0, 8, 2):  # half the views 64×40: the canvas stays 64×64
        for sub in ("images", "masks"):
            p = ws / sub / f"{i:06d}.png"
            cv2.imwrite(str(p), cv2.imread(str(p), cv2.IMREAD_UNCHANGED)[:40])
    data = load_scene(ws, torch.device("cpu"))
    assert data.sizes[0].tolist() == [64, 40] and data.sizes[1].tolist() == [64, 64]
    s = RaySampler(data, boundary_fraction=0.25, generator=torch.Generator().manual_seed(0))
    flat = torch.cat([s.uniform(20000), s.band])
    N, H, W = data.shape
    view, row = flat // (H * W), (flat % (H * W)) // W
    assert (row < data.sizes[view, 1]).all()  # never in the padding below a short view
    counts = torch.bincount(view, minlength=N)[:8].float()
    assert counts[0] / counts[1] > 0.5  # short views are drawn in proportion to their pixels, not skipped
    # a point of the object that projects into a short view's padding is not carved by that view
    from dvr.hull import mask_lookup

    depth = np.load(small_ws / "gt" / "depth" / "000000.npy")
    ii, jj = np.nonzero(depth[40:] > 0)  # object pixels of the full view below the short view's 40 rows
    uv = torch.from_numpy(np.stack([jj + 0.5, ii + 40.5], 1)).float()
    o, d = data.rays(torch.zeros(len(uv), dtype=torch.long), uv)
    pts = o + torch.from_numpy(depth[40:][ii, jj]).float()[:, None] * d  # on the object's surface
    _, seen = mask_lookup(pts, data.P, data.masks, data.sizes)
    assert len(pts) > 20 and not seen[0].any()
    assert outside_hull(pts, data.P, data.masks, sizes=data.sizes).float().mean() < 0.1
    assert outside_hull(pts, data.P, data.masks).all()  # without the sizes the padding would carve them


def test_truncated_sparse_depth_names_its_file(small_ws, tmp_path):
    """A depth/<view>.npz a killed depth stage left truncated (np.savez is not atomic): one ValueError naming it
    and the fix (not a zipfile.BadZipFile traceback through the train stage)."""
    ws = tmp_path / "ws"
    shutil.copytree(small_ws, ws)
    depth = sorted((ws / "depth").glob("*.npz"))[0]
    depth.write_bytes(depth.read_bytes()[:40])
    with pytest.raises(ValueError, match=rf"{depth.name}: unreadable sparse depth \(BadZipFile\); rerun the depth"):
        load_scene(ws, torch.device("cpu"))
    np.savez(depth, uv=np.zeros((3, 2)))  # no depths
    with pytest.raises(ValueError, match="unreadable sparse depth"):
        load_scene(ws, torch.device("cpu"))
