"""Options of the stages after mapping, compared on ONE SfM mapping, mapped once for every arm (before stop 28
COLMAP's runs differed, ±1 dB held-out on the same photos, which hid an option's effect).

    python bench/pair.py cow --arm "" --arm "--cameras.final-passes 3" [--preset balanced] [--remap]
    python bench/pair.py cow --over '{"cameras": {"n_views": 16, "rings": 2}}' --arm "" --arm "..."

The scene's photos (training and held-out, as in the bench's rows from photos) are mapped once by the cameras
stage with the defaults, and the model as mapped (no final adjustment, no object matches) is kept in
``bench/runs/pairs/<scene>/mapping`` (``--remap`` maps again; ``--over`` renders the scene with overrides first,
as the bench's conditions do, and names the pair's folder after the rendered scene; its ``photos_jpeg`` saves the
photos as JPEGs, for the mapping and the arms alike). Each arm (options in the CLI's spelling; "" for the
defaults) then runs the rest of the pipeline from that mapping and the ladder's rung that gave it — the cameras
stage's final adjustment and object matches (:func:`pipeline.cameras.mapping.finish_model`), masks, depth, training,
mesh, texture — and is measured like a bench row (:func:`bench.evaluate.run_synthetic`). Prints one line per arm
and writes ``bench/runs/pairs/<scene>/<preset>.jsonl``. The phone-size cow, verifying its object's matches at the
model's known poses against RANSAC (the default):

    python bench/pair.py cow --over '{"cameras": {"photo_scale": 3}, "photos_jpeg": 92}' \
        --arm=--cameras.object-verification=poses --arm ""
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
from pipeline.workspace import Workspace  # noqa: E402

PAIRS = ev.RUNS / "pairs"
SHOWN = ("mask_iou", "psnr", "psnr_gain_fit", "psnr_gt_pose", "psnr_reaimed", "reaim_deg", "chamfer_rel", "fscore")


def pair_folder(scene: str, over: dict) -> Path:
    """bench/runs/pairs/<the rendered scene's folder name>, with ``-jpeg<quality>`` where ``over`` saves the photos
    as JPEGs (``photos_jpeg``, as the bench's rows "photos as JPEG" do)."""
    jpeg = over.get("photos_jpeg")
    return PAIRS / (ev.scene(scene, ev.scene_overrides(over)).name + (f"-jpeg{jpeg}" if jpeg else ""))


def map_once(scene: str, over: dict, remap: bool = False) -> Path:
    """The workspace of the scene's photos (JPEGs where ``over`` says ``photos_jpeg``, as the arms get them) after
    the cameras stage with the defaults but no final passes and no object matches: the model as mapped, whose final
    adjustment and object matches (:func:`pipeline.cameras.mapping.keep_object_matches`, photos larger than the working
    size) each arm runs with its own options. Mapped on the first call, with ``remap``, or when the saved mapping
    already holds the object's matches (mapped before they became the arms')."""
    out = pair_folder(scene, over)
    ws = out / "mapping"
    done = (ws / "sfm" / "sparse" / "best").is_dir()
    if remap or not done or (Workspace(ws).stamp("cameras") or {}).get("object_matches"):
        shutil.rmtree(out, ignore_errors=True)
        photos = ev.photos_folder(ev.scene(scene, ev.scene_overrides(over)), out / "photos", over.get("photos_jpeg"))
        ev.stages(("cameras",), ws, ev.config(None, ["--cameras.final-passes", "0", "--cameras.climbed-passes", "0",
                                                     "--cameras.no-object-matches"]), images=photos)
    return ws


def mapped_rung(mapping: Path) -> str:
    """The ladder's rung that mapped the saved workspace ``mapping`` (its cameras stamp)."""
    return (Workspace(mapping).stamp("cameras") or {}).get("rung", "default")


def from_mapping(mapping: Path):
    """A stand-in for :func:`pipeline.cameras.mapping.map_photos` that returns the saved mapping of ``mapping`` (its SfM
    input folder copied into the new workspace, so that paths inside it stay valid) and the ladder's rung that
    mapped it (which decides the final adjustment's passes)."""
    from pipeline.colmaplib import pycolmap

    rung = mapped_rung(mapping)

    def map_photos(ws, photos, cfg):
        inp = ws.root / "sfm" / "input"
        shutil.copytree(mapping / "sfm" / "input", inp)
        rec = pycolmap.Reconstruction(mapping / "sfm" / "sparse" / "best")
        return rec, inp, mapping / "sfm" / "database.db", rung, []

    return map_photos


def run_arm(scene: str, over: dict, mapping: Path, preset: str, options: list[str], work: Path) -> dict:
    """One arm: the rest of the pipeline from ``mapping`` with ``options``, measured."""
    import pipeline.cameras.mapping as sfm_mapping

    sfm_mapping.map_photos = from_mapping(mapping)
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    spec = {"scene": scene, "cameras": "sfm", "preset": preset, "knob": "arm"}
    return ev.run_synthetic(spec, work, {"arm": (options, over)})


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", choices=sorted(ev.SCENES))
    ap.add_argument("--arm", action="append", default=None, help='options of one arm ("" for the defaults)')
    ap.add_argument("--preset", default="default")
    ap.add_argument("--remap", action="store_true", help="map the photos again (a new mapping)")
    ap.add_argument("--over", type=json.loads, default={}, help="scene overrides (JSON), as bench/run.py's")
    a = ap.parse_args()
    mapping = map_once(a.scene, a.over, a.remap)
    folder = pair_folder(a.scene, a.over)
    log = folder / f"{a.preset}.jsonl"
    rung = mapped_rung(mapping)
    for k, arm in enumerate(a.arm if a.arm is not None else [""]):
        r = run_arm(a.scene, a.over, mapping, a.preset, arm.split(), folder / "work" / str(k))
        row = {"arm": arm, "rung": rung,
               **{key: r.get(key) for key in (*SHOWN, "pose", "seconds")}}
        with log.open("a") as f:
            f.write(json.dumps(row) + "\n")
        print(f"{arm or '(defaults)':40s} " + "  ".join(f"{key} {r.get(key):.4f}" for key in SHOWN
                                                       if r.get(key) is not None), flush=True)


if __name__ == "__main__":
    main()
