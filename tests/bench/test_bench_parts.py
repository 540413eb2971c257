"""bench/parts.py: the true cameras brought into SfM's frame (what the `gt-cameras` parts train and bake with)."""
import cv2
import numpy as np

from bench.parts import Truth
from dvr.cameras import load_cameras, save_cameras


def _ring(n, phase=0.0):
    K = np.array([[300.0, 0, 64], [0, 300.0, 48], [0, 0, 1]])
    Ks, Rs, ts = [], [], []
    for k in range(n):
        a = phase + 2 * np.pi * k / n
        c = np.array([3 * np.cos(a), 3 * np.sin(a), 1.0])
        z = -c / np.linalg.norm(c)
        x = np.cross(z, [0, 0, 1.0])
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(z, x), z])  # world → camera, looking at the origin
        Ks.append(K), Rs.append(R), ts.append(-R @ c)
    return np.array(Ks), np.array(Rs), np.array(ts)


def test_the_true_cameras_land_on_sfms_in_its_frame(tmp_path):
    syn, full = tmp_path / "scene", tmp_path / "all"
    (syn / "gt" / "heldout").mkdir(parents=True)
    (full / "images").mkdir(parents=True)
    K, R, t = _ring(5)
    Kh, Rh, th = _ring(1, phase=0.3)
    save_cameras(syn / "gt" / "cameras.npz", K, R, t, np.eye(4))
    save_cameras(syn / "gt" / "heldout" / "cameras.npz", Kh, Rh, th, np.eye(4))
    # SfM's frame: the true world scaled by 0.5, turned 30° about z and shifted
    a = np.radians(30.0)
    S = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])
    s, shift = 0.5, np.array([1.0, -2.0, 0.5])
    names = [f"{i:06d}" for i in range(5)] + ["heldout_000000"]
    Ka, Ra, ta = np.concatenate([K, Kh]), np.concatenate([R, Rh]), np.concatenate([t, th])
    centres = -np.einsum("nji,nj->ni", Ra, ta)
    R_sfm = Ra @ S.T
    t_sfm = -np.einsum("nij,nj->ni", R_sfm, s * centres @ S.T + shift)
    scale_mat = np.diag([2.0, 2.0, 2.0, 1.0])
    scale_mat[:3, 3] = shift
    save_cameras(full / "cameras.npz", Ka, R_sfm, t_sfm, scale_mat, ground=np.array([0, 0, 1.0, -0.5]))
    for n in names:
        cv2.imwrite(str(full / "images" / f"{n}.png"), np.zeros((4, 4, 3), np.uint8))
    truth = Truth(syn, full)
    assert abs(truth.s - s) < 1e-9
    truth.write_in_sfm_frame(names[:5], full / "cameras.npz", tmp_path / "true_in_sfm.npz")
    got, sfm = load_cameras(tmp_path / "true_in_sfm.npz"), load_cameras(full / "cameras.npz")
    assert np.allclose(got.sfm_centers, sfm.sfm_centers[:5], atol=1e-9)
    assert np.allclose(got.R, sfm.R[:5], atol=1e-9)
    assert np.allclose(got.scale_mat, scale_mat) and np.allclose(got.ground, sfm.ground)
