"""Batch against one capture at a time: four small synthetic captures (photos only, through SfM), reconstructed
one after the other with ``python -m pipeline reconstruct`` (what a shell loop does) and then all at once with
``python -m pipeline batch`` on a local Ray cluster. Prints the wall time and the mean CPU utilisation of both (all
cores, from /proc/stat, so Ray's worker processes count), and the seconds per stage of a capture in each.

    python bench/batch.py [--config configs/fast.yaml] [--gpu-train SECONDS]
    python bench/batch.py --gpu-train SECONDS --rows-from bench/results/<date>-batch.json   # the table only

``--gpu-train``: the train stage's seconds per capture measured on a GPU (``bench/gpu.py train`` on the four
captures); with it the scaling table also has GPU rows. ``--rows-from``: the table from an earlier run's seconds per
stage, without running anything. Writes bench/results/<date>-batch.json.

    python bench/batch.py --faults 20 [--seed 0]     # kill -9 at 20 random moments, each run again to the end

``--faults N``: the first capture's photos through SfM, with its true masks (the automatic masks would take most of
the time) and a short training, run once stage by stage; then N times: the workspace as it was before a stage drawn
at random, ``python -m pipeline reconstruct`` killed with SIGKILL at a random moment of that stage (its own process
only: a child of it must end with it), the files checked for one a write left cut short (:func:`torn_files`), and
the same command run again. Prints how many reruns finished, with the GLB of the uninterrupted run (faces, texture
size), how many files were torn, how many child processes outlived their run, and any traceback. Writes
bench/results/<date>-faults.json.
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


# ----------------------------------------------------------------------------- kills (--faults N)
FAULT_OPTIONS = {"train": {"iterations": 100, "batch_rays": 1024, "checkpoint_every": 20, "progress": False},
                 "mesh": {"resolution": 128, "max_faces": 20000}, "texture": {"size": 256}}
"""The options of the runs that ``--faults`` kills, over ``--config``'s: a training of well under a minute on 2 idle
cores, checkpointed often enough that a kill during it resumes."""


def fault_config(base: str, out: Path) -> Path:
    """The preset ``base`` with :data:`FAULT_OPTIONS` over it, written to ``out``."""
    import yaml

    d = yaml.safe_load(Path(base).read_text()) or {}
    for section, over in FAULT_OPTIONS.items():
        d[section] = {**d.get(section, {}), **over}
    out.write_text(yaml.safe_dump(d))
    return out


def torn_files(ws: Path) -> list[str]:
    """The files of the workspace ``ws`` that do not read back whole, each with why: JSON, NPZ, PNG/JPEG, PLY and
    GLB, torch files, COLMAP databases (SQLite's integrity check) and models, report.html (its end), an OBJ (its faces
    against the GLB's). The temporary files of writes a kill interrupted (``.<name>.<pid>.partial``, which nothing
    reads), the lock's own files and append-only logs are not checked."""
    import sqlite3

    import numpy as np
    import torch
    import trimesh
    from PIL import Image

    from dvr.atomic import PARTIAL

    torn = []
    models = set()
    for f in sorted(p for p in ws.rglob("*") if p.is_file()):
        rel = f.relative_to(ws)
        if any(part.endswith(PARTIAL) for part in rel.parts) or rel.parts[0] == "logs" or f.suffix in (".log",
                                                                                                        ".jsonl"):
            continue
        try:
            if f.suffix == ".json":
                json.loads(f.read_text())
            elif f.suffix == ".npz":
                with np.load(f) as z:
                    [z[k] for k in z.files]
            elif f.suffix in (".png", ".jpg"):
                with Image.open(f) as im:
                    im.load()
            elif f.suffix in (".ply", ".glb"):
                trimesh.load(f, process=False)
            elif f.suffix == ".pt":
                torch.load(f, map_location="cpu", weights_only=False)
            elif f.suffix == ".db":
                with sqlite3.connect(f"file:{f}?mode=ro", uri=True) as db:
                    if db.execute("PRAGMA integrity_check").fetchone()[0] != "ok":
                        raise ValueError("integrity check")
            elif f.suffix == ".bin":
                models.add(f.parent)
            elif f.name == "report.html" and not f.read_text().rstrip().endswith("</html>"):
                raise ValueError("no </html> at its end")
            elif f.name == "textured.obj" and (ws / "mesh" / "textured.glb").exists():
                faces = sum(1 for line in f.read_text().splitlines() if line.startswith("f "))
                glb = trimesh.load(ws / "mesh" / "textured.glb", force="mesh", process=False)
                if faces != len(glb.faces):
                    raise ValueError(f"{faces} faces, the GLB {len(glb.faces)}")
        except Exception as exc:  # noqa: BLE001 - whatever the reader raises, the file is not whole
            torn.append(f"{rel} ({type(exc).__name__}: {str(exc)[:80]})")
    from pipeline.colmaplib import pycolmap

    for folder in sorted(models):
        try:
            pycolmap.Reconstruction(folder)
        except Exception as exc:  # noqa: BLE001 - a model cut short reads as anything from bad_alloc to a parse error
            torn.append(f"{folder.relative_to(ws)} ({type(exc).__name__})")
    return torn


def glb_summary(ws: Path) -> tuple[int, tuple[int, int]] | None:
    """(faces, texture size) of the workspace's textured GLB, or None without one."""
    from pipeline.texture.export import read_textured

    glb = ws / "mesh" / "textured.glb"
    if not glb.exists():
        return None
    mesh, tex = read_textured(glb)
    return len(mesh.faces), tex.shape[:2]


def _alive(pgid: int) -> bool:
    """Whether a process of the process group ``pgid`` still runs (a child the killed run left)."""
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    return True


def faults(n: int, seed: int, config: str) -> None:
    """``--faults N`` (the module's docstring)."""
    import random

    from bench.evaluate import fresh_folder, scene
    from pipeline.stages import STAGES
    from pipeline.workspace import Workspace

    work = RUNS / "faults"
    shutil.rmtree(work, ignore_errors=True)
    syn = scene("e2e", {})
    work.mkdir(parents=True)
    photos, masks = syn / "images", ["--masks-dir", str(syn / "masks")]
    py = [sys.executable, "-m", "pipeline"]
    opts = ["--config", str(fault_config(config, work / "config.yaml"))]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    ws, snaps = work / "ws", work / "before"
    names = [st.name for st in STAGES]
    t0 = time.perf_counter()
    for name in names:  # the uninterrupted run, stage by stage, the workspace kept as each stage found it
        if ws.exists():
            shutil.copytree(ws, snaps / name, symlinks=True)
        sources = {"cameras": ["--images", str(photos)], "masks": masks}.get(name, [])
        measured([*py, name, str(ws), *sources, *opts])
    clean, secs = glb_summary(ws), Workspace(ws).seconds()
    print(f"uninterrupted: {time.perf_counter() - t0:.0f} s, GLB {clean[0]} faces, texture {clean[1]}; seconds per "
          f"stage {json.dumps({k: round(v, 1) for k, v in secs.items()})}", flush=True)
    rng = random.Random(seed)
    rows = []
    for k in range(n):
        stage = rng.choice(names)
        frac = rng.random()
        shutil.rmtree(ws, ignore_errors=True)
        if (snaps / stage).exists():
            shutil.copytree(snaps / stage, ws, symlinks=True)
        cmd = [*py, "reconstruct", str(ws), "--images", str(photos), *masks, *opts]
        p = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                             start_new_session=True)
        marker = Workspace(ws).stages / f"{stage}.unfinished"
        while p.poll() is None and not marker.exists():
            time.sleep(0.005)
        time.sleep(frac * secs.get(stage, 0.0))
        killed = p.poll() is None
        p.kill()
        p.wait()
        hit = sorted(m.stem for m in Workspace(ws).stages.glob("*.unfinished")) if killed else []
        for _ in range(200):  # a child still importing when its run was killed ends at its call (≤ 20 s)
            if not _alive(p.pid):
                break
            time.sleep(0.1)
        orphans = _alive(p.pid)
        if orphans:
            os.killpg(p.pid, 9)
        torn = torn_files(ws)
        again = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True)
        glb = glb_summary(ws) if again.returncode == 0 else None
        row = {"stage": stage, "at": round(frac, 3), "killed_in": hit, "torn": torn, "orphans": orphans,
               "rerun_rc": again.returncode, "traceback": "Traceback" in again.stderr, "glb_as_clean": glb == clean,
               "taken_over": "taking it over" in again.stderr, "torn_after": torn_files(ws)}
        rows.append(row)
        print(f"[{k + 1}/{n}] killed in {', '.join(hit) or '(ended first)'} ({stage} at {frac:.2f}): torn {len(torn)}, "
              f"orphans {int(orphans)}; rerun rc {again.returncode}, GLB as uninterrupted: {glb == clean}"
              + (f"\n    {again.stderr.strip().splitlines()[-1]}" if again.returncode else ""), flush=True)
    done = sum(r["rerun_rc"] == 0 and r["glb_as_clean"] for r in rows)
    torn_n = sum(len(r["torn"]) + len(r["torn_after"]) for r in rows)
    per_stage = ", ".join(f"{s} {sum(s in r['killed_in'] for r in rows)}" for s in names)
    print(f"kill -9 at {n} moments (seed {seed}): {sum(bool(r['killed_in']) for r in rows)} inside a stage "
          f"({per_stage}); reruns finished with the "
          f"uninterrupted GLB: {done}/{n}; files torn: {torn_n}; child processes left running: "
          f"{sum(r['orphans'] for r in rows)}; reruns with a traceback: {sum(r['traceback'] for r in rows)}")
    out = ROOT / "bench" / "results" / f"{datetime.date.today().isoformat()}-faults.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"seed": seed, "config": Path(config).name, "options": FAULT_OPTIONS,
                               "clean": {"faces": clean[0], "texture": list(clean[1]), "stage_seconds": secs},
                               "reruns_finished": done, "kills": rows}, indent=1))
    fresh_folder(work / "ws")
    print(f"→ {out}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default=str(ROOT / "configs" / "fast.yaml"))
    ap.add_argument("--gpu-train", type=float, default=None, help="train stage seconds per capture on one GPU")
    ap.add_argument("--rows-from", type=Path, default=None, help="an earlier run's JSON: print its scaling table")
    ap.add_argument("--faults", type=int, default=None, help="kill -9 at this many random moments, then rerun")
    ap.add_argument("--seed", type=int, default=0, help="with --faults: the random moments' seed")
    args = ap.parse_args()
    if args.faults is not None:
        faults(args.faults, args.seed, args.config)
        return
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
