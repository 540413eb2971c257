"""The benchmark's outputs: the tables of docs/benchmarks.md (reconstruction, cameras), the accuracy-against-time
plot and the findings (what each knob costs and buys, the Pareto fronts)."""

from __future__ import annotations

import re
from pathlib import Path

# The versions of the pipeline's defaults a reconstruction row can have trained with (run.py stamps each row it runs
# with the latest; a row without a stamp is version 1), each with the default it adds and the presets it changes
# (None: every preset; a preset that sets those options itself keeps its rows); rows a later version changes are
# marked † in the table and in the findings until they are run again.
DEFAULTS_CHANGES: dict[int, tuple[str, tuple[str, ...] | None]] = {
    2: ("`train.carve_min_views` 2, the hull and its carving term need two masks", None),
    3: ("`train.carve_sparse_views` 5, one mask carves where fewer than 5 views see a point", None),
    4: ("`train.iterations` 1000 at twice the learning rates, `train.lr_grid` 0.04 and `train.lr_mlp` 0.004",
        ("default", "fast")),
}
DEFAULTS_VERSION = max(DEFAULTS_CHANGES)
STALE_NOTE = (f"† trained with older defaults, before version {DEFAULTS_VERSION} "
              f"({DEFAULTS_CHANGES[DEFAULTS_VERSION][0]}); not comparable with rows without †, to be run again.")


def is_stale(r: dict) -> bool:
    """True when a later version of the defaults than the one row ``r`` trained with changes its preset."""
    version, preset = r.get("defaults", 1), r.get("preset", "default")
    return any(version < v and (presets is None or preset in presets)
               for v, (_, presets) in DEFAULTS_CHANGES.items())


COLORS = {"cow": "tab:orange", "jar": "tab:green", "book": "tab:purple", "cow_float": "tab:blue", "dtu": "tab:red"}


def pareto(points: list[tuple[float, ...]]) -> list[int]:
    """Indices of the points no other point dominates (every coordinate ≤, one <; all to be minimised)."""
    return [i for i, p in enumerate(points)
            if not any(all(a <= b for a, b in zip(q, p)) and any(a < b for a, b in zip(q, p)) for q in points)]


def _objectives(r: dict) -> tuple[float, ...]:
    """(seconds, Chamfer, −PSNR): accuracy is both the geometry and the appearance a user sees."""
    return (r["total_s"], r["chamfer_rel"] if r["chamfer_rel"] is not None else 0.0, -r["psnr"])


def label(r: dict) -> str:
    """A run's name in the tables: its knob (with the preset when that is not the default), condition or preset."""
    if r.get("knob") and r.get("preset", "default") != "default":
        return f"{r['knob']} ({r['preset']})"
    return r.get("knob") or r.get("condition") or r["preset"]


def stale(*rows: dict) -> str:
    """" †" when a later version of the defaults changes any of ``rows`` (:func:`is_stale`), else ""."""
    return " †" if any(is_stale(r) for r in rows) else ""


def reconstructions(results: list[dict]) -> list[dict]:
    return [r for r in results if r.get("kind", "reconstruct") == "reconstruct"]


def plot(results: list[dict], out: Path, mach: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = [r for r in reconstructions(results) if "error" not in r]
    fig, ax = plt.subplots(1, 2, figsize=(12, 4.8))
    for scene, color in COLORS.items():
        for cams, mk in (("gt", "o"), ("sfm", "s")):
            rs = sorted([r for r in ok if r["scene"] == scene and r["cameras"] == cams], key=lambda r: r["total_s"])
            if not rs:
                continue
            lab = f"{scene} ({'GT cameras + masks' if cams == 'gt' else 'photos only: COLMAP + auto masks'})"
            front = pareto([_objectives(r) for r in rs])
            for k, (key, scale, name) in enumerate((("chamfer_rel", 100, "Chamfer, % of GT diagonal ↓"),
                                                      ("psnr", 1, "held-out PSNR, dB ↑"))):
                pts = [(r["total_s"], r[key] * scale) for r in rs if r[key] is not None]
                if not pts:
                    continue
                a = ax[k]
                a.plot(*zip(*pts), mk + ("-" if cams == "gt" else ":"), color=color, alpha=0.7, label=lab)
                for i in front:
                    if rs[i][key] is not None:
                        a.plot(rs[i]["total_s"], rs[i][key] * scale, "*", ms=15, color=color, markeredgecolor="k")
                for r, (x, y) in zip([r for r in rs if r[key] is not None], pts):
                    a.annotate(label(r), (x, y), fontsize=6, xytext=(3, 3), textcoords="offset points")
                a.set_xlabel("seconds, all stages")
                a.set_ylabel(name)
                a.set_xscale("log")
                if key == "chamfer_rel":
                    a.set_yscale("log")
    ax[0].legend(fontsize=6)
    fig.suptitle(f"accuracy against time (★ Pareto front of time, Chamfer and PSNR, per scene and cameras) — "
                 f"{mach.get('model')}, {mach.get('torch_threads')} threads"
                 f"{', ' + mach['gpu'] if 'gpu' in mach else ''}",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def _fmt(v, f):
    return "–" if v is None or v != v else f.format(v)


def _pose(r: dict) -> str:
    pose = r.get("pose")
    pe = f"{100 * pose['center_err_rel_max']:.2f} / {pose['rot_err_deg_mean']:.2f}" if pose else "–"
    return pe + (f" ({r['registered']})" if r.get("registered") and pose else "")


def _psnr(r: dict) -> str:
    txt = _fmt(r["psnr"], "{:.1f}")
    if r.get("psnr_gt_pose") is not None:
        txt += f" ({r['psnr_gt_pose']:.1f} at GT pose)"
    if r.get("psnr_reaimed") is not None:  # each held-out view turned about its centre onto its photo
        txt += f"; re-aimed {r['psnr_reaimed']:.1f}"
    if r.get("psnr_train") is not None:
        txt += f" (training views {r['psnr_train']:.1f})"
    if r.get("psnr_train_gain_fit") is not None:  # DTU: each photo's own exposure, fitted
        txt += f"; each photo's gains fitted: {r['psnr_gain_fit']:.1f} (training views {r['psnr_train_gain_fit']:.1f})"
    return txt


def table(results: list[dict], mach: dict) -> str:
    lines = [f"Machine: {mach.get('model')}, {mach.get('cores')} cores, {mach.get('torch_threads')} torch threads"
             f"{', GPU ' + mach['gpu'] if 'gpu' in mach else ', no GPU'}.", "",
             "| scene | cameras | preset / knob | total s | cameras+masks s | train s | mesh+texture s | mask IoU "
             "| Chamfer % | F@1 % | held-out PSNR dB | pose err (centre % / rot °) | peak RSS GB |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in reconstructions(results):
        cams = "GT" if r["cameras"] == "gt" else "photos only"
        if "error" in r:
            lines.append(f"| {r['scene']} | {cams} | {label(r)} | failed: {r['error'].split(' (')[0]} |||||||||")
            continue
        s = r["seconds"]
        ch = None if r["chamfer_rel"] is None else 100 * r["chamfer_rel"]
        lines.append(
            f"| {r['scene']} | {cams} | {label(r)}{stale(r)} | {r['total_s']:.0f} | "
            f"{s.get('cameras', 0) + s.get('masks', 0) + s.get('depth', 0):.0f} | {s.get('train', 0):.0f} | "
            f"{s.get('mesh', 0) + s.get('texture', 0):.0f} | {_fmt(r.get('mask_iou'), '{:.3f}')} | "
            f"{_fmt(ch, '{:.2f}')} | {_fmt(r['fscore'], '{:.3f}')} | {_psnr(r)} | {_pose(r)} | "
            f"{r['peak_rss_gb']:.2f} |")
    if any(stale(r) for r in reconstructions(results)):
        lines += ["", STALE_NOTE]
    return "\n".join(lines)


def cameras_table(results: list[dict]) -> str:
    rows = [r for r in results if r.get("kind") == "cameras"]
    if not rows:
        return ""
    lines = ["| capture condition | rung | registered | pose err (centre % of orbit / rot °) | seconds "
             "| support plane |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['condition']} | failed: {r['error']} |||||")
            continue
        pose = r.get("pose")
        pe = f"{100 * pose['center_err_rel_max']:.2f} / {pose['rot_err_deg_mean']:.2f}" if pose else \
            "stopped with a clear error" if r.get("stopped") else "–"
        sup = r.get("support")
        sp = f"{sup['inliers']} points, object {sup['object_height']:.2f} high" if sup else "none"
        if r.get("metric"):  # a printed board: metres, no alignment
            mt = r["metric"]
            pe += f"; in metres: centres {mt['centre_err_mm_mean']:.1f} mm off (max {mt['centre_err_mm_max']:.1f}), " \
                  f"scale ×{mt['scale']:.4f}"
        climbed = " → ".join(x["rung"] for x in r.get("rungs") or [])
        rung = r.get("rung") or "–"
        rung = f"{rung} ({climbed})" if climbed else "board (SfM failed)" if rung == "board" else rung
        lines.append(f"| {r['condition']} | {rung} | {r['registered']} | {pe} | "
                     f"{r['seconds'].get('cameras', 0):.0f} | {sp} |")
    return "\n".join(lines)


REAL_NAMES = {"dtu": "DTU scan24: 49 photos of a toy house on a table (384×384)",
              "mouse": "a mouse on a white table: 59 phone photos, portrait and landscape (1440×1920)",
              "blowtorch": "a shiny brass blowtorch on a carpet: 67 photos (1600×1068), hand masks",
              "mouse24": "a phone folder: 24 of the mouse's photos at 12 MP (4032×3024; `bench/subset.py`)"}
STAGE_ORDER = ("cameras", "masks", "depth", "train", "mesh", "texture")


def real_table(results: list[dict]) -> str:
    """Real captures from their photos alone, default preset: photos posed, seconds per stage, mask IoU against
    hand masks where they exist, held-out PSNR (every 7th photo held out)."""
    rows = [r for r in results if r.get("scene") in REAL_NAMES and r.get("cameras") == "sfm"
            and r.get("preset") == "default" and not r.get("knob")]
    if not rows:
        return ""
    lines = ["| capture | posed | " + " | ".join(STAGE_ORDER) + " | total s | mask IoU | held-out PSNR (gain fit) |",
             "|---|---|" + "---|" * len(STAGE_ORDER) + "---|---|---|"]
    for r in sorted(rows, key=lambda r: list(REAL_NAMES).index(r["scene"])):
        if "error" in r:
            posed = re.search(r"only (\d+/\d+) photos registered", r["error"])
            why = f"{posed.group(1)}: stopped, too few posed" if posed else f"failed: {r['error'].split(':')[0]}"
            lines.append(f"| {REAL_NAMES[r['scene']]} | {why} |" + " |" * (len(STAGE_ORDER) + 3))
            continue
        secs = r["seconds"]
        iou = f"{r['mask_iou']:.3f}" if r.get("mask_iou") is not None else "–"
        lines.append(f"| {REAL_NAMES[r['scene']]} | {r['registered']} | "
                     + " | ".join(f"{secs.get(s, 0):.0f}" for s in STAGE_ORDER)
                     + f" | {sum(secs.get(s, 0) for s in STAGE_ORDER):.0f} | {iou} | {r['psnr']:.2f} "
                       f"({r['psnr_gain_fit']:.2f}) |")
    where = sorted({f"{r['machine']['model']}, {r['machine']['cores']} cores" for r in rows if r.get("machine")})
    return "\n".join(lines) + (f"\n\nMeasured on {'; '.join(where)} (rows without a machine: the bench's)." if where
                               else "")


def findings(results: list[dict]) -> list[str]:
    """Which knob buys the most accuracy per second, and whether the default preset is on the Pareto front."""
    ablations = [r for r in reconstructions(results) if "error" not in r and r.get("ablation")]
    ok = [r for r in reconstructions(results) if "error" not in r and not r.get("ablation")]
    out = []
    base = next((r for r in ok if r["scene"] == "cow" and r["cameras"] == "gt" and r["preset"] == "default"
                 and not r.get("knob")), None)
    if base:
        rates = []
        for r in ok:
            if r["scene"] == "cow" and r["cameras"] == "gt" and (r.get("knob") or r["preset"] != "default"):
                dt = r["total_s"] - base["total_s"]
                dc = 100 * (base["chamfer_rel"] - r["chamfer_rel"])  # Chamfer points gained
                dp = r["psnr"] - base["psnr"]
                rates.append((label(r) + stale(r, base), dt, dc, dp))
        for name, dt, dc, dp in sorted(rates, key=lambda x: x[1]):
            out.append(f"- {name}: {dt:+.0f} s, Chamfer {-dc:+.3f} points, PSNR {dp:+.2f} dB")
        dearer = [x for x in rates if x[1] > 5 and x[3] > 0]
        if dearer:
            name, dt, dc, dp = max(dearer, key=lambda x: x[3] / x[1])
            out.append(f"- most accuracy per extra second: **{name}** ({60 * dp / dt:+.2f} dB PSNR per minute; "
                       f"Chamfer {-dc:+.3f} points)")
        cheaper = [x for x in rates if x[1] < -5]
        if cheaper:
            name, dt, dc, dp = max(cheaper, key=lambda x: x[3] / -x[1])
            out.append(f"- cheapest saving: **{name}** ({-dt:.0f} s less for {dp:+.2f} dB PSNR, Chamfer {-dc:+.3f} "
                       "points)")
    for scene in sorted({r["scene"] for r in ok if r["cameras"] == "gt"}):
        rs = [r for r in ok if r["scene"] == scene and r["cameras"] == "gt"]
        front = [rs[i] for i in pareto([_objectives(r) for r in rs])]
        d = [r for r in front if r["preset"] == "default" and not r.get("knob")]
        out.append(f"- {scene}{stale(*rs)}: default preset {'on' if d else 'NOT on'} the Pareto front of "
                   "(time, Chamfer, PSNR) "
                   f"(front: {', '.join(label(r) for r in sorted(front, key=lambda r: r['total_s']))})")
    return out + ablation_findings(ablations, results)


def ablation_findings(rows: list[dict], all_results: list[dict]) -> list[str]:
    """The ablations, each a run without and with its knob: per-view appearance (``--train.appearance``), view shading
    (``--train.view-shading``), the bake's discrete view selection (``--texture.view-selection``) and the final SfM
    adjustment (``--cameras.final-passes 3``; with its rotation error), then the appearance reference."""
    base = {(r["preset"], r["scene"], r["cameras"]): r for r in reconstructions(all_results) if "error" not in r
            and not r.get("knob")}
    by = {(r["preset"], r["scene"], r["cameras"], r.get("knob")): r for r in rows}

    def cow(knob: str | None, preset: str = "balanced") -> dict | None:
        """The cow's run with GT cameras under ``knob`` (None: the preset's plain run)."""
        return by.get((preset, "cow", "gt", knob)) if knob else base.get((preset, "cow", "gt"))

    appearance = "per-view appearance"
    looks = "the cow photographed with exposure ±25 %, white balance ±8 % and specular highlights"
    pairs = [(appearance, looks + ("" if p == "default" else f" (`{p}` preset)"),
              cow("exposure+specular", p), cow("exposure+specular, appearance", p)) for p in ("default", "balanced")]
    pairs += [(appearance, "the cow photographed with exposure ±25 % and white balance ±8 % only (`balanced` preset)",
               cow("exposure"), cow("exposure, appearance")),
              (appearance, "the plain cow (one exposure, no highlights)", cow(None, "default"),
               cow("appearance", "default")),
              (appearance, "DTU scan24", by.get(("default", "dtu", "sfm", "appearance off"),
                                                base.get(("default", "dtu", "sfm"))),  # else the default's row
               by.get(("default", "dtu", "sfm", "appearance"))),
              ("per-view appearance, auto (the default)",
               "the cow photographed with exposure ±25 % and white balance ±8 %, from photos",
               by.get(("default", "cow", "sfm", "exposure, appearance off")),
               by.get(("default", "cow", "sfm", "exposure"))),
              ("per-view appearance, auto (the default)", looks + ", from photos",
               by.get(("default", "cow", "sfm", "exposure+specular, appearance off")),
               by.get(("default", "cow", "sfm", "exposure+specular"))),
              ("the exposure measured and used (masks' stereo on evened photos, appearance auto)",
               looks + ", from photos, against neither",
               by.get(("default", "cow", "sfm", "exposure+specular, no exposure handling")),
               by.get(("default", "cow", "sfm", "exposure+specular")))]
    shading, gloss = "view shading in training", "the exposure + specular cow (`balanced` preset"
    pairs += [(shading, gloss + ", both without appearance)", cow("exposure+specular"),
               cow("exposure+specular, view shading")),
              (shading, gloss + ", both with appearance)", cow("exposure+specular, appearance"),
               cow("exposure+specular, appearance + view shading")),
              ("per-view appearance + view shading", gloss + ", against neither)", cow("exposure+specular"),
               cow("exposure+specular, appearance + view shading")),
              (shading, "the plain cow (`balanced`)", cow(None), cow("view shading")),
              (shading, "DTU scan24 (both with appearance)", by.get(("default", "dtu", "sfm", "appearance")),
               by.get(("default", "dtu", "sfm", "appearance + view shading")))]
    selection = "view selection in the bake"
    pairs += [(selection, what, base.get(("default", *key)), by.get(("default", *key, "view selection")))
              for what, key in (("the cow, GT cameras", ("cow", "gt")), ("the cow from photos", ("cow", "sfm")),
                                ("DTU scan24", ("dtu", "sfm")))]
    final = "final SfM adjustment (`--cameras.final-passes 3`, on the same SfM mapping: COLMAP runs on one thread)"
    pairs += [(final, f"{what} from photos" + ("" if p == "default" else f" (`{p}` preset)"),
               base.get((p, scene, "sfm")), by.get((p, scene, "sfm", "final adjustment")))
              for what, scene, p in (("the cow", "cow", "default"), ("the cow", "cow", "balanced"),
                                     ("the jar", "jar", "default"), ("the book", "book", "default"),
                                     ("the floating cow", "cow_float", "default"), ("DTU scan24", "dtu", "default"))]
    framing = "the framing rule (`train.framing` auto: on where the object leaves most frames)"
    pairs += [(framing, f"the cow photographed close up (cameras at 1.6 instead of 2.6 from it), {what}",
               by.get(("default", "cow", c, "close-up photos, framing off")), by.get(("default", "cow", c,
                                                                                      "close-up photos")))
              for what, c in (("GT cameras and masks", "gt"), ("from photos", "sfm"))]
    out = []
    for name, what, off, on in pairs:
        if off is None or on is None:
            continue
        line = (f"- {name}, {what}{stale(off, on)}, without / with it: held-out PSNR {off['psnr']:.2f} / "
                f"{on['psnr']:.2f} dB ({on['psnr'] - off['psnr']:+.2f}")
        if "psnr_gain_fit" in off and "psnr_gain_fit" in on:
            line += (f"; after fitting each held-out photo's own colour gains {off['psnr_gain_fit']:.2f} / "
                     f"{on['psnr_gain_fit']:.2f} dB")
        if name == final:
            at, key = ("the held-out photos' GT poses", "psnr_gt_pose") if "psnr_gt_pose" in off else \
                ("the training views", "psnr_train")
            line += (f"; rotation error {off['pose']['rot_err_deg_mean']:.3f} / {on['pose']['rot_err_deg_mean']:.3f}°"
                     f", at {at} {off[key]:.2f} / {on[key]:.2f} dB")
        line += ")"
        if off.get("chamfer_rel") is not None:
            line += f", Chamfer {100 * off['chamfer_rel']:.3f} / {100 * on['chamfer_rel']:.3f} %"
        out.append(line + f", {off['total_s']:.0f} / {on['total_s']:.0f} s")
    return out + appearance_reference(by)


def appearance_reference(by: dict) -> list[str]:
    """The exposure + specular held-out photos against the model of the same cow photographed without effects:
    what the photos' exposure and highlights cost a texture, next to what the appearance and view shading win."""
    key = ("balanced", "cow", "gt")
    off, top = by.get((*key, "exposure+specular")), by.get((*key, "exposure+specular held-out, effect-free training"))
    if not (off and top and "psnr_gain_fit" in off and "psnr_gain_fit" in top):
        return []
    line = (f"- reference for the exposure + specular cow (`balanced`){stale(off, top)}: the model of the cow "
            f"photographed without effects scores {top['psnr_gain_fit']:.2f} dB on those held-out photos after fitting "
            f"their gains "
            f"({top['psnr']:.2f} raw; the training photos' effects cost the run without appearance "
            f"{top['psnr_gain_fit'] - off['psnr_gain_fit']:.2f} dB against it)")
    for name, knob in (("appearance", "exposure+specular, appearance"),
                       ("appearance + view shading", "exposure+specular, appearance + view shading")):
        on = by.get((*key, knob))
        if on and "psnr_gain_fit" in on:
            line += f"; with {name}: {on['psnr_gain_fit'] - top['psnr_gain_fit']:+.2f} dB against it"
    return [line]


def write(results: list[dict], mach: dict, total: float, stem: Path, page: Path | None) -> None:
    """Plot, tables and findings; printed, and (with ``page``, docs/benchmarks.md) written between its BENCH
    markers."""
    plot(results, stem.with_suffix(".png"), mach)
    md, cams, notes = table(results, mach), cameras_table(results), findings(results)
    real = real_table(results)
    print(md)
    print(cams)
    print(real)
    print("\n".join(notes))
    print(f"bench: {len(results)} runs in {total / 60:.1f} min → {stem}.json, .png")
    if page is None:
        return
    txt = page.read_text()
    start, end = "<!-- BENCH START -->", "<!-- BENCH END -->"
    if start in txt and end in txt:
        pre, rest = txt.split(start, 1)
        _, post = rest.split(end, 1)
        body = (f"{md}\n\n" + (f"Cameras stage alone on capture conditions (photos only; pose error after Sim(3) "
                               f"against the GT cameras):\n\n{cams}\n\n" if cams else "") +
                (f"Real captures from their photos alone, default preset (seconds per stage; mask IoU against hand "
                 f"masks; PSNR at every 7th photo, held out of training):\n\n{real}\n\n" if real else "") +
                f"Whole benchmark: {total / 60:.0f} min (`make bench`). Each knob against the default preset (cow on "
                f"the floor, GT cameras), and the Pareto fronts:\n\n" + "\n".join(notes) +
                f"\n\n![accuracy against time](../bench/results/{stem.name}.png)\n")
        page.write_text(f"{pre}{start}\n{body}{end}{post}")
