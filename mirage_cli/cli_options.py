"""The option shapes the commands share, each declared once: files (a folder refused),
the -o/--output file, --camera, the INPUT... argument, and options whose default --help
shows. The flag names and help texts stay with the commands."""

from __future__ import annotations

import click

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
