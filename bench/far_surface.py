"""Where a mesh trained with a synthetic scene's GT cameras is off: the points of its surface farther than 1 % of the
ground truth's diagonal from it (the F-score's threshold), how many of the exact masks call each background, and
at which height of the ground truth's box (its third axis) they lie.

    python bench/gt_arm.py cow && python bench/far_surface.py cow bench/runs/work/gt_arm/cow/ws

Points that one mask alone calls background are the price of ``train.carve_min_views`` 2 (README, "Stop 53").
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
import trimesh
from scipy.spatial import cKDTree

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import evaluate as ev  # noqa: E402
from dvr.data import load_scene  # noqa: E402
from dvr.hull import view_votes  # noqa: E402
from dvr.metrics import sample_surface  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", choices=sorted(ev.SCENES))
    ap.add_argument("workspace", type=Path, help="a workspace trained with the scene's GT cameras (mesh/clean.ply)")
    a = ap.parse_args()
    syn = ev.scene(a.scene, {})
    gt, mesh = trimesh.load(syn / "gt" / "mesh.ply"), trimesh.load(a.workspace / "mesh" / "clean.ply")
    lo, hi = gt.bounds
    threshold = 0.01 * float(np.linalg.norm(hi - lo))
    pts = sample_surface(mesh, 50000, 0)
    dist, _ = cKDTree(sample_surface(gt, 50000, 1)).query(pts)
    far = pts[dist > threshold]
    data = load_scene(syn, torch.device("cpu"), use_depth=False)
    n_out = view_votes(torch.from_numpy(far).float(), data.P, data.masks, data.sizes)[0].numpy()
    height = (far[:, 2] - lo[2]) / (hi[2] - lo[2])
    print(f"{len(far)} of {len(pts)} surface points farther than 1 % of the diagonal from the truth")
    print("views whose exact mask calls them background (0, 1, 2, 3, 4, 5, ≥ 6):",
          np.bincount(np.minimum(n_out, 6), minlength=7).tolist())
    print("height in the truth's box (below 0, tenths 0–1, above 1):",
          np.histogram(np.clip(height, -0.05, 1.05), bins=[-1, 0, *np.linspace(0.1, 0.9, 9), 1, 2])[0].tolist())


if __name__ == "__main__":
    main()
