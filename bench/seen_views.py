"""Where ``train.carve_sparse_views`` can act in the synthetic scenes with their ground-truth cameras and masks: the
points of the unit sphere (where the hull and the frame are built) and of the training sphere (the working sphere
after :func:`dvr.trainer.training_frame`, where the carving term samples), on a 96³ lattice, above the support plane,
that at least one but fewer than ``carve_sparse_views`` views see. Where there are none, the rule changes nothing in
the scene's runs with GT cameras (points no view sees, or below the support, are free either way).

    python bench/seen_views.py [cow jar ...]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import evaluate as ev  # noqa: E402
from dvr.cameras import plane_height  # noqa: E402
from dvr.config import TrainConfig  # noqa: E402
from dvr.data import load_scene  # noqa: E402
from dvr.hull import grid_points, view_votes  # noqa: E402
from dvr.trainer import training_frame  # noqa: E402

GT_SCENES = ("cow", "jar", "book", "cow_float", "stool", "mug")


def sparsely_seen(data, pts: torch.Tensor, fewer_than: int) -> int:
    """How many of ``pts`` above ``data``'s support plane 1 to ``fewer_than`` − 1 views see."""
    n = view_votes(pts, data.P, data.masks, data.sizes)[1]
    g = data.cams.ground
    above = torch.ones_like(n, dtype=torch.bool) if g is None else plane_height(g, pts) >= 0
    return int(((n >= 1) & (n < fewer_than) & above).sum())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenes", nargs="*", default=list(GT_SCENES))
    a = ap.parse_args()
    cfg = TrainConfig()
    pts = grid_points(96)
    pts = pts[pts.norm(dim=-1) <= 1.0]
    for name in a.scenes:
        data = load_scene(ev.scene(name, {}), torch.device("cpu"), use_depth=False)
        framed = training_frame(cfg, data)
        k = cfg.carve_sparse_views
        print(f"{name}: {len(data.P)} views; points that 1 to {k - 1} views see: {sparsely_seen(data, pts, k)} of "
              f"{len(pts)} in the unit sphere, {sparsely_seen(framed, pts, k)} in the training sphere"
              f"{'' if framed is not data else ' (the same: no tighter frame)'}")


if __name__ == "__main__":
    main()
