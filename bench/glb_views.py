"""The GLB as a glTF viewer opens it (Google's model-viewer, the report's, in headless Chromium), from four sides
around its up axis and once from above, as one PNG: what a user sees on opening ``mesh/textured.glb``.

    python bench/glb_views.py work/dtu_scan24/mesh/textured.glb bench/results/dtu_scan24_glb.png

Needs ``make setup-web`` (model-viewer) and Chromium; the screenshot waits until every viewer shows its model
(``bench/glb_shot.mjs``)."""
from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pipeline.report.stage import VIEWER_JS, inlined_viewer  # noqa: E402

ORBITS = ("0deg 75deg auto", "90deg 75deg auto", "180deg 75deg auto", "270deg 75deg auto", "0deg 5deg auto")
SIDE = 300


def glb_views(glb: Path, out: Path) -> None:
    if not VIEWER_JS.exists():
        sys.exit(f"{VIEWER_JS}: missing; run make setup-web")
    js, src = inlined_viewer(glb)
    style = f"width:{SIDE}px;height:{SIDE}px;background:#eee;flex:none"
    views = "".join(f'<model-viewer loading="eager" src="{src}" camera-orbit="{o}" style="{style}"></model-viewer>'
                    for o in ORBITS)
    with tempfile.TemporaryDirectory() as tmp:
        page = Path(tmp) / "views.html"
        page.write_text('<html><body style="margin:0;display:flex;overflow:hidden">'
                        f'<script type="module">{js}</script>{views}</body></html>')
        done = subprocess.run(["node", "--experimental-websocket", str(ROOT / "bench" / "glb_shot.mjs"), str(page),
                               str(out), str(SIDE * len(ORBITS)), str(SIDE)])
    if done.returncode:
        sys.exit(f"{glb}: no screenshot (above)")
    print(f"glb views: {out}")


if __name__ == "__main__":
    glb_views(Path(sys.argv[1]), Path(sys.argv[2]))
