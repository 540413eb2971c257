"""bench-core: field throughput, FLOP rate, rays/s of a training step, and seconds to Chamfer ≤ 1 %.

    python bench/core.py [--device auto|cpu|cuda] [--budget 300] [--json out.json]

Prints numbers; asserts nothing. The standard scene is configs/scenes/torus.yaml (24 views, 128 px).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import torch
import trimesh

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dvr.config import FieldConfig, TrainConfig  # noqa: E402
from dvr.data import load_scene  # noqa: E402
from dvr.device import resolve_device  # noqa: E402
from dvr.extract import extract_mesh  # noqa: E402
from dvr.fields import GridField  # noqa: E402
from dvr.metrics import chamfer_fscore  # noqa: E402
from dvr.trainer import Trainer  # noqa: E402
from synth import load_scene_file, write_scene  # noqa: E402


def cpu_info() -> dict:
    info = {"cores": os.cpu_count(), "torch_threads": torch.get_num_threads(), "model": platform.processor()}
    try:
        txt = Path("/proc/cpuinfo").read_text()
        for line in txt.splitlines():
            if line.startswith("model name"):
                info["model"] = line.split(":", 1)[1].strip()
                break
        flags = next((ln for ln in txt.splitlines() if ln.startswith("flags")), "")
        mhz = [float(ln.split(":")[1]) for ln in txt.splitlines() if ln.startswith("cpu MHz")]
        fpc = 64 if "avx512f" in flags else 32 if "fma" in flags else 8  # fp32 FLOP/cycle/core (2 FMA units)
        info["peak_gflops_est"] = round(torch.get_num_threads() * (mhz[0] if mhz else 2000) * 1e-3 * fpc, 1)
        info["flop_per_cycle_assumed"] = fpc
    except (OSError, StopIteration, ValueError):
        pass
    return info


def field_flops_per_point(cfg: FieldConfig) -> float:
    """Analytic fp32 FLOPs of occupancy + texture at one point (forward)."""

    def planes(res: tuple[int, ...]) -> tuple[float, int]:  # bilinear lookups on 3 planes per level, features
        return len(res) * 3 * 4 * 2 * cfg.plane_features, len(res) * cfg.plane_features

    flops = 8 * 2.0  # trilinear lookup in the dense occupancy logit grid (one channel)
    if cfg.occ_plane_res:  # optional tri-plane residual + its one-hidden-layer head
        f, d = planes(tuple(cfg.occ_plane_res))
        flops += f + 2 * (d * cfg.hidden + cfg.hidden * 1)
    f, d = planes(tuple(cfg.plane_res))  # texture: tri-plane + one-hidden-layer head
    return flops + f + 2 * (d * cfg.hidden + cfg.hidden * 3)


def throughput(dev: torch.device, cfg: FieldConfig, n: int = 262144, reps: int = 5) -> dict:
    f = GridField(cfg).to(dev)
    p = torch.rand(n, 3, device=dev) * 2 - 1

    def sync():
        if dev.type == "cuda":
            torch.cuda.synchronize()

    def fwd():
        with torch.no_grad():
            f.occupancy(p)
            f.texture(p)

    def fb():
        (f.occupancy(p).sum() + f.texture(p).sum()).backward()

    out = {}
    for name, fn in (("forward", fwd), ("forward_backward", fb)):
        fn()
        sync()
        t0 = time.perf_counter()
        for _ in range(reps):
            fn()
        sync()
        dt = (time.perf_counter() - t0) / reps
        out[f"{name}_points_per_s"] = n / dt
    flops = field_flops_per_point(cfg)
    out["flops_per_point"] = flops
    out["forward_gflops"] = out["forward_points_per_s"] * flops / 1e9
    out["forward_backward_gflops"] = out["forward_backward_points_per_s"] * 3 * flops / 1e9
    return out


def time_to_chamfer(ws: Path, dev: torch.device, cfg: TrainConfig, target: float, budget: float, every: int) -> dict:
    data = load_scene(ws, dev)
    gt = trimesh.load(ws / "gt" / "mesh.ply")
    with tempfile.TemporaryDirectory() as td:
        t0 = time.perf_counter()
        tr = Trainer(cfg, data, Path(td))
        setup = time.perf_counter() - t0
        curve = []
        while True:
            v, fc, _ = extract_mesh(tr.model, 128, refine_steps=1)
            m = trimesh.Trimesh(v, fc, process=False)
            m.apply_transform(tr.data.cams.scale_mat)
            r = chamfer_fscore(m, gt, n=50000) if len(fc) else {"chamfer_rel": float("inf"), "fscore": 0.0}
            curve.append({"step": tr.step, "train_s": round(setup + tr.elapsed, 2), "chamfer_rel": r["chamfer_rel"],
                          "fscore": r["fscore"]})
            print(f"  step {tr.step:5d}  {setup + tr.elapsed:7.1f} s  chamfer {100 * r['chamfer_rel']:.3f} %  "
                  f"F {r['fscore']:.3f}", flush=True)
            if r["chamfer_rel"] <= target or setup + tr.elapsed > budget or tr.step >= tr.cfg.iterations:
                break
            tr.fit(stop_after=every)
        hit = next((c for c in curve if c["chamfer_rel"] <= target), None)
        return {"seconds_to_target": None if hit is None else hit["train_s"], "curve": curve,
                "rays_per_s": tr.step * tr.cfg.batch_rays / max(tr.elapsed, 1e-9) if tr.step else None}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="auto")
    ap.add_argument("--budget", type=float, default=300.0, help="training seconds allowed per run")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    dev = resolve_device(a.device)
    res: dict = {"device": str(dev), "cpu": cpu_info(), "torch": torch.__version__}
    if dev.type == "cuda":
        res["gpu"] = torch.cuda.get_device_name(0)
    print(json.dumps({k: res[k] for k in res}, indent=1))
    fcfg = FieldConfig()
    tp = throughput(dev, fcfg)
    res["field"] = tp
    print(f"field (default grid): forward {tp['forward_points_per_s'] / 1e6:.2f} M points/s, "
          f"forward+backward {tp['forward_backward_points_per_s'] / 1e6:.2f} M points/s; "
          f"{tp['flops_per_point']:.0f} FLOP/point → {tp['forward_gflops']:.1f} GFLOP/s forward "
          f"(peak est. {res['cpu'].get('peak_gflops_est', '?')} GFLOP/s on {res['cpu']['torch_threads']} threads)")
    with tempfile.TemporaryDirectory() as td:
        ws = Path(td) / "torus"
        write_scene(load_scene_file(ROOT / "configs" / "scenes" / "torus.yaml"), ws)
        for name, hull in (("default (visual-hull init)", True), ("ablation: no hull init (sphere start)", False)):
            print(f"time to Chamfer ≤ 1 %: {name}")
            cfg = TrainConfig(iterations=20000, progress=False, hull_init=hull, device=a.device, preview_every=0,
                              checkpoint_every=10 ** 9)
            r = time_to_chamfer(ws, dev, cfg, 0.01, a.budget, every=100)
            res[f"time_to_1pct_{'hull' if hull else 'nohull'}"] = r
            print(f"  → {r['seconds_to_target']} s   ({r['rays_per_s']} rays/s)" if r["rays_per_s"] else
                  f"  → {r['seconds_to_target']} s")
        # rays/s of the full training step, measured over 100 steps of the default config
        data = load_scene(ws, dev)
        tr = Trainer(TrainConfig(iterations=100, progress=False, preview_every=0, device=a.device,
                                 checkpoint_every=10 ** 9), data, Path(td) / "m")
        tr.fit()
        res["train_step"] = {"seconds_per_step": tr.elapsed / 100, "rays_per_s": 100 * 2048 / tr.elapsed}
        print(f"training step (2048 rays, 64→96 samples): {tr.elapsed / 100 * 1000:.1f} ms, "
              f"{100 * 2048 / tr.elapsed:.0f} rays/s")
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
