"""Project config files: the example in configs/ matches the real options, and typos or
wrong types in mirage.yaml are one-line errors that name the file, section and key."""

import re

import click
import pytest
import yaml
from conftest import ROOT, assert_one_line_error, run_here

from mirage_cli.build_model import BuildSettings
from mirage_cli.calibrate import CalibOptions
from mirage_cli.cli import cli
from mirage_cli.cli.config import check_config, read_config
from mirage_cli.tracking import TrackSettings

EXAMPLE = ROOT / "configs" / "example-mirage.yaml"


def _keys(cmd) -> set[str]:
    """The names a config file uses for a command's parameters: long flags, arguments."""
    out = set()
    for p in cmd.params:
        longs = [f[2:] for f in p.opts if f.startswith("--")]
        out.update(longs or [p.name.replace("_", "-")])
    return out


def test_example_config_lists_exactly_the_real_options():
    text = EXAMPLE.read_text()
    raw = yaml.safe_load(text)
    assert set(raw) == set(cli.commands), "one section per command"
    commented = {}  # positional arguments are documented as comments
    section = None
    for line in text.splitlines():
        if m := re.match(r"^([a-z-]+):", line):
            section = m.group(1)
        elif m := re.match(r"^\s+#\s*([a-z-]+):", line):
            commented.setdefault(section, set()).add(m.group(1))
    for name, cmd in cli.commands.items():
        listed = set(raw[name]) | commented.get(name, set())
        missing, unknown = _keys(cmd) - listed, listed - _keys(cmd)
        assert not missing, f"configs/example-mirage.yaml: add {sorted(missing)} to '{name}'"
        assert not unknown, f"configs/example-mirage.yaml: '{name}' has no {sorted(unknown)}"


def test_example_config_passes_the_check_and_its_defaults_are_the_real_ones():
    raw, src = read_config(EXAMPLE)
    default_map = check_config(raw, cli.commands, src)
    assert default_map["track"]["model_path"] == str(EXAMPLE.parent / "landmark.mirage")
    # every value the file calls "default" is the default --help shows
    section, checked = None, 0
    for line in EXAMPLE.read_text().splitlines():
        if m := re.match(r"^([a-z-]+):", line):
            section = cli.commands[m.group(1)]
        elif m := re.match(r"^\s+([a-z-]+):\s*(\S.*?)\s+#\s*default\s*(;|$)", line):
            p = next(p for p in section.params if f"--{m.group(1)}" in p.opts)
            value = yaml.safe_load(m.group(2))
            ctx = click.Context(section)  # get_default: click >= 8.3 keeps unset defaults unset
            assert p.type_cast_value(ctx, value) == p.get_default(ctx), line
            checked += 1
    assert checked >= 30


def test_click_defaults_are_the_core_settings():
    """Each default is written once, in the core; the options read it."""
    opts = {n: {p.name: p.default for p in c.params} for n, c in cli.commands.items()}
    assert opts["track"]["redetect_every"] == TrackSettings.redetect_every
    assert opts["track"]["min_inliers"] == TrackSettings.min_inliers
    assert opts["track"]["max_rmse"] == TrackSettings.max_ok_rmse_px
    assert opts["track"]["method"] == TrackSettings.method
    assert opts["build-model"]["spacing_deg"] == BuildSettings.spacing_deg
    assert opts["build-model"]["max_reproj_px"] == BuildSettings.max_reproj_px
    assert opts["build-model"]["min_angle_deg"] == BuildSettings.min_angle_deg
    assert opts["build-model"]["roi"] == BuildSettings().roi.kind
    assert opts["calibrate"]["model"] == str(CalibOptions.model)
    assert opts["calibrate"]["reject_factor"] == CalibOptions.reject_factor


def test_help_shows_the_core_defaults(mirage):
    p = mirage("track", "--help")
    assert p.returncode == 0
    flat = " ".join(p.stdout.split())
    assert "--redetect-every INTEGER Full feature" in flat
    assert f"[default: {TrackSettings.redetect_every}; x>=1]" in flat
    assert f"[default: {TrackSettings.max_ok_rmse_px}; x>0]" in flat


@pytest.mark.parametrize(
    "text, contains",
    [
        ("trak:\n  model: m.mirage\n", "unknown section 'trak' (did you mean 'track'?)"),
        ("buld_model:\n  camera: c.yaml\n", "did you mean 'build-model'?"),
        (
            "track:\n  mdoel: m.mirage\n",
            "unknown key 'mdoel' in section 'track' (did you mean 'model'?)",
        ),
        ("track:\n  max_rmsee: 1\n", "(did you mean 'max_rmse'?)"),
        ("synth:\n  xyzzy: 1\n", "unknown key 'xyzzy' in section 'synth' (valid keys: "),
        ("track:\n  max-rmse: [1, 2]\n", "'track: max-rmse' must be a number, not a list"),
        (
            "track:\n  camera: {file: c.yaml}\n",
            "'track: camera' must be a file path, not a mapping",
        ),
        ("track:\n  max-rmse: lots\n", "'track: max-rmse' must be a number, not 'lots'"),
        ("track:\n  redetect-every: 2.5\n", "'track: redetect-every' must be an integer, not 2.5"),
        ("track:\n  min-inliers: yes\n", "'track: min-inliers' must be an integer, not True"),
        ("track:\n  no-flow: 3\n", "'track: no-flow' must be true or false, not 3"),
        ("track:\n  start: [1, 2]\n", "'track: start' must be a single value, not a list"),
        ("track: 5\n", "'track' must be a mapping of options"),
        ("- track\n", "must be a mapping of command -> options"),
    ],
)
def test_config_mistakes_are_one_line_errors(tmp_path, text, contains):
    cfg = tmp_path / "proj.yaml"
    cfg.write_text(text)
    # in this process (24 runs): the CLI's one-line errors are the same as in a subprocess
    p = run_here("--config", cfg, "track", "v.mp4", "--model", tmp_path / "none.mirage")
    assert_one_line_error(p, 2, contains)
    assert str(cfg) in p.stderr
    # the same from ./mirage.yaml, before any command runs (even --help)
    (tmp_path / "mirage.yaml").write_text(text)
    assert_one_line_error(run_here("report", "--help", cwd=tmp_path), 2, contains)


def test_out_of_range_value_fails_when_used_and_names_the_file(mirage, tmp_path):
    (tmp_path / "mirage.yaml").write_text("track:\n  max-rmse: -1\n")
    p = mirage("track", "v.mp4", "--model", "none.mirage", cwd=tmp_path)
    assert_one_line_error(p, 2, "'track: max-rmse' (--max-rmse): -1")
    assert "mirage.yaml" in p.stderr
    # a flag overrides the bad value: the run gets as far as the missing model
    p = mirage("track", "v.mp4", "--model", "none.mirage", "--max-rmse", "1", cwd=tmp_path)
    assert_one_line_error(p, 2, "model file none.mirage not found")


def test_empty_value_keeps_the_default_and_underscores_work(tmp_path):
    (tmp_path / "mirage.yaml").write_text("build_model:\n  spacing_deg:\n  max_reproj_px: 1.5\n")
    raw, src = read_config(cwd=tmp_path)
    assert check_config(raw, cli.commands, src) == {"build-model": {"max_reproj_px": 1.5}}
