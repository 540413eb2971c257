"""What accuracy costs in time: run presets and knob sweeps end to end on synthetic scenes with ground truth.

    python bench/run.py --quick          # ≤ 10 min on 2 cores: fast + default presets, GT cameras
    python bench/run.py                  # full set: + quality, SfM cameras, knob sweep

Each run is its own process (peak memory = its max RSS). Per run: seconds per stage, Chamfer and F-score@1 %
of the GT diagonal (after Sim(3) alignment when cameras come from SfM), PSNR of the textured mesh at held-out
views (object pixels). Writes bench/results/<date>-<machine>.json, a PNG plot of Chamfer against seconds with
the Pareto front marked, and a Markdown table (printed; also between the BENCH markers of README.md with
--readme).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SCENES = {
    "convex": ROOT / "configs" / "scenes" / "sphere_checker.yaml",
    "cow": ROOT / "configs" / "scenes" / "cow_backdrop.yaml",
    "thin": ROOT / "configs" / "scenes" / "thin_plate.yaml",
}


def machine() -> dict:
    from bench.core import cpu_info

    info = cpu_info()
    try:
        import torch

        if torch.cuda.is_available():
            info["gpu"] = torch.cuda.get_device_name(0)
    except Exception:  # noqa: BLE001
        pass
    info["host"] = platform.node()
    return info


def runs(quick: bool) -> list[dict]:
    out = []
    for scene in ("convex", "cow"):
        for preset in ("fast", "default"):
            out.append({"scene": scene, "cameras": "gt", "preset": preset, "overrides": []})
    if quick:
        return out
    for scene in SCENES:
        out.append({"scene": scene, "cameras": "gt", "preset": "quality", "overrides": []})
        if scene != "convex":
            out.append({"scene": scene, "cameras": "sfm", "preset": "default", "overrides": []})
    for name, ov in [("iterations=250", ["--train.iterations", "250"]), ("iterations=3000", ["--train.iterations", "3000"]),
                     ("n_steps=32", ["--train.n-steps", "32", "--train.n-steps-final", "32"]),
                     ("base_res=64", ["--train.field.base-res", "64"]), ("texture=1024", ["--texture.size", "1024"])]:
        out.append({"scene": "cow", "cameras": "gt", "preset": "default", "overrides": ov, "knob": name})
    return out


def one(spec: dict, work: Path) -> dict:
    """Run one configuration end to end in this process; return its metrics."""
    import cv2
    import numpy as np
    import trimesh

    from dvr.cameras import load_cameras
    from dvr.metrics import chamfer_fscore, umeyama
    from pipeline.cli import main
    from pipeline.synth import load_scene_file, write_scene
    from pipeline.texture import render_textured
    from pipeline.workspace import Workspace

    syn = work / "synthetic"
    write_scene(load_scene_file(SCENES[spec["scene"]]), syn)
    ws = work / "ws"
    cfg = ["--config", str(ROOT / "configs" / f"{spec['preset']}.yaml")]
    ov = spec.get("overrides", [])
    if spec["cameras"] == "gt":
        shutil.copytree(syn, ws, ignore=shutil.ignore_patterns("gt"))
        if (ws / "depth").exists():
            shutil.rmtree(ws / "depth")
    else:
        assert main(["cameras", str(ws), "--images", str(syn / "images"), *cfg]) == 0
        assert main(["masks", str(ws), *cfg]) == 0
        assert main(["depth", str(ws), *cfg]) == 0
    assert main(["train", str(ws), *cfg, "--train.no-progress", *_pairs(ov, "--train")]) == 0
    assert main(["mesh", str(ws), *cfg, *_pairs(ov, "--mesh")]) == 0
    assert main(["texture", str(ws), *cfg, *_pairs(ov, "--texture")]) == 0

    def centres(c):
        return c.centers @ c.scale_mat[:3, :3].T + c.scale_mat[:3, 3]

    est, gtc = load_cameras(ws / "cameras.npz"), load_cameras(syn / "cameras.npz")
    s, R, t = umeyama(centres(gtc), centres(est)) if spec["cameras"] == "sfm" else (1.0, np.eye(3), np.zeros(3))
    gt = trimesh.load(syn / "gt" / "mesh.ply")
    gt.apply_transform(np.block([[s * R, t[:, None]], [np.zeros((1, 3)), np.ones((1, 1))]]))
    geo = chamfer_fscore(trimesh.load(ws / "mesh" / "clean.ply"), gt, n=50000)
    tm = trimesh.load(ws / "mesh" / "textured.glb", force="mesh")
    tex = np.asarray(tm.visual.material.baseColorTexture.convert("RGB"), np.float32) / 255.0
    hc = load_cameras(syn / "gt" / "heldout" / "cameras.npz")
    psnr = []
    for i in range(len(hc)):
        photo = cv2.cvtColor(cv2.imread(str(syn / "gt" / "heldout" / "images" / f"{i:06d}.png")), cv2.COLOR_BGR2RGB)
        h, w = photo.shape[:2]
        img, hit = render_textured(tm.vertices, tm.faces, tm.visual.uv, tex, hc.K[i], hc.R[i] @ R.T,
                                   s * R @ centres(hc)[i] + t, w, h)
        m = (cv2.imread(str(syn / "gt" / "heldout" / "masks" / f"{i:06d}.png"), 0) > 127) | hit
        psnr.append(float(-10 * np.log10(max(((img - photo / 255.0)[m] ** 2).mean(), 1e-10))))
    secs = Workspace(ws).seconds()
    return {**spec, "seconds": secs, "total_s": round(sum(secs.values()), 2), "chamfer_rel": geo["chamfer_rel"],
            "fscore": geo["fscore"], "psnr": float(np.mean(psnr))}


def _pairs(ov: list[str], prefix: str) -> list[str]:
    out = []
    i = 0
    while i < len(ov):
        if ov[i].startswith(prefix):
            out += ov[i : i + 2 if i + 1 < len(ov) and not ov[i + 1].startswith("--") else i + 1]
        i += 1
    return out


def pareto(points: list[tuple[float, float]]) -> list[int]:
    """Indices of points not dominated in (time ↓, error ↓)."""
    idx = []
    for i, (t, e) in enumerate(points):
        if not any((t2 <= t and e2 <= e) and (t2 < t or e2 < e) for t2, e2 in points):
            idx.append(i)
    return idx


def plot(results: list[dict], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for scene in sorted({r["scene"] for r in results}):
        rs = sorted([r for r in results if r["scene"] == scene and "error" not in r], key=lambda r: r["total_s"])
        if not rs:
            continue
        pts = [(r["total_s"], 100 * r["chamfer_rel"]) for r in rs]
        line = ax.plot(*zip(*pts), "o-", alpha=0.6, label=scene)[0]
        front = pareto(pts)
        ax.plot([pts[i][0] for i in front], [pts[i][1] for i in front], "*", ms=14, color=line.get_color())
        for r, (x, y) in zip(rs, pts):
            ax.annotate(r.get("knob") or f"{r['preset']}/{r['cameras']}", (x, y), fontsize=7)
    ax.set_xlabel("seconds, all stages (2 CPU cores)")
    ax.set_ylabel("Chamfer, % of GT diagonal")
    ax.set_title("accuracy against time (★ Pareto front)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def table(results: list[dict], mach: dict) -> str:
    lines = [f"Machine: {mach.get('model')} ({mach.get('torch_threads')} threads){', GPU ' + mach['gpu'] if 'gpu' in mach else ''}",
             "", "| scene | cameras | preset / knob | seconds (all stages) | train s | Chamfer % | F@1 % | PSNR dB | peak RSS GB |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        if "error" in r:
            lines.append(f"| {r['scene']} | {r['cameras']} | {r.get('knob') or r['preset']} | failed: {r['error']} |||||| ")
            continue
        lines.append(f"| {r['scene']} | {r['cameras']} | {r.get('knob') or r['preset']} | {r['total_s']:.0f} | "
                     f"{r['seconds'].get('train', 0):.0f} | {100 * r['chamfer_rel']:.2f} | {r['fscore']:.3f} | "
                     f"{r['psnr']:.1f} | {r['peak_rss_gb']:.2f} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--readme", action="store_true", help="write the table into README.md between BENCH markers")
    ap.add_argument("--one", type=str, default=None, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.one:  # child process: one run
        spec = json.loads(a.one)
        with tempfile.TemporaryDirectory() as td:
            res = one(spec, Path(td))
        res["peak_rss_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
        print("RESULT " + json.dumps(res))
        return
    mach = machine()
    results = []
    for spec in runs(a.quick):
        print(f"bench: {spec}", flush=True)
        p = subprocess.run([sys.executable, __file__, "--one", json.dumps(spec)], capture_output=True, text=True,
                           cwd=ROOT, env={**os.environ, "PYTHONUNBUFFERED": "1"})
        line = next((x for x in p.stdout.splitlines() if x.startswith("RESULT ")), None)
        if line is None:
            results.append({**spec, "error": (p.stderr.strip().splitlines() or ["?"])[-1][:200]})
        else:
            results.append(json.loads(line[7:]))
        print("   ", {k: results[-1].get(k) for k in ("total_s", "chamfer_rel", "fscore", "psnr", "error")}, flush=True)
    out = ROOT / "bench" / "results"
    out.mkdir(parents=True, exist_ok=True)
    stem = f"{datetime.date.today().isoformat()}-{platform.node() or 'machine'}{'-quick' if a.quick else ''}"
    (out / f"{stem}.json").write_text(json.dumps({"machine": mach, "results": results}, indent=1))
    plot(results, out / f"{stem}.png")
    md = table(results, mach)
    print(md)
    if a.readme:
        readme = ROOT / "README.md"
        txt = readme.read_text()
        start, end = "<!-- BENCH START -->", "<!-- BENCH END -->"
        if start in txt and end in txt:
            pre, rest = txt.split(start, 1)
            _, post = rest.split(end, 1)
            readme.write_text(f"{pre}{start}\n{md}\n\n![accuracy against time](bench/results/{stem}.png)\n{end}{post}")


if __name__ == "__main__":
    main()
