"""bench/batch.py's captures-per-hour table: the slower pool (CPU cores or GPUs) bounds the rate."""

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from bench.batch import scaling  # noqa: E402

PER_CAPTURE = {"cameras": 10.0, "masks": 20.0, "depth": 1.0, "train": 30.0, "mesh": 3.0, "texture": 5.0,
               "report": 1.0}  # 40 s of CPU work besides training


def test_cpu_only_rows_count_every_stage_on_the_cores():
    rows = {(r["cpu_workers"], r["gpus"]): r["captures_per_hour"] for r in scaling(PER_CAPTURE, None)}
    assert set(rows) == {(2, 0), (8, 0), (32, 0)}  # no GPU rows without a GPU's train seconds
    assert rows[(8, 0)] == round(3600 * 8 / 70.0, 1)


def test_gpu_rows_split_training_between_gpus_and_cores():
    rows = {(r["cpu_workers"], r["gpus"]): r for r in scaling(PER_CAPTURE, 20.0)}
    assert rows[(8, 1)]["gpu_only"] == round(3600 / 20.0, 1)  # every training on the GPU: it bounds, 180 < 720
    # the GPU trains 180 an hour, the cores the rest of the trainings besides every capture's other stages
    assert rows[(8, 1)]["captures_per_hour"] == round(3600 * (8 + 30 / 20.0) / 70.0, 1)
    assert rows[(32, 4)]["gpu_only"] == round(3600 * 4 / 20.0, 1)
    fast = {(r["cpu_workers"], r["gpus"]): r for r in scaling(PER_CAPTURE, 1.0)}
    assert fast[(8, 1)]["captures_per_hour"] == fast[(8, 1)]["gpu_only"] == round(3600 * 8 / 40.0, 1)  # cores bound


def test_rows_from_an_earlier_run_print_without_running(tmp_path):
    rec = tmp_path / "batch.json"
    rec.write_text(json.dumps({"per_capture_stage_seconds_1core": PER_CAPTURE}))
    out = subprocess.run([sys.executable, str(ROOT / "bench" / "batch.py"), "--gpu-train", "20",
                          "--rows-from", str(rec)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert "8 CPU workers + 1 GPU: 488.6 captures/hour (every training on the GPUs: 180.0)" in out.stdout
