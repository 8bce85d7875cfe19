"""The package's import graph, read from the source (every import, module-level or not): no circle, no
import from a higher layer, viser only under studio/, and the core loads neither viser nor torch when
imported. docs/ARCHITECTURE.md draws the same layers; `python -m tests.test_architecture` prints the graph."""

import ast
import subprocess
import sys
from pathlib import Path

import pytest

from .conftest import REPO

PKG = REPO / "apose_studio"

# lowest first: a module may import its own package and the layers below it, nothing above
LAYERS = [
    ["apose_studio", "apose_studio.errors", "apose_studio.safeio"],
    ["apose_studio.geometry"],
    ["apose_studio.params"],
    ["apose_studio.assembly"],
    ["apose_studio.masks", "apose_studio.data", "apose_studio.robot"],
    ["apose_studio.synth", "apose_studio.registration"],
    ["apose_studio.estimation"],
    ["apose_studio.evaluate"],
    ["apose_studio.api"],
    ["apose_studio.cli", "apose_studio.studio", "apose_studio.service"],
]


def modules() -> dict[str, tuple[Path, bool]]:
    out = {}
    for f in PKG.rglob("*.py"):
        parts = list(f.relative_to(REPO).with_suffix("").parts)
        is_pkg = parts[-1] == "__init__"
        out[".".join(parts[:-1] if is_pkg else parts)] = (f, is_pkg)
    return out


def graph() -> dict[str, set[str]]:
    """module -> the apose_studio modules it imports (anywhere in its source)."""
    mods = modules()

    def resolve(name: str) -> str:
        while name and name not in mods:
            name = name.rpartition(".")[0]
        return name

    edges = {}
    for m, (f, is_pkg) in mods.items():
        base = m.split(".") if is_pkg else m.split(".")[:-1]
        out = set()
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.Import):
                out |= {resolve(a.name) for a in node.names if a.name.split(".")[0] == "apose_studio"}
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    target = ".".join(base[: len(base) - node.level + 1] + ([node.module] if node.module else []))
                elif (node.module or "").split(".")[0] == "apose_studio":
                    target = node.module
                else:
                    continue
                for a in node.names:
                    full = f"{target}.{a.name}"
                    out.add(full if full in mods else resolve(target))
        out.discard(m)
        out.discard("")
        edges[m] = out
    return edges


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, found, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in edges.get(v, ()):
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
                found.append(sorted(comp))

    for v in edges:
        if v not in index:
            visit(v)
    return found


def layer(module: str) -> int:
    best, level = "", None
    for k, names in enumerate(LAYERS):
        for n in names:
            if (module == n or module.startswith(n + ".")) and len(n) > len(best):
                best, level = n, k
    if level is None:
        raise AssertionError(f"{module} is in no layer of tests/test_architecture.py: add it where it belongs")
    return level


def upward(edges) -> list[str]:
    return [f"{a} (layer {layer(a)}) imports {b} (layer {layer(b)})" for a, bs in sorted(edges.items()) for b in sorted(bs)
            if layer(b) > layer(a) and not b.startswith(a + ".")]


def test_no_import_circles():
    assert cycles(graph()) == []


def test_no_import_from_a_higher_layer():
    assert upward(graph()) == []


def test_the_checks_see_a_planted_circle_and_upward_arrow():
    """The two checks above on a graph with a circle and an upward arrow planted (they must not pass vacuously)."""
    edges = graph()
    assert edges["apose_studio.estimation"] and edges["apose_studio.geometry.se3"] == set()
    planted = {**edges, "apose_studio.geometry.se3": {"apose_studio.evaluate"}}
    assert any("apose_studio.geometry.se3" in c for c in cycles(planted))
    assert any(u.startswith("apose_studio.geometry.se3 ") for u in upward(planted))


def test_viser_is_imported_only_under_studio():
    users = []
    for m, (f, _) in modules().items():
        for node in ast.walk(ast.parse(f.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                     [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            if any(n.split(".")[0] == "viser" for n in names):
                users.append(m)
    assert users and all(m.startswith("apose_studio.studio") for m in users), users


@pytest.mark.parametrize("module", ["apose_studio.api", "apose_studio.estimation", "apose_studio.evaluate",
                                    "apose_studio.cli.commands", "apose_studio.synth.render"])
def test_the_core_loads_neither_viser_nor_torch(module):
    code = f"import sys, {module}; print(sorted(m for m in ('viser', 'torch') if m in sys.modules))"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[]", r.stdout


if __name__ == "__main__":
    for m, bs in sorted(graph().items()):
        print(f"{m} (layer {layer(m)}) -> {', '.join(sorted(bs)) or '-'}")
