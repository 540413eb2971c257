"""Where each stage's seconds go: the stages of a reconstruction, each under cProfile, and a table per stage of the
functions that take the most of its time.

    python bench/profile_stages.py --scene cow_floor                 # a scene of configs/scenes, photos only
    python bench/profile_stages.py --images DIR [--ws WS]            # your photos
    python bench/profile_stages.py --scene cow_floor --stages masks,train --top 8 --json bench/results/profile-cow.json

The scene is rendered once into ``bench/runs/profile/<scene>/`` (the workspace beside it). Each stage runs with
``--force`` through the same API as ``python -m pipeline <stage>`` and prints, after its own output, its wall
seconds and the ``--top`` functions by their own time (calls, own and cumulative seconds). cProfile sees the main
thread: work the stage hands to other threads or processes (GrabCut's pool in masks, COLMAP's SfM rungs in a child
process) shows as the time spent waiting for it, under the function that waits. cProfile's own cost falls on
Python calls: a stage that makes many of them runs slower profiled (training the cow: 105 s against 54 s), so read the
tables for where the time goes, not for how long a stage takes. A summary table of the stages ends the output;
``--json`` keeps it all.
"""
from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.evaluate import config  # noqa: E402

STAGES = ("cameras", "masks", "depth", "train", "mesh", "texture")
"""The stages profiled by default, in order (the report is left out: it only renders what the others made)."""


def where(file: str) -> str:
    """A function's file, short: relative to the project or to site-packages; built-ins as cProfile names them."""
    if file.startswith("~") or file.startswith("<"):
        return file
    p = Path(file)
    for base in (*[Path(s) for s in sys.path if s.endswith("site-packages")], ROOT):  # the venv may be in ROOT
        try:
            return str(p.relative_to(base))
        except ValueError:
            continue
    return p.name


def top_functions(stats: pstats.Stats, n: int) -> list[dict]:
    """The ``n`` functions with the most own time in ``stats``: name, calls, own and cumulative seconds."""
    entries = sorted(stats.stats.items(), key=lambda e: -e[1][2])[:n]  # type: ignore[attr-defined]
    return [{"function": func if file == "~" else f"{where(file)}:{line}({func})", "calls": calls,
             "own_s": round(own, 3), "cumulative_s": round(cumulative, 3)}
            for (file, line, func), (_, calls, own, cumulative, _) in entries]


def profile_stage(name: str, ws: Path, cfg, images: Path | None) -> tuple[float, pstats.Stats]:
    """Run stage ``name`` in ``ws`` (forced) under cProfile; (wall seconds, its profile)."""
    from pipeline.stages import run_stage

    prof = cProfile.Profile()
    start = time.perf_counter()
    prof.enable()
    try:
        run_stage(name, ws, cfg, force=True, images=images if name == "cameras" else None)
    finally:
        prof.disable()
    return time.perf_counter() - start, pstats.Stats(prof)


def scene_photos(scene: str) -> tuple[Path, Path]:
    """The photos of ``configs/scenes/<scene>.yaml`` (rendered once) and the workspace beside them."""
    from synth import scene_from_dict, write_scene

    spec = ROOT / "configs" / "scenes" / f"{scene}.yaml"
    if not spec.is_file():
        raise SystemExit(f"{spec}: no such scene; pick one of configs/scenes/*.yaml")
    out = ROOT / "bench" / "runs" / "profile" / scene
    if not (out / "syn" / "images").is_dir():
        import yaml

        write_scene(scene_from_dict(yaml.safe_load(spec.read_text()), spec.parent), out / "syn")
    return out / "syn" / "images", out / "ws"


def table(rows: list[dict], top: int) -> str:
    """The summary: per stage its seconds and its first functions by own time."""
    lines = ["| stage | seconds | most own time |", "|---|---|---|"]
    for r in rows:
        first = "; ".join(f"{f['function']} {f['own_s']:.1f} s" for f in r["functions"][:min(3, top)])
        lines.append(f"| {r['stage']} | {r['seconds']:.1f} | {first} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--scene", help="a scene of configs/scenes (cow_floor, jar_floor, …), photos only")
    src.add_argument("--images", type=Path, help="a folder of photos")
    ap.add_argument("--ws", type=Path, help="workspace (default: bench/runs/profile/<scene or folder name>/ws)")
    ap.add_argument("--stages", default=",".join(STAGES), help="stages to profile, in order (comma-separated)")
    ap.add_argument("--preset", help="a preset of configs/ (default: the defaults)")
    ap.add_argument("--top", type=int, default=12, help="functions listed per stage")
    ap.add_argument("--json", type=Path, help="write the tables here")
    args = ap.parse_args()
    names = [s.strip() for s in args.stages.split(",") if s.strip()]
    unknown = [s for s in names if s not in STAGES]
    if unknown:
        raise SystemExit(f"--stages: unknown stage(s) {', '.join(unknown)}; pick from {', '.join(STAGES)}")
    if args.scene:
        images, ws = scene_photos(args.scene)
    else:
        if not args.images.is_dir():
            raise SystemExit(f"{args.images}: not a folder of photos")
        images, ws = args.images, ROOT / "bench" / "runs" / "profile" / args.images.name / "ws"
    ws = args.ws or ws
    cfg = config(args.preset)
    rows = []
    for name in names:
        seconds, stats = profile_stage(name, ws, cfg, images)
        functions = top_functions(stats, args.top)
        rows.append({"stage": name, "seconds": round(seconds, 2), "functions": functions})
        print(f"\n{name}: {seconds:.1f} s; most own time:")
        for f in functions:
            print(f"  {f['own_s']:8.2f} s own {f['cumulative_s']:8.2f} s cumulative {f['calls']:>9} calls  "
                  f"{f['function']}")
        sys.stdout.flush()
    print("\n" + table(rows, args.top))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"source": args.scene or str(args.images), "preset": args.preset,
                                         "stages": rows}, indent=1))
        print(f"→ {args.json}")


if __name__ == "__main__":
    main()
