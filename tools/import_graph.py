"""The package's import graph, read with `ast` (imports inside functions count too), and
the layering rules it must keep; `tests/test_layout.py` runs `check()`.

    python tools/import_graph.py            # the problems, if any, and the layers' sizes
    python tools/import_graph.py --dot      # the graph between packages, for graphviz

Layers (what may import what):

    mirage_cli.cli        the command line: click, printing; may import everything below
    mirage_cli.pipelines  the workflow's steps (track, build, calibrate, report, campaign)
    mirage_cli.tracking   the Tracker and the smoother     } the core: no click, no
    mirage_cli.*          solver, model, frames, ...         } printing
    benchmarks/, tools/   scripts: the pipelines and the core, never the CLI layer

Rules: no import cycle between modules; the core imports neither `pipelines` nor `cli`;
`pipelines` does not import `cli`; only `cli` imports click; nothing outside `cli`
imports a command module.
"""

from __future__ import annotations

import ast
import sys
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "mirage_cli"


def module_name(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _resolve(mod: str, is_pkg: bool, node: ast.ImportFrom) -> str:
    if not node.level:
        return node.module or ""
    base = mod.split(".") if is_pkg else mod.split(".")[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def imports(path: Path, known: set[str]) -> set[str]:
    """The modules `path` imports (of `known`, plus click), from any depth of the file."""
    mod = module_name(path)
    is_pkg = path.name == "__init__.py"
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            target = _resolve(mod, is_pkg, node)
            names = [target] + [f"{target}.{a.name}" for a in node.names]
        else:
            continue
        for n in names:
            if n == "click" or n.startswith("click."):
                out.add("click")
            elif n in known:
                out.add(n)
    out.discard(mod)
    return out


def graph() -> dict[str, set[str]]:
    files = sorted((ROOT / PACKAGE).rglob("*.py"))
    scripts = sorted((ROOT / "benchmarks").glob("*.py")) + sorted((ROOT / "tools").glob("*.py"))
    known = {module_name(p) for p in files}
    return {module_name(p): imports(p, known) for p in files + scripts}


def layer(mod: str) -> str:
    if mod == f"{PACKAGE}.__main__":  # the `mirage` entry point
        return "cli"
    for name in ("cli", "pipelines", "tracking"):
        if mod == f"{PACKAGE}.{name}" or mod.startswith(f"{PACKAGE}.{name}."):
            return name
    return "core" if mod.startswith(PACKAGE) else "script"


# the layers each layer must not import (the core includes `tracking`)
FORBIDDEN = {
    "core": {"pipelines", "cli"},
    "tracking": {"pipelines", "cli"},
    "pipelines": {"cli"},
    "script": {"cli"},
    "cli": set(),
}


def cycles(g: dict[str, set[str]]) -> list[list[str]]:
    """Every strongly connected component of more than one module (Tarjan), each a cycle."""
    index, low, on, stack, out, counter = {}, {}, set(), [], [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in g.get(v, ()):
            if w not in g:
                continue
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

    sys.setrecursionlimit(10000)
    for v in sorted(g):
        if v not in index:
            visit(v)
    return out


def check() -> list[str]:
    """Every broken rule, one line each (empty: the layout holds)."""
    g = graph()
    problems = [f"import cycle: {' -> '.join(c)}" for c in cycles(g)]
    for mod, deps in sorted(g.items()):
        here = layer(mod)
        for d in sorted(deps):
            if d == "click":
                if here != "cli":
                    problems.append(f"{mod} imports click (only {PACKAGE}.cli may)")
                continue
            if layer(d) in FORBIDDEN[here]:
                problems.append(f"{mod} ({here}) imports {d} ({layer(d)})")
    return problems


def main() -> int:
    g = graph()
    if "--dot" in sys.argv:
        edges = {(layer(m), layer(d)) for m, ds in g.items() for d in ds if d != "click"}
        print("digraph layers {")
        for a, b in sorted(edges):
            if a != b:
                print(f'  "{a}" -> "{b}";')
        print("}")
        return 0
    problems = check()
    for p in problems:
        print(p)
    sizes = defaultdict(int)
    for m in g:
        sizes[layer(m)] += 1
    print(", ".join(f"{k}: {v} modules" for k, v in sorted(sizes.items())))
    print(f"{len(problems)} problem(s)")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
