"""The `mirage` command line: a thin layer over the core modules.

Every user-caused failure is a MirageError -> `mirage: error: ...`, exit 2. Anything
unexpected is one line and exit 1; `--debug` shows the traceback.
"""

from __future__ import annotations

import sys
import traceback

import click

from . import __version__, ui
from .config import check_config, read_config
from .errors import MirageError

_debug = {"on": False}


@click.group(context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(__version__, "-V", "--version", prog_name="mirage")
@click.option(
    "--config",
    "config_path",
    type=click.Path(dir_okay=False),
    help="YAML config (default: ./mirage.yaml if present).",
)
@click.option("-v", "--verbose", count=True, help="More detail (repeat for more).")
@click.option("-q", "--quiet", is_flag=True, help="Only errors; no progress bars or summaries.")
@click.option("--debug", is_flag=True, help="Show tracebacks of unexpected errors.")
@click.pass_context
def cli(ctx, config_path, verbose, quiet, debug):
    """mirage: camera pose around a known landmark, from one video.

    Typical project: calibrate -> build-model -> track -> report.
    Options can also come from ./mirage.yaml (section per command).
    """
    _debug["on"] = debug
    ui.setup(verbose, quiet)
    raw, src = read_config(config_path)
    ctx.default_map = check_config(raw, cli.commands, src) if src is not None else {}
    ctx.obj = {"config": ctx.default_map, "config_path": src}


def _register() -> None:
    """Commands are added here as they start to work (one module per stage)."""
    from .calibrate_cli import calibrate
    from .synth_cli import synth_cmd

    cli.add_command(calibrate)
    cli.add_command(synth_cmd)
    from .build_model_cli import build_model_cmd, inspect_cmd

    cli.add_command(build_model_cmd)
    cli.add_command(inspect_cmd)
    from .demo_cli import demo_cmd
    from .report_cli import report_cmd

    cli.add_command(report_cmd)
    cli.add_command(demo_cmd)
    from .track_cli import track_cmd

    cli.add_command(track_cmd)


_register()


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else list(argv)
    if "--debug" in argv:
        _debug["on"] = True
    try:
        cli.main(args=argv, prog_name="mirage", standalone_mode=False)
    except MirageError as e:
        if _debug["on"]:
            traceback.print_exc()
        click.echo(f"mirage: error: {e}", err=True)
        sys.exit(2)
    except click.exceptions.NoArgsIsHelpError as e:
        click.echo(e.ctx.get_help() if e.ctx else str(e))
        sys.exit(2)
    except click.UsageError as e:
        hint = (
            f" (see 'mirage {e.ctx.info_name} --help')"
            if e.ctx and e.ctx.parent
            else " (see 'mirage --help')"
        )
        click.echo(f"mirage: error: {e.format_message()}{hint}", err=True)
        sys.exit(2)
    except click.ClickException as e:
        click.echo(f"mirage: error: {e.format_message()}", err=True)
        sys.exit(e.exit_code or 2)
    except (KeyboardInterrupt, click.exceptions.Abort):
        click.echo("mirage: interrupted", err=True)
        sys.exit(130)
    except click.exceptions.Exit as e:
        sys.exit(e.exit_code)
    except BrokenPipeError:
        sys.exit(1)
    except Exception as e:  # noqa: BLE001 - the last line of defence
        if _debug["on"]:
            traceback.print_exc()
        msg = str(e).strip().splitlines()[-1] if str(e).strip() else ""
        click.echo(
            f"mirage: error: unexpected {type(e).__name__}: {msg} "
            f"(rerun with --debug for the traceback)",
            err=True,
        )
        sys.exit(1)
