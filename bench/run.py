"""What accuracy costs in time: presets and knob sweeps, end to end, on synthetic scenes with ground truth and
on the real DTU scan24 photos; and the cameras stage on a matrix of capture conditions.

    python bench/run.py --quick      # ≤ 10 min on 2 cores: fast + default on the cow on its floor, GT cameras
    python bench/run.py --docs       # the full set (≈ 3 h on 2 cores), tables + plot into docs/benchmarks.md
    python bench/run.py --photos --update bench/results/<full>.json --docs   # only the rows that run SfM

The main synthetic scenes stand on a surface, as real objects do: the textured cow on a wooden floor, a weakly
textured jar on a blocky floor, a flat book on a stone-like table top (and, default preset only, a plain stool
coloured like its floor and an open mug on a table); the cow floating in front of a backdrop is kept as the one
floating scene. Each runs with the GT cameras and masks (four presets) and photos only (COLMAP + automatic masks,
default preset; see bench/evaluate.py for the held-out protocol); the cow and DTU also with the preview preset. A
knob sweep around the default preset runs on the cow with GT cameras; DTU scan24 (49 real photos) runs photos only.

Every run is its own process (peak memory = its max RSS) and calls the stage API the CLI calls. Per run:
seconds per stage, mask IoU (photos only), Chamfer and F-score@1 % of the GT bounding-box diagonal, held-out PSNR,
pose error, peak RSS. Scenes are rendered once and cached in bench/runs/ (ignored by git).

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

from bench.evaluate import (  # noqa: E402
    FOLDERS,
    REAL,
    RUNS,
    fresh_folder,
    run_cameras,
    run_dtu,
    run_real,
    run_synthetic,
)
from bench.report import DEFAULTS_VERSION, is_stale, write  # noqa: E402

FLOOR_SCENES = ("cow", "jar", "book")
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
# ablation (cow on the floor, GT cameras, default preset): the same scene photographed with per-view exposure and
# white balance and with specular highlights, trained without and with the per-view appearance
EXPOSURE = {"kind": "exposure", "amount": 0.25, "white_balance": 0.08}
LOOKS = [EXPOSURE, {"kind": "specular", "amount": 0.25, "shininess": 30.0}]
ABLATIONS = {
    "exposure+specular": ([], {"effects_add": LOOKS}),
    "exposure+specular, appearance": (["--train.appearance", "on"], {"effects_add": LOOKS}),
    "exposure+specular, appearance + view shading": (["--train.appearance", "on", "--train.view-shading"],
                                                     {"effects_add": LOOKS}),
    # a reference on those held-out photos: the model of the plain cow (no exposure change, no highlights) measured
    # against them (same cameras)
    "exposure+specular held-out, effect-free training": ([], {"heldout_from": {"effects_add": LOOKS}}),
    "exposure": ([], {"effects_add": [EXPOSURE]}),  # what the per-view appearance is for, without highlights
    "exposure, appearance": (["--train.appearance", "on"], {"effects_add": [EXPOSURE]}),
    "appearance": (["--train.appearance", "on"], {}),  # the plain cow (nothing to fix) and DTU
    # the default is "auto": on where the cameras stage measures the photos' exposure differing (DTU, the exposure cow
    # from photos), off without SfM points (every GT-camera row)
    "appearance off": (["--train.appearance", "off"], {}),
    "exposure, appearance off": (["--train.appearance", "off"], {"effects_add": [EXPOSURE]}),
    "exposure+specular, appearance off": (["--train.appearance", "off"], {"effects_add": LOOKS}),
    # from photos, no exposure handling at all: the masks' stereo on the photos as taken, no per-view appearance
    "exposure+specular, no exposure handling": (["--masks.no-even-exposure", "--train.appearance", "off"],
                                                {"effects_add": LOOKS}),
    "view shading": (["--train.view-shading"], {}),
    "appearance + view shading": (["--train.appearance", "on", "--train.view-shading"], {}),
    "exposure+specular, view shading": (["--train.view-shading"], {"effects_add": LOOKS}),
    "view selection": (["--texture.view-selection"], {}),  # the bake: one view per face, Potts smoothness
    "final adjustment": (["--cameras.final-passes", "3"], {}),  # SfM: final robust bundle adjustment passes
    "photo hull": (["--train.photo-hull"], {}),  # start from the photo hull (a cup's inside)
    "photo hull, contrast 2": (["--train.photo-hull", "--train.photo-contrast", "2"], {}),
    # a capture that looks into the cup: the top ring at 80° instead of 55°
    "views to 80°": ([], {"cameras": {"elevation": [15, 80]}}),
    "views to 80°, photo hull": (["--train.photo-hull"], {"cameras": {"elevation": [15, 80]}}),
    # the photos saved as a phone saves them (JPEG, quality 92, 4:2:0 chroma) instead of the lossless renders
    "photos as JPEG": ([], {"photos_jpeg": 92}),
    # as a phone's: 3 × the working size (1200 × 900, each stage pixel the mean of 3 × 3 photo pixels), the SfM on
    # them as they are, the other stages on them shrunk; lossless, and as JPEGs
    "photos 3× larger": ([], {"cameras": {"photo_scale": 3}}),
    "photos 3× larger as JPEG": ([], {"cameras": {"photo_scale": 3}, "photos_jpeg": 92}),
    # close-up photos: the cameras at 1.6 instead of 2.6 from the cow, which leaves most frames; the
    # working sphere's space above and around it is framed by only a few photos (train.framing auto: on here)
    "close-up photos": ([], {"cameras": {"radius": 1.6}}),
    "close-up photos, framing off": (["--train.framing", "off"], {"cameras": {"radius": 1.6}}),
}


def phone_folder(syn: Path, out: Path) -> Path:
    """The scene's photos as a phone writes them: JPEG with EXIF orientation 1, 6, 3, 8 in turn (the pixels stored
    rotated accordingly), every fourth photo at twice the size, one file name with spaces."""
    from synth.phone import write_phone_folder

    return write_phone_folder(syn / "images", out.parent / "my phone photos")


# capture condition of the cameras table: name → (scene, scene overrides, photo-folder maker or None)
CONDITIONS = {
    "object on a surface, 400×300": ("cow", {}, None),
    "object on a wooden parquet (regular planks), 400×300": (
        "cow", {"effects": [{"kind": "ground", "pattern": "wood", "scale": 4.0}]}, None),
    "object on a surface, 1600×1200": ("cow", {"cameras": {"width": 1600, "height": 1200}}, None),
    "weakly textured object on a surface, 400×300": ("jar", {}, None),
    "weakly textured object, 24 views of 320×240": (
        "jar", {"cameras": {"n_views": 24, "rings": 2, "width": 320, "height": 240, "heldout": 0}}, None),
    "only 16 views": ("cow", {"cameras": {"n_views": 16, "rings": 2, "heldout": 0}}, None),
    "phone folder: EXIF 1/3/6/8, mixed sizes, JPEG": ("cow", {}, phone_folder),
    "checkered sphere (symmetric, repetitive)": ("sphere", {}, None),
    "torus on a printed ChArUco board (metric scale)": ("torus_board", {}, None),
    "checkered sphere on a printed ChArUco board (poses from the board)": ("sphere_board", {}, None),
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
    out = [{"scene": s, "cameras": "gt", "preset": p} for s in FLOOR_SCENES for p in ("fast", "default", "quality")]
    out += [{"scene": s, "cameras": "gt", "preset": "balanced"} for s in FLOOR_SCENES]
    out += [{"scene": s, "cameras": "gt", "preset": "default"} for s in ("cow_float", "stool", "mug")]
    out += [{"scene": "cow", "cameras": c, "preset": "preview"} for c in ("gt", "sfm")]
    from_photos = (*FLOOR_SCENES, "cow_float", "sphere_board", "jar_alike", "stool", "mug")
    out += [{"scene": s, "cameras": "sfm", "preset": "default"} for s in from_photos]
    out += [{"scene": "cow", "cameras": "gt", "preset": "default", "knob": k} for k in KNOBS]
    out += [{"scene": "cow", "cameras": "gt", "preset": "default", "knob": k, "ablation": True}
            for k in ("exposure+specular", "exposure+specular, appearance", "appearance", "view selection")]
    # the appearance ablation where the geometry is better (silhouette pixels hold most of the default's error)
    out += [{"scene": "cow", "cameras": "gt", "preset": "balanced", "knob": k, "ablation": True}
            for k in ("exposure+specular", "exposure+specular, appearance",
                      "exposure+specular held-out, effect-free training", "exposure", "exposure, appearance",
                      "exposure+specular, view shading", "exposure+specular, appearance + view shading",
                      "view shading")]
    out += [{"scene": "dtu", "cameras": "sfm", "preset": p}
            for p in ("preview", "fast", "default", "balanced", "quality")]
    out += [{"scene": "cow", "cameras": "sfm", "preset": "balanced"}]
    out += [{"scene": "cow", "cameras": "sfm", "preset": "default", "knob": "view selection", "ablation": True}]
    out += [{"scene": "dtu", "cameras": "sfm", "preset": "default", "knob": k, "ablation": True}
            for k in ("appearance off", "appearance", "view selection", "appearance + view shading")]
    # the exposure cow from photos: the default (masks on evened photos, appearance auto: on), with the
    # appearance off, and the glossy cow also with neither
    out += [{"scene": "cow", "cameras": "sfm", "preset": "default", "knob": k, "ablation": True}
            for k in ("exposure", "exposure, appearance off", "exposure+specular", "exposure+specular, appearance off",
                      "exposure+specular, no exposure handling")]
    out += [{"scene": s, "cameras": "sfm", "preset": "default", "knob": "final adjustment", "ablation": True}
            for s in (*FLOOR_SCENES, "cow_float", "dtu")]
    out += [{"scene": "cow", "cameras": "sfm", "preset": "default", "knob": k, "ablation": True}
            for k in ("photos as JPEG", "photos 3× larger", "photos 3× larger as JPEG")]
    out += [{"scene": "cow", "cameras": "sfm", "preset": "balanced", "knob": "final adjustment", "ablation": True}]
    out += [{"scene": "cow", "cameras": c, "preset": "default", "knob": k, "ablation": True}
            for c in ("gt", "sfm") for k in ("close-up photos", "close-up photos, framing off")]
    out += [{"scene": "mug", "cameras": c, "preset": "default", "knob": "photo hull", "ablation": True}
            for c in ("gt", "sfm")]
    # the photo hull beyond the mug: two captures from photos whose automatic masks miss bits of the object (read at
    # the hull's surface alone, the views' colours disagree there), and DTU, where it carves a slab under a roof
    out += [{"scene": s, "cameras": "sfm", "preset": "default", "knob": "photo hull", "ablation": True}
            for s in ("cow_float", "jar_alike", "dtu")]
    out += [{"kind": "cameras", "condition": c, "scene": CONDITIONS[c][0]} for c in CONDITIONS]
    out += [{"scene": s, "cameras": "sfm", "preset": "default"} for s in (*REAL, *FOLDERS)]
    return out


def one(spec: dict, work: Path) -> dict:
    if spec.get("kind") == "cameras":
        r = run_cameras(spec, work, CONDITIONS)
    elif spec["scene"] == "dtu":
        r = run_dtu(spec, work, ABLATIONS)
    elif spec["scene"] in REAL or spec["scene"] in FOLDERS:
        r = run_real(spec, work)
    else:
        r = run_synthetic(spec, work, {**KNOBS, **ABLATIONS})
    r["machine"] = machine()  # rows merged into an earlier run's JSON say where they ran
    r["total_s"] = round(sum(r["seconds"].values()), 2)
    if spec.get("kind") != "cameras":
        r["defaults"] = DEFAULTS_VERSION
    return {**spec, **r}


def run_child(spec: dict) -> None:
    """Child process: one run, its result printed as one RESULT line."""
    work = fresh_folder(RUNS / "work" / f"{os.getpid()}")
    try:
        res = one(spec, work)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    res["peak_rss_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
    print("RESULT " + json.dumps(res))


def stale_dtu_stages(specs: list[dict]) -> list[Path]:
    """DTU's cameras, masks and depth cached by earlier runs (``bench/runs/dtu_all*``, which
    :func:`bench.evaluate.run_dtu` makes only when missing): a bench that runs DTU rows afresh makes them again, so
    that a change to those stages reaches DTU's rows too."""
    if not any(s.get("scene") == "dtu" for s in specs):
        return []
    return sorted(p for p in RUNS.glob("dtu_all*") if p.is_dir())


def run_all(specs: list[dict], resume: bool) -> list[dict]:
    results = []
    t0 = time.perf_counter()
    done = RUNS / "done"
    if not resume:
        shutil.rmtree(done, ignore_errors=True)
        for stale in stale_dtu_stages(specs):
            shutil.rmtree(stale)
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
            err = [x for x in p.stderr.strip().splitlines() if not x.startswith(("I20", "W20", "E20"))] or ["?"]
            results.append({**spec, "error": err[-1][:200]})
        else:
            results.append(json.loads(line[7:]))
        results[-1]["wall_s"] = round(time.perf_counter() - t1, 1)
        if results[-1].get("error") is None:
            key.write_text(json.dumps(results[-1]))
        print("   ", {k: results[-1].get(k) for k in ("total_s", "mask_iou", "chamfer_rel", "fscore", "psnr",
                                                     "registered", "error")}, flush=True)
    return results


def spec_key(r: dict) -> tuple:
    """What identifies a bench row: its spec (the fields :func:`plan` sets)."""
    return tuple(r.get(k) for k in ("kind", "condition", "scene", "cameras", "preset", "knob", "ablation"))


def merged(path: Path, new: list[dict]) -> list[dict]:
    """The rows of the results JSON ``path`` with those of ``new`` put in their place (same spec); a failed new
    row keeps the old one and says so (without one it is added: the tables show the failure)."""
    rows = json.loads(path.read_text())["results"]
    index = {spec_key(r): k for k, r in enumerate(rows)}
    for r in new:
        k = index.get(spec_key(r))
        if r.get("error") is not None and k is not None:
            print(f"bench: {spec_key(r)} failed ({r['error']}); its earlier row is kept", file=sys.stderr)
        elif k is None:
            rows.append(r)
        else:
            rows[k] = r
    return rows


def selected(spec: dict, only: str | None) -> bool:
    """Whether ``--only`` picks ``spec``: one of its comma-separated words is in the scene, preset, knob or
    condition."""
    if only is None:
        return True
    fields = (spec["scene"], spec.get("preset") or "", spec.get("condition", ""), spec.get("knob") or "")
    return any(w in f for w in only.split(",") for f in fields)


def kept(spec: dict, photos: bool = False, plain: bool = False, trained: bool = False) -> bool:
    """Whether the flags keep ``spec``: ``photos`` the rows that run SfM (from photos, and the cameras table),
    ``plain`` the rows without a knob that train, ``trained`` the rows that train (not the cameras table)."""
    table = spec.get("kind") == "cameras"
    return ((not photos or spec.get("cameras") == "sfm" or table)
            and (not plain or (not table and not spec.get("knob"))) and (not trained or not table))


def stale_specs(specs: list[dict], path: Path) -> list[dict]:
    """The ``specs`` whose training row in the results JSON ``path`` a later version of the defaults changes
    (:func:`bench.report.is_stale`: the rows its tables mark †)."""
    old = {spec_key(r) for r in json.loads(path.read_text())["results"]
           if r.get("kind") != "cameras" and is_stale(r)}
    return [s for s in specs if spec_key(s) in old]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="fast + default on the cow with GT cameras (≤ 10 min)")
    ap.add_argument("--docs", "--readme", dest="docs", action="store_true",
                    help="write the tables and plot into docs/benchmarks.md (between its BENCH markers)")
    ap.add_argument("--only", type=str, default=None,
                    help="run only the specs whose scene, preset, knob or cameras-table condition contains this (or "
                         "one of these, comma-separated)")
    ap.add_argument("--plain", action="store_true",
                    help="run only the rows without a knob: each scene's presets, with GT cameras and from photos")
    ap.add_argument("--photos", action="store_true",
                    help="run only the rows that run SfM: from photos (SfM cameras, automatic masks) and the "
                         "cameras table (with --update)")
    ap.add_argument("--trained", action="store_true",
                    help="run only the rows that train (not the cameras table); with --photos: the rows from photos")
    ap.add_argument("--stale", action="store_true",
                    help="with --update: only the rows that its JSON holds from older defaults (marked †)")
    ap.add_argument("--update", type=Path, default=None,
                    help="a full bench's results JSON: rerun the selected rows and replace them there (the others "
                         "kept as they are); tables, plot and docs/benchmarks.md (with --docs) from the merged set")
    ap.add_argument("--from", dest="from_json", type=Path, default=None,
                    help="redo the tables, plot and docs/benchmarks.md section from a results JSON (no runs)")
    ap.add_argument("--resume", action="store_true",
                    help="reuse runs already finished by an interrupted bench (bench/runs/done/)")
    ap.add_argument("--one", type=str, default=None, help=argparse.SUPPRESS)
    a = ap.parse_args()
    page = ROOT / "docs" / "benchmarks.md" if a.docs else None
    if a.from_json:
        rec = json.loads(a.from_json.read_text())
        write(rec["results"], rec["machine"], rec["bench_seconds"], a.from_json.with_suffix(""), page)
        return
    if a.one:
        run_child(json.loads(a.one))
        return
    specs = [s for s in plan(a.quick) if selected(s, a.only) and kept(s, a.photos, a.plain, a.trained)]
    if a.stale:
        if a.update is None:
            ap.error("--stale needs --update (the results JSON whose rows of older defaults to run again)")
        specs = stale_specs(specs, a.update)
    results = run_all(specs, a.resume)
    out = ROOT / "bench" / "results"
    out.mkdir(parents=True, exist_ok=True)
    stem = out / f"{datetime.date.today().isoformat()}-{platform.node() or 'machine'}{'-quick' if a.quick else ''}"
    mach = machine()
    if a.update:
        results, stem = merged(a.update, results), a.update.with_suffix("")
        mach = json.loads(a.update.read_text())["machine"]
    total = sum(r.get("wall_s", 0.0) for r in results)  # the runs' own time, also when resumed
    stem.with_suffix(".json").write_text(json.dumps({"machine": mach, "bench_seconds": round(total, 1),
                                                     "results": results}, indent=1))
    write(results, mach, total, stem, page)


if __name__ == "__main__":
    main()
