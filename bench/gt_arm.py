"""A synthetic scene with its ground-truth cameras and masks (the bench's GT rows' protocol,
:func:`bench.evaluate.run_synthetic`) trained with options of any stage after them:

    python bench/gt_arm.py cow --train.contact-band=3
    python bench/gt_arm.py jar --preset balanced
    python bench/gt_arm.py cow --over '{"cameras": {"radius": 1.6}}'    # the scene rendered with overrides

Prints one JSON line: held-out PSNR (raw and gain-fitted), Chamfer (% of the diagonal as a fraction), F-score,
seconds per stage; the run is kept in ``bench/runs/work/gt_arm/<scene>``.
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
    ap.add_argument("scene", choices=sorted(ev.SCENES))
    ap.add_argument("--preset", default="default")
    ap.add_argument("--over", type=json.loads, default={}, help="scene overrides (JSON), as bench/run.py's")
    a, options = ap.parse_known_args()
    work = ev.RUNS / "work" / "gt_arm" / a.scene
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    r = ev.run_synthetic({"scene": a.scene, "cameras": "gt", "preset": a.preset, "knob": "arm"}, work,
                         {"arm": (options, a.over)})
    keys = ("psnr", "psnr_gain_fit", "chamfer_rel", "fscore", "seconds")
    print(json.dumps({"scene": a.scene, "over": a.over, "options": " ".join(options), "preset": a.preset,
                      **{k: r.get(k) for k in keys}}))


if __name__ == "__main__":
    main()
