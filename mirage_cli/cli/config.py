"""Layered options: the commands' defaults < ./mirage.yaml or --config FILE < flags.

Each default lives once: in the core settings dataclasses (`TrackSettings`,
`BuildSettings`, `CalibOptions`, ...) that the click options read, so `--help` shows it.
A project file is keyed by command name then option name (e.g. `track: {method:
mirage-s, model: landmark.mirage}`) and becomes click's `default_map`. It is checked
against the real options before any command runs: a misspelt section or key would
otherwise be ignored silently, and a wrong type would surface as an unexpected error.
"""

from __future__ import annotations

import dataclasses
import difflib
import inspect
from pathlib import Path

import click

from ..errors import InputError
from ..fileio import read_yaml, require_file

PROJECT_CONFIG = "mirage.yaml"


def read_config(path: str | None = None, cwd: Path | None = None) -> tuple[dict, Path | None]:
    """The project file as written (sections -> options) and its path; ({}, None) if none."""
    if path is not None:
        src = require_file(path, "config file")
    else:
        src = (cwd or Path.cwd()) / PROJECT_CONFIG
        if not src.is_file():
            return {}, None
    data = read_yaml(src, "config file")
    if data is None:
        return {}, src
    if not isinstance(data, dict):
        raise InputError(f"config file {src} must be a mapping of command -> options")
    for key, value in data.items():
        if value is not None and not isinstance(value, dict):
            raise InputError(f"config file {src}: '{key}' must be a mapping of options")
    return data, src


def check_config(raw: dict, commands: dict[str, click.Command], src: Path) -> dict[str, dict]:
    """click's default_map for a project file: sections become commands, keys (the flags
    users know, `model` for --model, dashes or underscores) become parameter names, every
    value is checked against the option's type, and relative file options are taken
    relative to the config file so `--config project/mirage.yaml` works from anywhere."""
    out: dict[str, dict] = {}
    for section, opts in raw.items():
        name = str(section).replace("_", "-")
        cmd = commands.get(name)
        if cmd is None:
            raise InputError(
                f"config file {src}: unknown section '{section}'"
                + _suggest(name, sorted(commands), "commands")
            )
        out[name] = _check_section(str(section), opts or {}, cmd, src)
    return out


def _option_names(cmd: click.Command) -> dict[str, click.Parameter]:
    """Key (underscored flag or parameter name) -> parameter."""
    names: dict[str, click.Parameter] = {}
    for p in cmd.params:
        names[p.name] = p
        for flag in getattr(p, "opts", []):
            if flag.startswith("--"):
                names[flag[2:].replace("-", "_")] = p
    return names


def _check_section(section: str, opts: dict, cmd: click.Command, src: Path) -> dict:
    names = _option_names(cmd)
    flags = sorted({f[2:] for p in cmd.params for f in getattr(p, "opts", []) if f[:2] == "--"})
    out = {}
    for key, value in opts.items():
        norm = str(key).lstrip("-").replace("-", "_")
        p = names.get(norm)
        if p is None:
            dashed = norm.replace("_", "-")
            hint = _suggest(dashed, flags + [a.name for a in cmd.params if a.opts == [a.name]], "")
            if "_" in str(key):
                hint = hint.replace("-", "_")
            raise InputError(f"config file {src}: unknown key '{key}' in section '{section}'{hint}")
        if value is None:
            continue  # an empty key leaves the default
        if isinstance(p.type, click.Path) and isinstance(value, str | int | float) and value:
            value = str(value)
            value = value if Path(value).is_absolute() else str(src.parent / value)
        out[p.name] = _check_value(p, value, f"config file {src}: '{section}: {key}'")
    return out


def _check_value(p: click.Parameter, value, where: str):
    """The value if its type fits the parameter, else a one-line InputError naming the
    key. A value of the right type but out of range (or not a choice) fails only when it
    is used, so a flag on the command line still overrides it."""
    if isinstance(p, click.Option) and p.is_flag and not p.count:
        if not isinstance(value, bool):
            raise InputError(f"{where} must be true or false, not {_kind(value)}")
        return value
    if p.multiple or p.nargs != 1:
        items = value if isinstance(value, list) else [value]
        value = [_check_type(p, v, where) for v in items]
    else:
        value = _check_type(p, value, where)
    try:
        p.type_cast_value(None, value)
    except click.BadParameter as e:
        flag = next((f for f in getattr(p, "opts", []) if f.startswith("--")), None)
        message = f"{where}{f' ({flag})' if flag else ''}: {e.message}"

        def fail():
            raise InputError(message)

        return fail  # click calls a callable default_map value when it needs the value
    return value


def _check_type(p: click.Parameter, value, where: str):
    if isinstance(value, list | dict) or (isinstance(value, bool) and _wants_number(p)):
        raise InputError(f"{where} must be {_expected(p)}, not {_kind(value)}")
    if isinstance(p.type, click.Path):
        return str(value)
    base = (
        click.INT
        if isinstance(p.type, click.types.IntParamType)
        else click.FLOAT
        if isinstance(p.type, click.types.FloatParamType)
        else None
    )
    if base is not None:
        if isinstance(value, float) and base is click.INT and not value.is_integer():
            raise InputError(f"{where} must be {_expected(p)}, not {value!r}")
        try:
            base.convert(value, None, None)
        except (click.BadParameter, TypeError, ValueError):
            raise InputError(f"{where} must be {_expected(p)}, not {value!r}") from None
    return value


def _wants_number(p: click.Parameter) -> bool:
    return isinstance(p.type, click.types.IntParamType | click.types.FloatParamType)


def _expected(p: click.Parameter) -> str:
    t = p.type
    if isinstance(t, click.types.IntParamType):
        return "an integer"
    if isinstance(t, click.types.FloatParamType):
        return "a number"
    if isinstance(t, click.Path):
        return "a file path"
    if isinstance(t, click.Choice):
        return "one of " + ", ".join(map(str, t.choices))
    return "a single value"


def _kind(value) -> str:
    if isinstance(value, dict):
        return "a mapping"
    if isinstance(value, list):
        return "a list"
    return repr(value)


def _suggest(name: str, valid: list[str], what: str) -> str:
    close = difflib.get_close_matches(name, valid, n=1, cutoff=0.6)
    if close:
        return f" (did you mean '{close[0]}'?)"
    return f" (valid {what or 'keys'}: {', '.join(valid)})"


def default_of(owner, name: str):
    """The default of a core settings field or function parameter, for a click option:
    the value is written once, in the core, and `--help` still shows it."""
    if dataclasses.is_dataclass(owner):
        f = {f.name: f for f in dataclasses.fields(owner)}[name]
        if f.default is not dataclasses.MISSING:
            return f.default
        return f.default_factory()
    return inspect.signature(owner).parameters[name].default
