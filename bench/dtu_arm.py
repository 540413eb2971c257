"""DTU scan24 through the bench's protocol (:func:`bench.evaluate.run_dtu`: our SfM, automatic masks, every 7th
photo held out) with options of any stage, e.g. another SfM mapping of the same photos:

    python bench/dtu_arm.py --cameras.seed 1
    python bench/dtu_arm.py --preset balanced --train.iterations 3000
    python bench/dtu_arm.py --reference-cameras     # DTU's own calibrated cameras instead of our SfM

Prints one JSON line: held-out PSNR, PSNR at the training views (both also after fitting each photo's own colour
gains), re-aimed (:mod:`bench.reaim`) and on the mesh's own held-out pixels, pose error against DTU's cameras,
seconds per stage. Options of the stages before training get their own cached cameras, masks and depth
(``bench/runs/dtu_all-<options>``; delete it to redo them); the training runs in ``bench/runs/work/dtu_arm``.
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="default")
    ap.add_argument("--reference-cameras", action="store_true",
                    help="DTU's own calibrated cameras (given to the cameras stage) instead of our SfM")
    a, options = ap.parse_known_args()
    work = ev.RUNS / "work" / "dtu_arm"
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    r = ev.run_dtu({"knob": "arm", "preset": a.preset, "reference_cameras": a.reference_cameras}, work,
                   {"arm": (options, {})})
    keys = ("psnr", "psnr_train", "psnr_gain_fit", "psnr_train_gain_fit", "psnr_on_model", "psnr_reaimed",
            "reaim_deg", "pose", "seconds", "rung")
    print(json.dumps({"options": " ".join(options), "preset": a.preset, "reference_cameras": a.reference_cameras,
                      **{k: r[k] for k in keys}}))


if __name__ == "__main__":
    main()
