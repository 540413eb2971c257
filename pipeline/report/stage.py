"""Stage ``report``: a self-contained ``report.html`` (+ PNG plots in ``report/``).

Per-stage seconds, the SfM summary, mask overlays, loss and PSNR curves, renders of the textured mesh next
to the photos (and next to held-out photos when the workspace has ``gt/heldout``), and the mesh in an
interactive viewer: Google's model-viewer, installed from npm (``make setup-web``) and inlined — no CDN.
Without it the report says so and shows the static renders only.
"""

from __future__ import annotations

import base64
import html
import json
import time
from pathlib import Path

import cv2
import numpy as np

from dvr.atomic import atomic_file, write_image, write_text
from pipeline.messages import size_in_words
from pipeline.workspace import Done, Job, Workspace

VIEWER_JS = Path(__file__).resolve().parents[2] / "node_modules" / "@google" / "model-viewer" / "dist" / \
    "model-viewer.min.js"


def inlined_viewer(glb: Path) -> tuple[str, str]:
    """(model-viewer's script, with every "</script" escaped so that it can sit inside a <script> element; the
    GLB ``glb`` as a data URI): a page that shows the GLB with nothing fetched."""
    js = VIEWER_JS.read_text().replace("</script", "<\\/script")
    return js, "data:model/gltf-binary;base64," + base64.b64encode(glb.read_bytes()).decode()


def _png_b64(img_rgb: np.ndarray) -> str:
    ok, buf = cv2.imencode(".png", cv2.cvtColor(img_rgb, cv2.COLOR_RGB2BGR))
    return "data:image/png;base64," + base64.b64encode(buf.tobytes()).decode()


def _jpg_b64(path: Path, max_side: int = 320) -> str:
    img = cv2.imread(str(path))
    s = max_side / max(img.shape[:2])
    if s < 1:
        img = cv2.resize(img, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 85])
    return "data:image/jpeg;base64," + base64.b64encode(buf.tobytes()).decode()


def curves(log: Path, out: Path) -> Path | None:
    """Loss and PSNR against step → PNG."""
    if not log.exists():
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rec = []
    for line in log.read_text(errors="replace").splitlines():
        try:
            rec.append(json.loads(line))
        except ValueError:  # a line a kill cut short (the trainer drops it when it resumes)
            continue
    rec = [r for r in rec if isinstance(r, dict) and "step" in r]
    if not rec:
        return None
    step = [r["step"] for r in rec]
    fig, ax = plt.subplots(1, 2, figsize=(9, 3.2))
    for k in ("loss", "rgb", "freespace", "occupancy", "carve", "depth"):
        v = [r.get(k) for r in rec]
        if any(x is not None and x > 0 for x in v):
            ax[0].plot(step, [np.nan if x is None else x for x in v], label=k)
    ax[0].set_yscale("log")
    ax[0].set_xlabel("step")
    ax[0].legend(fontsize=7)
    ax[0].set_title("losses")
    ax[1].plot(step, [r.get("psnr") or np.nan for r in rec])
    ax[1].set_xlabel("step")
    ax[1].set_title("training PSNR (dB)")
    fig.tight_layout()
    with atomic_file(out) as f:
        fig.savefig(f, format="png", dpi=100)
    plt.close(fig)
    return out


def renders(ws: Workspace, n: int = 4, out_dir: Path | None = None) -> list[tuple[str, str, float]]:
    """(photo, render, masked PSNR) for a few views: the textured mesh ray-cast at the photos' cameras.

    With ``out_dir``, each photo | render pair is also written there as ``render_<tag>_<view>.png``.
    """

    from dvr.cameras import load_cameras, to_sfm
    from dvr.data import list_images, read_mask, read_rgb
    from dvr.metrics import masked_psnr
    from pipeline.render.textured import render_textured
    from pipeline.texture.export import read_textured

    glb = ws.mesh / "textured.glb"
    if not glb.exists():
        return []
    sets = [(ws.images, ws.masks, ws.cameras, "view")]
    held = ws.root / "gt" / "heldout"
    if (held / "cameras.npz").exists() and not (ws.root / "sfm").exists():  # GT frame == workspace frame
        sets.insert(0, (held / "images", held / "masks", held / "cameras.npz", "held-out"))
    tm, tex = read_textured(glb)
    out = []
    for img_dir, mask_dir, cam_file, tag in sets:
        paths = list_images(img_dir)
        cams = load_cameras(cam_file, n_views=len(paths))
        for i in np.linspace(0, len(paths) - 1, min(n, len(paths))).round().astype(int):
            photo = read_rgb(paths[i])
            h, w = photo.shape[:2]
            img, hit = render_textured(tm.vertices, tm.faces, tm.visual.uv, tex, cams.K[i], cams.R[i],
                                       to_sfm(cams.centers[i], cams.scale_mat), w, h)
            mp = mask_dir / f"{paths[i].stem}.png"
            m = read_mask(mp) > 0 if mp.exists() else hit
            m = m | hit if m.shape == hit.shape else hit  # masks of another image size (images/ redone): the mesh
            p = masked_psnr(img, photo, m)
            pair = (np.concatenate([photo, img], 1) * 255).round().astype(np.uint8)
            if out_dir is not None:
                write_image(out_dir / f"render_{tag.replace('-', '')}_{paths[i].stem}.png",
                            cv2.cvtColor(pair, cv2.COLOR_RGB2BGR))
            out.append((f"{tag} {paths[i].stem}", _png_b64(pair), p))
        if tag == "held-out":
            break
    return out


def rung_in_words(rung: dict) -> str:
    """One rung of the cameras stage's stamp (``rungs``) in words: what it registered in how long, or why not."""
    if "skipped" in rung:
        return f"{rung['rung']}: not tried ({rung['skipped']})"
    return (f"{rung['rung']}: {rung.get('registered', 0)} registered in {rung.get('seconds', 0)} s"
            + (f", {len(rung['dropped'])} views with wrong poses dropped" if rung.get("dropped") else "")
            + (f", rejected ({rung['rejected']} poses not credible or not agreeing)" if rung.get("rejected") else "")
            + (f", {rung['error']}" if rung.get("error") else ""))


def capture_section(ws: Workspace, cameras_stamp: dict) -> str:
    """SfM (the ladder's rungs) and the support plane, in words."""
    out = ["<h2>Cameras and support</h2><ul>"]
    video = cameras_stamp.get("video")
    if video:
        out.append(f"<li>From the video {html.escape(video['clip'])}: {video['taken']} of its "
                   f"{video['frames_in_clip']} frames, the sharpest of each equal stretch of it (frames/, "
                   "frames/frames.json).</li>")
    if cameras_stamp.get("rungs"):
        steps = "; ".join(rung_in_words(r) for r in cameras_stamp["rungs"])
        out.append(f"<li>SfM ladder: {html.escape(steps)} → kept <b>{html.escape(str(cameras_stamp.get('rung')))}</b>"
                   "</li>")
    object_note = cameras_stamp.get("object_matches")  # the object's matches verified again (large photos)
    for note in (cameras_stamp.get("final_adjustment") or []) + ([object_note] if object_note else []):
        out.append(f"<li>{html.escape(note[0].upper() + note[1:])}</li>")
    doubtful = cameras_stamp.get("unexplained_pairs") or []
    if doubtful:
        a, b, n, e = doubtful[0]
        out.append(f"<li><b>Cameras in doubt</b>: the model explains {e} of the {n} verified matches of "
                   f"{html.escape(a)} with {html.escape(b)}" + (f" ({len(doubtful) - 1} more such pairs)" if
                                                                 len(doubtful) > 1 else "")
                   + ": a group of photos may be posed at the wrong side of the object.</li>")
    if cameras_stamp.get("rejoined"):
        out.append("<li><b>Cameras mapped again</b>: the first model posed a group of photos at the wrong side of the "
                   "object (a pair of photos' matches showed it); the model mapped again explains them, but part of "
                   "the group can still be off: look at the mesh.</li>")
    spread = cameras_stamp.get("exposure_spread")
    if spread is not None:
        out.append(f"<li>The photos' exposure differs by {100 * spread:.1f} % (per-view gains measured on the SfM "
                   "points' colours, exposure.json); the masks' stereo compares the photos evened out by them.</li>")
    board = cameras_stamp.get("board") or {}
    from_board = board.get("poses_from") == "board"
    if from_board:
        out.append(f"<li>SfM could not pose the photos ({html.escape(str(board.get('sfm_failed', '')))}); the printed "
                   f"board posed {board.get('views')}/{board.get('photos')} of them instead (corners fit to "
                   f"{board.get('rms_px')} px, focal {board.get('focal_px')} px): cameras and mesh in metres, no "
                   "SfM points, no sparse depth.</li>")
    ground = None
    if ws.cameras.exists():
        z = np.load(ws.cameras)
        ground = z["ground_plane"] if "ground_plane" in z.files else None
    sup = cameras_stamp.get("support")
    if ground is not None:
        on_it = f"the board's plane, {sup['inliers']} of its corners" if from_board and sup else \
            f"{sup['inliers']} SfM points on it" if sup else ""
        detail = f": {on_it}, the object stands {sup['object_height']:.2f} unit-sphere radii high on it" if sup else ""
        out.append(f"<li>support plane found{detail} (normal {np.round(ground[:3], 3).tolist()} in the SfM frame). "
                   "It is background for the masks (orange outline in the overlays), nothing below it is object, "
                   "and the mesh is closed flat where the object touches it.</li>")
        footprint = (ws.stamp("masks") or {}).get("footprint")
        if footprint is not None:
            points = "its sparse points on the plane, widened"
            # True: an older workspace's stamp, from a masks stage whose only source was the sparse points
            source = {"sparse points": points, True: points,
                      "masks' hull": "the visual hull of the first masks: too few sparse points on the object",
                      "sparse points and masks' hull": f"{points}, united with the visual hull of the first masks"}
            out.append("<li>" + (f"automatic masks: every pixel that sees past the object's footprint "
                                 f"({source.get(footprint, footprint)}) is background, the table in front of it too."
                                 if footprint else "automatic masks: no footprint of the object could be built; the "
                                 "floor near it is left to GrabCut's colours.") + "</li>")
    else:
        out.append("<li>no support plane: the object is not standing on a textured surface the SfM points show "
                   "(held, hung, or on a plain backdrop); masks and mesh as without one.</li>")
    out += saliency_note(ws.stamp("masks") or {})
    return "".join(out) + "</ul>"


def saliency_note(masks_stamp: dict) -> list[str]:
    """The report's line on the salient-object model in the automatic masks, from the masks stage's stamp: the
    share of the masks' area it saw beyond them (its check) and whether it voted; none for masks made without it."""
    beyond, voted = masks_stamp.get("salient_beyond"), masks_stamp.get("saliency")
    if beyond is None:
        return ["<li>automatic masks made with the salient-object model's vote (masks.saliency).</li>"] if voted else []
    seen = f"the salient-object model saw {100 * beyond:.1f} % of the first masks' area beyond them in three of four " \
        "of the photos it looked at"
    if voted:
        return [f"<li>automatic masks made again with the salient-object model's vote: {seen}.</li>"]
    return [f"<li>automatic masks checked against the salient-object model: {seen}; kept as the geometry made "
            "them.</li>"]


def appearance_choice(ws: Workspace) -> str:
    """Why the train stage turned the per-view appearance on or off when it was left to decide (``auto``), from
    its stamp; "" when it was asked for (on, off) or the stage has not run."""
    why = ((ws.stamp("train") or {}).get("appearance")) or {}
    if not why.get("auto"):
        return ""
    if why.get("spread") is None:
        return ("Per-view appearance off (auto): no SfM points to measure the photos' exposure on (given "
                "cameras); <code>--train.appearance on</code> turns it on.")
    word = "on" if why.get("appearance") == "on" else "off"
    return (f"Per-view appearance {word} (auto): the photos' exposure differs by {100 * why['spread']:.1f} % "
            f"(measured on the SfM points' colours, <code>exposure.json</code>), "
            f"{'above' if word == 'on' else 'within'} {100 * why.get('threshold', 0.05):.0f} %.")


def appearance_section(ws: Workspace) -> str:
    """The per-view exposure and white balance fitted in training (``model/appearance.json``), as a table; without
    it, the auto decision that left it off (:func:`appearance_choice`)."""
    path = ws.model / "appearance.json"
    choice = appearance_choice(ws)
    if not path.exists():
        return f"<h2>Per-view appearance</h2><p>{choice}</p>" if choice else ""
    from pipeline.errors import StageError
    from pipeline.texture.appearance import read_appearance, relative_looks

    try:
        looks = read_appearance(path)
    except StageError as exc:
        return f"<h2>Per-view appearance</h2><p>{html.escape(str(exc))}</p>"
    if not looks:
        return ""
    rel_of, common = relative_looks(looks)
    rel = np.stack(list(rel_of.values()))
    rows = "".join(f"<tr><td>{html.escape(n)}</td>" + "".join(f"<td>{g:.3f}</td>" for g in r) + "</tr>"
                   for n, r in rel_of.items())
    return (f"<h2>Per-view appearance</h2><p>{choice + ' ' if choice else ''}"
            f"Exposure and white balance fitted per photo: a gain per channel, "
            f"relative to the average view (the texture is baked from the photos with these undone). Relative "
            f"gains range {rel.min():.2f}–{rel.max():.2f}; the part common to all views, "
            f"{' / '.join(f'{c:.3f}' for c in common)} (R / G / B), stays in the texture.</p><table><tr><th>photo"
            f"</th><th>gain R</th><th>gain G</th><th>gain B</th></tr>{rows}</table>")


def readable(value, nested: bool = False) -> str:
    """A stage's record as a person reads it: ``key: value`` pairs, numbers to four significant digits, short lists of
    numbers as they are, longer lists and lists of records by their length (the full record stays in the raw JSON
    beside it)."""
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return str(value)
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, dict):
        inner = ", ".join(f"{k}: {readable(v, True)}" for k, v in value.items())
        return f"({inner})" if nested else inner
    if isinstance(value, (list, tuple)):
        if not value:
            return "none"
        if len(value) <= 4 and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
            return "[" + ", ".join(readable(v) for v in value) + "]"
        return f"{len(value)} entr{'y' if len(value) == 1 else 'ies'}"
    return str(value)


def stage_row(stage: str, seconds: float, record: dict) -> str:
    """One row of the report's stage table: the record readable, its raw JSON folded away beneath."""
    return (f"<tr><td>{stage}</td><td>{seconds:.1f}</td><td>{html.escape(readable(record))}"
            f"<details><summary>raw</summary><code>{html.escape(json.dumps(record))}</code></details></td></tr>")


def size_paragraph(texture_stamp: dict) -> str:
    """The object's size as the texture stage measured it (millimetres with a printed board, else that the scale is
    arbitrary); empty for a stamp without it."""
    size = texture_stamp.get("object_size")
    if not size:
        return ""
    return f"<p>Size: {html.escape(size_in_words(size, size.get('units') == 'metres'))}.</p>"


INLINED_LEVELS_BYTES = 20_000_000
"""The detail levels' GLBs inlined in the report (so its viewer can show them) up to this many bytes in all,
lightest first; heavier ones are named by their file."""


def levels_paragraph(texture_stamp: dict, mesh_dir: Path | None = None, viewer: bool = False) -> str:
    """The detail levels the texture stage wrote besides the default mesh: faces and GLB size of each, and where it
    is; with the ``viewer`` on the page, a button per level that shows it there (its GLB, under ``mesh_dir``,
    inlined while :data:`INLINED_LEVELS_BYTES` allows). Empty without levels."""
    levels = texture_stamp.get("levels") or {}
    if not levels:
        return ""
    sources, budget = {}, INLINED_LEVELS_BYTES
    for name, lv in sorted(levels.items(), key=lambda kv: kv[1]["glb_bytes"]):
        glb = None if mesh_dir is None else mesh_dir / "levels" / name / "textured.glb"
        if viewer and glb is not None and glb.exists() and lv["glb_bytes"] <= budget:
            sources[name] = "data:model/gltf-binary;base64," + base64.b64encode(glb.read_bytes()).decode()
            budget -= lv["glb_bytes"]

    def show(name: str) -> str:
        if name in sources or (name == "default" and viewer):
            return f'<button onclick="showLevel({html.escape(json.dumps(name))})">show</button>'
        return "open the file" if viewer else ""

    rows = "".join(f"<tr><td>{html.escape(name)}</td><td>{lv['faces']}</td><td>{lv['glb_bytes'] / 1e6:.1f} MB</td>"
                   f"<td>mesh/levels/{html.escape(name)}/textured.glb</td><td>{show(name)}</td></tr>"
                   for name, lv in levels.items())
    main = f"<tr><td>default</td><td>{texture_stamp.get('faces', '–')}</td><td>" + (
        f"{texture_stamp['glb_bytes'] / 1e6:.1f} MB" if "glb_bytes" in texture_stamp else "–") + \
        f"</td><td>mesh/textured.glb</td><td>{show('default')}</td></tr>"
    script = ""
    if viewer:  # the default mesh's source is the viewer's own, kept when another level is shown
        script = ("<script>const levelSources = " + json.dumps(sources) + ";"
                  "function showLevel(name) { const v = document.getElementById('viewer');"
                  " if (!levelSources.default) levelSources.default = v.src;"
                  " v.src = levelSources[name]; document.getElementById('level-shown').textContent = name; }"
                  "</script><p>In the viewer: <b id=\"level-shown\">default</b></p>")
    return ("<h3>Detail levels</h3><table><tr><th>level</th><th>faces</th><th>GLB</th><th>file</th><th>viewer</th>"
            f"</tr>{main}{rows}</table>{script}")


def build(ws: Workspace, stage_order: tuple[str, ...], stats: dict | None = None) -> str:
    """The self-contained HTML of the report: stage table (its rows in ``stage_order``), capture, masks, training
    curves, renders, viewer. ``stats`` (when given) receives the mean PSNR of the renders: ``psnr`` and ``psnr_views``
    (held-out or training)."""
    secs = ws.seconds()
    stamps = {}
    for p in sorted(ws.stages.glob("*.json")) if ws.stages.exists() else []:
        stamp = ws.stamp(p.stem)  # None for a damaged stamp: that stage counts as not done
        if stamp is not None:
            stamps[p.stem] = stamp
    rep = ws.root / "report"
    rep.mkdir(exist_ok=True)
    parts = [f"<h1>Reconstruction report: {html.escape(ws.root.name)}</h1>",
             f"<p>generated {time.strftime('%Y-%m-%d %H:%M')}</p>", "<h2>Stages</h2><table><tr><th>stage</th>"
             "<th>seconds</th><th>details</th></tr>"]
    for st in stage_order:
        if st in stamps:
            det = {k: v for k, v in stamps[st].items() if k not in ("config", "seconds", "finished")}
            parts.append(stage_row(st, secs.get(st, 0), det))
        elif ws.unfinished(st) and st != "report":  # the report's own marker: this is that run
            parts.append(f"<tr><td>{st}</td><td>–</td><td><b>last run did not finish</b>: rerun it</td></tr>")
    parts.append(f"<tr><td><b>total</b></td><td><b>{sum(secs.values()):.1f}</b></td><td></td></tr></table>")
    parts.append(capture_section(ws, stamps.get("cameras", {})))
    glb = ws.mesh / "textured.glb"
    if glb.exists():
        parts.append("<h2>Mesh</h2>")
        parts.append(size_paragraph(stamps.get("texture") or {}))
        if VIEWER_JS.exists():
            js, src = inlined_viewer(glb)
            parts.append(f'<script type="module">{js}</script>'
                         f'<model-viewer id="viewer" src="{src}" camera-controls auto-rotate shadow-intensity="0.5" '
                         'style="width:720px;height:540px;background:#eee"></model-viewer>')
        else:
            parts.append("<p>(interactive viewer: run <code>make setup-web</code> to install model-viewer, then "
                         "rerun the report stage)</p>")
        parts.append(levels_paragraph(stamps.get("texture") or {}, ws.mesh, VIEWER_JS.exists()))
    ren = renders(ws, out_dir=rep)
    if stats is not None and ren:  # the mean PSNR of the held-out views when there are any, else the photos'
        tag_of = "held-out" if ren[0][0].startswith("held-out") else "view"
        stats.update(psnr=float(np.mean([p for tag, _, p in ren if tag.startswith(tag_of)])),
                     psnr_views="held-out" if tag_of == "held-out" else "training")
    if ren:
        parts.append("<h2>Photos (left) and the textured mesh (right)</h2>")
        for tag, uri, p in ren:
            parts.append(f'<figure><img src="{uri}"><figcaption>{html.escape(tag)}: PSNR {p:.2f} dB (object '
                         "pixels)</figcaption></figure>")
    parts.append(appearance_section(ws))
    c = curves(ws.model / "log.jsonl", rep / "curves.png")
    if c:
        parts.append(f'<h2>Training</h2><img src="{_png_b64(cv2.cvtColor(cv2.imread(str(c)), cv2.COLOR_BGR2RGB))}">')
    ov = sorted((ws.masks / "overlays").glob("*.jpg")) if (ws.masks / "overlays").exists() else []
    if ov:
        conf = json.loads((ws.masks / "confidence.json").read_text()) if (ws.masks / "confidence.json").exists() else {}
        parts.append("<h2>Masks</h2><div>")
        for p in ov[:: max(1, len(ov) // 12)]:
            parts.append(f'<figure style="display:inline-block"><img src="{_jpg_b64(p)}"><figcaption>{p.stem} '
                         f"confidence {conf.get(p.stem, float('nan')):.2f}</figcaption></figure>")
        parts.append("</div>")
    style = ("body{font-family:sans-serif;margin:2em}table{border-collapse:collapse}td,th{border:1px solid #ccc;"
             "padding:4px 8px}code{font-size:80%}")
    return f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(ws.root.name)}</title>" \
           f"<style>{style}</style></head><body>{''.join(parts)}</body></html>"


def run(job: Job) -> Done:
    """Stage ``report`` (called by :func:`pipeline.stages.run_stage`, always): report.html from what the
    workspace holds so far."""
    stats: dict = {}
    doc = build(job.ws, job.stage_order, stats)
    out = job.ws.root / "report.html"
    write_text(out, doc)
    print(f"report: {out} ({len(doc) / 1e6:.1f} MB)")
    return Done(stats)

