"""Whether an arm of :mod:`bench.pair` wins by its masks: arm A's workspace (cameras, points, depth as its cameras,
masks and depth stages left them) trained with arm B's masks, then measured as a bench row from photos
(:func:`bench.evaluate.run_synthetic`, its photo stages skipped). Arms are numbered as ``bench/pair.py`` ran them
(``bench/runs/pairs/<scene>/work/<k>``):

    python bench/pair.py cow --over '{"cameras": {"photo_scale": 3}, "photos_jpeg": 92}' \\
        --arm=--cameras.object-verification=poses --arm ""
    python bench/swap_masks.py cow --over '{"cameras": {"photo_scale": 3}, "photos_jpeg": 92}' 0 1   # and 1 0

The swapped workspace is ``bench/runs/pairs/<scene>/swap/<A>-masks-<B>``; prints one JSON line.
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import evaluate as ev  # noqa: E402
from bench import pair  # noqa: E402

PHOTO_STAGES = ("cameras", "masks", "depth")


def swapped(folder: Path, arm: str, masks_arm: str) -> Path:
    """A copy of arm ``arm``'s photo workspace with the masks of arm ``masks_arm``; its work folder."""
    work = folder / "swap" / f"{arm}-masks-{masks_arm}"
    shutil.rmtree(work, ignore_errors=True)
    shutil.copytree(folder / "work" / arm / "all", work / "all")
    for m in (folder / "work" / masks_arm / "all" / "masks").glob("*.png"):
        shutil.copy(m, work / "all" / "masks" / m.name)
    return work


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", choices=sorted(ev.SCENES))
    ap.add_argument("arm", help="the arm whose workspace trains (bench/pair.py's work/<arm>)")
    ap.add_argument("masks_arm", help="the arm whose masks it trains with")
    ap.add_argument("--over", type=json.loads, default={}, help="the pair's scene overrides (JSON)")
    ap.add_argument("--preset", default="default")
    a = ap.parse_args()
    folder = pair.pair_folder(a.scene, a.over)
    for k in (a.arm, a.masks_arm):
        if not (folder / "work" / k / "all" / "masks").is_dir():
            sys.exit(f"{folder / 'work' / k}: no arm there; run bench/pair.py with this scene and --over first")
    work = swapped(folder, a.arm, a.masks_arm)
    run_stages = ev.stages
    ev.stages = lambda names, ws, cfg, **kw: None if names == PHOTO_STAGES else run_stages(names, ws, cfg, **kw)
    ev.photos_folder = lambda syn, out, jpeg_quality=None: out  # the photo stages are done: no photos needed
    r = ev.run_synthetic({"scene": a.scene, "cameras": "sfm", "preset": a.preset, "knob": "arm"}, work,
                         {"arm": ([], a.over)})
    print(json.dumps({"workspace_of": a.arm, "masks_of": a.masks_arm, **{k: r.get(k) for k in pair.SHOWN}}))


if __name__ == "__main__":
    main()
