"""The option shapes the commands share, each declared once: files (a folder refused),
the -o/--output file, --camera, the INPUT... argument, and options whose default --help
shows. The flag names and help texts stay with the commands."""

from __future__ import annotations

import functools
import math

import click

from ..errors import OptionError
from ..validate import When, parse_when

FILE = click.Path(dir_okay=False)
FOLDER = click.Path(file_okay=False)


def inputs_argument(name: str = "inputs", metavar: str = "INPUT..."):
    """One or more inputs: image files, folders, globs or a video."""
    return click.argument(name, nargs=-1, required=True, metavar=metavar)


def file_option(*decls: str, help: str, **kw):
    """An option naming a file."""
    return click.option(*decls, type=FILE, help=help, **kw)


def output_option(default: str, help: str):
    """-o/--output: the command's main output file."""
    return file_option("-o", "--output", default=default, show_default=True, help=help)


def camera_option(help: str, required: bool = False):
    """--camera FILE, a camera YAML (the parameter camera_path)."""
    return file_option("--camera", "camera_path", required=required, help=help)


def shown(*decls: str, **kw):
    """An option whose default --help shows."""
    return click.option(*decls, show_default=True, **kw)


def topic_option():
    """--topic NAME: the image topic of a ROS bag input (the parameter topic)."""
    return click.option(
        "--topic",
        default=None,
        metavar="NAME",
        help="ROS bag input: the image topic to read (sensor_msgs/Image or CompressedImage) "
        "[default: the bag's only image topic].",
    )


# --------------------------------------------------------------------------------------
# numbers from users: NaN and +-inf refused (see validate.py)
# --------------------------------------------------------------------------------------
def _describe(rng) -> str:
    """click's range text for --help, or nothing without bounds (click would print
    '[x<=None]')."""
    if rng.min is None and rng.max is None:
        return ""
    return click.types._NumberRangeBase._describe_range(rng)


class FiniteFloat(click.FloatRange):
    """A finite float within optional bounds (NaN and +-inf are refused with one line)."""

    name = "number"

    def _describe_range(self) -> str:
        return _describe(self)

    def convert(self, value, param, ctx):
        if isinstance(value, bool) or isinstance(value, list | dict | tuple):
            self.fail(f"{value!r} is not a number", param, ctx)
        rv = click.FLOAT.convert(value, param, ctx)
        if not math.isfinite(rv):
            self.fail(f"{value!r} is not a finite number", param, ctx)
        return super().convert(rv, param, ctx)


class BoundedInt(click.IntRange):
    """An integer within bounds; refuses floats with a fraction and lists from a config."""

    name = "integer"

    def _describe_range(self) -> str:
        return _describe(self)

    def convert(self, value, param, ctx):
        if isinstance(value, bool) or isinstance(value, list | dict | tuple):
            self.fail(f"{value!r} is not an integer", param, ctx)
        if isinstance(value, float) and not value.is_integer():
            self.fail(f"{value!r} is not an integer", param, ctx)
        return super().convert(value, param, ctx)


class FrameOrTime(click.ParamType):
    """'120' (frame number) or '4s' / '2.5s' (seconds); never negative, NaN or infinite."""

    name = "frame|seconds"

    def convert(self, value, param, ctx):
        if value is None or isinstance(value, When):
            return value
        try:
            return parse_when(value)
        except ValueError as e:
            self.fail(str(e), param, ctx)


FRAME_OR_TIME = FrameOrTime()


def float_list(text, option: str, min_value: float | None = None) -> list[float]:
    """Comma-separated finite numbers (e.g. --heights 0.4,0.8)."""
    parts = [t.strip() for t in str(text).split(",")]
    try:
        vals = [float(t) for t in parts]
    except ValueError:
        vals = []
    if not vals or not all(math.isfinite(v) for v in vals):
        raise click.BadParameter(
            f"{text!r} is not a comma-separated list of finite numbers", param_hint=f"'{option}'"
        )
    if min_value is not None and min(vals) < min_value:
        raise click.BadParameter(
            f"{text!r}: every value must be >= {min_value:g}", param_hint=f"'{option}'"
        )
    return vals


def option_errors(command):
    """The core's OptionError (e.g. frame_range's '--end') as click's usage error for that
    option, inside the command (so click names the command in the message)."""

    @functools.wraps(command)
    def wrapper(*args, **kwargs):
        try:
            return command(*args, **kwargs)
        except OptionError as e:
            raise click.BadParameter(e.message, param_hint=f"'{e.option}'") from None

    return wrapper
