"""Batch against one capture at a time: four small synthetic captures (photos only, through SfM), reconstructed
one after the other with ``python -m pipeline reconstruct`` (what a shell loop does) and then all at once with
``python -m pipeline batch`` on a local Ray cluster. Prints the wall time and the mean CPU utilisation of both (all
cores, from /proc/stat, so Ray's worker processes count), and the seconds per stage of a capture in each.

    python bench/batch.py [--config configs/fast.yaml] [--gpu-train SECONDS]
    python bench/batch.py --gpu-train SECONDS --rows-from bench/results/<date>-batch.json   # the table only

``--gpu-train``: the train stage's seconds per capture measured on a GPU (``bench/gpu.py train`` on the four
captures); with it the scaling table also has GPU rows. ``--rows-from``: the table from an earlier run's seconds per
stage, without running anything. Writes bench/results/<date>-batch.json.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.evaluate import RUNS  # noqa: E402

# four captures: the end-to-end floor scene with other textures, shapes and camera rings (different work per capture)
VARIANTS = {
    "torus_noise": {},
    "torus_fine": {"albedo": {"scale": 3.5}},
    "torus_thick": {"shape": {"kind": "torus", "radius": 0.5, "minor": 0.26}},
    "torus_high": {"cameras": {"elevation": [30, 60]}},
}


def cpu_times() -> tuple[float, float]:
    """(busy, total) jiffies of all cores since boot."""
    fields = [float(x) for x in Path("/proc/stat").read_text().splitlines()[0].split()[1:]]
    idle = fields[3] + fields[4]  # idle + iowait
    return sum(fields) - idle, sum(fields)


def measured(cmd: list[str]) -> dict:
    """Run ``cmd``; its wall seconds and the mean utilisation of all cores meanwhile."""
    b0, t0, w0 = *cpu_times(), time.perf_counter()
    out = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    b1, t1 = cpu_times()
    if out.returncode != 0:
        sys.exit(f"{' '.join(cmd[:4])}: failed\n{out.stdout[-2000:]}{out.stderr[-2000:]}")
    return {"wall_s": round(time.perf_counter() - w0, 1), "cpu_util": round((b1 - b0) / max(t1 - t0, 1e-9), 3)}


def make_captures(folder: Path) -> Path:
    """The four captures' photo folders under ``folder`` (scenes rendered once, cached in bench/runs/scenes)."""
    from bench.evaluate import photos_folder, scene

    shutil.rmtree(folder, ignore_errors=True)
    for name, over in VARIANTS.items():
        photos_folder(scene("e2e", over), folder / name)
    return folder


def stage_seconds(ws: Path) -> dict[str, float]:
    """Seconds per stage of a finished workspace."""
    from pipeline.workspace import Workspace

    return {k: round(v, 1) for k, v in Workspace(ws).seconds().items()}


def scaling(per_capture: dict[str, float], gpu_train: float | None) -> list[dict]:
    """Captures per hour for N CPU workers (cores, one stage each) and M GPUs, from the seconds per stage of one
    capture on one core. ``captures_per_hour``: training on the GPUs while they keep up and on the cores beyond
    (the batch's ``spill_to_cpu``), the best split of the captures; ``gpu_only``: every training on the GPUs, the
    slower pool bounding the rate."""
    train, cpu_other = per_capture["train"], sum(v for k, v in per_capture.items() if k != "train")
    rows = []
    for n_cpu, n_gpu in [(2, 0), (8, 0), (32, 0), (8, 1), (32, 1), (32, 4)]:
        if n_gpu and gpu_train is None:
            continue
        if not n_gpu:
            rate = 3600 * n_cpu / (cpu_other + train)
            rows.append({"cpu_workers": n_cpu, "gpus": 0, "captures_per_hour": round(rate, 1)})
            continue
        gpu_only = min(3600 * n_cpu / cpu_other, 3600 * n_gpu / gpu_train)
        # a share g of the trainings on the GPUs: R·g·gpu_train ≤ 3600·M and R·(other + (1 − g)·train) ≤ 3600·N
        split = min(3600 * n_cpu / cpu_other, 3600 * (n_cpu + n_gpu * train / gpu_train) / (cpu_other + train))
        rows.append({"cpu_workers": n_cpu, "gpus": n_gpu, "captures_per_hour": round(max(split, gpu_only), 1),
                     "gpu_only": round(gpu_only, 1)})
    return rows


def _scaling_line(r: dict) -> str:
    gpu_only = f" (every training on the GPUs: {r['gpu_only']})" if "gpu_only" in r else ""
    return f"  {r['cpu_workers']} CPU workers + {r['gpus']} GPU: {r['captures_per_hour']} captures/hour{gpu_only}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default=str(ROOT / "configs" / "fast.yaml"))
    ap.add_argument("--gpu-train", type=float, default=None, help="train stage seconds per capture on one GPU")
    ap.add_argument("--rows-from", type=Path, default=None, help="an earlier run's JSON: print its scaling table")
    args = ap.parse_args()
    if args.rows_from is not None:
        per_capture = json.loads(args.rows_from.read_text())["per_capture_stage_seconds_1core"]
        for r in scaling(per_capture, args.gpu_train):
            print(_scaling_line(r))
        return
    work = RUNS / "batch"
    captures = make_captures(work / "captures")
    py = [sys.executable, "-m", "pipeline"]
    singles, single_secs = {}, {}
    for name in VARIANTS:
        ws = work / "single" / name
        shutil.rmtree(ws, ignore_errors=True)
        singles[name] = measured([*py, "reconstruct", str(ws), "--images", str(captures / name), "--config",
                                  args.config, "--train.no-progress"])
        single_secs[name] = stage_seconds(ws)
        print(f"single {name}: {singles[name]['wall_s']:.0f} s, CPU {100 * singles[name]['cpu_util']:.0f} %",
              flush=True)
    shutil.rmtree(work / "batch_out", ignore_errors=True)
    batch = measured([*py, "batch", str(captures), str(work / "batch_out"), "--config", args.config,
                      "--train.no-progress"])
    batch_secs = {n: stage_seconds(work / "batch_out" / n) for n in VARIANTS}
    summary = json.loads((work / "batch_out" / "summary.json").read_text())
    sum_single = sum(s["wall_s"] for s in singles.values())
    mean_single_util = sum(s["cpu_util"] * s["wall_s"] for s in singles.values()) / sum_single
    per_capture = {k: round(sum(b[k] for b in batch_secs.values()) / len(batch_secs), 1)
                   for k in next(iter(batch_secs.values()))}
    rec = {"date": datetime.date.today().isoformat(), "cores": os.cpu_count(), "config": Path(args.config).name,
           "single": singles, "single_stage_seconds": single_secs, "single_wall_sum_s": round(sum_single, 1),
           "single_cpu_util": round(mean_single_util, 3), "batch": batch, "batch_stage_seconds": batch_secs,
           "batch_done": f"{summary['done']}/{summary['captures']}", "per_capture_stage_seconds_1core": per_capture,
           "gpu_train_s": args.gpu_train, "scaling": scaling(per_capture, args.gpu_train)}
    out = ROOT / "bench" / "results" / f"{rec['date']}-batch.json"
    out.write_text(json.dumps(rec, indent=1))
    print(f"four captures one after the other: {sum_single:.0f} s, mean CPU {100 * mean_single_util:.0f} %")
    print(f"the same four as one batch on Ray: {batch['wall_s']:.0f} s, mean CPU {100 * batch['cpu_util']:.0f} % "
          f"({summary['done']}/{summary['captures']} done)")
    print("seconds per stage of a capture (batch, one core per stage):", per_capture)
    for r in rec["scaling"]:
        print(_scaling_line(r))
    print(f"→ {out}")


if __name__ == "__main__":
    main()
