"""Training on a GPU against 2 CPU cores: the train stage of the bench's cow and jar (GT cameras) and DTU scan24
(photos only) workspaces on whatever device ``device: auto`` finds, then mesh, texture and held-out PSNR as in
``bench/run.py``.

    python bench/gpu.py prepare DIR            # here: the training workspaces (images, masks, cameras, depth)
    python bench/gpu.py train DIR [RUN...]     # on the GPU machine: the train stage per run → DIR/gpu.json
                                               # (RUN: SCENE:PRESET[:eager][:scaleN], eager: no CUDA graphs,
                                               #  scaleN: --train.gpu-batch-scale N; default cow:default
                                               #  cow:default:scale1 jar:default dtu:default dtu:default:scale1
                                               #  cow:quality;
                                               #  the batch's captures: torus_noise:fast … as in bench/batch.py)
    python bench/gpu.py evaluate DIR           # here again: mesh + texture + held-out PSNR per trained model
    python bench/gpu.py profile DIR [SCALE...] # on the GPU machine: where a default training step's time goes, at
                                               # each --train.gpu-batch-scale (default: the preset's and 1)
    python bench/gpu.py share DIR N...         # on the GPU machine: the batch's captures trained N at a time on the
                                               # one GPU, one torch thread each (Ray's --batch.train-gpus 1/N)
    python bench/gpu.py graph DIR              # on the GPU machine: a step's surface finding eagerly, with fixed
                                               # shapes, and as trained (on CUDA replayed as one CUDA graph)

The GPU machine needs torch, numpy, scipy, scikit-image, opencv, tyro, trimesh, kornia and PyYAML (no pycolmap,
pymeshlab, xatlas: the stages that need them run in the evaluate step); bench/gpu_check.sh installs the ones its
image lacks from wheels carried with the call.
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SYNTHETIC = ("cow", "jar")  # with their ground-truth cameras; the jar's fine print shows what fewer steps cost
SCENES = (*SYNTHETIC, "dtu")
BATCH = ("torus_noise", "torus_fine", "torus_thick", "torus_high")  # bench/batch.py's four captures (fast preset)


def prepare(out: Path) -> None:
    """The workspaces ``bench/run.py`` trains on: the cow and the jar with GT cameras, DTU without every 7th
    photo."""
    from bench.evaluate import RUNS, dtu_heldout, scene, subset_workspace
    from dvr.data import list_images

    for name in SYNTHETIC:
        shutil.copytree(scene(name, {}), out / name, ignore=shutil.ignore_patterns("gt", "depth"))
    full = RUNS / "dtu_all"
    if not (full / ".stages" / "depth.json").exists():
        sys.exit(f"{full}: missing; run `python bench/run.py` once (its DTU row) to build it")
    n = len(list_images(full / "images"))
    held = dtu_heldout(n)
    subset_workspace(full, out / "dtu", [i for i in range(n) if i not in held])
    prepare_batch(out)


def prepare_batch(out: Path) -> None:
    """bench/batch.py's four captures from their photos through cameras, masks and depth (fast preset): the GPU's
    train seconds per capture give that bench's rows with GPUs (``bench/batch.py --gpu-train S``)."""
    from bench.batch import VARIANTS, make_captures
    from bench.evaluate import config, stages

    captures = make_captures(out / "batch_photos")
    for name in VARIANTS:
        stages(("cameras", "masks", "depth"), out / name, config("fast"), images=captures / name)
        shutil.rmtree(out / name / "sfm")  # COLMAP's database and model: training reads cameras.npz (23 MB less)
    shutil.rmtree(captures)


def train(out: Path, runs: list[str]) -> None:
    """Train each ``scene:preset[:eager][:scaleN]`` on the device ``auto`` picks; seconds into ``out/gpu.json``."""
    import torch

    from bench.evaluate import config

    rec = {"device": torch.cuda.get_device_name() if torch.cuda.is_available() else "cpu", "runs": []}
    for run in runs:
        name, preset, *extras = run.split(":")
        if name not in SCENES + BATCH:
            sys.exit(f"{name}: not a scene of this bench ({', '.join(SCENES + BATCH)})")
        cfg = config(preset)
        cfg.train.cuda_graphs = "eager" not in extras  # :eager: the surface finding without CUDA graphs
        for extra in extras:  # :scaleN: --train.gpu-batch-scale N
            if extra.startswith("scale"):
                cfg.train.gpu_batch_scale = int(extra[len("scale"):])
        ws = out / "runs" / run_folder(run)
        shutil.rmtree(ws, ignore_errors=True)
        shutil.copytree(out / name, ws)
        train_stage(ws, cfg.train)
        stamp = json.loads((ws / ".stages" / "train.json").read_text())
        secs = stamp["seconds"]
        rec["runs"].append({"run": run, "scene": name, "preset": preset, "cuda_graphs": cfg.train.cuda_graphs,
                            "gpu_batch_scale": cfg.train.gpu_batch_scale, "steps": stamp.get("steps"),
                            "batch_rays": stamp.get("batch_rays"), "train_seconds": secs})
        print(f"{run}: train {secs:.1f} s on {rec['device']}", flush=True)
        (out / "gpu.json").write_text(json.dumps(rec, indent=1))  # after each run: a call cut short keeps its rows


def train_stage(ws: Path, cfg) -> None:
    """The train stage in ``ws`` with the train options ``cfg``, then its stamp: what ``python -m pipeline train``
    runs, without :mod:`pipeline.stages`, whose other stages load pycolmap, which the GPU machine's image lacks."""
    from pipeline.train.stage import run
    from pipeline.workspace import Job, Workspace, config_hash

    w = Workspace(ws)
    job = Job(w, cfg, config_hash=config_hash(cfg), inputs=[w.images])
    done = run(job)
    w.mark_done("train", job.config_hash, done.seconds, done.details)


def run_folder(run: str) -> str:
    """The workspace folder of a run ``scene:preset[:eager][:scaleN]`` under ``DIR/runs``."""
    return run.replace(":", "_")


def evaluate(out: Path) -> None:
    """Mesh and texture here for each trained workspace, then held-out PSNR (bench/evaluate.py's protocol)."""
    from bench.evaluate import RUNS, _read_mask, _read_rgb, config, dtu_heldout, render_psnr, stages, textured
    from dvr.cameras import load_cameras
    from dvr.data import list_images

    rec = json.loads((out / "gpu.json").read_text())
    for run in rec["runs"]:
        if run["scene"] in BATCH:  # their train seconds are what bench/batch.py --gpu-train takes
            continue
        ws = out / "runs" / run_folder(run["run"])
        if not (ws / "model" / "final.pt").exists():
            print(f"{ws}: no trained model came back from the GPU machine; not evaluated")
            continue
        shutil.copytree(out / run["scene"], ws, dirs_exist_ok=True)  # only the model came back from the GPU
        stages(("mesh", "texture"), ws, config(run["preset"]))
        tm, tex = textured(ws)
        if run["scene"] in SYNTHETIC:
            syn = RUNS / "scenes" / run["scene"]
            cams = load_cameras(syn / "gt" / "heldout" / "cameras.npz")
            photos = sorted((syn / "gt" / "heldout" / "images").glob("*.png"))
            views = [(i, p, syn / "gt" / "heldout" / "masks" / p.name) for i, p in enumerate(photos)]
        else:
            full = RUNS / "dtu_all"
            cams, photos = load_cameras(full / "cameras.npz"), list_images(full / "images")
            views = [(i, photos[i], full / "masks" / f"{photos[i].stem}.png") for i in dtu_heldout(len(photos))]
        run["psnr"] = float(np.mean([render_psnr(tm, tex, cams.K[i], cams.R[i], cams.sfm_centers[i], _read_rgb(p),
                                                 _read_mask(m)) for i, p, m in views]))
        print(f"{run['run']}: train {run['train_seconds']:.1f} s on {rec['device']}, "
              f"held-out PSNR {run['psnr']:.2f} dB")
    (out / "gpu.json").write_text(json.dumps(rec, indent=1))


def share(out: Path, at_once: list[int]) -> None:
    """Train bench/batch.py's captures (fast preset) ``n`` at a time on one GPU, each in its own process with one
    torch thread, as a batch with ``--batch.train-gpus 1/n`` runs them: wall seconds and captures per hour of the
    GPU for each ``n`` in ``at_once`` (``n`` trainings: the four captures, repeated where ``n`` > 4)."""
    import os
    import subprocess
    import time
    from concurrent.futures import ThreadPoolExecutor

    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    rows = []
    for n in at_once:
        names = [BATCH[i % len(BATCH)] for i in range(max(n, len(BATCH)))]

        def one(k: int, name: str, n: int = n) -> float:
            d = out / "share" / f"{n}_{k}"
            shutil.rmtree(d, ignore_errors=True)
            d.mkdir(parents=True)
            (d / name).symlink_to((out / name).resolve())
            subprocess.run([sys.executable, __file__, "train", str(d), f"{name}:fast"], env=env, check=True,
                           capture_output=True)
            return json.loads((d / "gpu.json").read_text())["runs"][0]["train_seconds"]

        t0 = time.perf_counter()
        with ThreadPoolExecutor(n) as pool:
            secs = list(pool.map(one, range(len(names)), names))
        wall = time.perf_counter() - t0
        rows.append({"at_once": n, "trainings": len(names), "wall_s": round(wall, 1),
                     "train_s_each": round(sum(secs) / len(secs), 1),
                     "captures_per_hour": round(3600 * len(names) / wall, 1)})
        print(f"{n} at once: {len(names)} trainings in {wall:.1f} s (each {rows[-1]['train_s_each']} s), "
              f"{rows[-1]['captures_per_hour']} captures/hour on one GPU", flush=True)
        (out / "share.json").write_text(json.dumps(rows, indent=1))  # after each n: a run cut short keeps its rows


def graph(out: Path, repeats: int = 50) -> None:
    """The cow's default training field after 200 steps, one step's rays (default batch and samples): the surface
    finding eagerly (``find_surface``, the trainer's way on CPU), with fixed shapes (``find_surface_fixed``) and as
    the trainer runs it (``SurfaceFinder``: on CUDA replayed as one CUDA graph, inputs and outputs copied), ms each
    and whether they agree."""
    import time

    import torch

    from dvr.data import load_scene
    from dvr.device import resolve_device
    from dvr.march import find_surface, find_surface_fixed, sample_fractions
    from dvr.trainer import Trainer
    from pipeline.config import load_config

    cfg = load_config(ROOT / "configs" / "default.yaml").train
    cfg.progress = False
    dev = resolve_device("auto")
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
    t = Trainer(cfg, load_scene(out / "cow", dev), out / "graph")
    for i in range(200):
        t.train_step(i)
    origins, dirs = t.sampler.sample(t.cfg.batch_rays)[:2]  # as trained on this device
    n = t.n_steps_at(200)
    occ = t.model.occupancy
    fractions = sample_fractions(origins.shape[0], n, False, dev, origins.dtype)

    def timed(fn) -> float:
        for _ in range(3):
            fn()
        sync()
        t0 = time.perf_counter()
        for _ in range(repeats):
            fn()
        sync()
        return (time.perf_counter() - t0) / repeats * 1e3

    calls = {"eager": lambda: find_surface(occ, origins, dirs, n_steps=n, n_secant=cfg.n_secant),
             "fixed shapes": lambda: find_surface_fixed(occ, origins, dirs, fractions, cfg.n_secant),
             "as trained": lambda: t.find_surface(origins, dirs, n_steps=n, jitter=False)}
    eager = calls["eager"]()
    rows, agree = {}, {}
    for name, fn in calls.items():
        res = fn()
        agree[name] = bool(torch.equal(eager.status, res.status) and torch.allclose(eager.depth, res.depth, atol=1e-5))
        rows[name] = timed(fn)
        print(f"surface finding, {name}: {rows[name]:.2f} ms on {dev} (agrees: {agree[name]})")
    print(f"graphs captured: {t.find_surface.captures}")
    (out / "graph.json").write_text(json.dumps({"device": str(dev), "ms": rows, "agrees": agree,
                                                "captures": t.find_surface.captures}, indent=1))


def profile(out: Path, scales: list[int], steps: int = 20) -> None:
    """Time default-preset training steps on the cow at each ``gpu_batch_scale`` of ``scales`` (none: the preset's
    and 1), and profile ``steps`` of each: host time, device time, kernel launches and waits for the device per
    step."""
    import time
    from dataclasses import replace

    import torch
    from torch.autograd import DeviceType
    from torch.profiler import ProfilerActivity
    from torch.profiler import profile as torch_profile

    from dvr.data import load_scene
    from dvr.device import resolve_device
    from dvr.trainer import Trainer
    from pipeline.config import load_config

    dev = resolve_device("auto")
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
    default = load_config(ROOT / "configs" / "default.yaml").train
    for scale in scales or sorted({default.gpu_batch_scale, 1}, reverse=True):
        cfg = replace(default, progress=False, gpu_batch_scale=scale)
        t = Trainer(cfg, load_scene(out / "cow", dev), out / "profile")
        start, timed = int(0.6 * t.cfg.iterations), max(10, t.cfg.iterations // 10)  # past the grid's upsampling
        for i in range(start):  # warm-up
            t.train_step(i)
        sync()
        t0 = time.perf_counter()
        for i in range(start, start + timed):
            t.train_step(i)
        sync()
        print(f"gpu_batch_scale {scale}: {(time.perf_counter() - t0) / timed * 1e3:.1f} ms per step of "
              f"{t.cfg.batch_rays} rays on {dev}")
        with torch_profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
            for i in range(start + timed, start + timed + steps):
                t.train_step(i)
            sync()
        ka = prof.key_averages()
        print(ka.table(sort_by="self_cpu_time_total", row_limit=15, max_name_column_width=40))
        busy = sum(e.self_device_time_total for e in ka if e.device_type == DeviceType.CUDA) / steps / 1e3
        launches = sum(e.count for e in ka if e.key in ("cudaLaunchKernel", "cuLaunchKernel", "cudaLaunchKernelExC"))
        waits = sum(e.count for e in ka if "Synchronize" in e.key)
        print(f"per step: device busy {busy:.2f} ms, {launches / steps:.0f} kernel launches, {waits / steps:.0f} waits")


if __name__ == "__main__":
    if len(sys.argv) < 3 or sys.argv[1] not in ("prepare", "train", "evaluate", "profile", "share", "graph"):
        sys.exit(__doc__)
    step, folder = sys.argv[1], Path(sys.argv[2])
    default_runs = ["cow:default", "cow:default:scale1", "jar:default", "dtu:default", "dtu:default:scale1",
                    "cow:quality"]
    {"prepare": lambda: prepare(folder), "train": lambda: train(folder, sys.argv[3:] or default_runs),
     "evaluate": lambda: evaluate(folder), "profile": lambda: profile(folder, [int(k) for k in sys.argv[3:]]),
     "graph": lambda: graph(folder),
     "share": lambda: share(folder, [int(n) for n in sys.argv[3:]] or [1, 4, 8])}[step]()
