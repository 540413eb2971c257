"""What a scene from photos loses against its ground truth, part by part, on the last arm `bench/pair.py` ran:

    python bench/pair.py cow --preset balanced --arm ""        # maps once, runs the pipeline in work/0
    python bench/parts.py cow --preset balanced --part gt-masks

Each part copies the arm's training workspace (``bench/runs/pairs/<scene>/work/0/ws``: SfM's cameras, automatic masks,
sparse depth), swaps one input for the truth, and runs training, mesh and texture again:

- ``as-is``: nothing swapped (reproduces the arm);
- ``gt-masks``: the generator's masks instead of the automatic ones;
- ``no-depth``: no sparse depth;
- ``gt-cameras``: the true cameras (brought into SfM's frame by the similarity of the camera centres) in training and
  the bake, without sparse depth (SfM's depths belong to its own cameras);
- ``gt-cameras-bake``: the arm's model and mesh, baked with the true cameras.

Prints held-out PSNR at the poses SfM gave the held-out photos and at their true poses (as the bench's rows), and
per held-out photo. Extra options (the CLI's spelling) go to every stage. ``--picture OUT.jpg --views 9 27``: each
view's photo next to the textured mesh ray-cast at its camera (white where it misses), cropped to the mesh.
"""
from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import evaluate as ev  # noqa: E402
from dvr.cameras import load_cameras, plane_in_frame, save_cameras  # noqa: E402
from dvr.data import list_images  # noqa: E402
from pipeline.stages import run_stage  # noqa: E402

PARTS = ("as-is", "gt-masks", "no-depth", "gt-cameras", "gt-cameras-bake")


class Truth:
    """The scene's true cameras of every photo the arm mapped, and the similarity true world → SfM frame."""

    def __init__(self, syn: Path, full: Path):
        train, held = load_cameras(syn / "gt" / "cameras.npz"), load_cameras(syn / "gt" / "heldout" / "cameras.npz")
        self.of = ev.true_cameras_of(train, held)
        self.held, self.names = held, [p.stem for p in list_images(full / "images")]
        self.est = load_cameras(full / "cameras.npz")
        _, _, (self.s, self.R, self.t) = ev.true_in_sfm_frame(train, held, self.names, self.est)

    def write_in_sfm_frame(self, names: list[str], like: Path, out: Path) -> None:
        """The true cameras of ``names`` in SfM's frame, with the scale_mat and support plane of ``like``."""
        ref = load_cameras(like)
        K, R, t = [], [], []
        for n in names:
            cams, i = self.of[n]
            rot = cams.R[i] @ self.R.T
            K.append(cams.K[i]), R.append(rot), t.append(-rot @ (self.s * self.R @ cams.sfm_centers[i] + self.t))
        ground = plane_in_frame(ref.ground, np.linalg.inv(ref.scale_mat))
        save_cameras(out, np.array(K), np.array(R), np.array(t), ref.scale_mat, ground)


def heldout_psnr(ws: Path, syn: Path, truth: Truth) -> tuple[list[float], list[float]]:
    """Held-out PSNR of the textured mesh at SfM's poses and at the true poses, per held-out photo."""
    tm, tex = ev.textured(ws)
    psnrs = ev.heldout_psnrs(tm, tex, sorted((syn / "gt" / "heldout" / "images").glob("*.png")),
                             syn / "gt" / "heldout" / "masks", truth.names, truth.est, truth.held,
                             (truth.s, truth.R, truth.t))
    return psnrs.at_sfm, psnrs.at_true


def swap(part: str, arm_ws: Path, ws: Path, syn: Path, truth: Truth) -> None:
    """``ws``: a copy of the arm's workspace with the part's input swapped for the truth."""
    shutil.rmtree(ws, ignore_errors=True)
    left = {"report", "report.html"} | (set() if part == "gt-cameras-bake" else {"model", "mesh"})
    shutil.copytree(arm_ws, ws, ignore=lambda d, names: left & set(names) if Path(d) == arm_ws else set())
    names = [p.stem for p in list_images(ws / "images")]
    if part == "gt-masks":
        for n in names:
            shutil.copy(syn / "gt" / "masks" / f"{n}.png", ws / "masks" / f"{n}.png")
    if part in ("no-depth", "gt-cameras"):
        shutil.rmtree(ws / "depth")
    if part in ("gt-cameras", "gt-cameras-bake"):
        truth.write_in_sfm_frame(names, ws / "cameras.npz", ws / "cameras.npz")


def picture(ws: Path, views: list[int], out: Path) -> None:
    """Photo | textured mesh at the training views ``views`` of ``ws``, in one row."""
    import cv2

    from pipeline.render.textured import render_textured

    tm, tex = ev.textured(ws)
    cams, paths = load_cameras(ws / "cameras.npz"), list_images(ws / "images")
    row = []
    for v in views:
        photo = cv2.imread(str(paths[v]))
        h, w = photo.shape[:2]
        img, hit = render_textured(tm.vertices, tm.faces, tm.visual.uv, tex, cams.K[v], cams.R[v],
                                   cams.sfm_centers[v], w, h)
        img = np.ascontiguousarray((np.clip(img, 0, 1) * 255).astype(np.uint8)[..., ::-1])
        img[~hit] = 255
        ys, xs = np.nonzero(hit) if hit.any() else ([0, h - 1], [0, w - 1])  # both cropped to the mesh, 8 px round
        y0, y1, x0, x1 = max(0, np.min(ys) - 8), min(h, np.max(ys) + 9), max(0, np.min(xs) - 8), min(w, np.max(xs) + 9)
        row += [photo[y0:y1, x0:x1], img[y0:y1, x0:x1]]
    height = max(t.shape[0] for t in row)
    row = [np.pad(t, ((0, height - t.shape[0]), (0, 0), (0, 0)), constant_values=255) for t in row]
    cv2.imwrite(str(out), np.concatenate(row, 1), [cv2.IMWRITE_JPEG_QUALITY, 88])
    print(f"picture: {out}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", choices=sorted(ev.SCENES))
    ap.add_argument("--part", choices=PARTS, required=True)
    ap.add_argument("--preset", default="default")
    ap.add_argument("--picture", type=Path, help="write photo | textured mesh of --views here")
    ap.add_argument("--views", type=int, nargs="+", default=[0])
    ap.add_argument("--reuse", action="store_true", help="measure the part's last run again, without re-running it")
    a, options = ap.parse_known_args()
    syn = ev.scene(a.scene, {})
    arm = ev.RUNS / "pairs" / syn.name / "work" / "0"
    full, ws = arm / "all", ev.RUNS / "work" / "parts" / syn.name / a.part
    if not (arm / "ws" / "mesh" / "textured.glb").exists():
        sys.exit(f"{arm}: no finished arm; run python bench/pair.py {a.scene} --preset {a.preset} --arm \"\" first")
    truth = Truth(syn, full)
    if not (a.reuse and (ws / "mesh" / "textured.glb").exists()):
        swap(a.part, arm / "ws", ws, syn, truth)
        cfg = ev.config(a.preset, options)
        for stage in ("texture",) if a.part == "gt-cameras-bake" else ("train", "mesh", "texture"):
            run_stage(stage, ws, cfg, force=True)
    at_sfm, at_true = heldout_psnr(ws, syn, truth)
    print(f"{a.scene} {a.preset} {a.part} {' '.join(options)}: held-out PSNR {np.mean(at_sfm):.2f} dB at SfM's poses, "
          f"{np.mean(at_true):.2f} at the true poses (per photo {', '.join(f'{x:.2f}' for x in at_sfm)})")
    if a.picture:
        picture(ws, a.views, a.picture)


if __name__ == "__main__":
    main()
