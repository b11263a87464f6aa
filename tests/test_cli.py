"""The CLI contract: version, help, config layering and one-line errors."""

import os
import subprocess
import sys

import click
import pytest
from conftest import assert_one_line_error

from mirage_cli import __version__
from mirage_cli.cli import COMMANDS, cli
from mirage_cli.cli.config import check_config, read_config

HEAVY = ("cv2", "numpy", "numba", "pandas", "scipy", "matplotlib", "yaml")


def test_version(mirage):
    p = mirage("--version")
    assert p.returncode == 0 and __version__ in p.stdout


@pytest.mark.parametrize("args", [["--version"], ["--help"]])
def test_version_and_help_load_no_command(args):
    """Commands import on use (issue 15): `mirage --version` and `mirage --help` load no
    command module, hence none of OpenCV, numba, numpy, pandas."""
    code = (
        "import sys\n"
        "from mirage_cli.cli import main\n"
        "try:\n    main(sys.argv[1:])\nexcept SystemExit:\n    pass\n"
        f"print(sorted(m for m in sys.modules if m.split('.')[0] in {HEAVY!r}"
        " or m.startswith('mirage_cli.') and m.endswith('_cli')), file=sys.stderr)"
    )
    p = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    assert p.stderr.strip() == "[]", p.stderr


@pytest.mark.parametrize(("given", "used"), [(None, "1"), ("", "1"), (" ", "1"), ("3", "3")])
def test_numpys_blas_runs_in_the_calling_thread_unless_the_user_says(given, used):
    """OpenBLAS's helper threads spin against mirage's own (issue 15): the command sets one
    thread before numpy loads, also over an empty value (OpenBLAS reads it as unset), and
    keeps a value the user chose."""
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    if given is not None:
        env["OPENBLAS_NUM_THREADS"] = given
    code = "import os, mirage_cli.cli; print(os.environ['OPENBLAS_NUM_THREADS'])"
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip() == used


def test_help_lists_every_command_as_click_would():
    """The lazy table's summaries give the very lines click derives from each command."""
    assert set(COMMANDS) == {c.name for c in cli.commands.values()}
    ctx = click.Context(cli, info_name="mirage")
    for width in (50, 80, 100, 200):
        lazy, eager = click.HelpFormatter(width=width), click.HelpFormatter(width=width)
        cli.format_commands(ctx, lazy)
        click.Group.format_commands(cli, ctx, eager)  # imports every command
        assert lazy.getvalue() == eager.getvalue()


def test_unknown_command_is_one_line(mirage):
    assert_one_line_error(mirage("frobnicate"), 2, "no such command")


def test_bad_config_yaml(mirage, tmp_path):
    cfg = tmp_path / "bad.yaml"
    cfg.write_text("synth: [1, 2\n")
    assert_one_line_error(mirage("--config", cfg, "synth", tmp_path / "o"), 2, "not valid YAML")


def test_missing_config(mirage, tmp_path):
    assert_one_line_error(mirage("--config", tmp_path / "nope.yaml", "synth", "x"), 2, "not found")


def test_config_layering(tmp_path):
    """The project file's values over the command's defaults (what click's default_map
    does with them); the defaults it does not name survive."""
    defaults = {p.name: p.default for p in cli.commands["synth"].params}
    raw, src = read_config(None, tmp_path)
    assert src is None and defaults["noise"] == 1.5
    (tmp_path / "mirage.yaml").write_text("synth:\n  noise: 0.5\n  jpeg-quality: 90\n")
    raw, src = read_config(None, tmp_path)
    assert src.name == "mirage.yaml"
    cfg = defaults | check_config(raw, cli.commands, src)["synth"]
    assert cfg["noise"] == 0.5 and cfg["jpeg_quality"] == 90
    assert cfg["seed"] == 0  # untouched defaults survive


def test_project_config_used_and_flags_win(mirage, tmp_path):
    (tmp_path / "mirage.yaml").write_text("synth:\n  calib_views: -3\n")
    # the config's (bad) value is used ...
    assert_one_line_error(
        mirage("synth", "out", "--only", "calibration", cwd=tmp_path), 2, "calib-views"
    )
    # ... and a flag overrides it
    p = mirage(
        "synth",
        "out",
        "--only",
        "calibration",
        "--calib-views",
        "1",
        "--width",
        "160",
        cwd=tmp_path,
    )
    assert p.returncode == 0, p.stderr
    assert len(list((tmp_path / "out" / "calibration").glob("*.jpg"))) == 1


def test_config_paths_are_relative_to_the_config_file(mirage, tmp_path):
    proj = tmp_path / "proj"
    proj.mkdir()
    (proj / "mirage.yaml").write_text("synth:\n  camera: cam.yaml\n")
    (proj / "cam.yaml").write_text(
        "image_width: 160\nimage_height: 120\n"
        "camera_matrix: {rows: 3, cols: 3, data: [130, 0, 80, 0, 130, 60, 0, 0, 1]}\n"
    )
    p = mirage(
        "--config",
        proj / "mirage.yaml",
        "synth",
        "out",
        "--only",
        "calibration",
        "--calib-views",
        "1",
        cwd=tmp_path,
    )
    assert p.returncode == 0, p.stderr
    img = (tmp_path / "out" / "calibration" / "calib_000.jpg").read_bytes()
    import cv2
    import numpy as np

    assert cv2.imdecode(np.frombuffer(img, np.uint8), 0).shape == (120, 160)
