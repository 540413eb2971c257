"""A smaller capture of the same object: evenly spaced photos of a folder, optionally enlarged to a phone's size.

    python bench/subset.py SRC OUT --take 24 [--long-side 4032]

Takes ``--take`` photos of ``SRC`` (sorted by name, evenly spaced: the 24 of the mouse's 59 are every 2.5th) into
``OUT`` (made afresh). ``--long-side``: each photo resized to that longest side at its own aspect (bicubic, JPEG
quality 92): 4032 gives a 12 MP phone's 4032×3024. The photos of ``SRC`` are only read.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.evaluate import take_photos  # noqa: E402
from pipeline.inputs.photos import list_photos  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("src", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--take", type=int, required=True, help="photos to take, evenly spaced in name order")
    ap.add_argument("--long-side", type=int, default=0, help="resize each to this longest side, px (0: as is)")
    args = ap.parse_args()
    out = take_photos(args.src, args.out, args.take, args.long_side)
    print(f"{args.take} of {len(list_photos(args.src)[0])} photos → {out}")


if __name__ == "__main__":
    main()
