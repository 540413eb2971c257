"""What the photo hull carves on the bench's captures (GT cameras and masks; DTU with its automatic masks), and how
long it takes: the counts of :func:`dvr.photohull.photo_carve` with the trainer's settings, one line per capture.

    python bench/carves.py            # every capture (renders the scenes the bench has not cached yet)
    python bench/carves.py mug dtu    # only these

A capture where nothing is carved trains exactly as without ``--train.photo-hull``.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.evaluate import RUNS, scene  # noqa: E402
from bench.run import ABLATIONS, KNOBS  # noqa: E402

CAPTURES = [("cow", {}), ("jar", {}), ("book", {}), ("cow_float", {}), ("stool", {}), ("mug", {}),
            ("cow", KNOBS["images 200x150"][1]), ("cow", ABLATIONS["exposure"][1]),
            ("cow", ABLATIONS["exposure+specular"][1]), ("mug", ABLATIONS["views to 80°"][1]), ("dtu", {})]


def carve(name: str, over: dict) -> dict:
    from dvr.data import load_scene
    from dvr.hull import hull_inside
    from dvr.photohull import photo_carve
    from dvr.trainer import TrainConfig

    cfg = TrainConfig()
    ws = RUNS / "dtu_all" if name == "dtu" else scene(name, over)
    if not (ws / "cameras.npz").exists():
        raise SystemExit(f"bench/carves.py: {ws} has no cameras.npz; run a DTU row of bench/run.py first")
    data = load_scene(ws, torch.device("cpu"), use_depth=False)
    t0 = time.perf_counter()
    inside = hull_inside(data.P, data.masks, cfg.photo_hull_res, cfg.carve_min_views, ground=data.cams.ground,
                         sizes=data.sizes, contact_band=cfg.contact_band)
    r = photo_carve(inside, data.P, data.images, data.masks, data.sizes, spread_floor=cfg.photo_spread,
                    contrast_weight=cfg.photo_contrast, min_depth=cfg.photo_min_depth)
    counts = {k: v for k, v in vars(r).items() if k != "inside"}
    return {"capture": name, "overrides": over, "seconds": round(time.perf_counter() - t0, 1), **counts}


def main() -> None:
    only = sys.argv[1:]
    for name, over in CAPTURES:
        if not only or name in only:
            print(json.dumps(carve(name, over)), flush=True)


if __name__ == "__main__":
    main()
