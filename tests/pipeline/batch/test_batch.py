"""Batch reconstruction on Ray (pipeline/batch/runner.py): a good and a bad capture, the summary, and a rerun that
does no work."""

import json
import os
import shutil
from pathlib import Path

import pytest

from pipeline.batch.config import BatchConfig
from pipeline.batch.runner import Capture, find_captures, run_batch
from pipeline.cli import main
from pipeline.errors import StageError
from pipeline.stages import STAGES

TINY = ["--train.iterations", "30", "--train.batch-rays", "256", "--train.preview-every", "0", "--train.hull-res", "32",
        "--train.field.base-res", "32", "--train.field.plane-res", "16", "32", "--mesh.resolution", "64",
        "--mesh.max-faces", "3000", "--texture.size", "128", "--cameras.no-triangulate-given", "--train.no-progress"]


def _captures(small_ws, root):
    """good/: photos, masks/, cameras.npz (given: no SfM); too_few/: two photos."""
    good, bad = root / "captures" / "good", root / "captures" / "too_few"
    shutil.copytree(small_ws / "images", good / "images")
    shutil.copytree(small_ws / "masks", good / "masks")
    shutil.copy(small_ws / "cameras.npz", good / "cameras.npz")
    bad.mkdir()
    for p in sorted((small_ws / "images").glob("*.png"))[:2]:
        shutil.copy(p, bad / p.name)
    return root / "captures"


def test_find_captures_layouts_and_bad_input(small_ws, tmp_path):
    caps = find_captures(_captures(small_ws, tmp_path), tmp_path / "out")
    assert [c.name for c in caps] == ["good", "too_few"]
    good, bad = caps
    assert good.photos.name == "images" and good.masks_dir.name == "masks" and good.given_cameras.name == "cameras.npz"
    assert bad.photos == tmp_path / "captures" / "too_few" and bad.masks_dir is None and bad.given_cameras is None
    assert good.workspace == (tmp_path / "out" / "good").resolve()
    assert find_captures(tmp_path / "captures", tmp_path / "captures" / "out")[0].name == "good"  # OUT inside: skipped
    with pytest.raises(StageError, match="no capture folders"):
        find_captures(tmp_path / "captures" / "too_few", tmp_path / "out")
    with pytest.raises(StageError, match="not a folder"):
        find_captures(tmp_path / "nope", tmp_path / "out")


def test_capture_sources_follow_the_stage_table():
    cap = Capture("c", "/p", "/w", masks_dir="/m", given_cameras="/c.npz")
    by_stage = {s.name: cap.sources(s) for s in STAGES}
    assert by_stage["cameras"] == {"images": "/p", "given_cameras": "/c.npz"}
    assert by_stage["masks"] == {"masks_dir": "/m"} and by_stage["train"] == {}


def _local_ray_with_one_gpu(monkeypatch, cpus: int) -> None:
    """The batch's local Ray cluster declares one GPU (Ray schedules it whether or not the machine has one)."""
    import pipeline.batch.runner as batch_module

    monkeypatch.setattr(batch_module, "LOCAL_RAY", {"num_cpus": cpus, "num_gpus": 1,
                                                    "object_store_memory": 128 * 1024**2})


def test_batch_good_and_bad_capture_then_nothing_to_do(small_ws, tmp_path, capsys, monkeypatch):
    import tempfile

    from pipeline.config import config_from_args

    _local_ray_with_one_gpu(monkeypatch, cpus=2)  # none is here: the stage's device stays the CPU
    captures, out = _captures(small_ws, tmp_path), tmp_path / "out"
    shutil.copytree(small_ws / "images", captures / "no_mask" / "images")  # its masks/ lacks one photo's
    shutil.copytree(small_ws / "masks", captures / "no_mask" / "masks", ignore=shutil.ignore_patterns("000000.*"))
    cfg = config_from_args(None, TINY)
    rays_default = Path(tempfile.gettempdir()) / "ray"
    sessions_before = set(rays_default.iterdir()) if rays_default.exists() else set()
    made = []
    mkdtemp = tempfile.mkdtemp
    monkeypatch.setattr(tempfile, "mkdtemp", lambda *a, **k: made.append(mkdtemp(*a, **k)) or made[-1])
    summary = run_batch(captures, out, cfg, BatchConfig(cpus_per_stage=1))
    # the local cluster's session files went to a folder of its own, gone after the batch; none to Ray's default
    assert len(made) == 1 and not Path(made[0]).exists()
    assert (set(rays_default.iterdir()) if rays_default.exists() else set()) == sessions_before
    rows = {r["capture"]: r for r in summary["rows"]}
    assert rows["good"]["train_gpu"] is True and rows["good"]["train_device"] == "cpu"  # Ray gave training the GPU
    assert (out / "good" / "mesh" / "textured.glb").exists() and rows["good"]["status"] == "done"
    assert rows["good"]["registered"] == rows["good"]["total"] == 8 and rows["good"]["psnr"] > 10
    assert set(rows["good"]["seconds"]) == {s.name for s in STAGES}
    assert rows["too_few"]["status"] == "failed" and rows["too_few"]["failed_stage"] == "cameras"
    assert "at least 3 are needed" in rows["too_few"]["error"] and "\n" not in rows["too_few"]["error"]
    assert not (out / "too_few" / "mesh").exists()
    assert rows["no_mask"]["status"] == "failed" and rows["no_mask"]["failed_stage"] == "masks"  # before its SfM
    assert "no mask for 000000" in rows["no_mask"]["error"] and not (out / "no_mask" / "cameras.npz").exists()
    assert json.loads((out / "summary.json").read_text())["failed"] == 2
    page = (out / "index.html").read_text()
    assert "good/report.html" in page and "good/mesh/textured.glb" in page and "at least 3 are needed" in page
    stamps = {p.name: p.stat().st_mtime_ns for p in (out / "good" / ".stages").glob("*.json")}
    capsys.readouterr()
    # the same batch again through the CLI: the good capture is done (nothing runs), the bad one fails again
    rc = main(["batch", str(captures), str(out), *TINY])
    captured = capsys.readouterr()
    assert rc == 2 and "good: up to date" in captured.out
    assert len(captured.err.strip().splitlines()[-1:]) == 1 and "2 of 3 captures failed" in captured.err
    assert {p.name: p.stat().st_mtime_ns for p in (out / "good" / ".stages").glob("*.json")} == stamps
    again = {r["capture"]: r for r in json.loads((out / "summary.json").read_text())["rows"]}
    assert again["good"]["status"] == "up to date" and again["good"]["ran"] == []


def test_task_resources_and_retries():
    """Every stage asks for its cores and is retried when its worker dies; training asks for a GPU only where the
    cluster has one and the config allows it."""
    from pipeline.batch.runner import _task_options

    train = next(s for s in STAGES if s.name == "train")
    masks = next(s for s in STAGES if s.name == "masks")
    batch = BatchConfig(cpus_per_stage=2, train_gpus=1.0, retries=3)
    assert _task_options(masks, batch, on_gpu=True) == {"num_cpus": 2, "max_retries": 3}
    assert _task_options(train, batch, on_gpu=True) == {"num_cpus": 2, "max_retries": 3, "num_gpus": 1.0}
    assert "num_gpus" not in _task_options(train, batch, on_gpu=False)


def test_training_spills_to_cpu_cores_only_when_the_gpus_are_full():
    """One training running and one waiting per GPU slot keep the GPUs busy; a capture ready to train beyond that
    trains on its cores (an H100 trains a fast-preset capture no faster than one core)."""
    from pipeline.batch.runner import train_on_gpu

    one = BatchConfig(train_gpus=1.0)
    assert not train_on_gpu(one, cluster_gpus=0, gpu_trainings=0)  # no GPU in the cluster
    assert not train_on_gpu(BatchConfig(train_gpus=0), cluster_gpus=1, gpu_trainings=0)  # training kept on CPU
    assert [train_on_gpu(one, 1, n) for n in range(4)] == [True, True, False, False]
    assert [train_on_gpu(one, 2, n) for n in (3, 4)] == [True, False]
    eighth = BatchConfig(train_gpus=0.125)  # eight trainings share a GPU: 8 slots, 16 before spilling
    assert [train_on_gpu(eighth, 1, n) for n in (15, 16)] == [True, False]
    assert train_on_gpu(BatchConfig(train_gpus=1.0, spill_to_cpu=False), 1, 10)  # every training waits for a GPU
    assert train_on_gpu(one, 1, 10, device="cuda")  # training set to CUDA waits for a GPU: on cores it would fail
    assert not train_on_gpu(one, 1, 0, device="cpu")  # training set to the CPU takes no GPU slot


def test_a_task_without_a_gpu_hides_the_workers_gpus(small_ws, tmp_path, monkeypatch):
    """Ray leaves a task that asked for no GPU seeing the node's GPUs, and ``device: auto`` would train on them
    outside Ray's count (a batch with ``--batch.train-gpus 0`` on a GPU node trained on the GPU): a task without
    one hides them before its stage runs; a task given one keeps what Ray set."""
    from pipeline.batch.runner import run_stage_task
    from pipeline.config import config_from_args

    cap = Capture("good", small_ws / "images", tmp_path / "ws")
    failed_upstream = {"status": "failed"}  # the stage itself is skipped: only the worker's environment matters
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "0")
    rec = run_stage_task(cap, "train", None, 1, failed_upstream, gpu=True)
    assert os.environ["CUDA_VISIBLE_DEVICES"] == "0" and rec["gpu"] is True and rec["status"] == "skipped"
    rec = run_stage_task(cap, "mesh", None, 1, failed_upstream, gpu=False)
    assert os.environ["CUDA_VISIBLE_DEVICES"] == "" and rec["gpu"] is False
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "0")  # a stage set to cuda keeps the GPUs (the user's choice)
    run_stage_task(cap, "texture", config_from_args(None, ["--texture.device", "cuda"]), 1, failed_upstream)
    assert os.environ["CUDA_VISIBLE_DEVICES"] == "0"


def _stage_worker_pids() -> list[int]:
    """PIDs of the Ray workers running a stage task (their process title names the task)."""
    from pathlib import Path

    pids = []
    for proc in Path("/proc").iterdir():
        try:
            if proc.name.isdigit() and b"ray::run_stage_task" in (proc / "cmdline").read_bytes():
                pids.append(int(proc.name))
        except OSError:
            pass
    return pids


def test_a_killed_worker_s_stage_is_retried(small_ws, tmp_path):
    """SIGKILL the worker while it trains (no train stamp yet): Ray runs the stage again and the capture ends done."""
    import signal
    import threading
    import time

    from pipeline.config import config_from_args

    captures, out = _captures(small_ws, tmp_path), tmp_path / "out"
    shutil.rmtree(captures / "too_few")
    slow = [*TINY[:1], "400", *TINY[2:]]  # 400 steps: time to catch the train stage running
    result, killed = {}, []
    runner = threading.Thread(target=lambda: result.update(
        run_batch(captures, out, config_from_args(None, slow), BatchConfig(retries=2))))
    runner.start()
    train_log, stamp = out / "good" / "logs" / "train.log", out / "good" / ".stages" / "train.json"
    t0 = time.time()
    while not killed and runner.is_alive() and time.time() - t0 < 300:
        if train_log.exists() and not stamp.exists():
            time.sleep(0.5)  # inside the stage
            pids = _stage_worker_pids()
            if pids and not stamp.exists():
                for pid in pids:
                    os.kill(pid, signal.SIGKILL)
                killed.extend(pids)
        time.sleep(0.05)
    runner.join(600)
    assert killed, "the train stage was never caught running"
    row = result["rows"][0]
    assert row["status"] == "done" and (out / "good" / "mesh" / "textured.glb").exists()


def test_summary_page_names_a_training_device_other_than_the_cpu(tmp_path):
    from pipeline.batch.summary import _html_row

    row = {"capture": "mug", "status": "done", "failed_stage": None, "error": None, "registered": 30, "total": 30,
           "seconds": {"masks": 29.1, "train": 25.1, "mesh": 3.1}, "mask_confidence": 0.95, "psnr": 28.0,
           "psnr_views": "held-out", "report": None, "glb": None, "logs": None, "train_device": "cuda"}
    assert "masks 29 train 25 (cuda) mesh 3" in _html_row(tmp_path, row)
    assert "train 25 mesh" in _html_row(tmp_path, {**row, "train_device": "cpu"})


def test_more_gpus_per_training_than_any_node_has_is_a_one_line_error(small_ws, tmp_path, monkeypatch):
    """Ray would wait forever for a node with that many GPUs: the batch says so before it submits anything."""
    import ray

    from pipeline.config import config_from_args

    _local_ray_with_one_gpu(monkeypatch, cpus=1)
    captures = _captures(small_ws, tmp_path)
    with pytest.raises(StageError, match=r"--batch.train-gpus 2: no node of the cluster has that many GPUs "
                                         r"\(at most 1\)"):
        run_batch(captures, tmp_path / "out", config_from_args(None, TINY), BatchConfig(train_gpus=2))
    assert not ray.is_initialized()  # the cluster it started is shut down
    assert not (tmp_path / "out" / "good" / ".stages").exists()  # nothing ran
