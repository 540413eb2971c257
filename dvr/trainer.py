"""DVR training loop: Adam + exponential LR decay, checkpoints and exact resume, log.jsonl, previews."""

from __future__ import annotations

import json
import math
import random
import time
import warnings
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import cv2
import numpy as np
import torch
from tqdm import tqdm

from dvr import losses as L
from dvr.appearance import ViewAppearance
from dvr.atomic import save_torch, write_image, write_json, write_text
from dvr.cameras import in_contact_band, plane_height
from dvr.checkpoint import read_saved, save_model
from dvr.config import LossWeights, TrainConfig
from dvr.data import RaySampler, SceneData
from dvr.device import resolve_device
from dvr.fields import finite_difference_normals, make_field
from dvr.hull import (
    carve_along_rays,
    coarse_points,
    cut_by_frame,
    hull_bounding_sphere,
    hull_inside,
    inside_logits,
    near_object,
    outside_hull,
)
from dvr.implicit import implicit_depth
from dvr.march import INSIDE, MISS, SurfaceResult, render_view
from dvr.photohull import PhotoCarveResult, photo_carve
from dvr.shading import ViewShading
from dvr.surface_graph import SurfaceFinder


@dataclass
class RayBatchRender:
    """One step's batch of pixels rendered by :meth:`Trainer.render_batch` (B rays, H of them hits)."""

    origins: torch.Tensor
    """(B, 3) ray origins."""
    dirs: torch.Tensor
    """(B, 3) unit ray directions."""
    in_mask: torch.Tensor
    """(B,) True where the pixel's mask says object."""
    surface: SurfaceResult
    """The march along every ray (status, depth, sphere entry/exit, depth of the largest logit)."""
    hit: torch.Tensor
    """(B,) True for rays that hit the surface."""
    surface_points: torch.Tensor
    """(H, 3) surface points of the hits at the implicit depth (differentiable w.r.t. the occupancy)."""
    rendered_rgb: torch.Tensor
    """(K, 3) rendered colour of the K hits inside the mask (after the view's colour transform, if any)."""
    observed_rgb: torch.Tensor
    """(K, 3) the photos' colours of those pixels."""
    shading: torch.Tensor | None = None
    """(K, 3) the view-dependent residual in ``rendered_rgb`` (with ``view_shading``), else None."""


@dataclass
class SparseDepthRender:
    """The step's sparse-depth rays rendered by :meth:`Trainer.render_sparse_depth`."""

    rendered_depth: torch.Tensor
    """(H,) implicit depth of the rays that hit (differentiable w.r.t. the occupancy)."""
    known_depth: torch.Tensor
    """(H,) their sparse SfM depth."""
    missed_points: torch.Tensor
    """(M, 3) points at the known depth of the rays that miss (pushed occupied)."""
    free_points: torch.Tensor
    """(F, 3) one random point per ray in front of its known depth (pushed free)."""


def _set_seed(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def device_schedule(cfg: TrainConfig, device: torch.device) -> TrainConfig:
    """The steps ``cfg`` trains in on ``device``. On a GPU a step costs its kernel launches far more than its rays:
    ``gpu_batch_scale`` times the rays, sparse-depth rays and carving points a step, in as many times fewer steps
    (rounded up), the learning rates × √scale and the step counts between checkpoints, log lines and previews
    divided alike. On the CPU, or with a scale of 1, ``cfg`` itself."""
    k = cfg.gpu_batch_scale
    if device.type == "cpu" or k == 1:
        return cfg
    lr = math.sqrt(k)
    return replace(cfg, iterations=-(-cfg.iterations // k), batch_rays=cfg.batch_rays * k,
                   depth_rays=cfg.depth_rays * k, carve_points=cfg.carve_points * k, lr_grid=cfg.lr_grid * lr,
                   lr_mlp=cfg.lr_mlp * lr, lr_appearance=cfg.lr_appearance * lr,
                   checkpoint_every=max(1, cfg.checkpoint_every // k), log_every=max(1, cfg.log_every // k),
                   preview_every=cfg.preview_every // k)


_CHECKPOINT_KEYS = ("step", "elapsed", "skipped", "field", "opt", "sched", "rng_torch", "rng_gen", "rng_np",
                    "rng_py")


def sure_background(cfg: TrainConfig, data: SceneData) -> torch.Tensor | None:
    """:func:`dvr.hull.near_object` of the masks at ``carve_sure_depth`` of each view's diagonal (``None`` when off):
    where it is 0, that view's mask alone carves."""
    if cfg.carve_sure_depth <= 0:
        return None
    diagonals = data.sizes.double().cpu().norm(dim=1).numpy()  # of each view's own (width, height)
    return near_object(data.masks, cfg.carve_sure_depth * diagonals)


def carve_rules(cfg: TrainConfig, data: SceneData, near: torch.Tensor | None = None) -> dict:
    """The masks' carving rules of this run, as keyword arguments of :func:`dvr.hull.outside_hull` (and of the hull
    and frame built on it): the same for the initial hull, the training frame and the carving term. ``near``: the
    run's :func:`sure_background`, when already made (a distance transform of every mask)."""
    if near is None:
        near = sure_background(cfg, data)
    return dict(min_views=cfg.carve_min_views, sparse_views=cfg.carve_sparse_views, contact_band=cfg.contact_band,
                ground=data.cams.ground, sizes=data.sizes, near=near, min_framing=framing_views(cfg, data)[0])


def framing_views(cfg: TrainConfig, data: SceneData) -> tuple[int, int]:
    """(how many photos must frame a point for it to be occupied, how many of the photos cut the object at the
    frame's edge: :func:`dvr.hull.cut_by_frame`) under ``cfg.framing``."""
    cut = int(cut_by_frame(data.masks, data.sizes).sum())
    on = cfg.framing == "on" or (cfg.framing == "auto" and cut > cfg.framing_cut_share * data.P.shape[0])
    return (min(cfg.min_framing_views, data.P.shape[0]) if on else 1), cut


def training_frame(cfg: TrainConfig, data: SceneData, near: torch.Tensor | None = None) -> SceneData:
    """The scene as training sees it: with ``fit_frame``, reframed so that the working sphere is the visual hull's
    bounding sphere (as it is when the hull is empty or fills the sphere, or without ``fit_frame``). ``near``: as
    :func:`carve_rules` takes it."""
    if not cfg.fit_frame:
        return data
    sphere = hull_bounding_sphere(data.P, data.masks, cfg.hull_res, margin=cfg.frame_margin,
                                  **carve_rules(cfg, data, near))
    return data if sphere is None else data.reframe(*sphere)


def initial_inside(cfg: TrainConfig, data: SceneData,
                   near: torch.Tensor | None = None) -> tuple[np.ndarray, PhotoCarveResult | None]:
    """The initial occupancy, a (hull_res+1)³ bool lattice: the visual hull; with ``photo_hull``, less what the
    photo hull carves at its own, finer lattice (where it carves nothing, the visual hull exactly), and what it
    did. ``near``: as :func:`carve_rules` takes it."""

    rules = carve_rules(cfg, data, near)

    def visual_hull(res: int) -> np.ndarray:
        return hull_inside(data.P, data.masks, res, **rules)

    inside = visual_hull(cfg.hull_res)
    if not cfg.photo_hull:
        return inside, None
    fine = visual_hull(cfg.photo_hull_res)
    carving = photo_carve(fine, data.P, data.images, data.masks, data.sizes, spread_floor=cfg.photo_spread,
                          contrast_weight=cfg.photo_contrast, min_depth=cfg.photo_min_depth)
    return inside & ~coarse_points(fine & ~carving.inside, cfg.hull_res), carving


class Trainer:
    """Trains a field on a SceneData, writing into ``out_dir`` (the workspace's ``model/``)."""

    def __init__(self, cfg: TrainConfig, data: SceneData, out_dir: Path):
        t_setup = time.perf_counter()
        self.cfg = cfg = device_schedule(cfg, data.masks.device)  # the steps this device trains in
        # once, a distance transform of every mask (reframing moves the cameras, not the masks)
        self.near = sure_background(cfg, data)
        self.data = data = training_frame(cfg, data, self.near)
        self.rules = carve_rules(cfg, data, self.near)  # once: the carving term asks at every step
        # the hull gate's masks: each widened by hull_gate_px, so a point a pixel or two outside a view's silhouette
        # (where the views' masks disagree by their edges) is no mask error that the gate must outvote
        self.gate_masks = near_object(data.masks, cfg.hull_gate_px) if cfg.hull_gate and cfg.hull_gate_px > 0 \
            else data.masks
        self.out = Path(out_dir)
        self.out.mkdir(parents=True, exist_ok=True)
        self.device = data.masks.device
        if cfg.threads > 0:
            torch.set_num_threads(cfg.threads)
        _set_seed(cfg.seed)
        self.gen = torch.Generator().manual_seed(cfg.seed)
        self.model = make_field(cfg.field).to(self.device)
        self.model.set_support(data.cams.ground)  # nothing below the floor or table is object
        if self.coarse:
            if not 0.0 < cfg.upsample_at < 1.0:
                raise ValueError(f"upsample_at must lie in (0, 1), got {cfg.upsample_at}")
            self.model.resize_base(cfg.coarse_res)
        if cfg.hull_init:
            vol = self._initial_logits()
            if cfg.depth_carve_init and data.depth_val is not None:
                o, d = data.rays(data.depth_views, data.depth_uv)
                vol = carve_along_rays(vol, o, d, data.depth_val - cfg.depth_free_margin,
                                       value=3.0)  # just free: −10 would pull the nearby surface inwards
            self.model.init_occupancy(vol)
        if cfg.appearance not in ("auto", "on", "off"):
            raise ValueError(f"appearance must be 'auto', 'on' or 'off', got {cfg.appearance!r}")
        on = cfg.appearance == "on"  # "auto" is decided before (pipeline/train/stage.py); dvr alone has no measurement
        self.appearance = ViewAppearance(data.images.shape[0]).to(self.device) if on else None
        self.shading = ViewShading().to(self.device) if cfg.view_shading else None
        grid_ids = {id(p) for p in self.model.grid_parameters()}
        groups = [
            {"params": [p for p in self.model.parameters() if id(p) in grid_ids], "lr": cfg.lr_grid},
            {"params": [p for p in self.model.parameters() if id(p) not in grid_ids], "lr": cfg.lr_mlp},
            {"params": list(self.appearance.parameters()) if self.appearance is not None else [],
             "lr": cfg.lr_appearance},
            {"params": list(self.shading.parameters()) if self.shading is not None else [], "lr": cfg.lr_mlp},
        ]
        groups = [g for g in groups if g["params"]]
        fused = {"fused": True} if self.device.type in ("cpu", "cuda") else {}
        self.opt = torch.optim.Adam(groups, betas=(0.9, 0.99), eps=1e-15, **fused)
        gamma = cfg.lr_decay ** (1.0 / max(1, cfg.iterations))
        self.sched = torch.optim.lr_scheduler.ExponentialLR(self.opt, gamma)
        self.sampler = RaySampler(data, cfg.boundary_fraction, generator=self.gen)
        self.find_surface = SurfaceFinder(self.model.occupancy, self._occupancy_tensors, cfg.n_secant,
                                          graphs=cfg.cuda_graphs)
        self.step = 0
        self.skipped = 0
        self.setup_seconds = time.perf_counter() - t_setup
        self.elapsed = self.setup_seconds  # what training took includes its setup (visual hull, photo hull)

    def _occupancy_tensors(self) -> list[torch.Tensor | None]:
        """What the occupancy reads: the field's parameters and buffers and its support plane."""
        return [*self.model.parameters(), *self.model.buffers(), self.model.support]

    def _initial_logits(self) -> torch.Tensor:
        """The initial occupancy's logit volume (:func:`initial_inside`); the photo hull's counts, with
        ``photo_hull``, to ``photo_hull.json``."""
        inside, carving = initial_inside(self.cfg, self.data, self.near)
        if carving is not None:
            summary = {k: (v if math.isfinite(v) else None) for k, v in vars(carving).items() if k != "inside"}
            write_json(self.out / "photo_hull.json", summary, indent=1)
        return inside_logits(inside, device=self.data.masks.device)

    # ----------------------------------------------------------------- checkpoints
    @property
    def ckpt_path(self) -> Path:
        """Where the checkpoint for resuming lives."""
        return self.out / "checkpoint.pt"

    def save_checkpoint(self) -> None:
        """Write everything an exact resume needs: step, weights, optimizer, schedule and every RNG state."""
        save_torch({
            "step": self.step, "iterations": self.cfg.iterations, "elapsed": self.elapsed, "skipped": self.skipped,
            "field": self.model.state_dict(), "opt": self.opt.state_dict(), "sched": self.sched.state_dict(),
            "appearance": self.appearance.state_dict() if self.appearance is not None else None,
            "shading": self.shading.state_dict() if self.shading is not None else None,
            "rng_torch": torch.get_rng_state(), "rng_gen": self.gen.get_state(),
            "rng_np": np.random.get_state(), "rng_py": random.getstate(),
            "rng_cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None,
        }, self.ckpt_path)

    @property
    def upsample_step(self) -> int | None:
        """The step at which the coarse occupancy grid is upsampled (None: one resolution throughout)."""
        c = self.cfg
        return int(round(c.upsample_at * c.iterations)) if self.coarse else None

    @property
    def coarse(self) -> bool:
        """Coarse to fine: the field can change its resolution and 0 < coarse_res < field.base_res (a field that
        cannot, the 'mlp' reference, trains at one resolution whatever coarse_res says)."""
        c = self.cfg
        return self.model.supports_resize and 0 < c.coarse_res < c.field.base_res

    def _resize_grid(self, res: int) -> None:
        """Upsample the occupancy grid and swap it into the optimizer (its Adam moments start afresh)."""
        old, new = self.model.resize_base(res)
        if new is old:
            return
        for g in self.opt.param_groups:
            g["params"] = [new if p is old else p for p in g["params"]]
        self.opt.state.pop(old, None)

    def try_resume(self) -> bool:
        """Continue from ``checkpoint.pt`` when there is one (True), exactly where it stopped. A ValueError naming
        it, with the trainer untouched, when it is damaged or not a checkpoint."""
        if not self.ckpt_path.exists():
            return False
        ck = read_saved(self.ckpt_path, self.device, _CHECKPOINT_KEYS)  # before anything of it is loaded
        steps = ck.get("iterations", self.cfg.iterations)
        if steps != self.cfg.iterations:  # another device's steps (device_schedule): its schedule is not this run's
            raise ValueError(f"{self.ckpt_path}: a checkpoint of {steps} steps, where this run trains "
                             f"{self.cfg.iterations} (another device's schedule)")
        saved_res = self.model.grid_resolution_in(ck["field"])
        if saved_res is not None and saved_res != self.model.grid_resolution:
            self._resize_grid(saved_res)  # the checkpoint is past the upsampling
        self.model.load_state_dict(ck["field"])
        if self.appearance is not None and ck.get("appearance") is not None:
            self.appearance.load_state_dict(ck["appearance"])
        if self.shading is not None and ck.get("shading") is not None:
            self.shading.load_state_dict(ck["shading"])
        self.opt.load_state_dict(ck["opt"])
        self.sched.load_state_dict(ck["sched"])
        torch.set_rng_state(ck["rng_torch"])
        self.gen.set_state(ck["rng_gen"])
        np.random.set_state(ck["rng_np"])
        random.setstate(ck["rng_py"])
        if ck.get("rng_cuda") is not None and torch.cuda.is_available():
            torch.cuda.set_rng_state_all(ck["rng_cuda"])
        self.step, self.skipped = ck["step"], ck["skipped"]
        self.elapsed = ck["elapsed"] + self.setup_seconds  # the earlier runs' time and this run's setup
        self._trim_log()
        return True

    def _trim_log(self) -> None:
        """``log.jsonl`` up to the resumed step: the lines of the steps after the checkpoint go (they are logged again
        as they are redone), and so does a line a kill or a full disk cut short."""
        log = self.out / "log.jsonl"
        if not log.exists():
            return
        kept = []
        for line in log.read_text(errors="replace").splitlines():
            try:
                rec = json.loads(line)
            except ValueError:
                continue
            if isinstance(rec, dict) and isinstance(rec.get("step"), int) and rec["step"] <= self.step:
                kept.append(line + "\n")
        write_text(log, "".join(kept))

    # ----------------------------------------------------------------- one step
    def n_steps_at(self, step: int) -> int:
        """Marching samples at ``step`` (linear from n_steps to n_steps_final)."""
        c = self.cfg
        a = step / max(1, c.iterations - 1)
        return int(round(c.n_steps + a * (c.n_steps_final - c.n_steps)))

    def carved(self, pts: torch.Tensor) -> torch.Tensor:
        """(M,) True where the masks carve the points (:func:`outside_hull` with this run's rules)."""
        return outside_hull(pts, self.data.P, self.data.masks, **self.rules)

    def gated(self, pts: torch.Tensor) -> torch.Tensor:
        """(M,) True where the hull gate holds the occupancy term back: the masks, each widened by ``hull_gate_px``,
        carve the points (:func:`outside_hull` with this run's rules)."""
        return outside_hull(pts, self.data.P, self.gate_masks, **self.rules)

    def below_support(self, pts: torch.Tensor) -> torch.Tensor:
        """(M,) True for points below the support plane (none without one)."""
        g = self.data.cams.ground
        return torch.zeros(pts.shape[0], dtype=torch.bool, device=pts.device) if g is None else plane_height(g, pts) < 0

    def contact_doubt(self, pts: torch.Tensor) -> torch.Tensor:
        """(M,) True for points in the contact band above the support plane that fewer than two views' masks
        carve: one mask calling them background is not enough to push them free."""
        g, band = self.data.cams.ground, self.cfg.contact_band
        out = torch.zeros(pts.shape[0], dtype=torch.bool, device=pts.device)
        if g is None or band <= 0 or pts.shape[0] == 0:
            return out
        hgt = plane_height(g, pts)
        near = in_contact_band(hgt, band)
        if near.any():
            out[near] = ~self.carved(pts[near])
        return out

    # ----------------------------------------------------------------- one batch: render, points, loss terms
    def render_batch(self, step: int) -> RayBatchRender:
        """Sample the step's pixels, find the surface along their rays (exact implicit depth at hits) and render the
        colour of the hits inside the mask (through this photo's colour transform with ``appearance``)."""
        c, m = self.cfg, self.model
        origins, dirs, observed, mask, view = self.sampler.sample(c.batch_rays)
        surface = self.find_surface(origins, dirs, n_steps=self.n_steps_at(step), jitter=c.jitter)
        hit = surface.hit
        hit_rays = hit.nonzero().view(-1)
        hit_depth = implicit_depth(m.occupancy, m.occupancy_parameters(), origins[hit_rays], dirs[hit_rays],
                                   surface.depth[hit_rays], c.grad_eps)
        hit_points = origins[hit_rays] + hit_depth[:, None] * dirs[hit_rays]
        in_mask = mask > 0.5
        hit_in_mask = in_mask[hit_rays]
        rendered = m.texture(hit_points[hit_in_mask])
        shading = None
        if self.shading is not None:  # what the diffuse field cannot show (highlights), from detached geometry
            pts = hit_points[hit_in_mask].detach()
            normals = finite_difference_normals(m.occupancy, pts).detach()
            shading = self.shading(pts, dirs[hit_rays][hit_in_mask], normals)
            rendered = rendered + shading
        if self.appearance is not None:  # the shared colour as this photo's camera rendered it
            rendered = self.appearance(rendered, view[hit_rays][hit_in_mask])
        return RayBatchRender(origins, dirs, in_mask, surface, hit, hit_points, rendered,
                              observed[hit_rays][hit_in_mask], shading)

    def freespace_points(self, batch: RayBatchRender) -> torch.Tensor:
        """Points pushed free: the hit point of a ray outside the mask, or a random point of such a ray that misses
        (one random draw per ray); rays starting inside the object are wrong whatever the mask says (the object lies
        inside the unit sphere): their entry point. Points of the contact band one mask alone calls free are left
        out (:meth:`contact_doubt`)."""
        o, d, surface = batch.origins, batch.dirs, batch.surface
        inside = surface.status == INSIDE
        u = torch.rand(o.shape[0], device=o.device)
        random_depth = surface.near + u * (surface.far - surface.near)
        depth = torch.where(batch.hit, surface.depth, torch.where(inside, surface.near, random_depth))
        free_rays = ~batch.in_mask | inside
        points = (o + depth[:, None] * d)[free_rays]
        return points[~self.contact_doubt(points)]

    def occupancy_points(self, batch: RayBatchRender) -> torch.Tensor:
        """Points pushed occupied: for mask rays the rendering misses, the sample of largest logit (with
        ``hull_gate``, only where the other masks, each widened by ``hull_gate_px``, do not carve it)."""
        o, d, surface = batch.origins, batch.dirs, batch.surface
        missed = batch.in_mask & (surface.status == MISS)
        points = (o + surface.max_depth[:, None] * d)[missed]
        if self.cfg.hull_gate and points.shape[0]:
            # a mask pixel whose best point the other masks carve is a mask error, not missing surface: pushing it
            # occupied against the carving grows floaters (a speck of floor kept in one view's automatic mask)
            points = points[~self.gated(points)]
        return points

    def render_sparse_depth(self, step: int) -> SparseDepthRender | None:
        """The step's sparse-depth rays (None without sparse depth, or with the depth weight 0): their surface
        (implicit depth at hits), the known-depth points of rays that miss, and a random free point in front of
        each depth (carves what the masks cannot: concavities, objects that fill the frame)."""
        c, m = self.cfg, self.model
        sample = self.sampler.sample_depth(c.depth_rays) if c.weights.depth > 0 else None
        if sample is None:
            return None
        o, d, known = sample
        surface = self.find_surface(o, d, n_steps=self.n_steps_at(step), jitter=c.jitter)
        hit_rays = surface.hit.nonzero().view(-1)
        rendered = implicit_depth(m.occupancy, m.occupancy_parameters(), o[hit_rays], d[hit_rays],
                                  surface.depth[hit_rays], c.grad_eps)
        missed_points = (o + known[:, None] * d)[~surface.hit]  # missed: push occupancy at the known depth
        in_front = known - c.depth_free_margin > surface.near
        u = torch.rand(known.shape[0], device=o.device)
        free_depth = surface.near + u * (known - c.depth_free_margin - surface.near).clamp_min(0.0)
        free_points = (o + free_depth[:, None] * d)[in_front]
        return SparseDepthRender(rendered, known[hit_rays], missed_points, free_points)

    def carve_points(self, device: torch.device) -> torch.Tensor:
        """Random points of the unit sphere outside the visual hull (and above the support plane, below which the
        field is clipped already)."""
        n = self.cfg.carve_points
        p = torch.randn(n, 3, device=device)
        p = p / p.norm(dim=-1, keepdim=True) * torch.rand(n, 1, device=device) ** (1 / 3)
        return p[self.carved(p) & ~self.below_support(p)]

    def classification_logits(self, point_sets: dict[str, list[torch.Tensor]],
                              device: torch.device) -> dict[str, torch.Tensor]:
        """Occupancy logits of several named point sets (each a list of (M_i, 3) tensors) by one field evaluation,
        split back per name."""
        parts = [p for ps in point_sets.values() for p in ps]
        every = torch.cat(parts)
        logits = self.model.occupancy(every) if every.shape[0] else torch.zeros(0, device=device)
        out, start = {}, 0
        for name, ps in point_sets.items():
            n = sum(p.shape[0] for p in ps)
            out[name] = logits[start : start + n]
            start += n
        return out

    def normal_loss(self, surface_points: torch.Tensor) -> torch.Tensor:
        """Normal smoothness at the hit points: finite-difference normals there vs at randomly jittered points."""
        p = surface_points.detach()
        n_at = finite_difference_normals(self.model.occupancy, p)
        n_near = finite_difference_normals(self.model.occupancy, p + 0.01 * torch.randn_like(p))
        return L.normal_smoothness_loss(n_at, n_near)

    def losses(self, step: int) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """The weighted loss of one batch and its terms and statistics (detached 0-d tensors: reading them waits for
        the device, so the loop reads them only when it logs). Each term is named after its :class:`LossWeights`
        field and logged unweighted; the total is Σ weight × term in the order below."""
        w = self.cfg.weights
        # random draws, in this order: pixels + march jitter, free-space depths, sparse depth, carving, normals
        batch = self.render_batch(step)
        dev = batch.origins.device
        free_pts, occupied_pts = self.freespace_points(batch), self.occupancy_points(batch)
        sparse = self.render_sparse_depth(step)
        empty = torch.zeros(0, 3, device=dev)
        logits = self.classification_logits({
            "freespace": [free_pts],
            "occupancy": [occupied_pts, empty if sparse is None else sparse.missed_points],
            "depth_free": [empty if sparse is None else sparse.free_points],
            "carve": [self.carve_points(dev)],
        }, dev)

        terms: dict[str, torch.Tensor] = {}
        if self.appearance is not None:
            terms["appearance"] = self.appearance.regulariser()
        brighter = self.appearance is not None or self.shading is not None  # the render can pass 1
        clipped = self.cfg.clipped_level if brighter else float("inf")
        terms["rgb"] = L.rgb_loss(batch.rendered_rgb, batch.observed_rgb, clipped)
        if batch.shading is not None:
            terms["shading"] = ViewShading.regulariser(batch.shading)
        terms["freespace"] = L.freespace_loss(logits["freespace"])
        terms["occupancy"] = L.occupancy_loss(logits["occupancy"])
        terms["depth"] = torch.zeros((), device=dev) if sparse is None else \
            L.depth_loss(sparse.rendered_depth, sparse.known_depth)
        terms["depth_free"] = L.freespace_loss(logits["depth_free"])
        terms["carve"] = L.freespace_loss(logits["carve"])
        if w.tv > 0:  # a pass over the whole grid and its gradient: only when it counts
            terms["tv"] = self.model.tv_loss()
        if w.normal > 0 and batch.surface_points.shape[0] > 0:
            terms["normal"] = self.normal_loss(batch.surface_points)
        total = sum(getattr(w, name) * term for name, term in terms.items())

        stats = {"psnr": L.psnr(batch.rendered_rgb, batch.observed_rgb)}
        stats.update({name: term.detach() for name, term in terms.items()})
        stats["hit_frac"] = batch.hit.float().mean()
        return total, stats

    def train_step(self, step: int) -> dict[str, torch.Tensor]:
        """One optimiser step; returns the batch's statistics as detached 0-d tensors (:meth:`losses`)."""
        if step == self.upsample_step:
            self._resize_grid(self.cfg.field.base_res)
        self.opt.zero_grad(set_to_none=True)
        total, stats = self.losses(step)
        if total.requires_grad:
            total.backward()  # a non-finite loss leaves non-finite gradients or none: both are refused below
        # guard: never let a non-finite loss or gradient reach the parameters (one wait for the device per step)
        grads = [p.grad for g in self.opt.param_groups for p in g["params"] if p.grad is not None]
        finite = all_finite([total, *grads])
        if bool(finite):
            self.opt.step()
            self.sched.step()
        else:
            self.skipped += 1
            with warnings.catch_warnings():  # the schedule follows the step count, skipped steps included
                warnings.simplefilter("ignore", UserWarning)
                self.sched.step()
        stats["loss"] = total.detach()
        return stats

    # ----------------------------------------------------------------- loop
    def preview(self, tag: str) -> None:
        """Write ``preview_<tag>.png``: a photo next to the field's rendering of it (views in turn)."""
        v = self.step % len(self.data.names)
        w, h = self.data.view_size(v)
        img, _ = render_view(self.model, self.data, v, scale=min(1.0, 256 / max(w, h)))
        gt = self.data.images[v, :h, :w].cpu().numpy()
        gt = cv2.resize(gt, (img.shape[1], img.shape[0]), interpolation=cv2.INTER_AREA)
        both = np.concatenate([gt, img.cpu().numpy()], axis=1)
        write_image(self.out / f"preview_{tag}.png", cv2.cvtColor((both * 255).clip(0, 255).astype(np.uint8),
                                                                  cv2.COLOR_RGB2BGR))

    def fit(self, stop_after: int | None = None) -> dict[str, float]:
        """Train until ``cfg.iterations`` (or ``stop_after`` steps in this call, for tests of resume)."""
        c = self.cfg
        log = open(self.out / "log.jsonl", "a")
        bar = tqdm(total=c.iterations, initial=self.step, disable=not c.progress, dynamic_ncols=True)
        last: dict[str, float] = {}
        n_done = 0
        t_last = time.perf_counter()
        rays_since = 0
        try:
            while self.step < c.iterations and (stop_after is None or n_done < stop_after):
                t0 = time.perf_counter()
                stats = self.train_step(self.step)
                self.elapsed += time.perf_counter() - t0
                self.step += 1
                n_done += 1
                rays_since += c.batch_rays
                last = stats
                if self.step % c.log_every == 0 or self.step == c.iterations:
                    stats = _floats(stats)
                    now = time.perf_counter()
                    stats["rays_per_s"] = rays_since / max(1e-9, now - t_last)
                    t_last, rays_since = now, 0
                    rec = {"step": self.step, "seconds": round(self.elapsed, 3), "skipped": self.skipped,
                           **{k: (None if isinstance(v, float) and math.isnan(v) else round(v, 6))
                              for k, v in stats.items()}}
                    log.write(json.dumps(rec) + "\n")
                    log.flush()
                    bar.set_postfix(loss=f"{stats['loss']:.4f}", psnr=f"{stats['psnr']:.1f}",
                                    rays_s=f"{stats['rays_per_s']:.0f}")
                bar.update(1)
                if self.step % c.checkpoint_every == 0 or self.step == c.iterations:
                    self.save_checkpoint()
                if c.preview_every and self.step % c.preview_every == 0:
                    self.preview(f"{self.step:06d}")
        finally:
            bar.close()
            log.close()
        return _floats(last)

    def write_appearance(self, path: Path) -> None:
        """The fitted per-view colour transforms, by image name: a gain per RGB channel."""
        gains = self.appearance.gains().cpu().numpy()
        rec = {name: {"gain": [round(float(x), 5) for x in g]} for name, g in zip(self.data.names, gains)}
        write_json(path, rec, indent=1)

    def finish(self) -> Path:
        """Write ``final.pt`` (weights + field config + scale_mat) and a last preview."""
        path = self.out / "final.pt"
        save_model(path, self.model, self.cfg.field, self.data.cams.scale_mat,
                   {"step": self.step, "elapsed": self.elapsed, "train_config": asdict(self.cfg)}, self.data.frame)
        if self.appearance is not None:
            self.write_appearance(self.out / "appearance.json")
        self.preview("final")
        return path


def all_finite(tensors: list[torch.Tensor]) -> torch.Tensor:
    """0-d bool tensor: True when every element of ``tensors`` is finite. A sum is NaN or ±Inf as soon as one
    element is (Inf − Inf is NaN), and reading each tensor once is a tenth of ``isfinite(t).all()``'s time on a
    large grid; finite values so large that their sum overflows count as non-finite too."""
    if not tensors:
        return torch.tensor(True)
    return torch.isfinite(torch.stack([t.detach().sum(dtype=torch.float32) for t in tensors]).sum())


def _floats(stats: dict[str, torch.Tensor | float]) -> dict[str, float]:
    """Statistics as plain floats (reading tensors waits for the device)."""
    return {k: float(v) for k, v in stats.items()}


def train(cfg: TrainConfig, data: SceneData, out_dir: Path, stop_after: int | None = None) -> Trainer:
    """Train (resuming from ``out_dir/checkpoint.pt`` when present) and return the trainer."""
    t = Trainer(cfg, data, out_dir)
    t.try_resume()
    t.fit(stop_after)
    if t.step >= t.cfg.iterations:  # the device's steps (device_schedule)
        t.finish()
    return t


__all__ = ["TrainConfig", "LossWeights", "Trainer", "train", "resolve_device"]
