"""What the detail levels cost: the mesh and texture stages of a trained workspace run without levels and with every
level, each on a copy of the workspace, timed; the run with every level against the whole run of the default mesh
alone.

    python bench/levels.py WS [--levels preview,reduced,medium,full,raw] [--whole SECONDS]
    python bench/levels.py WS --psnr

``WS``: a trained workspace (``model/final.pt``; the bench's DTU workspace after ``python bench/arms.py dtu``, or any
``make reconstruct`` workspace). ``--whole``: the seconds of the whole run with the default mesh alone (the bench's
row; default: the sum of the workspace's stage stamps). Prints the seconds of each stage both ways and the ratio of
the whole run with every level to the whole run without. ``--psnr``: the PSNR of the default mesh's and each level's
textured GLB of ``WS`` against every 5th of its photos, within their masks (``python -m pipeline texture WS --force``
with and without ``--texture.levels-from-photos`` compares levels carried from the default mesh with levels baked).
"""
from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
STAGES = ("cameras", "masks", "depth", "train", "mesh", "texture")


def timed_stages(ws: Path, levels: str) -> dict[str, float]:
    """Wall seconds of ``mesh --force --mesh.detail LEVELS`` then ``texture --force`` on ``ws``."""
    out = {}
    for stage, extra in (("mesh", ["--mesh.detail", levels]), ("texture", [])):
        start = time.perf_counter()
        subprocess.run([sys.executable, "-m", "pipeline", stage, str(ws), "--force", *extra], cwd=ROOT, check=True,
                       stdout=subprocess.DEVNULL)
        out[stage] = time.perf_counter() - start
    return out


def stamped_seconds(ws: Path) -> float:
    """The sum of the seconds the workspace's stage stamps record (the stages of :data:`STAGES` it has)."""
    total = 0.0
    for stage in STAGES:
        stamp = ws / ".stages" / f"{stage}.json"
        if stamp.exists():
            total += float(json.loads(stamp.read_text()).get("seconds", 0.0))
    return total


def level_psnrs(ws: Path, every: int = 5) -> dict[str, float]:
    """Mean PSNR (dB) of the default mesh's and each level's ``textured.glb`` rendered at every ``every``-th photo of
    ``ws`` (its cameras), against the photo within its mask."""
    import numpy as np

    sys.path.insert(0, str(ROOT))
    from bench.evaluate import _read_mask, _read_rgb, render_psnr
    from dvr.cameras import load_cameras
    from dvr.data import list_images
    from pipeline.texture.export import read_textured

    paths = list_images(ws / "images")
    cams = load_cameras(ws / "cameras.npz", n_views=len(paths))
    glbs = {"default": ws / "mesh" / "textured.glb"}
    glbs.update({p.name: p / "textured.glb" for p in sorted((ws / "mesh" / "levels").glob("*"))})
    out = {}
    for name, glb in glbs.items():
        mesh, texture = read_textured(glb)
        scores = []
        for i in range(0, len(paths), every):
            photo, mask = _read_rgb(paths[i]), _read_mask(ws / "masks" / f"{paths[i].stem}.png")
            scores.append(render_psnr(mesh, texture, cams.K[i], cams.R[i], cams.sfm_centers[i], photo, mask))
        out[name] = float(np.mean(scores))
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("ws", type=Path)
    ap.add_argument("--levels", default="preview,reduced,medium,full,raw", help="the levels of the second run")
    ap.add_argument("--whole", type=float, help="seconds of the whole run of the default mesh alone")
    ap.add_argument("--psnr", action="store_true", help="print each level's PSNR at the photos instead")
    args = ap.parse_args(argv)
    if args.psnr:
        psnrs = level_psnrs(args.ws)
        for name, value in psnrs.items():
            print(f"{name:10s} {value:7.3f} dB")
        print(json.dumps(psnrs))
        return
    whole = args.whole or stamped_seconds(args.ws)
    with tempfile.TemporaryDirectory() as tmp:
        copy = Path(tmp) / "ws"
        shutil.copytree(args.ws, copy, ignore=shutil.ignore_patterns("levels"))
        alone = timed_stages(copy, "")
        every = timed_stages(copy, args.levels)
    extra = sum(every.values()) - sum(alone.values())
    print(f"{'':24s} {'mesh s':>8s} {'texture s':>10s}")
    print(f"{'default mesh alone':24s} {alone['mesh']:8.1f} {alone['texture']:10.1f}")
    print(f"{'with every level':24s} {every['mesh']:8.1f} {every['texture']:10.1f}   ({args.levels})")
    print(f"every level adds {extra:.1f} s to a whole run of {whole:.0f} s: {(whole + extra) / whole:.3f} ×")
    print(json.dumps({"alone": alone, "every": every, "whole": whole, "ratio": (whole + extra) / whole}))


if __name__ == "__main__":
    main()
