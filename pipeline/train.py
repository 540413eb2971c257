"""Stage ``train``: fit the DVR fields to images/, masks/, optional depth/ and cameras.npz → model/."""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import asdict

from dvr.data import load_scene
from dvr.device import resolve_device
from dvr.trainer import TrainConfig, Trainer

from .config import config_hash
from .workspace import StageError, Workspace, newest_mtime


def run(ws: Workspace, cfg: TrainConfig, force: bool = False, stop_after: int | None = None) -> bool:
    """Train (or resume); returns False when the stage was already up to date."""
    ws.require(ws.images, ws.masks, ws.cameras, hint="run the cameras and masks stages first")
    h = config_hash(cfg)
    inputs = [ws.images, ws.masks, ws.cameras] + ([ws.depth] if ws.depth.exists() else [])
    final = ws.model / "final.pt"
    if not force and ws.up_to_date("train", h, inputs, [final]):
        print(f"train: up to date ({final})")
        return False
    ws.clear("train")
    cfg_file = ws.model / "config.json"
    inputs_time = max(newest_mtime(p) for p in inputs)
    old = json.loads(cfg_file.read_text()) if cfg_file.exists() else {}
    if force or old.get("hash") != h or old.get("inputs_time") != inputs_time:
        # another config, or new masks / images / cameras: that checkpoint is not ours to resume
        shutil.rmtree(ws.model, ignore_errors=True)
    ws.model.mkdir(parents=True, exist_ok=True)
    cfg_file.write_text(json.dumps({"hash": h, "inputs_time": inputs_time, "config": asdict(cfg)}, indent=1,
                                   default=str))
    try:
        data = load_scene(ws.root, resolve_device(cfg.device))
    except (FileNotFoundError, ValueError) as exc:
        raise StageError(str(exc)) from exc
    t0 = time.perf_counter()
    trainer = Trainer(cfg, data, ws.model)
    if trainer.try_resume():
        print(f"train: resuming at step {trainer.step}/{cfg.iterations}")
    trainer.fit(stop_after)
    if trainer.step < cfg.iterations:
        return True  # stopped early on request (tests); the next run resumes
    trainer.finish()
    ws.mark_done("train", h, trainer.elapsed, {"wall": round(time.perf_counter() - t0, 3), "skipped": trainer.skipped})
    print(f"train: {trainer.step} steps in {trainer.elapsed:.1f} s → {final}")
    return True
