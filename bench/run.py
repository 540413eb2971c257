"""What accuracy costs in time: presets and knob sweeps, end to end, on synthetic scenes with ground truth and
on the real DTU scan24 photos.

    python bench/run.py --quick      # ≤ 10 min on 2 cores: fast + default on the cow, GT cameras
    python bench/run.py --readme     # the full set (≤ 60 min on 2 cores), table + plot into README.md

Every run is its own process (peak memory = its max RSS) and goes through the same CLI a user runs. Per run:
seconds per stage (cameras/masks/depth only with SfM), Chamfer and F-score@1 % of the GT bounding-box diagonal
(after a Sim(3) alignment of the camera centres when cameras come from SfM), PSNR of the textured mesh at
held-out views (pixels of the object in the photo or in the rendering), peak RSS. Scenes are rendered once
and cached in bench/runs/ (ignored by git).

DTU scan24 (49 real photos, no masks): our SfM against the given cameras (centre error after Sim(3), as a
fraction of the orbit radius; rotation error), and held-out PSNR against time: every 7th photo is held out of
masks-free training (cameras and masks are estimated from all photos, as a user would), the textured mesh is
rendered at the held-out cameras and compared over the photo pixels the mesh or the automatic mask covers
(also reported: over the mesh's pixels alone, and the fraction of the mask the mesh covers).

Writes bench/results/<date>-<machine>[-quick].json and .png (accuracy against time, Pareto front marked).
"""

from __future__ import annotations

import argparse
import datetime
import hashlib
import json
import os
import platform
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

RUNS = ROOT / "bench" / "runs"
DTU = ROOT.parent / "shared" / "data" / "dtu_scan24"
SCENES = {
    "convex": ROOT / "configs" / "scenes" / "sphere_checker.yaml",
    "cow": ROOT / "configs" / "scenes" / "cow_backdrop.yaml",
    "thin": ROOT / "configs" / "scenes" / "thin_plate.yaml",
}
# knob sweep around the default preset (cow, GT cameras): name → (CLI overrides, scene overrides)
KNOBS = {
    "iterations=750": (["--train.iterations", "750"], {}),
    "iterations=3000": (["--train.iterations", "3000"], {}),
    "grid=64 (no coarse-to-fine)": (["--train.field.base-res", "64", "--train.coarse-res", "0"], {}),
    "grid=128": (["--train.field.base-res", "128"], {}),
    "n_steps=32→48": (["--train.n-steps", "32", "--train.n-steps-final", "48"], {}),
    "images 200x150": ([], {"cameras": {"width": 200, "height": 150}}),
    "texture=1024": (["--texture.size", "1024"], {}),
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


def plan(quick: bool) -> list[dict]:
    if quick:
        return [{"scene": "cow", "cameras": "gt", "preset": p} for p in ("fast", "default")]
    out = [{"scene": s, "cameras": "gt", "preset": p} for s in SCENES for p in ("fast", "default", "quality")]
    out += [{"scene": s, "cameras": "sfm", "preset": "default"} for s in SCENES]
    out += [{"scene": "cow", "cameras": "gt", "preset": "default", "knob": k} for k in KNOBS]
    out += [{"scene": "dtu", "cameras": "sfm", "preset": p} for p in ("fast", "default")]
    return out


# ----------------------------------------------------------------------------- one run (child process)
def _scene(name: str, over: dict) -> Path:
    """Render (once) the synthetic scene with overrides; returns its folder."""
    import yaml

    from pipeline.synth import scene_from_dict, write_scene

    tag = name + ("-" + "-".join(f"{k}{sorted(v.items())}" for k, v in over.items()) if over else "")
    tag = "".join(c if c.isalnum() or c in "-_" else "_" for c in tag)
    out = RUNS / "scenes" / tag
    if not (out / "gt" / "scene.json").exists():
        d = yaml.safe_load(SCENES[name].read_text())
        for k, v in over.items():
            d[k] = {**d.get(k, {}), **v}
        shutil.rmtree(out, ignore_errors=True)
        write_scene(scene_from_dict(d, SCENES[name].parent), out)
    return out


def _main(args: list[str]) -> None:
    from pipeline.cli import main

    rc = main(args)
    if rc != 0:
        raise RuntimeError(f"stage failed: {' '.join(args[:2])}")


def _pairs(ov: list[str], prefix: str) -> list[str]:
    out, i = [], 0
    while i < len(ov):
        if ov[i].startswith(prefix):
            out += ov[i : i + 2]
        i += 2
    return out


def _textured(ws: Path):
    import numpy as np
    import trimesh

    tm = trimesh.load(ws / "mesh" / "textured.glb", force="mesh")
    tex = np.asarray(tm.visual.material.baseColorTexture.convert("RGB"), np.float32) / 255.0
    return tm, tex


def run_synthetic(spec: dict, work: Path) -> dict:
    import cv2
    import numpy as np
    import trimesh

    from dvr.cameras import load_cameras
    from dvr.metrics import chamfer_fscore, masked_psnr, pose_errors, umeyama
    from pipeline.texture import render_textured
    from pipeline.workspace import Workspace

    cli, over = KNOBS.get(spec.get("knob"), ([], {}))
    syn = _scene(spec["scene"], over)
    ws = work / "ws"
    cfg = ["--config", str(ROOT / "configs" / f"{spec['preset']}.yaml")]
    extra: dict = {}
    if spec["cameras"] == "gt":
        shutil.copytree(syn, ws, ignore=shutil.ignore_patterns("gt", "depth"))
    else:
        _main(["cameras", str(ws), "--images", str(syn / "images"), *cfg])
        _main(["masks", str(ws), *cfg])
        _main(["depth", str(ws), *cfg])
    _main(["train", str(ws), *cfg, "--train.no-progress", *_pairs(cli, "--train")])
    _main(["mesh", str(ws), *cfg, *_pairs(cli, "--mesh")])
    _main(["texture", str(ws), *cfg, *_pairs(cli, "--texture")])

    def centres(c):
        return c.centers @ c.scale_mat[:3, :3].T + c.scale_mat[:3, 3]

    est, gtc = load_cameras(ws / "cameras.npz"), load_cameras(syn / "cameras.npz")
    s, R, t = 1.0, np.eye(3), np.zeros(3)
    if spec["cameras"] == "sfm":
        from dvr.data import list_images

        idx = [int(p.stem) for p in list_images(ws / "images")]  # the registered views (GT view i = i.png)
        s, R, t = umeyama(centres(gtc)[idx], centres(est))  # GT world → SfM frame
        extra["pose"] = pose_errors(centres(est), est.R, centres(gtc)[idx], gtc.R[idx])
        extra["registered"] = f"{len(idx)}/{len(gtc)}"
    gt = trimesh.load(syn / "gt" / "mesh.ply")
    gt.apply_transform(np.block([[s * R, t[:, None]], [np.zeros((1, 3)), np.ones((1, 1))]]))
    geo = chamfer_fscore(trimesh.load(ws / "mesh" / "clean.ply"), gt, n=50000)
    tm, tex = _textured(ws)
    hc = load_cameras(syn / "gt" / "heldout" / "cameras.npz")
    # SfM runs: the held-out photos' GT poses with the intrinsics SfM estimated for their camera (orbit captures
    # leave focal length vs scale nearly free; tests/test_e2e_photos.py); the GT focal's PSNR is kept too
    psnr, psnr_gt_focal = [], []
    for i in range(len(hc)):
        photo = cv2.cvtColor(cv2.imread(str(syn / "gt" / "heldout" / "images" / f"{i:06d}.png")), cv2.COLOR_BGR2RGB)
        h, w = photo.shape[:2]
        gm = cv2.imread(str(syn / "gt" / "heldout" / "masks" / f"{i:06d}.png"), 0) > 127
        Ks = [(est.K.mean(0), psnr), (hc.K[i], psnr_gt_focal)] if spec["cameras"] == "sfm" else [(hc.K[i], psnr)]
        for K, out in Ks:
            img, hit = render_textured(tm.vertices, tm.faces, tm.visual.uv, tex, K, hc.R[i] @ R.T,
                                       s * R @ centres(hc)[i] + t, w, h)
            out.append(masked_psnr(img, photo / 255.0, gm | hit))
    if psnr_gt_focal:
        extra["psnr_gt_focal"] = float(np.mean(psnr_gt_focal))
    secs = Workspace(ws).seconds()
    return {"seconds": secs, "chamfer_rel": geo["chamfer_rel"], "fscore": geo["fscore"],
            "psnr": float(np.mean(psnr)), **extra}


def _dtu_shared() -> tuple[Path, dict]:
    """Our SfM and automatic masks on all 49 DTU photos (cached): workspace and stage seconds."""
    from pipeline.workspace import Workspace

    ws = RUNS / "dtu_all"
    if not (ws / ".stages" / "masks.json").exists():
        shutil.rmtree(ws, ignore_errors=True)
        _main(["cameras", str(ws), "--images", str(DTU / "images")])
        _main(["masks", str(ws)])
        _main(["depth", str(ws)])
    return ws, Workspace(ws).seconds()


def run_dtu(spec: dict, work: Path) -> dict:
    import cv2
    import numpy as np

    from bench.dtu_reference import dtu_reference
    from dvr.cameras import load_cameras
    from dvr.data import list_images
    from dvr.metrics import masked_psnr, pose_errors
    from pipeline.texture import render_textured
    from pipeline.workspace import Workspace

    full, shared_secs = _dtu_shared()
    cams = load_cameras(full / "cameras.npz")
    names = [p.stem for p in list_images(full / "images")]
    _, Rg, Cg, _ = dtu_reference(DTU)
    idx = [int(n) for n in names]  # registered photos (all 49 when SfM registers them all)
    S = cams.scale_mat
    c_sfm = cams.centers @ S[:3, :3].T + S[:3, 3]
    pose = pose_errors(c_sfm, cams.R, Cg[idx], Rg[idx])
    held = [i for i in range(len(names)) if i % 7 == 0]
    train = [i for i in range(len(names)) if i % 7 != 0]
    ws = work / "ws"
    for sub in ("images", "masks", "depth"):
        (ws / sub).mkdir(parents=True)
        for i in train:
            for f in (full / sub).glob(f"{names[i]}.*"):
                shutil.copy2(f, ws / sub / f.name)
    z = np.load(full / "cameras.npz")  # the training views' cameras, renumbered (SfM frame, same scale_mat)
    np.savez(ws / "cameras.npz", scale_mat=z["scale_mat"],
             **{f"{k}_{j}": z[f"{k}_{i}"] for j, i in enumerate(train) for k in ("world_mat", "scale_mat", "camera_mat")})
    cfg = ["--config", str(ROOT / "configs" / f"{spec['preset']}.yaml")]
    _main(["train", str(ws), *cfg, "--train.no-progress"])
    _main(["mesh", str(ws), *cfg])
    _main(["texture", str(ws), *cfg])
    tm, tex = _textured(ws)
    psnr, psnr_hit, cover = [], [], []
    paths = list_images(full / "images")
    for i in held:
        photo = cv2.cvtColor(cv2.imread(str(paths[i])), cv2.COLOR_BGR2RGB) / 255.0
        h, w = photo.shape[:2]
        img, hit = render_textured(tm.vertices, tm.faces, tm.visual.uv, tex, cams.K[i], cams.R[i], c_sfm[i], w, h)
        mask = cv2.imread(str(full / "masks" / f"{names[i]}.png"), 0) > 127
        psnr.append(masked_psnr(img, photo, mask | hit))
        psnr_hit.append(masked_psnr(img, photo, hit))
        cover.append(float((mask & hit).sum() / max(1, mask.sum())))
    secs = {**shared_secs, **{k: v for k, v in Workspace(ws).seconds().items() if k not in shared_secs}}
    return {"seconds": secs, "chamfer_rel": None, "fscore": None, "psnr": float(np.mean(psnr)), "pose": pose,
            "psnr_on_model": float(np.mean(psnr_hit)), "mask_covered": float(np.mean(cover)),
            "views": {"train": len(train), "heldout": len(held), "registered": len(names)}}


def one(spec: dict, work: Path) -> dict:
    r = run_dtu(spec, work) if spec["scene"] == "dtu" else run_synthetic(spec, work)
    r["total_s"] = round(sum(r["seconds"].values()), 2)
    return {**spec, **r}


# ----------------------------------------------------------------------------- report
def pareto(points: list[tuple[float, ...]]) -> list[int]:
    """Indices of the points no other point dominates (every coordinate ≤, one <; all to be minimised)."""
    return [i for i, p in enumerate(points)
            if not any(all(a <= b for a, b in zip(q, p)) and any(a < b for a, b in zip(q, p)) for q in points)]


def _objectives(r: dict) -> tuple[float, ...]:
    """(seconds, Chamfer, −PSNR): accuracy is both the geometry and the appearance a user sees."""
    return (r["total_s"], r["chamfer_rel"] if r["chamfer_rel"] is not None else 0.0, -r["psnr"])


def label(r: dict) -> str:
    return r.get("knob") or r["preset"]


def plot(results: list[dict], out: Path, mach: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = [r for r in results if "error" not in r]
    fig, ax = plt.subplots(1, 2, figsize=(12, 4.8))
    colors = {"convex": "tab:blue", "cow": "tab:orange", "thin": "tab:green", "dtu": "tab:red"}
    for scene in colors:
        for cams, mk in (("gt", "o"), ("sfm", "s")):
            rs = sorted([r for r in ok if r["scene"] == scene and r["cameras"] == cams], key=lambda r: r["total_s"])
            if not rs:
                continue
            lab = f"{scene} ({'GT cameras + masks' if cams == 'gt' else 'COLMAP + auto masks'})"
            for k, (key, scale, name) in enumerate((("chamfer_rel", 100, "Chamfer, % of GT diagonal ↓"),
                                                      ("psnr", 1, "held-out PSNR, dB ↑"))):
                pts = [(r["total_s"], r[key] * scale) for r in rs if r[key] is not None]
                if not pts:
                    continue
                a = ax[k]
                a.plot(*zip(*pts), mk + ("-" if cams == "gt" and scene != "dtu" else ":"), color=colors[scene],
                       alpha=0.7, label=lab)
                front = pareto([_objectives(r) for r in rs])
                for i in front:
                    if rs[i][key] is not None:
                        a.plot(rs[i]["total_s"], rs[i][key] * scale, "*", ms=15, color=colors[scene],
                               markeredgecolor="k")
                for r, (x, y) in zip([r for r in rs if r[key] is not None], pts):
                    a.annotate(label(r), (x, y), fontsize=6, xytext=(3, 3), textcoords="offset points")
                a.set_xlabel("seconds, all stages")
                a.set_ylabel(name)
                a.set_xscale("log")
                if key == "chamfer_rel":
                    a.set_yscale("log")  # failures through SfM reach tens of percent
    ax[0].legend(fontsize=7)
    fig.suptitle(f"accuracy against time (★ Pareto front of time, Chamfer and PSNR, per scene and cameras) — "
                 f"{mach.get('model')}, "
                 f"{mach.get('torch_threads')} threads{', ' + mach['gpu'] if 'gpu' in mach else ''}", fontsize=9)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def _fmt(v, f):
    return "–" if v is None else f.format(v)


def _gt_focal(r: dict) -> str:
    """SfM runs: the held-out PSNR with the GT focal length instead of SfM's, in brackets."""
    return f" ({r['psnr_gt_focal']:.1f} at GT focal)" if r.get("psnr_gt_focal") is not None else ""


def table(results: list[dict], mach: dict) -> str:
    lines = [f"Machine: {mach.get('model')}, {mach.get('cores')} cores, {mach.get('torch_threads')} torch threads"
             f"{', GPU ' + mach['gpu'] if 'gpu' in mach else ', no GPU'}.", "",
             "| scene | cameras | preset / knob | total s | cameras+masks s | train s | mesh+texture s | Chamfer % "
             "| F@1 % | held-out PSNR dB | pose err (centre % / rot °) | peak RSS GB |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        if "error" in r:
            lines.append(f"| {r['scene']} | {r['cameras']} | {label(r)} | failed: {r['error']} |||||||||")
            continue
        s = r["seconds"]
        pose = r.get("pose")
        pe = f"{100 * pose['center_err_rel_max']:.2f} / {pose['rot_err_deg_mean']:.2f}" if pose else "–"
        reg = r.get("registered") or (f"{r['views']['registered']}/49" if "views" in r else None)
        pe += f" ({reg} registered)" if reg and pose else ""
        ch = None if r["chamfer_rel"] is None else 100 * r["chamfer_rel"]
        lines.append(
            f"| {r['scene']} | {'GT' if r['cameras'] == 'gt' else 'COLMAP'} | {label(r)} | {r['total_s']:.0f} | "
            f"{s.get('cameras', 0) + s.get('masks', 0) + s.get('depth', 0):.0f} | {s.get('train', 0):.0f} | "
            f"{s.get('mesh', 0) + s.get('texture', 0):.0f} | {_fmt(ch, '{:.2f}')} | {_fmt(r['fscore'], '{:.3f}')} | "
            f"{r['psnr']:.1f}{_gt_focal(r)} | {pe} | {r['peak_rss_gb']:.2f} |")
    return "\n".join(lines)


def findings(results: list[dict]) -> list[str]:
    """Which knob buys the most accuracy per second, and whether the default preset is on the Pareto front."""
    ok = [r for r in results if "error" not in r]
    out = []
    base = next((r for r in ok if r["scene"] == "cow" and r["cameras"] == "gt" and r["preset"] == "default"
                 and not r.get("knob")), None)
    if base:
        rates = []
        for r in ok:
            if r["scene"] == "cow" and r["cameras"] == "gt" and (r.get("knob") or r["preset"] != "default"):
                dt = r["total_s"] - base["total_s"]
                dc = 100 * (base["chamfer_rel"] - r["chamfer_rel"])  # Chamfer points gained
                dp = r["psnr"] - base["psnr"]
                rates.append((label(r), dt, dc, dp))
        for name, dt, dc, dp in sorted(rates, key=lambda x: x[1]):
            out.append(f"- {name}: {dt:+.0f} s → Chamfer {-dc:+.3f} points, PSNR {dp:+.2f} dB")
        dearer = [x for x in rates if x[1] > 5 and x[3] > 0]
        if dearer:
            name, dt, dc, dp = max(dearer, key=lambda x: x[3] / x[1])
            out.append(f"- most accuracy per extra second: **{name}** ({60 * dp / dt:+.2f} dB PSNR per minute; "
                       f"Chamfer {-dc:+.3f} points)")
        cheaper = [x for x in rates if x[1] < -5]
        if cheaper:
            name, dt, dc, dp = max(cheaper, key=lambda x: x[3] / -x[1])  # least PSNR lost per second saved
            out.append(f"- cheapest saving: **{name}** ({-dt:.0f} s less for {dp:+.2f} dB PSNR, Chamfer {-dc:+.3f} "
                       "points)")
    for scene in sorted({r["scene"] for r in ok if r["cameras"] == "gt"}):
        rs = [r for r in ok if r["scene"] == scene and r["cameras"] == "gt"]
        front = [rs[i] for i in pareto([_objectives(r) for r in rs])]
        d = [r for r in front if r["preset"] == "default" and not r.get("knob")]
        out.append(f"- {scene}: default preset {'on' if d else 'NOT on'} the Pareto front of (time, Chamfer, PSNR) "
                   f"(front: {', '.join(label(r) for r in sorted(front, key=lambda r: r['total_s']))})")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="fast + default on the cow with GT cameras (≤ 10 min)")
    ap.add_argument("--readme", action="store_true", help="write the table and plot into README.md")
    ap.add_argument("--only", type=str, default=None, help="run only specs whose scene matches (debugging)")
    ap.add_argument("--from", dest="from_json", type=Path, default=None,
                    help="redo the table, plot and README section from a results JSON (no runs)")
    ap.add_argument("--resume", action="store_true",
                    help="reuse runs already finished by an interrupted bench (bench/runs/done/)")
    ap.add_argument("--one", type=str, default=None, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.from_json:
        rec = json.loads(a.from_json.read_text())
        report(rec["results"], rec["machine"], rec["bench_seconds"], a.from_json.with_suffix(""), a.readme)
        return
    if a.one:  # child process: one run
        spec = json.loads(a.one)
        work = RUNS / "work" / f"{os.getpid()}"
        shutil.rmtree(work, ignore_errors=True)
        work.mkdir(parents=True)
        try:
            res = one(spec, work)
        finally:
            shutil.rmtree(work, ignore_errors=True)
        res["peak_rss_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
        print("RESULT " + json.dumps(res))
        return
    mach = machine()
    results = []
    t0 = time.perf_counter()
    specs = [s for s in plan(a.quick) if a.only is None or s["scene"] == a.only]
    done = RUNS / "done"
    if not a.resume:
        shutil.rmtree(done, ignore_errors=True)
    done.mkdir(parents=True, exist_ok=True)
    for k, spec in enumerate(specs):
        print(f"[{k + 1}/{len(specs)}, {time.perf_counter() - t0:.0f} s] {spec}", flush=True)
        key = done / (hashlib.sha1(json.dumps(spec, sort_keys=True).encode()).hexdigest()[:16] + ".json")
        if key.exists():
            results.append(json.loads(key.read_text()))
            print("    (finished earlier)", {k: results[-1].get(k) for k in ("total_s", "chamfer_rel", "psnr")})
            continue
        t1 = time.perf_counter()
        p = subprocess.run([sys.executable, __file__, "--one", json.dumps(spec)], capture_output=True, text=True,
                           cwd=ROOT, env={**os.environ, "PYTHONUNBUFFERED": "1"})
        line = next((x for x in p.stdout.splitlines() if x.startswith("RESULT ")), None)
        if line is None:
            err = [x for x in p.stderr.strip().splitlines() if not x.startswith(("I20", "W20"))] or ["?"]
            results.append({**spec, "error": err[-1][:200]})
        else:
            results.append(json.loads(line[7:]))
        results[-1]["wall_s"] = round(time.perf_counter() - t1, 1)
        if results[-1].get("error") is None:
            key.write_text(json.dumps(results[-1]))
        print("   ", {k: results[-1].get(k) for k in ("total_s", "chamfer_rel", "fscore", "psnr", "error")},
              flush=True)
    out = ROOT / "bench" / "results"
    out.mkdir(parents=True, exist_ok=True)
    stem = out / f"{datetime.date.today().isoformat()}-{platform.node() or 'machine'}{'-quick' if a.quick else ''}"
    total = sum(r.get("wall_s", 0.0) for r in results)  # the runs' own time, also when resumed
    stem.with_suffix(".json").write_text(json.dumps({"machine": mach, "bench_seconds": round(total, 1),
                                                     "results": results}, indent=1))
    report(results, mach, total, stem, a.readme)


def report(results: list[dict], mach: dict, total: float, stem: Path, readme: bool) -> None:
    plot(results, stem.with_suffix(".png"), mach)
    md = table(results, mach)
    notes = findings(results)
    print(md)
    print("\n".join(notes))
    print(f"bench: {len(results)} runs in {total / 60:.1f} min → {stem}.json, .png")
    if readme:
        path = ROOT / "README.md"
        txt = path.read_text()
        start, end = "<!-- BENCH START -->", "<!-- BENCH END -->"
        if start in txt and end in txt:
            pre, rest = txt.split(start, 1)
            _, post = rest.split(end, 1)
            body = (f"{md}\n\nWhole benchmark: {total / 60:.0f} min (`make bench`). Each knob against the default "
                    f"preset (cow, GT cameras), and the Pareto fronts:\n\n" + "\n".join(notes) +
                    f"\n\n![accuracy against time](bench/results/{stem.name}.png)\n")
            path.write_text(f"{pre}{start}\n{body}{end}{post}")

if __name__ == "__main__":
    main()
