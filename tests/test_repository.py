"""The repository as a newcomer meets it: a short README that starts with the two commands, documentation that
names only options that exist, no development history in tracked files, packages no larger than a person can
scan, and the layering (dvr/ below pipeline/ below synth/ and bench/) without import circles."""

import ast
import re
import subprocess
from pathlib import Path

from tests.conftest import ROOT, cli_options

HISTORY = re.compile(r"\b[Ss]tops? [0-9]+\b|\b[Ii]ssues? [0-9]+\b")
"""A development-history marker: the word stop(s) or issue(s) followed by a number."""


def _tracked() -> list[Path]:
    out = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True).stdout
    return [ROOT / p for p in out.split()]


def _text_files() -> list[Path]:
    return [p for p in _tracked() if p.suffix in (".py", ".md", ".yaml", ".toml", ".json", ".sh", ".mjs", ".txt")
            or p.name in ("Makefile", "run")]


def test_no_development_history_in_tracked_files():
    found = [f"{p.relative_to(ROOT)}:{n}: {line.strip()[:80]}" for p in _text_files() if p.is_file()
             for n, line in enumerate(p.read_text(errors="replace").splitlines(), 1) if HISTORY.search(line)]
    assert found == []


def test_the_marker_pattern_finds_markers():
    stop, issue = "stop", "issue"  # spelled apart, so that this file holds no marker itself
    marked = (f"since {stop} 53", f"{stop}s 15–18", f"{issue} 11 asks", f"S{stop[1:]} 57:")
    assert all(HISTORY.search(s) for s in marked)
    assert not any(HISTORY.search(s) for s in ("it stops at 3 views", "no issue", "the 57 stops"))


def test_readme_is_short_and_starts_with_the_two_commands():
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= 300
    head = "\n".join(lines[:12])
    assert lines[0].startswith("# ") and "make setup && make reconstruct IMAGES=" in head and "make test" in head


def test_every_option_the_docs_name_parses():
    """Each ``--section.option`` that the README, docs/, the CHANGELOG or the Makefile names is an option of
    ``python -m pipeline reconstruct`` or ``batch``."""
    from pipeline.cli import COMMAND_CLASSES

    known = cli_options(COMMAND_CLASSES["reconstruct"]) | cli_options(COMMAND_CLASSES["batch"])
    pages = [ROOT / "README.md", ROOT / "CHANGELOG.md", ROOT / "Makefile", *sorted((ROOT / "docs").glob("*.md"))]
    named = {}
    for page in pages:
        for option in re.findall(r"--[a-z][a-z0-9-]*(?:\.[a-z][a-z0-9-]*[a-z0-9])+", page.read_text()):
            named.setdefault(option, page.name)  # nested too: --train.weights.carve
    assert len(named) >= 30  # the docs explain options; the pattern finds them
    assert sorted(f"{o} ({page})" for o, page in named.items() if o not in known) == []
    assert {"--images", "--masks-dir", "--given-cameras", "--config", "--force"} <= known


def test_no_folder_of_python_code_holds_more_than_twenty_modules():
    counts: dict[Path, int] = {}
    for p in _tracked():
        if p.suffix == ".py" and p.is_file():
            counts[p.parent] = counts.get(p.parent, 0) + 1
    assert {str(d.relative_to(ROOT)): n for d, n in counts.items() if n > 20} == {}


def _imports() -> dict[str, set[str]]:
    """Module → the project modules it imports (at any depth of its code, relative imports resolved)."""
    layers = ("dvr", "pipeline", "synth", "bench")
    files = {p for p in _tracked() if p.suffix == ".py" and p.is_file() and p.parts[len(ROOT.parts)] in layers}
    name = {p: ".".join(p.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__") for p in files}
    modules = set(name.values())
    graph = {}
    for p, mod in name.items():
        package = mod if p.name == "__init__.py" else mod.rpartition(".")[0]
        found = set()
        for node in ast.walk(ast.parse(p.read_text())):
            if isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parts = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join(parts + ([node.module] if node.module else []))
                for alias in node.names:
                    found |= {m for m in (f"{base}.{alias.name}", base) if m in modules}
            elif isinstance(node, ast.Import):
                found |= {a.name for a in node.names if a.name in modules}
        graph[mod] = found - {mod}
    return graph


def _circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_layers_and_no_import_circles():
    """dvr/ imports nothing of the project above it, pipeline/ neither synth/ nor bench/, and no two modules reach
    each other through their imports."""
    graph = _imports()
    assert len(graph) > 60
    up = {m: sorted(t for t in ts if t.split(".")[0] not in allowed) for m, ts in graph.items()
          for allowed in [{"dvr": {"dvr"}, "pipeline": {"dvr", "pipeline"}}.get(m.split(".")[0])] if allowed}
    assert {m: t for m, t in up.items() if t} == {}
    assert _circles(graph) == []


def test_the_circle_finder_finds_a_circle():
    assert _circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _circles({"a": {"b"}, "b": set()}) == []
