"""Can one view's automatic mask be judged on its own? Per view of a trained workspace: how deep (in pixels at
400×300) the run's visual hull (its training frame and carving rules, ``train`` defaults) projects into that view's
mask background, and the masks stage's confidence of the view (IoU of its first mask with the hull's silhouette,
``masks/confidence.json`` of the photo folder's workspace ``all`` beside it). A view whose mask misses a part of the
object should stand out from the views whose masks only leave the two-mask hull a little fat (README, "Stop 55").

    python bench/pair.py cow_float --arm "" && python bench/mask_trust.py bench/runs/pairs/cow_float/work/0/ws
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.far_surface import view_background_depths  # noqa: E402
from dvr.config import TrainConfig  # noqa: E402
from dvr.data import list_images, load_scene  # noqa: E402
from dvr.hull import grid_points, hull_inside  # noqa: E402
from dvr.trainer import carve_rules, training_frame  # noqa: E402


def hull_depths(ws: Path, res: int) -> list[np.ndarray]:
    """Per view: the background depth (pixels at 400×300 to the mask's nearest object pixel) of every lattice point
    of the run's visual hull that the view sees."""
    data = load_scene(ws, torch.device("cpu"), use_depth=False)
    cfg = TrainConfig()
    data = training_frame(cfg, data)
    inside = hull_inside(data.P, data.masks, res, **carve_rules(cfg, data))
    points = grid_points(res)[torch.from_numpy(inside.reshape(-1))]
    vals, seen = view_background_depths(points, data)
    to_400 = 500.0 / data.sizes.double().norm(dim=1).numpy()
    return [vals[v][seen[v]].numpy() * to_400[v] for v in range(len(to_400))]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("workspace", type=Path, help="a training workspace of bench/pair.py (its 'all' beside it)")
    ap.add_argument("--res", type=int, default=128, help="hull lattice cells per axis")
    ap.add_argument("--top", type=int, default=5, help="views listed, deepest first")
    a = ap.parse_args()
    names = [p.stem for p in list_images(a.workspace / "images")]
    conf_path = a.workspace.parent / "all" / "masks" / "confidence.json"
    conf = json.loads(conf_path.read_text()) if conf_path.exists() else {}
    depths = hull_depths(a.workspace, a.res)
    deepest = [float(d.max()) if len(d) else 0.0 for d in depths]
    print(f"{a.workspace}: median of the views' deepest hull point {np.median(deepest):.1f} px; "
          f"confidence median {np.median(list(conf.values())) if conf else float('nan'):.3f}, "
          f"lowest {min(conf.values()) if conf else float('nan'):.3f}")
    for v in np.argsort(deepest)[::-1][: a.top]:
        d = depths[v]
        print(f"  {names[v]}: deepest {deepest[v]:.1f} px, ≥ 5 px {np.mean(d >= 5) * 100:.3f} %, ≥ 10 px "
              f"{np.mean(d >= 10) * 100:.3f} % of its hull points; confidence {conf.get(names[v], float('nan')):.3f}")


if __name__ == "__main__":
    main()
