"""``python -m synth SCENE.yaml OUT`` (``make synth``): render a synthetic scene into a workspace, with its ground
truth in ``OUT/gt/``."""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import tyro

from synth import load_scene_file, write_scene


@dataclass
class SynthArgs:
    """Render a synthetic scene (YAML) into a workspace with ground truth in gt/."""

    scene: tyro.conf.Positional[Path]
    """Scene file (see configs/scenes/)."""
    out: tyro.conf.Positional[Path]
    """Output workspace folder."""


def main(argv: list[str] | None = None) -> int:
    """The command line; returns the exit code (2 with a one-line message on a bad scene file)."""
    a = tyro.cli(SynthArgs, args=sys.argv[1:] if argv is None else argv, prog="python -m synth")
    try:
        meta = write_scene(load_scene_file(a.scene), a.out)
    except (FileNotFoundError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"synth: {meta['n_views']} views (+{meta['n_heldout']} held out) in {meta['seconds']:.1f} s → {a.out}; "
          f"passes: {', '.join(meta['passes'])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
