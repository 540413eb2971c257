"""The cow's photos at 3 × the working size as JPEGs (the bench's row "photos 3× larger as JPEG"), mapped once, then
the rest of the pipeline per arm with the object's matches verified again at the model's KNOWN poses
(``--cameras.object-verification poses``, the ``fast`` preset's; stop 49 found that it gave this cow over 100 object
points, which switch the masks to the points' footprint, whose prism cut the cow's ears until ``masks.footprint_union``
became the default in stop 50) and stage options:

    python bench/known_pose_verification.py "" "--masks.no-footprint-union"

The mapping (no final passes, no object matches) is kept in ``bench/runs/known_pose/mapping``; each arm prints the
cameras stage's object-matches note, where the masks' footprint came from, and the bench's figures
(:func:`bench.pair.run_arm`).
"""
from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import evaluate as ev  # noqa: E402
from bench import pair  # noqa: E402

SCALE = {"cameras": {"photo_scale": 3}}
OVER = {**SCALE, "photos_jpeg": 92}


def mapped(base: Path) -> Path:
    """The photos' workspace after the cameras stage without final passes or object matches (mapped once)."""
    mapping = base / "mapping"
    if not (mapping / "sfm" / "sparse" / "best").is_dir():
        shutil.rmtree(base, ignore_errors=True)
        photos = ev.photos_folder(ev.scene("cow", SCALE), base / "photos", OVER["photos_jpeg"])
        ev.stages(("cameras",), mapping, ev.config(None, ["--cameras.final-passes", "0", "--cameras.climbed-passes",
                                                          "0", "--cameras.no-object-matches"]), images=photos)
    return mapping


def main() -> None:
    base = ev.RUNS / "known_pose"
    mapping = mapped(base)
    for k, options in enumerate(sys.argv[1:] or [""]):
        work = base / "work" / str(k)
        r = pair.run_arm("cow", OVER, mapping, "default", ["--cameras.object-verification", "poses", *options.split()],
                         work)
        cams, masks = (json.loads((work / "all" / ".stages" / f"{s}.json").read_text()) for s in ("cameras", "masks"))
        print(json.dumps({"options": options, "object_matches": cams.get("object_matches"),
                          "footprint": masks.get("footprint"), **{key: r.get(key) for key in pair.SHOWN}}), flush=True)


if __name__ == "__main__":
    main()
