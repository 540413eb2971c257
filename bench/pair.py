"""Options of the stages after mapping, compared on ONE SfM mapping: COLMAP's runs differ (±1 dB held-out on the
same photos), which hides the effect of an option when each side of a comparison maps the photos afresh.

    python bench/pair.py cow --arm "" --arm "--cameras.final-passes 3" [--preset balanced] [--remap]

The scene's photos (training and held-out, as in the bench's rows from photos) are mapped once by the cameras
stage with the defaults, and the model as mapped is kept in ``bench/runs/pairs/<scene>/mapping`` (``--remap``
maps again). Each arm (options in the CLI's spelling; "" for the defaults) then runs the rest of the pipeline from
that mapping — the cameras stage's final adjustment (:func:`pipeline.cameras.finish_model`), masks, depth,
training, mesh, texture — and is measured like a bench row (:func:`bench.evaluate.run_synthetic`). Prints one
line per arm and writes ``bench/runs/pairs/<scene>/<preset>.jsonl``.
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import evaluate as ev  # noqa: E402

PAIRS = ev.RUNS / "pairs"
SHOWN = ("mask_iou", "psnr", "psnr_gt_pose", "chamfer_rel", "fscore")


def map_once(scene: str, remap: bool = False) -> Path:
    """The workspace of the scene's photos after the cameras stage (defaults, no final passes: the model as
    mapped); mapped on the first call or with ``remap``."""
    out = PAIRS / scene
    ws = out / "mapping"
    if remap or not (ws / "sfm" / "sparse" / "best").is_dir():
        shutil.rmtree(out, ignore_errors=True)
        photos = ev.photos_folder(ev.scene(scene, {}), out / "photos")
        ev.stages(("cameras",), ws, ev.config(None, ["--cameras.final-passes", "0"]), images=photos)
    return ws


def from_mapping(mapping: Path):
    """A stand-in for :func:`pipeline.cameras.map_photos` that returns the saved mapping of ``mapping`` (its SfM
    input folder copied into the new workspace, so that paths inside it stay valid)."""
    import pycolmap

    def map_photos(ws, photos, cfg):
        inp = ws.root / "sfm" / "input"
        shutil.copytree(mapping / "sfm" / "input", inp)
        rec = pycolmap.Reconstruction(mapping / "sfm" / "sparse" / "best")
        return rec, inp, mapping / "sfm" / "database.db", "saved mapping", []

    return map_photos


def run_arm(scene: str, mapping: Path, preset: str, options: list[str], work: Path) -> dict:
    """One arm: the rest of the pipeline from ``mapping`` with ``options``, measured."""
    import pipeline.cameras as cameras_stage

    cameras_stage.map_photos = from_mapping(mapping)
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    spec = {"scene": scene, "cameras": "sfm", "preset": preset, "knob": "arm"}
    return ev.run_synthetic(spec, work, {"arm": (options, {})})


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", choices=sorted(ev.SCENES))
    ap.add_argument("--arm", action="append", default=None, help='options of one arm ("" for the defaults)')
    ap.add_argument("--preset", default="default")
    ap.add_argument("--remap", action="store_true", help="map the photos again (a new mapping)")
    a = ap.parse_args()
    mapping = map_once(a.scene, a.remap)
    log = PAIRS / a.scene / f"{a.preset}.jsonl"
    for k, arm in enumerate(a.arm if a.arm is not None else [""]):
        r = run_arm(a.scene, mapping, a.preset, arm.split(), PAIRS / a.scene / "work" / str(k))
        row = {"arm": arm, **{key: r.get(key) for key in (*SHOWN, "pose", "seconds")}}
        with log.open("a") as f:
            f.write(json.dumps(row) + "\n")
        print(f"{arm or '(defaults)':40s} " + "  ".join(f"{key} {r.get(key):.4f}" for key in SHOWN
                                                       if r.get(key) is not None), flush=True)


if __name__ == "__main__":
    main()
