"""Stage ``train``: fit the DVR fields to images/, masks/, optional depth/ and cameras.npz → model/."""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import asdict, replace

from dvr.atomic import write_json
from dvr.config import TrainConfig
from dvr.data import list_images, load_scene
from dvr.device import resolve_device
from dvr.trainer import Trainer, framing_views
from pipeline.errors import StageError
from pipeline.scene.exposure import read_exposure
from pipeline.workspace import Done, Job, Workspace, newest_mtime


def _fresh_or_resume(job: Job) -> None:
    """Keep model/ (its checkpoint resumes) only when it was trained with this config on these inputs."""
    ws = job.ws
    cfg_file = ws.model / "config.json"
    inputs_time = max(newest_mtime(p) for p in job.inputs)
    try:  # a file a killed run or a hand left unreadable is no record of a checkpoint: start afresh
        old = json.loads(cfg_file.read_text()) if cfg_file.exists() else {}
    except (OSError, ValueError):
        old = {}
    old = old if isinstance(old, dict) else {}
    if job.force or old.get("hash") != job.config_hash or old.get("inputs_time") != inputs_time:
        # another config, or new masks / images / cameras: that checkpoint is not ours to resume
        shutil.rmtree(ws.model, ignore_errors=True)
    ws.model.mkdir(parents=True, exist_ok=True)
    write_json(cfg_file, {"hash": job.config_hash, "inputs_time": inputs_time, "config": asdict(job.cfg)}, indent=1,
               default=str)


def run(job: Job) -> Done | None:
    """Stage ``train`` (called by :func:`pipeline.stages.run_stage`): train, or resume the checkpoint in model/,
    → model/final.pt; None when ``job.stop_after`` stopped it early (the next run resumes)."""
    ws, cfg = job.ws, job.cfg
    try:  # before model/ of another config is discarded: a run that cannot start loses nothing
        data = load_scene(ws.root, resolve_device(cfg.device))
    except (FileNotFoundError, ValueError) as exc:
        raise StageError(str(exc)) from exc
    _fresh_or_resume(job)
    cfg, appearance = resolve_appearance(ws, cfg)
    framing = report_framing(cfg, data)
    t0 = time.perf_counter()
    trainer = Trainer(cfg, data, ws.model)
    report_schedule(cfg, trainer.cfg, trainer.device)
    try:
        if trainer.try_resume():
            print(f"train: resuming at step {trainer.step}/{trainer.cfg.iterations}")
    except ValueError as exc:  # a checkpoint cut short (a full disk, a copy), or of another device's steps
        print(f"train: {exc}; starting afresh")
        trainer.ckpt_path.unlink()
        (ws.model / "log.jsonl").unlink(missing_ok=True)  # the log of the steps it stood for
    trainer.fit(job.stop_after)
    if trainer.step < trainer.cfg.iterations:
        return None
    trainer.finish()
    print(f"train: {trainer.step} steps in {trainer.elapsed:.1f} s (setup {trainer.setup_seconds:.1f} s) → "
          f"{ws.model / 'final.pt'}")
    return Done({"wall": round(time.perf_counter() - t0, 3), "setup": round(trainer.setup_seconds, 3),
                 "skipped": trainer.skipped, "device": trainer.device.type,
                 "steps": trainer.cfg.iterations, "batch_rays": trainer.cfg.batch_rays, "appearance": appearance,
                 "framing": framing},
                seconds=trainer.elapsed)


def report_schedule(asked: TrainConfig, steps: TrainConfig, device) -> None:
    """Say so when the device trains in other steps than the options name (:func:`dvr.trainer.device_schedule`)."""
    if steps.iterations != asked.iterations:
        print(f"train: on {device.type}, {steps.iterations} steps of {steps.batch_rays} rays "
              f"(--train.gpu-batch-scale {asked.gpu_batch_scale}; 1 trains {asked.iterations} steps of "
              f"{asked.batch_rays})")


def report_framing(cfg: TrainConfig, data) -> dict:
    """Print and return how many photos must frame a point for training to let it be occupied
    (:func:`dvr.trainer.framing_views`: ``framing`` auto decides by the photos whose mask reaches the frame's edge)."""
    need, cut = framing_views(cfg, data)
    views = data.P.shape[0]
    state = "on" if need > 1 else "off"
    why = (f"auto: the object reaches the frame's edge in {cut} of {views} photos, "
           f"{'more than' if state == 'on' else 'at most'} {100 * cfg.framing_cut_share:.0f} %"
           if cfg.framing == "auto" else f"--train.framing {cfg.framing}")
    print(f"train: {need} photos must frame a point to be object ({why})" if state == "on" else
          f"train: every framed point may be object ({why})")
    return {"framing": state, "min_framing_views": need, "cut_views": cut, "auto": cfg.framing == "auto"}


def resolve_appearance(ws: Workspace, cfg: TrainConfig) -> tuple[TrainConfig, dict]:
    """``cfg`` with ``appearance`` "auto" decided: "on" when the photos' exposure spread that the cameras stage
    measured (``exposure.json``) exceeds ``appearance_spread``, else "off"; and what the stamp records."""
    if cfg.appearance != "auto":
        return cfg, {"appearance": cfg.appearance, "auto": False}
    if not ws.exposure.exists():
        print("train: per-view appearance off (auto: no exposure measured, no SfM points; --train.appearance on "
              "turns it on)")
        return replace(cfg, appearance="off"), {"appearance": "off", "auto": True, "spread": None,
                                                "threshold": cfg.appearance_spread}
    spread = read_exposure(ws.exposure, [p.stem for p in list_images(ws.images)]).spread()
    on = spread > cfg.appearance_spread
    choice = "on" if on else "off"
    print(f"train: per-view appearance {choice} (auto: the photos' exposure differs by "
          f"{100 * spread:.1f} %, {'above' if on else 'within'} {100 * cfg.appearance_spread:.0f} %)")
    return replace(cfg, appearance=choice), {"appearance": choice, "auto": True, "spread": round(spread, 4),
                                             "threshold": cfg.appearance_spread}

