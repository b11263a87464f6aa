#!/usr/bin/env python3
"""Mutation testing of one core module with mutmut (the [test] extra installs it).

    python tools/mutate.py fileio tests/test_fileio.py
    python tools/mutate.py tracking.smooth tests/test_smooth.py
    python tools/mutate.py solver tests/test_solver.py --max-children 2

mutmut copies the package into a scratch folder (build/mutation/MODULE/, not tracked),
mutates only mirage_cli/MODULE.py there (a dotted MODULE names a subpackage's module:
tracking.smooth is mirage_cli/tracking/smooth.py), and for each mutant runs only the given test
files' tests that call the mutated function (mutmut's own per-function selection). It
prints killed / total and the survivors, which are then either killed by a new test or
listed in docs/mutation.md as equivalent, with the reason. `--names 'PATTERN'` (mutmut's
mutant names, e.g. 'mirage_cli.solver.x__finish*') limits a run to some functions; the
previous results in the scratch folder are reused for mutants whose code did not change.

A run of fileio takes about a minute on 2 cores, smooth a few minutes; keep it to one
module at a time on a shared machine (`nice` is applied).
"""

from __future__ import annotations

import argparse
import fnmatch
import os
import re
import shutil
import subprocess
import sys
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _config(module: str, tests: list[str]) -> str:
    quoted = ", ".join(f'"{t}"' for t in tests)
    return f"""[tool.mutmut]
source_paths = ["mirage_cli"]
only_mutate = ["*mirage_cli/{module.replace(".", "/")}.py"]
pytest_add_cli_args_test_selection = [{quoted}]
pytest_add_cli_args = ["-p", "no:cacheprovider", "-x", "-q"]
also_copy = ["sample_data"]
use_git_change_detection = false

[tool.pytest.ini_options]
testpaths = ["tests"]
"""


def _chosen(name: str, patterns: list[str]) -> bool:
    return not patterns or any(fnmatch.fnmatch(name, p) for p in patterns)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("module", help="a module of mirage_cli, e.g. solver, tracking.smooth")
    ap.add_argument("tests", nargs="+", help="the test files that test it")
    ap.add_argument("--max-children", type=int, default=2)
    ap.add_argument("--names", nargs="*", default=[], help="mutmut mutant names / globs")
    ap.add_argument("--fresh", action="store_true", help="forget earlier results")
    a = ap.parse_args()

    src = ROOT / "mirage_cli" / f"{a.module.replace('.', '/')}.py"
    if not src.is_file():
        ap.error(f"{src} not found")
    work = ROOT / "build" / "mutation" / a.module
    if a.fresh and work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True, exist_ok=True)
    # the project's files as they are now (mutmut re-copies changed sources into mutants/)
    for name in ("mirage_cli", "tests"):
        if (work / name).exists():
            shutil.rmtree(work / name)
        shutil.copytree(ROOT / name, work / name, ignore=shutil.ignore_patterns("__pycache__"))
    if not (work / "sample_data").exists():
        shutil.copytree(ROOT / "sample_data", work / "sample_data")
    (work / "pyproject.toml").write_text(_config(a.module, a.tests))

    env = {**os.environ, "PYTHONDONTWRITEBYTECODE": "1"}
    run = ["nice", "-n", "10", sys.executable, "-m", "mutmut", "run",
           "--max-children", str(a.max_children), *a.names]  # fmt: skip
    with open(work / "mutmut.log", "w") as log:  # its progress line, kept out of the way
        subprocess.run(run, cwd=work, env=env, stdout=log, stderr=subprocess.STDOUT, check=False)
    out = subprocess.run(
        [sys.executable, "-m", "mutmut", "results", "--all", "true"],
        cwd=work, env=env, capture_output=True, text=True, check=False,
    )  # fmt: skip
    status = Counter()
    survivors = []
    for line in out.stdout.splitlines():
        m = re.match(r"\s*(\S+): (.+)$", line)
        if m and f"mirage_cli.{a.module}." in m.group(1) and _chosen(m.group(1), a.names):
            status[m.group(2)] += 1
            if m.group(2) in ("survived", "no tests"):
                survivors.append(f"{m.group(1)} ({m.group(2)})")
    total = sum(status.values())
    killed = status["killed"] + status["timeout"]
    print(f"\n{a.module}: {killed} / {total} killed ({100 * killed / max(total, 1):.1f}%)",
          dict(status))  # fmt: skip
    for s in survivors:
        print("  survived:", s)
    print(f"\nsee a mutant: (cd {work} && mutmut show NAME)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
