"""Metrics: Chamfer distance and F-score against a ground-truth mesh, masked image PSNR."""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial import cKDTree


def masked_psnr(img: np.ndarray, ref: np.ndarray, mask: np.ndarray) -> float:
    """PSNR (dB) of ``img`` against ``ref`` (values in [0, 1]) over the pixels of ``mask``; NaN for an empty mask,
    capped at 100 dB for identical images."""
    if not mask.any():
        return float("nan")
    return float(-10 * np.log10(max(((img - ref)[mask] ** 2).mean(), 1e-10)))


def sample_surface(mesh: trimesh.Trimesh, n: int, seed: int = 0) -> np.ndarray:
    """``n`` points uniformly on the surface (area-weighted), reproducible."""
    if len(mesh.faces) == 0:
        raise ValueError("cannot sample an empty mesh")
    pts, _ = trimesh.sample.sample_surface(mesh, n, seed=seed)
    return np.asarray(pts)


def chamfer_fscore(pred: trimesh.Trimesh, gt: trimesh.Trimesh, n: int = 50000, threshold: float | None = None,
                   seed: int = 0) -> dict[str, float]:
    """Chamfer = mean of the two mean nearest-neighbour distances (≥ n samples each), and F-score at
    ``threshold`` (default 1 % of the GT bounding-box diagonal). Also reported relative to that diagonal."""
    diag = float(np.linalg.norm(gt.bounds[1] - gt.bounds[0]))
    thr = 0.01 * diag if threshold is None else threshold
    if len(pred.faces) == 0:
        return {"chamfer": float("inf"), "chamfer_rel": float("inf"), "fscore": 0.0, "precision": 0.0,
                "recall": 0.0, "diag": diag}
    a, b = sample_surface(pred, n, seed), sample_surface(gt, n, seed + 1)
    da, _ = cKDTree(b).query(a, workers=-1)
    db, _ = cKDTree(a).query(b, workers=-1)
    ch = 0.5 * (da.mean() + db.mean())
    p, r = float((da < thr).mean()), float((db < thr).mean())
    f = 2 * p * r / (p + r) if p + r > 0 else 0.0
    return {"chamfer": float(ch), "chamfer_rel": float(ch / diag), "fscore": f, "precision": p, "recall": r,
            "diag": diag}


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R, t) minimising Σ|s R src + t − dst|² (Umeyama 1991); src, dst (N, 3), N ≥ 3."""
    src, dst = np.asarray(src, float), np.asarray(dst, float)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ValueError(f"umeyama needs two (N≥3, 3) arrays, got {src.shape} and {dst.shape}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1
    R = U @ S @ Vt
    var = (xs ** 2).sum() / len(src)
    s = float(np.trace(np.diag(D) @ S) / var) if var > 0 else 1.0
    t = mu_d - s * R @ mu_s
    return s, R, t


def rotation_angle_deg(R: np.ndarray) -> np.ndarray:
    """The angle (degrees) of a rotation matrix, or of each in a stack (..., 3, 3)."""
    return np.degrees(np.arccos(np.clip((np.trace(R, axis1=-2, axis2=-1) - 1) / 2, -1, 1)))


def pose_errors(centers_est: np.ndarray, R_est: np.ndarray, centers_gt: np.ndarray, R_gt: np.ndarray) -> dict:
    """Camera centre and rotation errors after a Sim(3) alignment of the estimated centres onto the GT ones."""
    s, R, t = umeyama(centers_est, centers_gt)
    c = (s * (R @ centers_est.T)).T + t
    dc = np.linalg.norm(c - centers_gt, axis=1)
    # world→camera rotations: R_est_aligned = R_est R^T
    rel = np.einsum("nij,nkj->nik", R_est @ R.T, R_gt)
    ang = rotation_angle_deg(rel)
    radius = float(np.linalg.norm(centers_gt - centers_gt.mean(0), axis=1).mean())
    return {"center_err_mean": float(dc.mean()), "center_err_max": float(dc.max()), "orbit_radius": radius,
            "center_err_rel_max": float(dc.max() / radius), "rot_err_deg_mean": float(ang.mean()),
            "rot_err_deg_max": float(ang.max()), "scale": s}
