"""Geometry metrics against a ground-truth mesh: Chamfer distance and F-score."""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial import cKDTree


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
