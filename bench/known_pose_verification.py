"""The cow's photos at 3 × the working size as JPEGs (the bench's row "photos 3× larger as JPEG"), mapped once, then
the rest of the pipeline per arm with the object's matches verified again at the model's KNOWN poses (COLMAP's
guided geometric verifier; tried at stop 49 in place of :func:`pipeline.sfm.verify_again` and not kept: over 100
object points switch the masks to the points' footprint, which cut the cow's ears) and stage options:

    python bench/known_pose_verification.py "" "--masks.footprint-union"

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


def verify_at_known_poses() -> None:
    """Patch the cameras stage: the object's matches verified against the model's poses, not by RANSAC again."""
    import pycolmap

    import pipeline.cameras as cameras_stage
    from pipeline.sfm import copy_unverified

    model = {}
    keep = cameras_stage.keep_object_matches

    def keep_object_matches(ws, rec, database, inp, cfg):
        model["rec"] = rec
        return keep(ws, rec, database, inp, cfg)

    def verify_again(database, out, max_h_inlier_ratio, seed, threads=-1):
        copy_unverified(database, out)
        pycolmap.guided_geometric_verification(model["rec"], out, num_threads=threads)

    cameras_stage.keep_object_matches = keep_object_matches
    cameras_stage.verify_again = verify_again


def main() -> None:
    base = ev.RUNS / "known_pose"
    mapping = mapped(base)
    verify_at_known_poses()
    for k, options in enumerate(sys.argv[1:] or [""]):
        work = base / "work" / str(k)
        r = pair.run_arm("cow", OVER, mapping, "default", options.split(), work)
        cams, masks = (json.loads((work / "all" / ".stages" / f"{s}.json").read_text()) for s in ("cameras", "masks"))
        print(json.dumps({"options": options, "object_matches": cams.get("object_matches"),
                          "footprint": masks.get("footprint"), **{key: r.get(key) for key in pair.SHOWN}}), flush=True)


if __name__ == "__main__":
    main()
