"""Campaigns: many flights tracked and reported in one go, on local cores or a Dask cluster.

A campaign YAML names the flights (a video or images each, or a glob of them) and their
shared model, camera and desired path. `load_campaign` checks all of it before any work,
so a typo in flight 40 fails in a second, not after an hour. `run_flight` is the one
function that runs a flight, in this process, a pool worker or a Dask worker alike: the
same track and report pipelines (pipelines/track.py, pipelines/report.py) as the two
commands, into OUT/<name>/, then a done-marker written last. The marker records the
inputs' sizes and mtimes, an options hash and the outputs' sizes and hashes, so a re-run
skips a flight only when what it would write is already there, whole.
"""

from __future__ import annotations

import contextlib
import dataclasses
import difflib
import glob
import hashlib
import json
import os
import signal
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import __version__, fileio, logs, signals
from ..errors import InputError, MirageError, cv_message
from ..validate import When, finite_float, parse_when

TOP_KEYS = ("defaults", "flights", "videos")
TRUTH_KEYS = ("truth_topic", "truth_transform", "t_offset", "t_max_diff")  # as mirage report's
DEFAULT_KEYS = ("model", "camera", "path", "output", "start", "end", *TRUTH_KEYS)
FLIGHT_KEYS = ("video", "name", "model", "camera", "path", "truth", "start", "end", *TRUTH_KEYS)
MARKER = "done.json"
MARKER_FORMAT = 1
OUTPUTS = ("poses.csv", "report.csv", "summary.yaml")
CAMPAIGN_CSV, CAMPAIGN_PNG = "campaign.csv", "campaign.png"
COLUMNS = [
    "flight", "status", "frames", "tracked_pct",
    "path_error_median_m", "path_error_p95_m",
    "position_error_median_m", "position_error_p95_m",
    "rotation_error_median_deg", "rotation_error_p95_deg",
    "seconds", "resumed", "reason",
]  # fmt: skip
_GLOB_CHARS = "*?["


@dataclass(frozen=True)
class Flight:
    """One flight, every path absolute (workers may run elsewhere on a shared folder)."""

    name: str
    video: str  # a video, an image folder or glob, or whatever FrameSource reads
    model: str
    path: str  # desired path file
    camera: str | None = None  # default: the model's camera
    truth: str | None = None
    start: When | None = None
    end: When | None = None
    truth_topic: str | None = None  # a bag's pose topic (default: its only one)
    truth_transform: str | None = None  # T_body_camera, "x y z qw qx qy qz"
    t_offset: float = 0.0  # s added to the truth stamps (TUM, bags)
    t_max_diff: float = 0.01  # s: nearest truth stamp within this


@dataclass(frozen=True)
class Campaign:
    source: Path
    output: Path
    flights: list[Flight]


@dataclass
class FlightResult:
    """One row of campaign.csv."""

    flight: str
    status: str  # ok | failed | interrupted
    frames: int | None = None
    tracked_pct: float | None = None
    path_error_median_m: float | None = None
    path_error_p95_m: float | None = None
    position_error_median_m: float | None = None
    position_error_p95_m: float | None = None
    rotation_error_median_deg: float | None = None
    rotation_error_p95_deg: float | None = None
    seconds: float | None = None
    resumed: bool = False  # outputs kept from an earlier run
    reason: str = ""

    @property
    def ok(self) -> bool:
        return self.status == "ok"


# --------------------------------------------------------------------------------------
# the campaign file
# --------------------------------------------------------------------------------------
def load_campaign(path, output: str | os.PathLike | None = None) -> Campaign:
    """The checked campaign: every key known, every file there, names distinct. `output`
    (e.g. --out) overrides the file's output folder; the default is <stem>_out beside it."""
    src = fileio.require_file(path, "campaign file")
    data = fileio.read_yaml(src, "campaign file")
    where = f"campaign {src}"
    if not isinstance(data, dict):
        raise InputError(f"{where} must be a mapping with 'flights' (a list) or 'videos' (a glob)")
    _known(data, TOP_KEYS, where, "")
    defaults = data.get("defaults") or {}
    if not isinstance(defaults, dict):
        raise InputError(f"{where}: 'defaults' must be a mapping of {', '.join(DEFAULT_KEYS)}")
    _known(defaults, DEFAULT_KEYS, where, " in 'defaults'")
    base = src.parent

    entries: list[tuple[str, dict]] = []  # (where, raw flight)
    flights = data.get("flights") or []
    if not isinstance(flights, list):
        raise InputError(f"{where}: 'flights' must be a list (one '- video: FILE' per flight)")
    for i, f in enumerate(flights, 1):
        w = f"{where}: flight {i}"
        if isinstance(f, str):
            f = {"video": f}
        if not isinstance(f, dict):
            raise InputError(f"{w} must be a mapping with 'video' (or a video path)")
        _known(f, FLIGHT_KEYS, w, "")
        if not f.get("video"):
            raise InputError(f"{w} has no 'video'")
        entries.append((w, f))
    patterns = data.get("videos") or []
    for pattern in [patterns] if isinstance(patterns, str) else patterns:
        if not isinstance(pattern, str):
            raise InputError(f"{where}: 'videos' must be a glob or a list of globs")
        hits = sorted(glob.glob(str(_abs(base, pattern))), key=_natural)
        if not hits:
            raise InputError(f"{where}: videos '{pattern}' matches no file")
        entries += [(f"{where}: video {h}", {"video": h}) for h in hits]
    if not entries:
        raise InputError(f"{where} lists no flights (give 'flights' or 'videos')")

    out = Path(output) if output is not None else None
    if out is None:
        out = _abs(base, defaults["output"]) if defaults.get("output") else None
    out = (out or base / f"{src.stem}_out").absolute()
    result, seen = [], {}
    for w, f in entries:
        fl = _flight(f, defaults, base, w)
        if fl.name in seen:
            raise InputError(
                f"{where}: {seen[fl.name]} and {w.split(': ', 1)[1]} are both named "
                f"'{fl.name}'; give them distinct 'name's"
            )
        seen[fl.name] = w.split(": ", 1)[1]
        result.append(fl)
    campaign = Campaign(src, out, result)
    check_outputs(campaign)
    return campaign


def flight_inputs(flight: Flight) -> dict:
    """Every file, folder or glob a flight reads, by its campaign key."""
    transform = flight.truth_transform
    return {
        "video": flight.video,
        "model": flight.model,
        "path": flight.path,
        "camera": flight.camera,
        "truth": flight.truth,
        "truth_transform": transform if transform and os.path.exists(transform) else None,
    }


def check_outputs(campaign: Campaign) -> None:
    """Before anything runs: no file a flight writes (OUT/<name>/poses.csv, ...) nor the
    campaign's table and plot may be, or be inside, any flight's input or the campaign
    file (a truth CSV or a keyframe folder's poses.csv in the output folder would be
    overwritten, then 'matched' against itself)."""
    inputs = {"campaign file": str(campaign.source)}
    for f in campaign.flights:
        inputs |= {f"flight '{f.name}' {k}": v for k, v in flight_inputs(f).items() if v}
    outputs = {
        "output": [str(campaign.output / n) for n in (CAMPAIGN_CSV, CAMPAIGN_PNG)],
    }
    for f in campaign.flights:
        d = campaign.output / f.name
        outputs[f"flight '{f.name}' output"] = [str(d / n) for n in (*OUTPUTS, MARKER)]
    try:
        fileio.refuse_overwrite(outputs, inputs)
    except InputError as e:
        raise InputError(f"campaign {campaign.source}: {e}") from None


def _natural(p: str):
    from ..frames import natural_key

    return natural_key(Path(p))


def _known(d: dict, keys: tuple[str, ...], where: str, section: str) -> None:
    for k in d:
        if str(k) not in keys:
            close = difflib.get_close_matches(str(k), keys, n=1, cutoff=0.6)
            hint = f"did you mean '{close[0]}'?" if close else f"valid keys: {', '.join(keys)}"
            raise InputError(f"{where}: unknown key '{k}'{section} ({hint})")


def _abs(base: Path, value) -> Path:
    p = Path(str(value)).expanduser()
    return (p if p.is_absolute() else base / p).absolute()


def _flight(f: dict, defaults: dict, base: Path, where: str) -> Flight:
    def get(key, required=False, what="file"):
        value = f.get(key, defaults.get(key))
        if value in (None, ""):
            if required:
                raise InputError(f"{where} has no '{key}' (set it there or under 'defaults')")
            return None
        if not isinstance(value, str | int | float) or isinstance(value, bool):
            raise InputError(f"{where}: '{key}' must be a {what}")
        return value

    video = str(get("video", True, "path"))
    vpath = _abs(base, video)
    if any(c in video for c in _GLOB_CHARS):
        if not glob.glob(str(vpath)):
            raise InputError(f"{where}: video '{video}' matches no file")
    elif not vpath.exists():
        raise InputError(f"{where}: video {vpath} not found")
    files = {}
    for key, required in (("model", True), ("path", True), ("camera", False), ("truth", False)):
        value = get(key, required)
        if value is None:
            files[key] = None
            continue
        p = _abs(base, value)
        try:
            if not (key == "truth" and _is_bag(p)):  # a ROS 2 bag is a folder
                fileio.require_file(p, f"{key} file")
        except InputError as e:
            raise InputError(f"{where}: {e}") from None
        files[key] = str(p)
    truth = _truth_options(get, base, where)
    when = {}
    for key in ("start", "end"):
        value = get(key, what="frame number or seconds ('4s')")
        try:
            when[key] = parse_when(value) if value is not None else None
        except ValueError as e:
            raise InputError(f"{where}: '{key}' {e}") from None
    s, e = when["start"], when["end"]
    if s is not None and e is not None and s.seconds == e.seconds and e.value <= s.value:
        raise InputError(f"{where}: 'end' {e} must come after 'start' {s}")
    if s is not None and e is not None and s.seconds != e.seconds:  # frames and seconds
        from ..frames import FrameSource

        try:
            fps = FrameSource([vpath]).fps
        except MirageError:
            fps = None  # an unreadable video fails as that flight's failure, later
        if fps is not None and e.frame(fps) <= s.frame(fps):
            raise InputError(
                f"{where}: 'end' {e} (frame {e.frame(fps)}) must come after 'start' {s} "
                f"(frame {s.frame(fps)})"
            )
    name = str(get("name", what="name") or _default_name(vpath))
    if name.startswith(".") or "/" in name or "\\" in name or name in (CAMPAIGN_CSV, CAMPAIGN_PNG):
        raise InputError(f"{where}: name '{name}' must be a plain folder name")
    return Flight(name, str(vpath), path=files.pop("path"), **files, **when, **truth)


def _is_bag(p: Path) -> bool:
    from ..bags import is_bag_path

    return is_bag_path(p)


def _truth_options(get, base: Path, where: str) -> dict:
    """The truth keys, checked as `mirage report` checks its options; a transform that
    names a file is resolved against the campaign's folder."""
    from ..truth import BodyToCamera, TruthSettings

    out: dict = {}
    topic = get("truth_topic", what="topic name")
    out["truth_topic"] = None if topic is None else str(topic)
    transform = get("truth_transform", what="'x y z qw qx qy qz' or a file")
    if transform is not None:
        transform = str(transform)
        if _abs(base, transform).is_file():
            transform = str(_abs(base, transform))
        try:
            BodyToCamera.parse(transform)
        except InputError as e:
            raise InputError(f"{where}: 'truth_transform' {e}") from None
    out["truth_transform"] = transform
    # the checks and defaults of report's --t-offset / --t-max-diff
    for key, positive, default in (
        ("t_offset", False, TruthSettings.t_offset_s),
        ("t_max_diff", True, TruthSettings.t_max_diff_s),
    ):
        value = get(key, what="number of seconds")
        try:
            bound = {"min": 0, "min_open": True} if positive else {}
            out[key] = default if value is None else finite_float(value, **bound)
        except ValueError as e:
            above = " above 0" if key == "t_max_diff" else ""
            msg = f"{where}: '{key}' must be a finite number of seconds{above}: {e}"
            raise InputError(msg) from None
    return out


def _default_name(video: Path) -> str:
    """The file name without its extension (a folder's own name; a glob's folder)."""
    if any(c in video.name for c in _GLOB_CHARS):
        video = video.parent
    name = video.name if video.is_dir() else video.stem
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name).lstrip(".") or "flight"


# --------------------------------------------------------------------------------------
# one flight: the function every executor runs
# --------------------------------------------------------------------------------------
def run_flight(flight: Flight, out: str | os.PathLike) -> FlightResult:
    """Track and report one flight into OUT/<name>/; write the done-marker last.

    A user-fixable failure (corrupt video, wrong camera) is the result's `failed` status
    and reason, so the other flights go on; an interrupt propagates, keeping the frames
    done (the marker is not written, so a re-run redoes the flight).
    """
    t0 = time.perf_counter()
    d = Path(out) / flight.name
    try:
        fileio.ensure_dir(d)
        with contextlib.suppress(FileNotFoundError):
            (d / MARKER).unlink()  # from here on the old outputs are not vouched for
        inputs = fingerprint(flight)
        res = _track_and_report(flight, d)
    except MirageError as e:
        return FlightResult(flight.name, "failed", seconds=_secs(t0), reason=str(e))
    except Exception as e:  # noqa: BLE001 - one flight's bug must not stop the campaign
        reason = f"unexpected {type(e).__name__}: {cv_message(e)}"
        return FlightResult(flight.name, "failed", seconds=_secs(t0), reason=reason)
    res.seconds = _secs(t0)
    marker = {
        "format": MARKER_FORMAT,
        "inputs": inputs,
        "options": options_hash(flight),
        "outputs": {n: _file_digest(d / n) for n in OUTPUTS},
        "result": dataclasses.asdict(res),
    }
    with fileio.atomic_write(d / MARKER) as f:
        json.dump(marker, f, indent=1)
    return res


def _secs(t0: float) -> float:
    return round(time.perf_counter() - t0, 3)


def _track_and_report(flight: Flight, d: Path) -> FlightResult:
    """What `mirage track` then `mirage report --summary` do (the same pipelines), silently."""
    from ..frames import FrameSource
    from ..model import LandmarkModel
    from ..path import load_path
    from ..truth import BodyToCamera, TruthSettings
    from .report import report, write_report
    from .track import open_job, track

    load_path(flight.path)  # a bad desired path fails before the tracking
    model = LandmarkModel.load(flight.model)
    src = FrameSource([flight.video])
    job = open_job(model, src, d / "poses.csv", flight.camera, start=flight.start, end=flight.end)
    result = track(job)
    if result.interrupted is not None:
        raise result.interrupted
    settings = TruthSettings(
        flight.truth_topic,
        BodyToCamera.parse(flight.truth_transform),
        flight.t_offset,
        flight.t_max_diff,
    )
    # a pose CSV, TUM or a bag pose topic, as `mirage report --truth`
    rep = report(d / "poses.csv", flight.path, flight.truth, settings).report
    write_report(rep, d / "report.csv", d / "summary.yaml")
    return result_of(flight.name, rep.table, rep.summary)


def result_of(name: str, table, summary: dict) -> FlightResult:
    """The campaign row of a report: tracked share and the medians / p95 of the errors.

    Path error is the distance to the nearest point of the desired path (cross-track and
    height error together)."""
    path_err = np.hypot(
        table["cross_track_m"].to_numpy(float), table["height_error_m"].to_numpy(float)
    )
    r = FlightResult(name, "ok", frames=summary["frames"], tracked_pct=summary["tracked_pct"])
    r.path_error_median_m, r.path_error_p95_m = _median_p95(path_err)
    if "position_error_m" in table:
        r.position_error_median_m, r.position_error_p95_m = _median_p95(
            table["position_error_m"].to_numpy(float)
        )
        r.rotation_error_median_deg, r.rotation_error_p95_deg = _median_p95(
            table["rotation_error_deg"].to_numpy(float)
        )
    return r


def _median_p95(v) -> tuple[float | None, float | None]:
    v = np.abs(np.asarray(v, float))
    v = v[np.isfinite(v)]
    if not len(v):
        return None, None
    return float(f"{np.median(v):.7g}"), float(f"{np.percentile(v, 95):.7g}")


# --------------------------------------------------------------------------------------
# resume: the done-marker
# --------------------------------------------------------------------------------------
def _stat(p: Path) -> list:
    st = p.stat()
    return [str(p), st.st_size, st.st_mtime_ns]


def fingerprint(flight: Flight) -> list:
    """Sizes and mtimes of every input file (an image folder's or a glob's files too)."""
    out = []
    v = flight.video
    paths = sorted(Path(h) for h in glob.glob(v)) if any(c in v for c in _GLOB_CHARS) else [Path(v)]
    for p in paths:
        if p.is_dir():
            out += [_stat(f) for f in sorted(p.iterdir()) if f.is_file()]
        else:
            out.append(_stat(p))
    for f in (flight.model, flight.camera, flight.path, flight.truth, flight.truth_transform):
        if f and Path(f).is_dir():  # a ROS 2 bag
            out += [_stat(g) for g in sorted(Path(f).iterdir()) if g.is_file()]
        elif f and Path(f).is_file():
            out.append(_stat(Path(f)))
    return out


def options_hash(flight: Flight) -> str:
    """What, besides the input files, decides the outputs: the range, the track settings
    and the software version."""
    from ..tracking import TrackSettings

    opts = {
        "version": __version__,
        "start": str(flight.start) if flight.start else None,
        "end": str(flight.end) if flight.end else None,
        "truth": bool(flight.truth),
        "truth_options": [
            flight.truth_topic,
            flight.truth_transform,
            flight.t_offset,
            flight.t_max_diff,
        ],  # fmt: skip
        "track": dataclasses.asdict(TrackSettings()),
    }
    return hashlib.sha256(json.dumps(opts, sort_keys=True).encode()).hexdigest()[:16]


def _file_digest(p: Path) -> list:
    h = hashlib.sha256()
    with open(p, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return [p.stat().st_size, h.hexdigest()]


def completed(flight: Flight, out: str | os.PathLike) -> FlightResult | None:
    """The earlier run's result if its marker vouches for outputs that are all there and
    for the same inputs and options; else None (the flight is to be run)."""
    d = Path(out) / flight.name
    try:
        marker = json.loads((d / MARKER).read_text())
        if marker.get("format") != MARKER_FORMAT or marker.get("options") != options_hash(flight):
            return None
        if marker.get("inputs") != fingerprint(flight):
            return None
        for name in OUTPUTS:
            if marker["outputs"].get(name) != _file_digest(d / name):
                return None
        res = FlightResult(**marker["result"])
    except (OSError, ValueError, TypeError, KeyError, AttributeError):
        return None
    res.resumed = True
    return res


# --------------------------------------------------------------------------------------
# executors
# --------------------------------------------------------------------------------------
_busy = {"on": False}


def _worker_init() -> None:
    """A pool worker: the parent handles Ctrl-C; SIGTERM (the parent stopping the pool)
    ends a running flight through the usual interrupt path (frames done are kept), an idle
    worker at once; OpenCV on one thread (N workers on N cores, not N x N threads)."""
    import cv2

    signals.install()
    inner = signal.getsignal(signal.SIGTERM)

    def term(signum, frame):
        if _busy["on"]:
            inner(signum, frame)
        else:
            os._exit(143)

    signal.signal(signal.SIGTERM, term)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    cv2.setNumThreads(1)
    logs.setup(0, quiet=True)


def _pool_flight(flight: Flight, out: str) -> FlightResult:
    _busy["on"] = True
    try:
        return run_flight(flight, out)
    except KeyboardInterrupt:
        fileio.cleanup_temps()
        os._exit(143)
    finally:
        _busy["on"] = False


def _dask_flight(flight: Flight, out: str) -> FlightResult:
    """On a Dask worker (a thread of a worker process): one OpenCV thread, no printing."""
    import cv2

    cv2.setNumThreads(1)
    logs.setup(0, quiet=True)
    return run_flight(flight, out)


def run_campaign(
    campaign: Campaign,
    workers: int | None = None,
    scheduler: str | None = None,
    force: bool = False,
    on_result: Callable[[FlightResult], None] = lambda r: None,
) -> list[FlightResult]:
    """Every flight's result, in campaign order. Complete flights are kept (unless
    `force`); the others run serially (`workers` 1), on a local process pool, or on the
    Dask scheduler at `scheduler`. `on_result` sees each result as it comes.

    Ctrl-C stops the running flights; the results so far (the rest `interrupted`) are on
    the exception as `.results`, for the caller to write out."""
    client = _dask_client(scheduler) if scheduler else None  # a wrong address fails first
    results: dict[str, FlightResult] = {}
    todo = []
    for f in campaign.flights:
        done = None if force else completed(f, campaign.output)
        if done is not None:
            results[f.name] = done
            on_result(done)
        else:
            todo.append(f)
    fileio.ensure_dir(campaign.output)
    out = str(campaign.output)

    def got(r: FlightResult) -> None:
        results[r.flight] = r
        on_result(r)

    try:
        if client is not None:
            _run_dask(todo, out, client, got)
        elif (workers or os.cpu_count() or 1) == 1 or len(todo) <= 1:
            for f in todo:
                got(run_flight(f, out))
        else:
            _run_pool(todo, out, min(workers or os.cpu_count() or 1, len(todo)), got)
    except KeyboardInterrupt as e:
        e.results = _ordered(campaign, results)
        raise
    finally:
        if client is not None:
            with contextlib.suppress(Exception):
                client.close()
    return _ordered(campaign, results)


def _ordered(campaign: Campaign, results: dict[str, FlightResult]) -> list[FlightResult]:
    return [
        results.get(f.name) or FlightResult(f.name, "interrupted", reason="not finished")
        for f in campaign.flights
    ]


def _run_pool(todo: list[Flight], out: str, workers: int, got) -> None:
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor, as_completed
    from concurrent.futures.process import BrokenProcessPool

    ex = ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn"), initializer=_worker_init)
    try:
        futures = {ex.submit(_pool_flight, f, out): f for f in todo}
        for fut in as_completed(futures):
            try:
                got(fut.result())
            except BrokenProcessPool:  # a worker died (a crash in native code)
                got(FlightResult(futures[fut].name, "failed", reason="its worker process died"))
    except BaseException:
        # Ctrl-C (or a failing output): stop now; running flights keep their frames done
        # (SIGTERM ends them through track's interrupt path), queued ones never start
        procs = list((getattr(ex, "_processes", None) or {}).values())
        ex.shutdown(wait=False, cancel_futures=True)
        for p in procs:
            with contextlib.suppress(Exception):
                p.terminate()
        for p in procs:
            with contextlib.suppress(Exception):
                p.join(10)
        raise
    ex.shutdown(wait=True)


def _dask_client(address: str):
    """A client of the scheduler at `address` (distributed is imported only here)."""
    try:
        from distributed import Client
    except ImportError:
        raise InputError(
            "--scheduler needs distributed: pip install -e '.[batch]' in the mirage-cli checkout"
        ) from None
    import logging

    logging.getLogger("distributed").setLevel(logging.ERROR)  # its reconnect chatter
    try:
        return Client(address, timeout="10s")
    except (OSError, TimeoutError, ValueError) as e:
        raise InputError(f"cannot reach the Dask scheduler at {address}: {e}") from None


def _run_dask(todo: list[Flight], out: str, client, got) -> None:
    from distributed import as_completed

    futures = {client.submit(_dask_flight, f, out, pure=False): f for f in todo}
    try:
        for fut in as_completed(list(futures)):
            try:
                got(fut.result())
            except Exception as e:  # noqa: BLE001 - e.g. the worker cannot import mirage_cli
                reason = f"on the Dask worker: {type(e).__name__}: {cv_message(e)}"
                got(FlightResult(futures[fut].name, "failed", reason=reason))
    except KeyboardInterrupt:
        with contextlib.suppress(Exception):
            client.cancel(list(futures))
        raise


# --------------------------------------------------------------------------------------
# campaign outputs
# --------------------------------------------------------------------------------------
def campaign_table(results: Iterable[FlightResult]):
    import pandas as pd

    return pd.DataFrame([dataclasses.asdict(r) for r in results], columns=COLUMNS)


def write_campaign_csv(results: list[FlightResult], path) -> None:
    with fileio.atomic_write(path, newline="") as f:
        campaign_table(results).to_csv(f, index=False, float_format="%.7g", lineterminator="\n")


def campaign_figure(results: list[FlightResult]):
    """Per flight: tracked %, then the median and p95 of the path error and (with truth)
    of the position and rotation errors, each on its own axis (they differ by orders of
    magnitude); flights that did not finish are marked."""
    from ..plotting import import_matplotlib

    import_matplotlib()
    from matplotlib.figure import Figure

    panels = [("path error (m)", "path_error_median_m", "path_error_p95_m", 1.0)]
    if any(r.position_error_median_m is not None for r in results):
        panels += [
            ("position error (cm)", "position_error_median_m", "position_error_p95_m", 100.0),
            ("rotation error (deg)", "rotation_error_median_deg", "rotation_error_p95_deg", 1.0),
        ]
    x = np.arange(len(results))
    fig = Figure(figsize=(max(6.0, 0.5 * len(results) + 3), 2.2 * (len(panels) + 1) + 0.8))
    axes = fig.subplots(len(panels) + 1, 1, sharex=True)
    tracked = [r.tracked_pct or 0.0 for r in results]
    axes[0].bar(x, tracked, color=["tab:blue" if r.ok else "tab:red" for r in results])
    for i, r in enumerate(results):
        if not r.ok:
            axes[0].annotate(r.status, (i, 3), ha="center", rotation=90, color="tab:red")
    axes[0].set(ylabel="tracked (%)", ylim=(0, 105))
    axes[0].set_title(f"campaign: {len(results)} flights, {sum(r.ok for r in results)} ok")
    for ax, (label, med, p95, scale) in zip(axes[1:], panels, strict=True):
        m = np.array([_nan(getattr(r, med)) for r in results]) * scale
        p = np.array([_nan(getattr(r, p95)) for r in results]) * scale
        ax.bar(x, p, 0.6, color="tab:orange", alpha=0.5, label="p95")
        ax.bar(x, m, 0.6, color="tab:blue", label="median")
        ax.set_ylabel(label)
        ax.legend(fontsize=8, loc="upper right")
    for ax in axes:
        ax.grid(alpha=0.3, axis="y")
    axes[-1].set_xticks(x, [r.flight for r in results], rotation=45, ha="right", fontsize=8)
    fig.tight_layout()
    return fig


def _nan(v) -> float:
    return float("nan") if v is None else float(v)
