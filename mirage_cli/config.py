"""Layered options: packaged defaults < ./mirage.yaml or --config FILE < command-line flags.

The merged mapping becomes click's `default_map`, keyed by command name then option
name (e.g. `track: {method: mirage-s, model: landmark.mirage}`), so every flag a
command has can be set in the project's YAML without extra code per command.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import yaml

from .errors import InputError
from .fileio import read_yaml, require_file

PROJECT_CONFIG = "mirage.yaml"


def _read_yaml(path: Path) -> dict:
    data = read_yaml(path, "config file")
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise InputError(f"config file {path} must be a mapping of command -> options")
    for key, value in data.items():
        if value is not None and not isinstance(value, dict):
            raise InputError(f"config file {path}: '{key}' must be a mapping of options")
    return data


def default_config() -> dict:
    text = resources.files("mirage_cli").joinpath("default_config.yaml").read_text()
    return yaml.safe_load(text) or {}


def merge(base: dict, over: dict) -> dict:
    out = {k: (dict(v) if isinstance(v, dict) else v) for k, v in base.items()}
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = merge(out[k], v)
        else:
            out[k] = v
    return out


def load_config(path: str | None = None, cwd: Path | None = None) -> tuple[dict, Path | None]:
    """Merged config and the project file it came from (None when only defaults)."""
    cfg = default_config()
    if path is not None:
        src = require_file(path, "config file")
    else:
        src = (cwd or Path.cwd()) / PROJECT_CONFIG
        if not src.is_file():
            return _normalise(cfg), None
    return _normalise(merge(cfg, _read_yaml(src))), src


def _normalise(cfg: dict) -> dict:
    """Accept both `build-model`/`build_model` and `--flag-name`/`flag_name` spellings."""
    out = {}
    for cmd, opts in cfg.items():
        out[cmd.replace("_", "-")] = {
            k.lstrip("-").replace("-", "_"): v for k, v in (opts or {}).items()
        }
    return out
