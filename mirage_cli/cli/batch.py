"""`mirage batch CAMPAIGN.yaml`: thin CLI over mirage_cli.batch (one line per flight, the
campaign CSV and plot)."""

from __future__ import annotations

import time

import click

from .. import signals
from ..errors import InputError
from ..fileio import check_writable, ensure_dir
from ..pipelines.campaign import (
    CAMPAIGN_CSV,
    CAMPAIGN_PNG,
    FlightResult,
    campaign_figure,
    load_campaign,
    run_campaign,
    write_campaign_csv,
)
from ..plotting import save_png
from . import ui
from .options import FILE, FOLDER, BoundedInt


@click.command("batch")
@click.argument("campaign", type=FILE)
@click.option(
    "--out",
    type=FOLDER,
    default=None,
    help="Output folder [default: the campaign's 'output', else <campaign>_out beside it].",
)
@click.option(
    "--workers",
    type=BoundedInt(min=1),
    default=None,
    help="Flights run at once on local processes [default: CPUs].",
)
@click.option(
    "--scheduler",
    metavar="ADDRESS",
    default=None,
    help="Run the flights on this Dask scheduler (tcp://host:8786); its workers need "
    "mirage-cli and the files on a shared path.",
)
@click.option("--force", is_flag=True, help="Recompute every flight, also complete ones.")
def batch_cmd(campaign, out, workers, scheduler, force):
    """Track and report every flight of a campaign YAML, in parallel; re-runs resume.

    \b
    Example:
      mirage batch campaign.yaml --workers 2      # OUT/<flight>/poses.csv, report.csv, ...
      mirage batch campaign.yaml --scheduler tcp://10.0.0.5:8786
    """
    t0 = time.perf_counter()
    c = load_campaign(campaign, out)
    ensure_dir(c.output)
    csv_path, png_path = check_writable(c.output / CAMPAIGN_CSV), c.output / CAMPAIGN_PNG
    where = f"Dask scheduler {scheduler}" if scheduler else _workers_text(workers)
    ui.echo(f"batch: {len(c.flights)} flights from {campaign} into {c.output}/ ({where})")
    try:
        results = run_campaign(c, workers, scheduler, force, on_result=_say)
    except KeyboardInterrupt as e:
        done = [r for r in getattr(e, "results", []) if r.status != "interrupted"]
        with signals.deferred():
            if done:
                write_campaign_csv(e.results, csv_path)
        signals.note(e, f"kept {len(done)} finished flight(s) in {c.output}; rerun to resume")
        raise
    write_campaign_csv(results, csv_path)
    save_png(campaign_figure(results), png_path, 100)
    failed = [r.flight for r in results if not r.ok]
    ok = len(results) - len(failed)
    ui.echo(
        f"batch: {ok} ok, {len(failed)} failed; wrote {csv_path}, {png_path} "
        f"({time.perf_counter() - t0:.1f} s)"
    )
    if failed:
        raise InputError(
            f"{len(failed)} of {len(results)} flights failed ({', '.join(failed)}); see {csv_path}"
        )


def _workers_text(workers: int | None) -> str:
    import os

    n = workers or os.cpu_count() or 1
    return "serial" if n == 1 else f"up to {n} local workers"


def _say(r: FlightResult) -> None:
    """One line a flight, as it finishes."""
    if r.resumed:
        ui.echo(f"  {r.flight}: complete from an earlier run, skipped")
        return
    if not r.ok:
        ui.echo(f"  {r.flight}: {r.status}: {r.reason}")
        return
    text = f"  {r.flight}: ok, {r.frames} frames, {r.tracked_pct:.1f}% tracked"
    if r.path_error_median_m is not None:
        text += f", path error median {r.path_error_median_m:.3f} m"
    if r.position_error_median_m is not None:
        text += (
            f", truth error median {r.position_error_median_m * 100:.2f} cm"
            f" / {r.rotation_error_median_deg:.2f} deg"
        )
    ui.echo(f"{text} ({r.seconds:.1f} s)")
