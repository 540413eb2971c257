"""Where on the ground-truth surface a mesh misses: the F-score's recall (GT points within 1 % of the GT bounding-box
diagonal of the mesh) split by which way the GT surface faces — up, down or sideways — and the precision by the
facing of the GT point nearest each mesh point. A surface no camera sees (the underside of a stool's seat when
every view looks down) shows up as the downward faces' recall.

    python bench/facing.py WS/mesh/clean.ply bench/runs/scenes/stool/gt/mesh.ply [--up 0,0,1]

Both meshes in the same frame: a run with the GT cameras (the scene's frame; the synthetic scenes' up is +z).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def facing_fscore(pred, gt, up: np.ndarray, n: int = 50000, slope: float = 0.7) -> dict[str, dict[str, float]]:
    """Per facing of the GT surface ("up": normal·up > ``slope``, "down": < −``slope``, "side": the rest): its
    share of the GT surface, recall and precision at 1 % of the GT diagonal (as :func:`dvr.metrics.chamfer_fscore`)."""
    import trimesh
    from scipy.spatial import cKDTree

    from dvr.metrics import sample_surface

    up = np.asarray(up, float) / np.linalg.norm(up)
    thr = 0.01 * float(np.linalg.norm(gt.bounds[1] - gt.bounds[0]))
    g, faces = trimesh.sample.sample_surface(gt, n, seed=1)  # the faces too, for their normals
    p = sample_surface(pred, n, seed=0)  # the samples chamfer_fscore takes (the same seeds)
    g_facing = gt.face_normals[faces] @ up
    to_pred, _ = cKDTree(p).query(g, workers=-1)
    to_gt, nearest = cKDTree(g).query(p, workers=-1)
    p_facing = g_facing[nearest]
    out = {}
    for name, test in (("up", lambda c: c > slope), ("down", lambda c: c < -slope),
                       ("side", lambda c: np.abs(c) <= slope)):
        gs, ps = test(g_facing), test(p_facing)
        out[name] = {"share": float(gs.mean()),
                     "recall": float((to_pred[gs] < thr).mean()) if gs.any() else float("nan"),
                     "precision": float((to_gt[ps] < thr).mean()) if ps.any() else float("nan")}
    return out


def main() -> None:
    import trimesh

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("mesh", type=Path)
    ap.add_argument("gt", type=Path)
    ap.add_argument("--up", default="0,0,1", help="the up direction, x,y,z (default +z)")
    a = ap.parse_args()
    up = np.array([float(v) for v in a.up.split(",")])
    for name, r in facing_fscore(trimesh.load(a.mesh), trimesh.load(a.gt), up).items():
        print(f"{name:5s} {r['share']:6.1%} of the GT surface: recall {r['recall']:.3f}, "
              f"precision {r['precision']:.3f}")


if __name__ == "__main__":
    main()
