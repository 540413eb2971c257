"""The README's pictures.

    python bench/figures.py photos WS OUT.jpg        # four photo | textured-mesh pairs of a workspace's report
    python bench/figures.py glb GLB OUT.png          # the GLB as a glTF viewer opens it, from five sides
    python bench/figures.py reaim ARM SCENE --out OUT.png [--view 0]   # a held-out photo, its render, re-aimed

e.g. ``python bench/figures.py photos work/dtu_scan24 bench/results/dtu_scan24.jpg``,
``python bench/figures.py glb work/dtu_scan24/mesh/textured.glb bench/results/dtu_scan24_glb.png``,
``python bench/figures.py reaim bench/runs/pairs/cow/work/0 cow --view 0 --out bench/results/cow_reaim.png``
(after ``python bench/arms.py pair cow --arm ""``).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

ORBITS = ("0deg 75deg auto", "90deg 75deg auto", "180deg 75deg auto", "270deg 75deg auto", "0deg 5deg auto")
BELOW = ("0deg 95deg auto", "90deg 100deg auto", "180deg 100deg auto", "270deg 100deg auto", "45deg 120deg auto")
"""``glb --below``: four sides from just below the base's rim and once from further below (what stands on a table
should end flat there)."""
SIDE = 300


def picture(ws: Path, out: Path) -> None:
    """Four photo | textured-mesh pairs of a workspace's report (``report/render_view_*.png``), two by two, as one
    JPEG."""
    import cv2

    pairs = sorted((ws / "report").glob("render_view_*.png"))[:4]
    if len(pairs) < 4:
        sys.exit(f"{ws / 'report'}: fewer than four render_view_*.png (run the report stage first)")
    imgs = [cv2.imread(str(p)) for p in pairs]
    h = min(i.shape[0] for i in imgs)
    imgs = [cv2.resize(i, (round(i.shape[1] * h / i.shape[0]), h), interpolation=cv2.INTER_AREA) for i in imgs]
    w = max(i.shape[1] for i in imgs)
    imgs = [np.pad(i, ((0, 0), (0, w - i.shape[1]), (0, 0)), constant_values=255) for i in imgs]
    grid = np.concatenate([np.concatenate(imgs[:2], 1), np.concatenate(imgs[2:], 1)], 0)
    cv2.imwrite(str(out), grid, [cv2.IMWRITE_JPEG_QUALITY, 88])
    print(f"picture: {out}")


def glb_views(glb: Path, out: Path, orbits: tuple[str, ...] = ORBITS) -> None:
    """The GLB as a glTF viewer opens it (Google's model-viewer, the report's, in headless Chromium), from each of
    the camera ``orbits`` (by default four sides around its up axis and once from above), as one PNG: what a user
    sees on opening ``mesh/textured.glb``. Needs ``make setup-web`` (model-viewer) and Chromium; the screenshot waits
    until every viewer shows its model (``bench/glb_shot.mjs``)."""
    from pipeline.report.stage import VIEWER_JS, inlined_viewer

    if not VIEWER_JS.exists():
        sys.exit(f"{VIEWER_JS}: missing; run make setup-web")
    js, src = inlined_viewer(glb)
    style = f"width:{SIDE}px;height:{SIDE}px;background:#eee;flex:none"
    views = "".join(f'<model-viewer loading="eager" src="{src}" camera-orbit="{o}" style="{style}"></model-viewer>'
                    for o in orbits)
    with tempfile.TemporaryDirectory() as tmp:
        page = Path(tmp) / "views.html"
        page.write_text('<html><body style="margin:0;display:flex;overflow:hidden">'
                        f'<script type="module">{js}</script>{views}</body></html>')
        done = subprocess.run(["node", "--experimental-websocket", str(ROOT / "bench" / "glb_shot.mjs"), str(page),
                               str(out), str(SIDE * len(orbits)), str(SIDE)])
    if done.returncode:
        sys.exit(f"{glb}: no screenshot (above)")
    print(f"glb views: {out}")


def reaim_picture(arm: Path, scene: str, view: int, out: Path) -> None:
    """One held-out photo of a ``bench/arms.py pair`` arm (``arm``: its work folder, with all/ and ws/): the photo,
    the textured mesh at SfM's pose of it and re-aimed (:mod:`bench.reaim`), and each render's error against the
    photo (|difference| × 4), cropped to the object; the PSNRs printed."""
    import cv2

    from bench import evaluate as ev
    from bench.reaim import degrees_turned, reaim
    from dvr.cameras import load_cameras
    from dvr.data import list_images
    from pipeline.render.textured import TexturedCaster

    syn = ev.scene(scene, {})
    tm, tex = ev.textured(arm / "ws")
    est, names = load_cameras(arm / "all" / "cameras.npz"), [p.stem for p in list_images(arm / "all" / "images")]
    path = sorted((syn / "gt" / "heldout" / "images").glob("*.png"))[view]
    photo, mask = ev._read_rgb(path), ev._read_mask(syn / "gt" / "heldout" / "masks" / path.name)
    k = names.index(f"{ev.HELDOUT}{path.stem}")
    caster = TexturedCaster(tm.vertices, tm.faces, tm.visual.uv, tex)
    h, w = photo.shape[:2]
    at_sfm = caster.render(est.K[k], est.R[k], est.sfm_centers[k], w, h)
    Rd, *aimed = reaim(caster, est.K[k], est.R[k], est.sfm_centers[k], photo, mask)
    tiles = [photo]
    for name, (img, hit) in (("SfM's pose", at_sfm), ("re-aimed", aimed)):
        print(f"{path.name} {name}: {ev.image_psnr(img, hit, photo, mask):.2f} dB")
        tiles.append(img)
    for img, hit in (at_sfm, aimed):
        tiles.append(np.clip(4 * np.abs(img - photo) * (mask | hit)[..., None], 0, 1))
    ys, xs = np.nonzero(mask | at_sfm[1])
    y0, y1, x0, x1 = max(0, ys.min() - 8), min(h, ys.max() + 9), max(0, xs.min() - 8), min(w, xs.max() + 9)
    row = np.concatenate([t[y0:y1, x0:x1] for t in tiles], 1)
    cv2.imwrite(str(out), (row * 255).round().astype(np.uint8)[..., ::-1])
    print(f"picture: {out} (re-aimed by {degrees_turned(Rd):.3f}°)")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="bench/figures.py", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="command", required=True)
    p = sub.add_parser("photos", help="four photo | textured-mesh pairs of a workspace's report, as one JPEG")
    p.add_argument("ws", type=Path, help="a workspace whose report stage has run")
    p.add_argument("out", type=Path, help="the JPEG to write")
    g = sub.add_parser("glb", help="the GLB in a glTF viewer (model-viewer, headless Chromium), five sides, one PNG")
    g.add_argument("glb", type=Path, help="a textured GLB (mesh/textured.glb)")
    g.add_argument("out", type=Path, help="the PNG to write")
    g.add_argument("--below", action="store_true", help="from below the base's rim instead (bench/figures.py BELOW)")
    r = sub.add_parser("reaim", help="photo | mesh at SfM's pose | re-aimed | their errors, one held-out view")
    r.add_argument("arm", type=Path, help="a bench/arms.py pair arm's work folder (bench/runs/pairs/<scene>/work/<k>)")
    r.add_argument("scene")
    r.add_argument("--view", type=int, default=0)
    r.add_argument("--out", type=Path, required=True)
    a = ap.parse_args(argv)
    if a.command == "photos":
        picture(a.ws, a.out)
    elif a.command == "glb":
        glb_views(a.glb, a.out, BELOW if a.below else ORBITS)
    else:
        reaim_picture(a.arm, a.scene, a.view, a.out)


if __name__ == "__main__":
    main()
