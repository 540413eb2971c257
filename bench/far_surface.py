"""Where a synthetic scene's mesh is off, and what its masks say there: the points of its surface farther than 1 % of
the ground truth's diagonal from it (the F-score's threshold), how many of the run's masks call each background, at
which height of the ground truth's box (its third axis) they lie, and how deep into the background of the view that
calls them background deepest they lie (pixels to that mask's nearest object pixel); the same depth for points of the
true surface, which a mask that calls them background at all has cut.

    python bench/gt_arm.py cow && python bench/far_surface.py cow bench/runs/work/gt_arm/cow/ws
    python bench/pair.py stool --arm "" && python bench/far_surface.py stool bench/runs/pairs/stool/work/0/ws --photos

``--photos``: a run from photos (``bench/pair.py``'s arm folder's ``ws``, its ``all`` beside it): the truth is brought
into the SfM frame by the camera centres' similarity, as the bench does. Points that one mask alone calls background
are the price of ``train.carve_min_views`` 2 (README, "Stop 53"); their depth says whether trusting a single mask
only far from its edge (a depth in pixels) would carve them without cutting the true surface (README, "Stop 54").
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
from dvr.cameras import load_cameras, to_normalized  # noqa: E402
from dvr.data import list_images, load_scene  # noqa: E402
from dvr.hull import background_distance, mask_lookup, view_votes  # noqa: E402
from dvr.metrics import sample_surface  # noqa: E402

DEPTHS_PX = (1.5, 3, 5, 8, 12)


def truth_in_sfm_frame(syn: Path, ws: Path) -> trimesh.Trimesh:
    """The scene's true mesh in the SfM frame of the run from photos whose training workspace is ``ws`` (its
    ``all`` beside it), by the similarity between the true and the estimated camera centres."""
    full = ws.parent / "all"
    names = [p.stem for p in list_images(full / "images")]
    gtc, hc = load_cameras(syn / "cameras.npz"), load_cameras(syn / "gt" / "heldout" / "cameras.npz")
    _, _, sim = ev.true_in_sfm_frame(gtc, hc, names, load_cameras(full / "cameras.npz"))
    gt = trimesh.load(syn / "gt" / "mesh.ply")
    gt.apply_transform(ev.similarity_matrix(sim))
    return gt


def view_background_depths(points: torch.Tensor, data) -> tuple[torch.Tensor, torch.Tensor]:
    """(V, N) pixels from each point's projection to each view's nearest object pixel (0 on the object; capped at
    10⁴ where a mask has no object pixel), and (V, N) whether the view sees the point (:func:`mask_lookup`)."""
    depth = torch.from_numpy(np.minimum(background_distance(data.masks), 1e4)).float()
    return mask_lookup(points, data.P, depth, data.sizes)


def background_depth(points: np.ndarray, data) -> np.ndarray:
    """(N,) pixels from each point's projection to the nearest object pixel of the mask that puts it deepest into
    its background (0 where every view that sees it calls it object)."""
    vals, seen = view_background_depths(torch.from_numpy(points).float(), data)
    return torch.where(seen, vals, torch.zeros_like(vals)).max(0).values.numpy()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", choices=sorted(ev.SCENES))
    ap.add_argument("workspace", type=Path, help="a trained workspace (mesh/clean.ply, its cameras and masks)")
    ap.add_argument("--photos", action="store_true", help="the workspace is a run from photos (bench/pair.py)")
    a = ap.parse_args()
    syn = ev.scene(a.scene, {})
    gt = truth_in_sfm_frame(syn, a.workspace) if a.photos else trimesh.load(syn / "gt" / "mesh.ply")
    mesh = trimesh.load(a.workspace / "mesh" / "clean.ply")
    lo, hi = gt.bounds
    threshold = 0.01 * float(np.linalg.norm(hi - lo))
    pts = sample_surface(mesh, 50000, 0)
    dist, _ = cKDTree(sample_surface(gt, 50000, 1)).query(pts)
    data = load_scene(a.workspace, torch.device("cpu"), use_depth=False)
    far = to_normalized(pts[dist > threshold], data.cams.scale_mat)
    true = to_normalized(sample_surface(gt, 50000, 2), data.cams.scale_mat)
    n_out = view_votes(torch.from_numpy(far).float(), data.P, data.masks, data.sizes)[0].numpy()
    height = None if a.photos else (pts[dist > threshold][:, 2] - lo[2]) / (hi[2] - lo[2])
    print(f"{len(far)} of {len(pts)} surface points farther than 1 % of the diagonal from the truth")
    print("views whose mask calls them background (0, 1, 2, 3, 4, 5, ≥ 6):",
          np.bincount(np.minimum(n_out, 6), minlength=7).tolist())
    if height is not None:
        print("height in the truth's box (below 0, tenths 0–1, above 1):",
              np.histogram(np.clip(height, -0.05, 1.05), bins=[-1, 0, *np.linspace(0.1, 0.9, 9), 1, 2])[0].tolist())
    for name, p in (("far points", far), ("true surface", true)):
        d = background_depth(p, data) if len(p) else np.zeros(0)
        shares = ", ".join(f"≥ {t} px {np.mean(d >= t) if len(d) else 0:.4f}" for t in DEPTHS_PX)
        print(f"{name}: share that one mask puts this deep into its background: {shares}")


if __name__ == "__main__":
    main()
