"""The package's layout holds (issue 29): layers and no import cycles (tools/import_graph.py),
click only in the CLI layer, and functions and classes of a readable size."""

import ast
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))

import import_graph  # noqa: E402

MAX_FUNCTION_LINES = 80  # numba kernels excepted: one compiled loop, not split
MAX_CLASS_LINES = 250
JIT_DECORATORS = {"_jit", "jit", "njit", "numba.jit", "numba.njit"}


def _sources():
    for folder in ("mirage_cli", "benchmarks", "tools"):
        yield from sorted((ROOT / folder).rglob("*.py"))


def test_layers_hold_and_no_module_imports_itself_round_a_cycle():
    assert import_graph.check() == []


def test_the_checker_finds_a_cycle_and_a_layer_broken():
    g = {"mirage_cli.a": {"mirage_cli.b"}, "mirage_cli.b": {"mirage_cli.a"}, "mirage_cli.c": set()}
    assert import_graph.cycles(g) == [["mirage_cli.a", "mirage_cli.b"]]
    assert import_graph.layer("mirage_cli.cli.track") == "cli"
    assert import_graph.layer("mirage_cli.pipelines.track") == "pipelines"
    assert import_graph.layer("mirage_cli.tracking.flow") == "tracking"
    assert "cli" in import_graph.FORBIDDEN["pipelines"]
    assert {"cli", "pipelines"} <= import_graph.FORBIDDEN["core"]


def test_click_and_command_modules_only_in_the_cli_layer():
    """What grep shows: no `import click` and no import of a command module outside
    mirage_cli/cli/ (the same rule as the graph's, read as text)."""
    cli = ROOT / "mirage_cli" / "cli"
    command = re.compile(
        r"\s*(from\s+(\.+|mirage_cli\.)cli\b|from\s+(\.+|mirage_cli)\s+import\s+(.*,\s*)?cli\b"
        r"|import\s+mirage_cli\.cli\b|(from|import)\s+\S*(?<!mirage)_cli\b)"
    )
    bad = []
    for path in _sources():
        if cli in path.parents or path == ROOT / "mirage_cli" / "__main__.py":
            continue  # the CLI layer and the entry point
        for i, line in enumerate(path.read_text().splitlines(), 1):
            if re.match(r"\s*(import click|from click)\b", line):
                bad.append(f"{path.relative_to(ROOT)}:{i}: {line.strip()}")
            if command.match(line):
                bad.append(f"{path.relative_to(ROOT)}:{i}: {line.strip()}")
    assert bad == []


def _is_kernel(fn: ast.FunctionDef) -> bool:
    names = {ast.unparse(d.func if isinstance(d, ast.Call) else d) for d in fn.decorator_list}
    return bool(names & JIT_DECORATORS)


def test_functions_and_classes_stay_small():
    long = []
    for path in _sources():
        for node in ast.walk(ast.parse(path.read_text())):
            if not hasattr(node, "end_lineno"):
                continue
            size = (node.end_lineno or 0) - getattr(node, "lineno", 0) + 1
            where = f"{path.relative_to(ROOT)}:{getattr(node, 'lineno', 0)}"
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                if size > MAX_FUNCTION_LINES and not _is_kernel(node):
                    long.append(f"{where} function {node.name}: {size} lines")
            elif isinstance(node, ast.ClassDef) and size > MAX_CLASS_LINES:
                long.append(f"{where} class {node.name}: {size} lines")
    assert long == []
