"""Many captures at once on Ray: ``python -m pipeline batch CAPTURES [OUT]`` / ``make batch CAPTURES=dir``.

Every sub-folder of CAPTURES is one capture: its photos (directly in it, or in ``images/``), optionally ``masks/``
(user masks) and ``cameras.npz`` (given cameras). Each gets the workspace ``OUT/<sub-folder>`` and the stages of
:data:`pipeline.stages.STAGES`, each stage one Ray task calling :func:`pipeline.stages.run_stage` (the API the CLI
calls, so a batch run and a single run write the same files). A capture's stages form a chain (each task waits
for the one before); the chains of different captures overlap. Resources: every stage asks for
``cpus_per_stage`` cores (its torch threads); training also asks for ``train_gpus`` GPUs when the cluster has
any, and a task given none sees none (unless its stage is set to cuda). A stage's own error (a one-line
StageError) ends its capture's chain and is reported; the others go on. A worker that dies (killed process, lost
node) has its stage retried ``retries`` times. Re-running the batch skips the captures that are done (every stage
up to date) and, inside the others, the stages that are.

Without ``--address`` Ray starts a local cluster on this machine; with one (``ray start --head`` prints it, or
``auto``) the same command runs on that cluster. Writes ``OUT/summary.json`` and ``OUT/index.html``
(:mod:`pipeline.batch.summary`).
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
import traceback
from dataclasses import dataclass
from pathlib import Path

from pipeline.batch.config import BatchConfig
from pipeline.errors import StageError
from pipeline.lock import workspace_lock
from pipeline.stages import STAGES, check_user_masks, is_up_to_date, run_stage, stage_named


@dataclass(frozen=True)
class Capture:
    """One sub-folder of the captures folder and its workspace."""

    name: str
    photos: Path
    workspace: Path
    masks_dir: Path | None = None
    given_cameras: Path | None = None

    def sources(self, stage) -> dict:
        """The user paths ``stage`` reads (keyword arguments of :func:`~pipeline.stages.run_stage`)."""
        given = {"images": self.photos, "masks_dir": self.masks_dir, "given_cameras": self.given_cameras}
        return {k: given[k] for k in stage.sources}


def find_captures(captures: Path, out: Path) -> list[Capture]:
    """The captures under ``captures`` (sorted sub-folders); StageError when there are none or ``out`` lies
    inside one of them."""
    captures, out = Path(captures).resolve(), Path(out).resolve()
    if not captures.is_dir():
        raise StageError(f"{captures}: not a folder; CAPTURES must be a folder of capture folders (one per object)")
    found = []
    for sub in sorted(p for p in captures.iterdir() if p.is_dir() and not p.name.startswith(".")):
        if sub == out or sub in out.parents:
            continue  # OUT inside CAPTURES: not a capture
        photos = sub / "images" if (sub / "images").is_dir() else sub
        found.append(Capture(sub.name, photos, out / sub.name, sub / "masks" if (sub / "masks").is_dir() else None,
                             sub / "cameras.npz" if (sub / "cameras.npz").is_file() else None))
    if not found:
        raise StageError(f"{captures}: no capture folders in it; put each object's photos in its own sub-folder")
    return found


def user_masks_error(cap: Capture) -> str | None:
    """The masks stage's one line when the capture's own ``masks/`` lacks a photo's mask (or holds two of one), said
    before the capture's SfM runs, as ``reconstruct`` says it (:func:`pipeline.stages.check_user_masks`); None when
    its masks are complete or it has none."""
    if cap.masks_dir is None:
        return None
    try:
        check_user_masks(cap.photos, cap.masks_dir)
    except StageError as exc:
        return str(exc)
    return None


def capture_done(cap: Capture, config) -> bool:
    """Whether every stage of ``cap`` is up to date (the report: written once)."""
    try:
        return all(is_up_to_date(s.name, cap.workspace, config, **cap.sources(s)) for s in STAGES)
    except (StageError, ValueError, OSError):
        return False


def run_stage_task(capture: Capture, stage_name: str, config, threads: int, upstream: dict | None,
                   gpu: bool = False) -> dict:
    """One stage of one capture, in a Ray worker: its output goes to ``<workspace>/logs/<stage>.log``; returns a
    record (capture, stage, gpu, status ok/failed/skipped, ran, seconds, error). ``gpu``: the task was given a GPU;
    without one the worker's GPUs are hidden from a stage whose ``device`` is auto (Ray leaves them visible to a
    task that asked for none, and ``auto`` would train on them, outside Ray's count)."""
    if not gpu and _stage_device(config, stage_name) == "auto":  # an explicit cuda is the user's to keep
        os.environ["CUDA_VISIBLE_DEVICES"] = ""  # before torch first looks: the task's worker never ran a GPU task
    rec = {"capture": capture.name, "stage": stage_name, "gpu": gpu, "status": "skipped", "ran": False,
           "seconds": 0.0}
    if upstream is not None and upstream["status"] != "ok":
        return rec  # an earlier stage of this capture failed
    import torch

    torch.set_num_threads(max(1, threads))
    stage = stage_named(stage_name)
    logs = capture.workspace / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    with open(logs / f"{stage_name}.log", "a") as log, contextlib.redirect_stdout(log), \
            contextlib.redirect_stderr(log):
        try:
            rec["ran"] = run_stage(stage_name, capture.workspace, config, **capture.sources(stage))
            rec["status"] = "ok"
        except (StageError, FileNotFoundError, ValueError) as exc:  # the one-line error a single run prints
            rec.update(status="failed", error=_one_line(exc))
            print(f"error: {rec['error']}", file=sys.stderr)
        except Exception as exc:  # noqa: BLE001 - a bug: its traceback goes to the log, one line to the summary
            traceback.print_exc()
            rec.update(status="failed", error=f"internal error ({type(exc).__name__}: {_one_line(exc)}); "
                                              f"traceback in {logs / (stage_name + '.log')}")
    rec["seconds"] = round(time.perf_counter() - t0, 3)
    return rec


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def _task_options(stage, batch: BatchConfig, on_gpu: bool) -> dict:
    """Ray resources of one stage task: CPU cores, ``train_gpus`` GPUs for a training placed on one, retries."""
    opts = {"num_cpus": batch.cpus_per_stage, "max_retries": batch.retries}
    if stage.name == "train" and on_gpu:
        opts["num_gpus"] = batch.train_gpus
    return opts


def train_on_gpu(batch: BatchConfig, cluster_gpus: float, gpu_trainings: int, device: str = "auto") -> bool:
    """Whether a capture ready to train now goes to a GPU, with ``gpu_trainings`` trainings already running or
    waiting on the cluster's ``cluster_gpus`` GPUs: never without GPUs, with ``train_gpus`` 0 or with the train
    ``device`` cpu; with ``spill_to_cpu`` (and ``device`` auto) only while fewer than two per GPU slot are there
    (one running, one waiting keeps them busy)."""
    if cluster_gpus <= 0 or batch.train_gpus <= 0 or device == "cpu":
        return False
    slots = max(1, int(cluster_gpus / batch.train_gpus + 1e-9))
    return not batch.spill_to_cpu or device == "cuda" or gpu_trainings < 2 * slots


def _stage_device(config, stage_name: str) -> str | None:
    """The ``device`` setting of a stage's config section (None for a stage without one)."""
    from pipeline.config import Config

    section = stage_named(stage_name).section
    return getattr(getattr(config or Config(), section), "device", None) if section else None


LOCAL_RAY = {"object_store_memory": 256 * 1024**2}
"""``ray.init``'s resources for the local cluster a batch starts when it is given no address."""


@contextlib.contextmanager
def _ray(address: str | None):
    """Ray connected to the cluster at ``address``, or a local one (:data:`LOCAL_RAY`), quiet (stages log to their
    workspace), shut down on the way out. A local cluster keeps its session files (sockets, worker logs) in a
    temporary folder of its own, removed at shutdown: Ray's default, ``/tmp/ray/session_*``, keeps every run's forever
    (117 sessions, 24 MB on this machine from the batch tests)."""
    import logging
    import shutil
    import tempfile

    import ray

    temp = None if address else tempfile.mkdtemp(prefix="dvr-ray-")  # short: Ray's socket paths have a limit
    kw = {"address": address} if address else {**LOCAL_RAY, "_temp_dir": temp}
    try:
        ray.init(include_dashboard=False, log_to_driver=False, logging_level=logging.WARNING, **kw)
        yield ray
    finally:
        ray.shutdown()
        if temp is not None:
            shutil.rmtree(temp, ignore_errors=True)


def _progress_line(rec: dict, done: int, total: int) -> str:
    what = {"ok": "done" if rec["ran"] else "up to date", "failed": f"FAILED: {rec.get('error', '')}"}[rec["status"]]
    return f"[{done}/{total}] {rec['capture']}: {rec['stage']} {what} ({rec['seconds']:.1f} s)"


class _Chains:
    """Each capture's stage tasks, chained: the stages before training at once, training and the rest once the stage
    before it has ended, on a GPU or on CPU cores as :func:`train_on_gpu` decides then. ``pending`` maps each
    submitted task to its (capture, stage)."""

    def __init__(self, ray, config, batch: BatchConfig):
        # a GPU task's worker ends with it (max_calls=1, as Ray's own default for functions declared with GPUs): the
        # GPU memory torch's allocator holds goes with it, and no later task inherits its CUDA context
        self.cpu_task, self.gpu_task = ray.remote(run_stage_task), ray.remote(max_calls=1)(run_stage_task)
        self.gpus = ray.cluster_resources().get("GPU", 0)
        node_gpus = max((n["Resources"].get("GPU", 0) for n in ray.nodes() if n.get("Alive")), default=0)
        if 0 < node_gpus < batch.train_gpus:  # Ray would wait forever for a node with that many
            raise StageError(f"--batch.train-gpus {batch.train_gpus:g}: no node of the cluster has that many GPUs "
                             f"(at most {node_gpus:g}); ask for at most {node_gpus:g}, or a fraction to share one")
        self.config, self.batch = config, batch
        self.pending: dict = {}
        self.before_train: dict = {}  # the task of the stage before training → its capture
        self.on_gpu: set = set()  # training tasks placed on a GPU, not yet ended
        self.split = [s.name for s in STAGES].index("train")

    def _submit(self, cap: Capture, stages, upstream, gpu: bool):
        for stage in stages:
            on_gpu = gpu and stage.name == "train"
            task = self.gpu_task if on_gpu else self.cpu_task
            upstream = task.options(**_task_options(stage, self.batch, on_gpu)).remote(
                cap, stage.name, self.config, self.batch.cpus_per_stage, upstream, on_gpu)
            self.pending[upstream] = (cap, stage.name)
            if on_gpu:
                self.on_gpu.add(upstream)
        return upstream

    def start(self, cap: Capture) -> None:
        self.before_train[self._submit(cap, STAGES[: self.split], None, False)] = cap

    def ended(self, ref) -> None:
        """Task ``ref`` has ended: a GPU slot may be free; after the stage before training, submit the rest."""
        self.on_gpu.discard(ref)
        cap = self.before_train.pop(ref, None)
        if cap is not None:
            gpu = train_on_gpu(self.batch, self.gpus, len(self.on_gpu), _stage_device(self.config, "train"))
            self._submit(cap, STAGES[self.split :], ref, gpu)


def _collect(ray, chains: _Chains, records: dict, total: int) -> None:
    """Wait for the stage tasks, one progress line per finished stage and an overall bar (stderr)."""
    from tqdm import tqdm

    bar = tqdm(total=total, unit="stage", file=sys.stderr, dynamic_ncols=True)
    failed: set[str] = set()
    pending = chains.pending
    while pending:
        (ref,), _ = ray.wait(list(pending), num_returns=1)
        cap, stage_name = pending.pop(ref)
        chains.ended(ref)
        try:
            rec = ray.get(ref)
        except Exception as exc:  # noqa: BLE001 - the worker died more often than retried, or upstream did
            rec = {"capture": cap.name, "stage": stage_name, "ran": False, "seconds": 0.0,
                   "status": "skipped" if cap.name in failed else "failed",
                   "error": f"worker lost after retries ({type(exc).__name__})"}
        failed |= {cap.name} if rec["status"] == "failed" else set()
        records[cap.name].append(rec)
        bar.update(1)
        if rec["status"] != "skipped":
            bar.write(_progress_line(rec, bar.n, total))
    bar.close()


def run_batch(captures: Path, out: Path, config=None, batch: BatchConfig | None = None) -> dict:
    """Reconstruct every capture under ``captures`` into ``out/<capture>`` on Ray; returns the summary (also
    written as ``out/summary.json`` and ``out/index.html``). Captures already done are not touched. One batch at a
    time works in ``out`` (:mod:`pipeline.lock`), and each stage task holds its capture's workspace, so a single run
    on a capture of a running batch stops with the lock's one line (and the batch's stage, meeting a single run,
    fails with it)."""
    from pipeline.config import Config

    out = Path(out).resolve()
    caps = find_captures(captures, out)
    out.mkdir(parents=True, exist_ok=True)
    with workspace_lock(out, "batch"):
        return _run_batch(caps, out, config or Config(), batch or BatchConfig())


def _run_batch(caps: list[Capture], out: Path, config, batch: BatchConfig) -> dict:
    from pipeline.batch.summary import write_summary

    records: dict[str, list] = {c.name: [] for c in caps}
    todo = [c for c in caps if not capture_done(c, config)]
    for c in list(todo):  # a capture whose masks lack a photo's fails before its SfM, the others go on
        error = user_masks_error(c)
        if error is not None:
            records[c.name].append({"capture": c.name, "stage": "masks", "gpu": False, "status": "failed",
                                    "ran": False, "seconds": 0.0, "error": error})
            print(f"{c.name}: masks FAILED before its cameras ran: {error}", file=sys.stderr)
            todo.remove(c)
    for c in caps:
        if c not in todo:
            print(f"{c.name}: up to date ({c.workspace / 'mesh' / 'textured.glb'})")
    t0 = time.perf_counter()
    if todo:
        with _ray(batch.address) as ray:
            chains = _Chains(ray, config, batch)
            for cap in todo:
                chains.start(cap)
            _collect(ray, chains, records, len(todo) * len(STAGES))
    return write_summary(out, caps, records, time.perf_counter() - t0)
