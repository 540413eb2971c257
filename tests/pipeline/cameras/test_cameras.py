"""Cameras: decomposition round trip, pixel-centre convention, unit-sphere bounds, loading errors."""

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from dvr.cameras import (
    decompose_projection,
    in_contact_band,
    load_cameras,
    pixel_centers,
    pixel_rays,
    project,
    project_points,
    save_cameras,
    sphere_bounds,
    to_normalized,
    to_sfm,
    transform_points,
)


def _cam(seed=0):
    rng = np.random.default_rng(seed)
    K = np.array([[300.0, 0.5, 160.0], [0, 310.0, 120.0], [0, 0, 1]])
    A = rng.normal(size=(3, 3))
    R, _ = np.linalg.qr(A)
    if np.linalg.det(R) < 0:
        R = -R
    t = rng.normal(size=3) + [0, 0, 4]
    return K, R, t


def test_decompose_round_trip_any_projective_scale():
    K, R, t = _cam()
    P = K @ np.concatenate([R, t[:, None]], 1)
    for s in (1.0, -3.0, 1e-6, 1e6):
        K2, R2, t2 = decompose_projection(s * P)
        assert np.allclose(K2, K) and np.allclose(R2, R) and np.allclose(t2, t)


def test_decompose_bad_input():
    with pytest.raises(ValueError, match="singular"):
        decompose_projection(np.zeros((3, 4)))
    with pytest.raises(ValueError, match="NaN"):
        decompose_projection(np.full((3, 4), np.nan))


def test_pixel_centre_convention_matches_grid_sample():
    """A ray through pixel (i, j)'s centre projects to (j + .5, i + .5); grid_sample(align_corners=False)
    at that point returns exactly pixel (i, j)."""
    K, R, t = _cam(1)
    H, W, i, j = 240, 320, 37, 201
    uv = torch.tensor([[j + 0.5, i + 0.5]], dtype=torch.float64)
    o, d = pixel_rays(torch.from_numpy(K), torch.from_numpy(R), torch.from_numpy(t), uv)
    P = torch.from_numpy(K @ np.concatenate([R, t[:, None]], 1))[None]
    back, z = project(o + 2.0 * d, P)
    assert torch.allclose(back[0], uv, atol=1e-9) and z.item() > 0
    img = torch.arange(H * W, dtype=torch.float64).view(1, 1, H, W)
    g = torch.stack([back[..., 0] / W * 2 - 1, back[..., 1] / H * 2 - 1], -1).view(1, 1, 1, 2)
    val = F.grid_sample(img, g, align_corners=False)
    assert val.item() == pytest.approx(i * W + j)


def test_sphere_bounds_hits_misses_inside():
    o = torch.tensor([[-3.0, 0, 0], [-3.0, 2.0, 0], [0.0, 0, 0]])
    w = torch.tensor([[1.0, 0, 0], [1.0, 0, 0], [1.0, 0, 0]])
    near, far, valid = sphere_bounds(o, w)
    assert valid.tolist() == [True, False, True]
    assert near.tolist() == pytest.approx([2.0, 0.0, 0.0]) and far.tolist() == pytest.approx([4.0, 0.0, 1.0])
    assert torch.isfinite(near).all() and torch.isfinite(far).all()


def test_save_load_normalized_frame(tmp_path):
    K, R, t = _cam(2)
    scale = np.diag([5.0, 5.0, 5.0, 1.0])
    scale[:3, 3] = [10, -3, 7]
    save_cameras(tmp_path / "cameras.npz", K[None], R[None], t[None], scale)
    cams = load_cameras(tmp_path / "cameras.npz")
    c_sfm = -R.T @ t
    assert np.allclose(cams.centers[0] * 5 + scale[:3, 3], c_sfm) and np.allclose(cams.sfm_centers[0], c_sfm)
    assert np.allclose(cams.K[0], K) and np.allclose(cams.R[0], R)


def test_frame_conversions_and_numpy_projection():
    """to_sfm / to_normalized invert each other (the uniform form for a scale_mat without rotation);
    project_points agrees with the torch project, one view or a stack, BLAS or einsum sums; the contact band."""
    rng = np.random.default_rng(4)
    S = np.diag([2.5, 2.5, 2.5, 1.0])
    S[:3, 3] = [1.0, -2.0, 0.5]
    x = rng.normal(size=(50, 3))
    assert np.allclose(to_normalized(to_sfm(x, S), S), x) and np.allclose(to_normalized(to_sfm(x, S), S, True), x)
    Rot = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    S2 = S.copy()
    S2[:3, :3] = 2.5 * Rot  # with a rotation only the general form inverts
    assert np.allclose(to_normalized(transform_points(S2, x), S2), x)
    Ps = np.stack([K @ np.c_[R, t] for K, R, t in (_cam(5), _cam(6))])
    uv_t, z_t = project(torch.from_numpy(x), torch.from_numpy(Ps))
    for blas in (True, False):
        uv, z = project_points(Ps, x, blas=blas)
        assert uv.shape == (2, 50, 2) and np.allclose(uv, uv_t.numpy()) and np.allclose(z, z_t.numpy())
        assert np.allclose(project_points(Ps[1], x, blas=blas)[0], uv[1])
    h = np.array([-0.01, 0.0, 0.02, 0.03, 0.5])
    assert in_contact_band(h, 0.03).tolist() == [False, True, True, False, False]
    assert in_contact_band(torch.from_numpy(h), 0.03).tolist() == [False, True, True, False, False]


def test_pixel_centers_are_the_grid_sample_convention():
    g = pixel_centers(3, 4)
    assert g.shape == (3, 4, 2) and g.dtype == torch.float32
    assert g[0, 0].tolist() == [0.5, 0.5] and g[2, 3].tolist() == [3.5, 2.5]


def test_load_errors(tmp_path):
    with pytest.raises(ValueError, match="cannot read"):
        load_cameras(tmp_path / "nope.npz")
    np.savez(tmp_path / "c.npz", foo=np.eye(3))
    with pytest.raises(ValueError, match="world_mat"):
        load_cameras(tmp_path / "c.npz")
    np.savez(tmp_path / "d.npz", world_mat_0=np.eye(4)[:3])
    with pytest.raises(ValueError, match="2 images"):
        load_cameras(tmp_path / "d.npz", n_views=2)


def _corrupt_member(path):
    """The npz at ``path`` with one byte of its first member's data flipped (the zip's CRC check fails)."""
    raw = bytearray(path.read_bytes())
    raw[200] ^= 0xFF
    path.write_bytes(bytes(raw))


@pytest.mark.parametrize("arrays, words", [
    ({"world_mat_0": np.eye(4), "world_mat_a": np.eye(4)}, "world_mat_a is no camera index"),
    ({"world_mat_0": np.eye(4), "scale_mat": np.eye(3)}, "scale_mat must be a finite, invertible 4x4"),
    ({"world_mat_0": np.eye(4), "scale_mat": np.zeros((4, 4))}, "scale_mat must be a finite, invertible 4x4"),
    ({"world_mat_0": np.eye(4), "ground_plane": np.ones(3)}, "ground_plane must be 4 finite numbers"),
    ({"world_mat_0": np.array([["a"] * 4] * 3)}, "world_mat_0 holds <U1 values, not numbers"),
    ({"world_mat_0": np.full((3, 4), np.nan)}, "world_mat_0: projection matrix contains NaN"),
    ({"world_mat_0": np.zeros((3, 4))}, "world_mat_0: projection matrix is singular"),
    ("corrupt", "cannot read camera file (BadZipFile)"),
])
def test_load_errors_name_the_file_and_the_entry(tmp_path, arrays, words):
    """A hand-made or damaged cameras.npz: one ValueError naming the file and the entry, not a
    BadZipFile traceback (a member is read lazily, after the guarded np.load), int()'s, numpy's matmul or
    decompose_projection's message without the file."""
    path = tmp_path / "cameras.npz"
    if arrays == "corrupt":
        np.savez(path, world_mat_0=np.eye(4) + np.arange(16).reshape(4, 4))
        _corrupt_member(path)
    else:
        np.savez(path, **arrays)
    with pytest.raises(ValueError) as err:
        load_cameras(path)
    assert str(path) in str(err.value) and words in str(err.value), str(err.value)


def test_reframe_keeps_projections_and_maps_depths():
    """A camera in a tighter frame (x = c + r·x') projects x' where the original projects x; scale_mat
    composes; ray depths scale by 1/r."""
    from dvr.cameras import Cameras

    K, R, t = _cam(3)
    cams = Cameras(K[None], R[None], t[None], np.diag([2.0, 2.0, 2.0, 1.0]))
    c, r = np.array([0.1, -0.2, 0.3]), 0.5
    new = cams.reframe(c, r)
    xp = np.random.default_rng(0).normal(size=(20, 3)) * 0.3
    x = c + r * xp
    assert np.allclose(project_points(cams.P[0], x)[0], project_points(new.P[0], xp)[0])
    assert np.allclose(np.linalg.norm(x - cams.centers[0], axis=1) / r, np.linalg.norm(xp - new.centers[0], axis=1))
    assert np.allclose(new.scale_mat[:3, 3], cams.scale_mat[:3, :3] @ c) and np.isclose(new.scale_mat[0, 0], 2 * r)
    with pytest.raises(ValueError, match="radius"):
        cams.reframe(c, 0.0)
