"""COLMAP's incremental and global mappers on the matches a cameras stage made, against a reference model.

    python bench/mappers.py WS [--database NAME] [--reference MODEL]

``WS``: a workspace whose cameras stage ran (its ``sfm/ladder/matches-*.db`` and ``sfm/input``); each mapper maps
those matches on one thread (as ``--cameras.deterministic``) and prints its seconds, the photos of its models and
its reprojection error. ``--reference``: a COLMAP model of the same photos (the mouse's author's,
``../shared/data/mouse_phone/colmap_model``); each largest model's camera centres and rotations are compared with
it after a similarity transform, and so is the stage's own model (``sfm/sparse/best``).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.evaluate import fresh_folder  # noqa: E402
from dvr.metrics import pose_errors  # noqa: E402
from pipeline.cameras.pose_sanity import model_views  # noqa: E402
from pipeline.cameras.sfm import Rung, _map  # noqa: E402
from pipeline.colmaplib import pycolmap  # noqa: E402


def poses(rec) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per photo stem of a COLMAP model: (world-to-camera rotation, camera centre)."""
    return {Path(v.name).stem: (v.R, v.center) for v in model_views(rec)}


def against(rec, reference) -> str:
    """Pose errors of ``rec`` against the ``reference`` model over the photos both posed (after Sim(3))."""
    mine, ref = poses(rec), poses(reference)
    common = sorted(set(mine) & set(ref))
    if len(common) < 3:
        return f"{len(common)} photos in common with the reference"
    e = pose_errors(np.stack([mine[n][1] for n in common]), np.stack([mine[n][0] for n in common]),
                    np.stack([ref[n][1] for n in common]), np.stack([ref[n][0] for n in common]))
    return (f"against the reference ({len(common)} photos): rotation {e['rot_err_deg_mean']:.2f}° mean, "
            f"{e['rot_err_deg_max']:.1f}° max; centres {e['center_err_rel_max']:.1%} of the orbit at most")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("ws", type=Path)
    ap.add_argument("--database", help="a matches database of sfm/ladder/ (default: the first rung's)")
    ap.add_argument("--reference", type=Path, help="a COLMAP model of the same photos")
    args = ap.parse_args()
    ladder = args.ws / "sfm" / "ladder"
    databases = sorted(ladder.glob("matches-*.db"), key=lambda p: len(p.name))
    db = ladder / args.database if args.database else (databases[0] if databases else None)
    if db is None or not db.exists():
        raise SystemExit(f"{ladder}: no matches database; run the cameras stage on this workspace first")
    reference = pycolmap.Reconstruction(args.reference) if args.reference else None
    if reference is not None and (args.ws / "sfm" / "sparse" / "best").is_dir():
        print(f"the stage's model: {against(pycolmap.Reconstruction(args.ws / 'sfm' / 'sparse' / 'best'), reference)}")
    for mapper in ("incremental", "global"):
        out = fresh_folder(args.ws / "sfm" / "mappers" / mapper)
        start = time.perf_counter()
        recs = _map(db, args.ws / "sfm" / "input", out, Rung(mapper, mapper=mapper), 0, "", 1)
        seconds = time.perf_counter() - start
        if not recs:
            print(f"{db.name} {mapper}: no model in {seconds:.0f} s")
            continue
        best = max(recs.values(), key=lambda r: r.num_reg_images())
        sizes = sorted((r.num_reg_images() for r in recs.values()), reverse=True)
        line = (f"{db.name} {mapper}: {seconds:.0f} s, models of {sizes} photos, "
                f"{best.compute_mean_reprojection_error():.2f} px")
        print(line + (f"; {against(best, reference)}" if reference is not None else ""), flush=True)


if __name__ == "__main__":
    main()
