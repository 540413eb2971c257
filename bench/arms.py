"""One-off comparisons: options of any stage, each run measured as a bench row (:mod:`bench.evaluate`).

    python bench/arms.py pair SCENE --arm "" --arm "OPTIONS" [--preset P] [--remap] [--over JSON]
    python bench/arms.py dtu [--preset P] [--reference-cameras] [OPTIONS]
    python bench/arms.py gt SCENE [--preset P] [--over JSON] [OPTIONS]
    python bench/arms.py real CAPTURE --arm "" --arm "OPTIONS" [--preset P]
    python bench/arms.py masks CAPTURE --arm "" --arm "OPTIONS"

``pair``: a synthetic scene from its photos, every arm on ONE SfM mapping (another mapping of the same photos moves
the held-out figure by up to about 1 dB, which would hide an option's effect). ``dtu``: DTU scan24 through the
bench's protocol. ``gt``: a synthetic scene with its ground-truth cameras and masks. ``real``: options of training
and after on a real capture's bench workspace. ``masks``: options of the masks stage on a real capture with hand
masks. ``python bench/arms.py COMMAND --help`` says more.
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

PAIR_HELP = """Options of the stages after mapping, compared on ONE SfM mapping, mapped once for every arm (another
mapping of the same photos, e.g. with another ``--cameras.seed``, moves the held-out figure by up to about 1 dB,
which would hide an option's effect).

    python bench/arms.py pair cow --arm "" --arm "--cameras.final-passes 3" [--preset balanced] [--remap]
    python bench/arms.py pair cow --over '{"cameras": {"n_views": 16, "rings": 2}}' --arm "" --arm "..."

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

    python bench/arms.py pair cow --over '{"cameras": {"photo_scale": 3}, "photos_jpeg": 92}' \\
        --arm=--cameras.object-verification=poses --arm ""
"""

DTU_HELP = """DTU scan24 through the bench's protocol (:func:`bench.evaluate.run_dtu`: our SfM, automatic masks, every
7th photo held out) with options of any stage, e.g. another SfM mapping of the same photos:

    python bench/arms.py dtu --cameras.seed 1
    python bench/arms.py dtu --preset balanced --train.iterations 3000
    python bench/arms.py dtu --reference-cameras     # DTU's own calibrated cameras instead of our SfM

Prints one JSON line: held-out PSNR, PSNR at the training views (both also after fitting each photo's own colour
gains), re-aimed (:mod:`bench.reaim`) and on the mesh's own held-out pixels, pose error against DTU's cameras,
seconds per stage. Options of the stages before training get their own cached cameras, masks and depth
(``bench/runs/dtu_all-<options>``; delete it to redo them); the training runs in ``bench/runs/work/dtu_arm``.
"""

GT_HELP = """A synthetic scene with its ground-truth cameras and masks (the bench's GT rows' protocol,
:func:`bench.evaluate.run_synthetic`) trained with options of any stage after them:

    python bench/arms.py gt cow --train.contact-band=3
    python bench/arms.py gt jar --preset balanced
    python bench/arms.py gt cow --over '{"cameras": {"radius": 1.6}}'    # the scene rendered with overrides

Prints one JSON line: held-out PSNR (raw and gain-fitted), Chamfer (% of the diagonal as a fraction), F-score,
seconds per stage; the run is kept in ``bench/runs/work/gt_arm/<scene>``.
"""


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
    holds the object's matches (they are each arm's own)."""
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
    input folder copied into the new workspace, so that paths inside it stay valid), the ladder's rung that
    mapped it (which decides the final adjustment's passes) and its pairs in doubt."""
    from pipeline.cameras.visibility import unexplained_pairs
    from pipeline.colmaplib import pycolmap

    rung = mapped_rung(mapping)

    def map_photos(ws, photos, cfg):
        inp = ws.root / "sfm" / "input"
        shutil.copytree(mapping / "sfm" / "input", inp)
        rec = pycolmap.Reconstruction(mapping / "sfm" / "sparse" / "best")
        database = mapping / "sfm" / "database.db"
        return rec, inp, database, rung, [], unexplained_pairs(rec, database)

    return map_photos


def run_arm(scene: str, over: dict, mapping: Path, preset: str, options: list[str], work: Path) -> dict:
    """One arm: the rest of the pipeline from ``mapping`` with ``options``, measured."""
    import pipeline.cameras.mapping as sfm_mapping

    sfm_mapping.map_photos = from_mapping(mapping)
    ev.fresh_folder(work)
    spec = {"scene": scene, "cameras": "sfm", "preset": preset, "knob": "arm"}
    return ev.run_synthetic(spec, work, {"arm": (options, over)})


REAL_HELP = """Options of training, mesh and texture on a real capture of the bench (``mouse``, ``blowtorch``), every
arm on the cameras, masks and depth of its bench row (``bench/runs/real_<capture>``, made by ``python bench/run.py
--only <capture>`` when missing) and the row's split (every 7th photo held out):

    python bench/arms.py real mouse --arm "" --arm "--train.hull-gate-px 0"

Prints one line per arm: the row's held-out PSNR (raw, gain-fitted, re-aimed), at the training photos, the share of
the held-out masks the mesh covers, and with the capture's hand masks the held-out PSNR over them (``psnr_hand``);
each arm's run is kept in ``bench/runs/work/real_arm/<capture>/<k>``.
"""


def real(argv: list[str]) -> None:
    ap = _parser("real", REAL_HELP)
    ap.add_argument("capture", choices=sorted(ev.REAL))
    ap.add_argument("--arm", action="append", default=None, help='options of one arm ("" for the defaults)')
    ap.add_argument("--preset", default="default")
    a = ap.parse_args(argv)
    full = ev.RUNS / f"real_{a.capture}"
    if not (full / ".stages" / "depth.json").exists():
        sys.exit(f"{full}: no bench workspace; make it with python bench/run.py --only {a.capture}")
    hand = ev.REAL[a.capture] / "masks"
    hand = ev.undistorted_hand_masks(full, hand) if hand.is_dir() else None
    for k, arm in enumerate(a.arm if a.arm is not None else [""]):
        ws = ev.fresh_folder(ev.RUNS / "work" / "real_arm" / a.capture / str(k)) / "ws"
        r = ev.heldout_scores(full, ws, a.preset, arm.split(), hand)
        print(f"{arm or '(defaults)':40s} " + "  ".join(f"{key} {r[key]:.4f}" for key in (
            "psnr", "psnr_gain_fit", "psnr_reaimed", "psnr_train", "mask_covered", "psnr_hand") if key in r),
              flush=True)


MASKS_HELP = """Options of the masks stage on a real capture of the bench with hand masks (``blowtorch``), every arm
on the cameras of its bench row (``bench/runs/real_<capture>``, made by ``python bench/run.py --only <capture>``
when missing):

    python bench/arms.py masks blowtorch --arm "" --arm "--masks.carve-fraction 0.07"

Prints one line per arm: the masks' mean IoU against the hand masks (:func:`bench.evaluate.masks_iou`) and the
stage's seconds; each arm's workspace is kept in ``bench/runs/work/masks_arm/<capture>/<k>``.
"""


def masks(argv: list[str]) -> None:
    ap = _parser("masks", MASKS_HELP)
    ap.add_argument("capture", choices=sorted(c for c, folder in ev.REAL.items() if (folder / "masks").is_dir()))
    ap.add_argument("--arm", action="append", default=None, help='options of one arm ("" for the defaults)')
    a = ap.parse_args(argv)
    full = ev.RUNS / f"real_{a.capture}"
    if not (full / ".stages" / "cameras.json").exists():
        sys.exit(f"{full}: no bench workspace; make it with python bench/run.py --only {a.capture}")
    hand = ev.undistorted_hand_masks(full, ev.REAL[a.capture] / "masks")
    for k, arm in enumerate(a.arm if a.arm is not None else [""]):
        ws = ev.fresh_folder(ev.RUNS / "work" / "masks_arm" / a.capture / str(k))
        for name in ("images", "sfm", "cameras.npz", "exposure.json", "points.ply", ".stages/cameras.json"):
            if (full / name).is_dir():
                shutil.copytree(full / name, ws / name)
            elif (full / name).exists():
                (ws / name).parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(full / name, ws / name)
        ev.stages(("masks",), ws, ev.config(None, arm.split()))
        print(f"{arm or '(defaults)':40s} mask_iou {ev.masks_iou(ws, hand):.4f}  "
              f"seconds {Workspace(ws).seconds()['masks']:.1f}", flush=True)


def _parser(command: str, text: str) -> argparse.ArgumentParser:
    return argparse.ArgumentParser(prog=f"bench/arms.py {command}", description=text,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)


def pair(argv: list[str]) -> None:
    ap = _parser("pair", PAIR_HELP)
    ap.add_argument("scene", choices=sorted(ev.SCENES))
    ap.add_argument("--arm", action="append", default=None, help='options of one arm ("" for the defaults)')
    ap.add_argument("--preset", default="default")
    ap.add_argument("--remap", action="store_true", help="map the photos again (a new mapping)")
    ap.add_argument("--over", type=json.loads, default={}, help="scene overrides (JSON), as bench/run.py's")
    a = ap.parse_args(argv)
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


def dtu(argv: list[str]) -> None:
    ap = _parser("dtu", DTU_HELP)
    ap.add_argument("--preset", default="default")
    ap.add_argument("--reference-cameras", action="store_true",
                    help="DTU's own calibrated cameras (given to the cameras stage) instead of our SfM")
    a, options = ap.parse_known_args(argv)
    work = ev.fresh_folder(ev.RUNS / "work" / "dtu_arm")
    r = ev.run_dtu({"knob": "arm", "preset": a.preset, "reference_cameras": a.reference_cameras}, work,
                   {"arm": (options, {})})
    keys = ("psnr", "psnr_train", "psnr_gain_fit", "psnr_train_gain_fit", "psnr_on_model", "psnr_reaimed",
            "reaim_deg", "pose", "seconds", "rung")
    print(json.dumps({"options": " ".join(options), "preset": a.preset, "reference_cameras": a.reference_cameras,
                      **{k: r[k] for k in keys}}))


def gt(argv: list[str]) -> None:
    ap = _parser("gt", GT_HELP)
    ap.add_argument("scene", choices=sorted(ev.SCENES))
    ap.add_argument("--preset", default="default")
    ap.add_argument("--over", type=json.loads, default={}, help="scene overrides (JSON), as bench/run.py's")
    a, options = ap.parse_known_args(argv)
    work = ev.fresh_folder(ev.RUNS / "work" / "gt_arm" / a.scene)
    r = ev.run_synthetic({"scene": a.scene, "cameras": "gt", "preset": a.preset, "knob": "arm"}, work,
                         {"arm": (options, a.over)})
    keys = ("psnr", "psnr_gain_fit", "chamfer_rel", "fscore", "seconds")
    print(json.dumps({"scene": a.scene, "over": a.over, "options": " ".join(options), "preset": a.preset,
                      **{k: r.get(k) for k in keys}}))


COMMANDS = {"pair": pair, "dtu": dtu, "gt": gt, "real": real, "masks": masks}


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] in COMMANDS:
        COMMANDS[argv[0]](argv[1:])
        return
    ap = argparse.ArgumentParser(prog="bench/arms.py", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("command", choices=sorted(COMMANDS), help="pair, dtu, gt, real or masks (each has its own --help)")
    ap.parse_args(argv[:1])


if __name__ == "__main__":
    main()
