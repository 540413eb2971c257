import os
import sys
from pathlib import Path

import cv2
import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
SHARED = ROOT.parent / "shared" / "data"

# The suite runs on 2 cores in two pytest-xdist workers (Makefile's `make test`): one thread each for torch, OpenCV
# and the processes a test starts, so the workers share the cores rather than fight over them; 2 threads without it.
THREADS = max(1, 2 // int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")))
os.environ["OMP_NUM_THREADS"] = str(THREADS)
torch.set_num_threads(THREADS)
cv2.setNumThreads(THREADS)


def pytest_collection_modifyitems(config, items):
    """The files in the order the two workers of ``make test`` take them (``--dist loadfile --no-loadscope-reorder``):
    those with a test marked slow first, in their order, then the others by their number of tests, most first
    (pytest-xdist's own reorder, by the number of tests alone, sends the one-test files last, so the slowest of them,
    2-3 minutes, would run on one worker after the other has finished)."""
    files: dict[str, list] = {}
    for item in items:
        files.setdefault(item.nodeid.split("::")[0], []).append(item)

    def rank(f: list) -> tuple[bool, int]:
        slow = any(i.get_closest_marker("slow") for i in f)
        return not slow, 0 if slow else -len(f)

    order = sorted(files.values(), key=rank)
    items[:] = [item for f in order for item in f]


def cli_options(cls) -> set[str]:
    """Every option string (``--train.iterations``, …) the generated command class ``cls`` parses."""
    import tyro

    return {o for a in tyro.extras.get_parser(cls)._actions for o in a.option_strings}


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)


def tiny_training(cfg, iterations: int, batch_rays: int):
    """``cfg`` (a pipeline Config) with a training of seconds on ``small_ws``: few steps, no progress bar or
    previews, a small hull and field."""
    t = cfg.train
    t.iterations, t.batch_rays, t.progress, t.preview_every = iterations, batch_rays, False, 0
    t.hull_res, t.field.base_res, t.field.plane_res = 32, 32, (16, 32)
    return cfg


def small_scene(**over):
    """8 views at 64 px of a checker torus (renders in well under a second)."""
    from synth import scene_from_dict

    d = {"name": "small", "shape": {"kind": "torus", "radius": 0.5, "minor": 0.2},
         "albedo": {"kind": "checker", "scale": 4.0},
         "cameras": {"n_views": 8, "width": 64, "height": 64, "radius": 2.6, "fov_deg": 40}}
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(d.get(k), dict):
            d[k] = {**d[k], **v}
        else:
            d[k] = v
    return scene_from_dict(d, ROOT)


@pytest.fixture(scope="session")
def small_ws(tmp_path_factory):
    from synth import write_scene

    ws = tmp_path_factory.mktemp("small")
    write_scene(small_scene(sparse_depth=50), ws)
    return ws


@pytest.fixture(scope="session")
def board_scene(tmp_path_factory):
    """configs/scenes/torus_board.yaml, 8 views, albedo only (≈ 15 s on 2 cores): images, GT cameras, gt/board.json."""
    import json

    import cv2
    import yaml

    from dvr.cameras import load_cameras
    from synth import write_scene
    from synth.scene import scene_from_dict

    d = yaml.safe_load((ROOT / "configs/scenes/torus_board.yaml").read_text())
    d["lighting"] = {"kind": "none"}
    d["cameras"].update(n_views=8, heldout=0)
    out = tmp_path_factory.mktemp("torus_board")
    write_scene(scene_from_dict(d, ROOT / "configs/scenes"), out)
    images = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in sorted((out / "images").glob("*.png"))]
    return out, images, load_cameras(out / "cameras.npz"), json.loads((out / "gt/board.json").read_text())
