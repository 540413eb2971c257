"""What the photo hull carves on the bench's captures (GT cameras and masks; DTU with its automatic masks), and how
long it takes: the counts of :func:`dvr.photohull.photo_carve` as the train stage carves (its frame, its
lattices, the default preset's settings), one line per capture.

    python bench/carves.py            # every capture (renders the scenes the bench has not cached yet)
    python bench/carves.py mug dtu    # only these
    python bench/carves.py --photos   # the synthetic captures from photos: SfM cameras, automatic masks (the
                                      # bench's training photos; stages run once, kept in bench/runs/photos/)
    python bench/carves.py --photos --gt-masks   # the same with the GT masks in place of the automatic ones

A capture where nothing is carved trains exactly as without ``--train.photo-hull``.
"""

from __future__ import annotations

import json
import shutil
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.evaluate import HELDOUT, RUNS, config, photos_folder, scene, stages  # noqa: E402
from bench.run import ABLATIONS, KNOBS  # noqa: E402

FROM_PHOTOS = ("cow", "jar", "book", "cow_float", "sphere_board", "jar_alike", "stool", "mug")
CAPTURES = [("cow", {}), ("jar", {}), ("book", {}), ("cow_float", {}), ("stool", {}), ("mug", {}),
            ("cow", KNOBS["images 200x150"][1]), ("cow", ABLATIONS["exposure"][1]),
            ("cow", ABLATIONS["exposure+specular"][1]), ("mug", ABLATIONS["views to 80°"][1]), ("dtu", {})]


def workspace(name: str, over: dict, from_photos: bool) -> tuple[Path, list[int] | None]:
    """The capture's workspace and its training views (None: all): the scene's own, DTU's as the bench ran its
    stages, or (``from_photos``) its photos through the cameras, masks and depth stages, run once."""
    if name == "dtu":
        ws = RUNS / "dtu_all"
        if not (ws / "cameras.npz").exists():
            raise SystemExit(f"bench/carves.py: {ws} has no cameras.npz; run a DTU row of bench/run.py first")
        return ws, None
    syn = scene(name, over)
    if not from_photos:
        return syn, None
    from dvr.data import list_images

    ws = RUNS / "photos" / name
    if not (ws / ".stages" / "depth.json").exists():
        shutil.rmtree(RUNS / "photos" / f"{name}-photos", ignore_errors=True)
        stages(("cameras", "masks", "depth"), ws, config("default"),
               images=photos_folder(syn, RUNS / "photos" / f"{name}-photos"))
    return ws, [k for k, p in enumerate(list_images(ws / "images")) if not p.stem.startswith(HELDOUT)]


def with_gt_masks(ws: Path, name: str) -> Path:
    """A copy of the photos workspace ``ws`` (its images and SfM's cameras) with the scene's GT masks in place of
    the automatic ones (bench/runs/photos/<name>-gt-masks)."""
    out = RUNS / "photos" / f"{name}-gt-masks"
    shutil.rmtree(out, ignore_errors=True)
    shutil.copytree(ws / "images", out / "images")
    shutil.copy2(ws / "cameras.npz", out / "cameras.npz")
    syn = scene(name, {})
    heldout = {p.name: p for p in (syn / "gt" / "heldout" / "masks").glob("*.png")}
    (out / "masks").mkdir()
    for p in sorted((ws / "masks").glob("*.png")):
        src = syn / "masks" / p.name if not p.stem.startswith(HELDOUT) else heldout[p.name[len(HELDOUT):]]
        shutil.copy2(src, out / "masks" / p.name)
    return out


def carve(name: str, over: dict, from_photos: bool = False, gt_masks: bool = False) -> dict:
    """The photo hull's counts on one capture as the train stage would carve it (its frame, its lattices), and
    the seconds the initial occupancy took with the photo hull and without; ``gt_masks`` (from photos): with the
    GT masks in place of the automatic ones."""
    from dvr.config import TrainConfig
    from dvr.data import load_scene
    from dvr.trainer import initial_inside, training_frame

    ws, views = workspace(name, over, from_photos)
    if gt_masks:
        ws = with_gt_masks(ws, name)
    cfg = TrainConfig(photo_hull=True)
    data = training_frame(cfg, load_scene(ws, torch.device("cpu"), views=views))
    t0 = time.perf_counter()
    initial_inside(TrainConfig(), data)
    t1 = time.perf_counter()
    _, r = initial_inside(cfg, data)
    counts = {k: v for k, v in vars(r).items() if k != "inside"}
    return {"capture": name, "overrides": over, "from_photos": from_photos, "gt_masks": gt_masks,
            "seconds": round(t1 - t0, 1),
            "seconds_photo_hull": round(time.perf_counter() - t1, 1), **counts}


def main() -> None:
    args = sys.argv[1:]
    from_photos, gt_masks = "--photos" in args, "--gt-masks" in args
    if gt_masks and not from_photos:
        raise SystemExit("bench/carves.py: --gt-masks goes with --photos (the GT-camera captures have GT masks)")
    only = [a for a in args if not a.startswith("--")]
    captures = [(n, {}) for n in FROM_PHOTOS] if from_photos else CAPTURES
    for name, over in captures:
        if not only or name in only:
            print(json.dumps(carve(name, over, from_photos, gt_masks)), flush=True)


if __name__ == "__main__":
    main()
