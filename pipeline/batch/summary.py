"""The batch summary: ``OUT/summary.json`` and ``OUT/index.html``, a row per capture (status, registered photos,
seconds per stage, mask confidence, PSNR, a thumbnail, links to its report, GLB and logs)."""

from __future__ import annotations

import base64
import html
import time
from pathlib import Path

import cv2

from dvr.atomic import write_json, write_text
from dvr.data import list_images
from pipeline.stages import STAGES
from pipeline.workspace import Workspace


def _photo_count(folder: Path) -> int:
    from pipeline.inputs.photos import list_photos

    try:
        return len(list_photos(folder)[0])
    except (OSError, ValueError):
        return 0


def _status(records: list[dict]) -> tuple[str, str | None, str | None]:
    """(status, failed stage, its error) from a capture's stage records; no records: it was already done."""
    if not records:
        return "up to date", None, None
    bad = next((r for r in records if r["status"] == "failed"), None)
    if bad is not None:
        return "failed", bad["stage"], bad.get("error")
    return "done", None, None


def capture_row(out: Path, cap, records: list[dict]) -> dict:
    """The summary row of one capture, from its stage records and what its workspace holds."""
    ws = Workspace(cap.workspace)
    status, stage, error = _status(records)
    registered = len(list_images(ws.images)) if ws.images.exists() else 0
    report, seconds = ws.stamp("report") or {}, ws.seconds()
    glb, page = ws.mesh / "textured.glb", ws.root / "report.html"
    return {
        "capture": cap.name, "status": status, "failed_stage": stage, "error": error,
        "photos": str(cap.photos), "workspace": str(ws.root),
        "registered": registered, "total": _photo_count(cap.photos),
        "seconds": {s.name: seconds[s.name] for s in STAGES if s.name in seconds},
        "ran": [r["stage"] for r in records if r.get("ran")],
        "train_gpu": next((r.get("gpu", False) for r in records if r["stage"] == "train" and r.get("ran")), None),
        "train_device": (ws.stamp("train") or {}).get("device"),
        "mask_confidence": (ws.stamp("masks") or {}).get("mean_confidence"),
        "psnr": report.get("psnr"), "psnr_views": report.get("psnr_views"),
        "glb": str(glb.relative_to(out)) if glb.exists() and status != "failed" else None,
        "report": str(page.relative_to(out)) if page.exists() and status != "failed" else None,
        "logs": str((ws.root / "logs").relative_to(out)) if (ws.root / "logs").exists() else None,
    }


def _thumbnail(ws: Path, width: int = 240) -> str | None:
    """The first photo | render pair of the capture's report, as a small inline JPEG."""
    pairs = sorted((ws / "report").glob("render_*.png")) if (ws / "report").exists() else []
    img = cv2.imread(str(pairs[0])) if pairs else None
    if img is None:
        return None
    img = cv2.resize(img, (width, max(1, round(img.shape[0] * width / img.shape[1]))), interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 85])
    return "data:image/jpeg;base64," + base64.b64encode(buf.tobytes()).decode() if ok else None


def _cell(row: dict) -> str:
    if row["status"] == "failed":
        return f"<b style='color:#b00'>failed</b> at {html.escape(row['failed_stage'])}: " \
               f"{html.escape(row['error'] or '')}"
    return html.escape(row["status"])


def _html_row(out: Path, row: dict) -> str:
    on = {"train": f" ({row['train_device']})"} if row.get("train_device") not in (None, "cpu") else {}
    secs = " ".join(f"{k} {v:.0f}{on.get(k, '')}" for k, v in row["seconds"].items())
    thumb = _thumbnail(out / row["capture"])
    links = [f"<a href='{html.escape(row[k])}'>{k}</a>" for k in ("report", "glb", "logs") if row[k]]
    psnr = f"{row['psnr']:.2f} dB ({row['psnr_views']})" if row["psnr"] is not None else "–"
    conf = f"{row['mask_confidence']:.3f}" if row["mask_confidence"] is not None else "–"
    return (f"<tr><td>{html.escape(row['capture'])}</td><td>{_cell(row)}</td>"
            f"<td>{row['registered']}/{row['total']}</td><td><code>{secs}</code></td><td>{conf}</td><td>{psnr}</td>"
            f"<td>{f'<img src={chr(39)}{thumb}{chr(39)}>' if thumb else ''}</td><td>{' · '.join(links)}</td></tr>")


def write_summary(out: Path, caps: list, records: dict[str, list], seconds: float) -> dict:
    """``out/summary.json`` and ``out/index.html`` for the batch; returns the summary."""
    rows = [capture_row(out, c, records[c.name]) for c in caps]
    summary = {"finished": time.strftime("%Y-%m-%d %H:%M:%S"), "wall_seconds": round(seconds, 1),
               "captures": len(rows), "done": sum(r["status"] in ("done", "up to date") for r in rows),
               "failed": sum(r["status"] == "failed" for r in rows), "rows": rows}
    write_json(out / "summary.json", summary, indent=1)
    head = ("<tr><th>capture</th><th>status</th><th>registered</th><th>seconds per stage</th>"
            "<th>mask confidence</th><th>PSNR</th><th>photo | mesh</th><th>links</th></tr>")
    style = "body{font-family:sans-serif;margin:2em}table{border-collapse:collapse}td,th{border:1px solid #ccc;" \
            "padding:4px 8px;vertical-align:top}code{font-size:80%}"
    doc = (f"<!doctype html><html><head><meta charset='utf-8'><title>batch: {html.escape(out.name)}</title>"
           f"<style>{style}</style></head><body><h1>Batch {html.escape(out.name)}</h1>"
           f"<p>{summary['done']}/{summary['captures']} done, {summary['failed']} failed, "
           f"{summary['wall_seconds']:.0f} s wall ({summary['finished']})</p><table>{head}"
           + "".join(_html_row(out, r) for r in rows) + "</table></body></html>")
    write_text(out / "index.html", doc)
    return summary
