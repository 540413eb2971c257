"""The cow on its floor filmed instead of photographed: a hand-held clip through every stage, measured.

    python bench/video.py [--frames N] [--preset P] [--clip-frames M] [--turns T] [--codec C] [--portrait]

The bench's cow (configs/scenes/cow_floor.yaml) rendered along one continuous path (``M`` frames, ``T`` turns
while the camera rises from 15° to 55°, 4 held-out views halfway between frames), written as an MP4 with every
third frame shaken (synth/video.py; ``--codec h264`` or ``hevc`` as phones record, ``--portrait``
filmed with the phone held upright: frames of 300×400 stored turned, the clip tagged 90°), then ``cameras``
(taking ``N`` frames: pipeline/inputs/video.py), masks, depth, train, mesh and texture from the clip alone. Printed:
frames registered, their pose error against the true cameras of the frames chosen, mask IoU against the frames'
true masks, Chamfer and F-score against the true mesh, held-out PSNR at the held-out views' true poses brought
into SfM's frame (the bench's ``psnr_gt_pose``), and the seconds of each stage.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import evaluate as ev  # noqa: E402


def main() -> None:
    import trimesh

    from dvr.cameras import load_cameras
    from dvr.metrics import chamfer_fscore, pose_errors, umeyama
    from pipeline.workspace import Workspace
    from synth.video import write_video

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=48, help="frames the cameras stage takes (cameras.video_frames)")
    ap.add_argument("--clip-frames", type=int, default=96, help="frames of the rendered clip")
    ap.add_argument("--turns", type=float, default=1.0, help="turns around the cow")
    ap.add_argument("--preset", default="default")
    ap.add_argument("--codec", default="mp4v", help="mp4v, MJPG, h264 or hevc (synth/video.py)")
    ap.add_argument("--portrait", action="store_true", help="the phone held upright: 300×400 frames, tagged 90°")
    a = ap.parse_args()
    over = {"cameras": {"n_views": a.clip_frames, "orbit_turns": a.turns, "rings": 0, "heldout": 4,
                        **({"width": 300, "height": 400} if a.portrait else {})}}
    syn = ev.scene("cow", over)
    work = ev.RUNS / "video" / f"cow_{a.clip_frames}_{a.turns:g}_{a.frames}_{a.preset}_{a.codec}" \
        f"{'_portrait' if a.portrait else ''}"
    shutil.rmtree(work, ignore_errors=True)
    clip = write_video(syn / "images", work / ("cow.mov" if a.codec == "hevc" else "cow.avi" if a.codec == "MJPG"
                                               else "cow.mp4"), codec=a.codec, rotation=90 if a.portrait else 0)
    ws = work / "ws"
    cfg = ev.config(a.preset, ["--cameras.video-frames", str(a.frames)])
    ev.stages(("cameras", "masks", "depth", "train", "mesh", "texture"), ws, cfg, images=clip)

    chosen = [c["frame"] for c in json.loads((ws / "frames" / "frames.json").read_text())["chosen"]]
    shaken = set(json.loads(clip.with_suffix(".json").read_text())["shaken"])
    from dvr.data import list_images

    names = [p.stem for p in list_images(ws / "images")]
    src = [chosen[int(n[len("frame"):])] for n in names]  # the clip's frame each registered one is
    gtc, hc, est = load_cameras(syn / "cameras.npz"), load_cameras(syn / "gt/heldout/cameras.npz"), \
        load_cameras(ws / "cameras.npz")
    s, R, t = umeyama(gtc.sfm_centers[src], est.sfm_centers)  # true world → SfM frame
    held = sorted((syn / "gt" / "heldout" / "images").glob("*.png"))
    tm, tex = ev.textured(ws)
    psnr = [ev.render_psnr(tm, tex, est.K.mean(0), hc.R[i] @ R.T, s * R @ hc.sfm_centers[i] + t, ev._read_rgb(p),
                           ev._read_mask(syn / "gt" / "heldout" / "masks" / p.name)) for i, p in enumerate(held)]
    gt_masks = {n: syn / "gt" / "masks" / f"{k:06d}.png" for n, k in zip(names, src)}
    gt = trimesh.load(syn / "gt" / "mesh.ply")
    gt.apply_transform(ev.similarity_matrix((s, R, t)))
    geo = chamfer_fscore(trimesh.load(ws / "mesh" / "clean.ply"), gt, n=50000)
    row = {"clip_frames": a.clip_frames, "turns": a.turns, "codec": a.codec, "portrait": a.portrait,
           "frames_taken": len(chosen),
           "shaken_taken": len(shaken & set(chosen)), "registered": f"{len(names)}/{len(chosen)}",
           "rung": (Workspace(ws).stamp("cameras") or {}).get("rung"),
           "support": (Workspace(ws).stamp("cameras") or {}).get("support") is not None,
           "pose": pose_errors(est.sfm_centers, est.R, gtc.sfm_centers[src], gtc.R[src]),
           "mask_iou": ev.mask_iou(ws, gt_masks), "chamfer_rel": geo["chamfer_rel"], "fscore": geo["fscore"],
           "psnr_gt_pose": float(np.mean(psnr)), "seconds": Workspace(ws).seconds()}
    print(json.dumps(row))


if __name__ == "__main__":
    main()
