"""`mirage track`'s pipeline: model -> frame source -> camera -> Tracker -> smoother ->
the pose CSV (and TUM / KITTI, overlay video, Rerun recording), written row by row.

The one place the tracking set-up is written (`open_job`) and the smoother composed
(`tracked_records`, `track`): the command, `demo`, `batch` and the benchmarks call these.
"""

from __future__ import annotations

import contextlib
import os
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from .. import refine, runtime, signals
from ..camera import Camera, lens_fold_warning
from ..errors import EnvironmentFailure, InputError, NothingFound, OutputError
from ..extend import ViewPicker, extended_model, why_not_extend
from ..fileio import atomic_path, video_frames_written
from ..frames import Frame, FrameSource, matching_camera, prefetch
from ..logs import log
from ..model import LandmarkModel
from ..plotting import draw_overlay
from ..records import FrameRecord, Status
from ..tracking import Tracker, TrackSettings, track_frames, warm_up
from ..tracking.smooth import Smoother, SmoothSettings, lapack_band_solvers, smoothed
from ..trajectory import TRACK_COLUMNS, TrajectoryWriter
from ..validate import When, frame_range
from ..viewer import TrackRecording
from .reporting import SILENT, Reporter


@dataclass
class TrackJob:
    """What one tracking run reads and writes."""

    source: FrameSource
    tracker: Tracker
    output: Path  # the pose CSV
    first: int = 0
    last: int | None = None  # the frame to stop before
    every: int = 1
    smooth: SmoothSettings = field(default_factory=SmoothSettings)
    formats: dict[str, str] = field(default_factory=dict)  # format name -> file, e.g. tum
    overlay: str | None = None
    rerun: str | None = None
    extend: bool = False  # track again against the model grown from the video (extend.py)
    extended_model: Path | None = None  # with `extend`: where to save the grown model


@dataclass
class TrackResult:
    """A finished (or interrupted) run: status and inliers per frame, for the summary."""

    output: Path
    rows: list[tuple[str, int]]  # (status, inliers) per frame
    elapsed: float  # seconds of tracking (after the solver's warm-up)
    interrupted: KeyboardInterrupt | None = None  # raise it once the summary is out
    records: list[tuple] = field(default_factory=list)  # with verbose: see `refusal_lines`
    written: list[FrameRecord] = field(default_factory=list)  # with --extend: every record
    added: int = 0  # with --extend: tracked frames that joined the model

    @property
    def frames_per_s(self) -> float:
        return len(self.rows) / self.elapsed if self.elapsed > 0 else float("inf")


def tracking_camera(
    model: LandmarkModel, camera_path, src: FrameSource, reporter: Reporter = SILENT
) -> Camera:
    """The camera to track `src` with: the camera file, else a bag's camera_info, else the
    model's own (at the frames' size). Another camera than the model's is fine (a model
    built from a phone's photos, a flight filmed by the drone's camera): the model is 3D
    points and scale-invariant descriptors, and the tracker projects with this camera."""
    camera, origin = model.camera, None
    if camera_path:
        camera, origin = Camera.load(camera_path), str(camera_path)
    elif (info := src.camera()) is not None:
        camera, origin = info, f"the camera_info of {src.bag.topic}"
    if origin and not camera.same_as(model.camera, tol_px=1.0):
        reporter.echo(
            f"track: the model was built with another camera ({_describe(model.camera)}); "
            f"tracking with {origin} ({_describe(camera)})"
        )
    camera = matching_camera(camera, *src.size)
    if (fold := lens_fold_warning(camera)) is not None:
        log.warning(f"{fold}; recalibrate with the board in the corners")
    return camera


def _describe(camera: Camera) -> str:
    return f"{camera.width}x{camera.height}, fx {camera.K[0, 0]:.0f} px"


def open_job(
    model: LandmarkModel,
    source: FrameSource,
    output,
    camera_path=None,
    settings: TrackSettings | None = None,
    start: When | None = None,
    end: When | None = None,
    reporter: Reporter = SILENT,
    **job,
) -> TrackJob:
    """The tracking set-up of `mirage track`: the camera (`tracking_camera`), the frame
    range (an empty one fails before any output), the Tracker with `settings` (default
    TrackSettings()) and OpenCV's threads sized for it. `job`: TrackJob's other fields."""
    settings = settings or TrackSettings()
    camera = tracking_camera(model, camera_path, source, reporter)
    first, last = frame_range(start, end, source.fps)
    if source.count == 0 and source.is_video:
        log.warning(f"{source.video}: frame count unknown; reading until the end")
    if settings.method == "ap3p":
        log.warning("ap3p solves from 3 points only: for comparing solvers, not for results")
    tracker = Tracker(model, camera, settings)
    runtime.opencv_threads_for_two_callers()
    return TrackJob(source, tracker, Path(output), first or 0, last, **job)


def tracked_records(
    frames: Iterable[Frame],
    tracker: Tracker,
    smoothing: SmoothSettings | None = None,
    keep_images: bool = False,
) -> Iterator[FrameRecord]:
    """The tracker's records of `frames`, each smoothed (`smoothing.lag` frames late;
    default settings when None, lag 0: each frame's own pose): what `mirage track` writes,
    for callers that hold the frames themselves (benchmarks, tests; the CLI's frames are
    `FrameSource.frames(luma=True)`: gray from a video's luma plane, a grey level or two
    off BGR2GRAY of its colour)."""
    return smoothed(track_frames(frames, tracker, keep_images), smoothing or SmoothSettings())


def extended_records(
    frames: Callable[[], Iterable[Frame]],
    tracker: Tracker,
    smoothing: SmoothSettings | None = None,
) -> tuple[list[FrameRecord], LandmarkModel | None]:
    """`tracked_records` with `--extend` (extend.py): the frames tracked once, the model
    built again with the well-tracked frames from new views, and the frames that were not
    ok tracked again against it; the first pass's ok records stand. `frames` gives the
    frames anew for each pass. Also the extended model (None: nothing to add)."""
    picker = ViewPicker(tracker.model)
    first = list(_picking(frames(), tracker, smoothing, picker))
    if why_not_extend(tracker.model, tracker.camera, picker, first) is not None:
        return first, None
    model = extended_model(tracker.model, picker.views)
    again = Tracker(model, tracker.camera, tracker.base_settings)
    second = tracked_records(frames(), again, smoothing)
    return [a if a.ok else b for a, b in zip(first, second, strict=True)], model


def _picking(frames: Iterable[Frame], tracker, smoothing, picker: ViewPicker):
    """`tracked_records`, offering each record to `picker` with its frame's image."""
    held: dict = {}
    for rec in tracked_records(_holding(frames, held), tracker, smoothing):
        picker.offer(rec, held.pop(rec.frame, None))
        yield rec


_early: dict = {}


def start_warm_up() -> None:
    """Load the compiled kernels from numba's cache on a thread of their own while the
    model and the video open: 9 kernels at ~45 ms each, mostly LLVM's linking with the
    GIL released, are 0.4 s of the 1.8 s wait for a first pose (144 keyframes; the
    imports are 0.9 s), 0.1 s less this way. A signal meanwhile interrupts the main
    thread as ever (the loads' callbacks run on this thread, where they cannot swallow
    it). Not on a first run: the compile is announced, then done."""
    if refine.cached_on_disk() and "thread" not in _early:
        _early["thread"] = _WarmUp()
        _early["thread"].start()


class _WarmUp(threading.Thread):
    """`warm_up` on its own thread; its error kept for the thread that waits for it."""

    def __init__(self) -> None:
        super().__init__(name="mirage-warm-up")
        self.error: Exception | None = None

    def run(self) -> None:
        try:
            warm_up()
            lapack_band_solvers()  # the smoother's scipy.linalg, imported here too
        except Exception as e:  # noqa: BLE001 - raised where the solver is first needed
            self.error = e


def warm_up_solver(reporter: Reporter = SILENT) -> None:
    """Compile or load the pose solver before the first frame's clock starts; loading from
    the cache (under a second) runs numba's callbacks, which would swallow a signal: held
    meanwhile. A load begun early (`start_warm_up`) is waited for."""
    early = _early.pop("thread", None)
    if early is not None:
        early.join()
        if early.error is not None:
            raise early.error
    if not refine.cached_on_disk():
        reporter.echo("compiling the pose solver for this machine (first run only, about 10 s)")
    with (
        reporter.stage("load the compiled solver"),
        signals.deferred() if refine.cached_on_disk() else contextlib.nullcontext(),
    ):
        warm_up()
        lapack_band_solvers()  # (imported on the early thread, else here: not in frame 1)
    signals.check()


def track(job: TrackJob, reporter: Reporter = SILENT) -> TrackResult:
    """Track the job's frames, writing each record to the pose CSV (and the other formats,
    the overlay and the Rerun recording) as it comes, `job.smooth.lag` frames late.
    Ctrl-C or SIGTERM keeps the finished frames in every output and comes back as the
    result's `interrupted`, for the caller to raise once it has said what was kept."""
    # OpenCV's RNG (a thread's own) as a new process has it: the model's KD-tree index is
    # randomized from it, so a run after others in one process (`batch` serially) matched
    # otherwise than a fresh one (9th digit of a pose, gray from luma on a flight of the
    # sample); 0 is RNG's default state
    cv2.setRNGSeed(0)
    warm_up_solver(reporter)
    runtime.keep_freed_memory()  # every detection's pyramid reuses the last one's pages
    points = job.tracker.model.points
    axis_m = float(np.ptp(points, axis=0).max() * 0.4) if len(points) else 0.2
    picker = ViewPicker(job.tracker.model) if job.extend else None
    result = _run(job, axis_m, reporter, picker=picker)
    reporter.detail(f"stage tracking: {result.elapsed:.2f} s")
    if picker is not None and result.interrupted is None:
        result = _track_again(job, result, picker, axis_m, reporter)
    return result


def _track_again(job: TrackJob, first: TrackResult, picker: ViewPicker, axis_m, reporter):
    """`--extend`'s second pass: the model built again with the picked frames, the frames
    tracked again against it, and every output written again: the first pass's ok records
    as they were, the second's for the rest (an interrupt keeps the first pass's rows
    for the frames it did not reach)."""
    tracker = job.tracker
    why = why_not_extend(tracker.model, tracker.camera, picker, first.written)
    if why is not None:
        reporter.echo(f"extend: {why}; the poses are the first pass's")
        return first
    t0 = time.perf_counter()
    with reporter.stage(f"extend the model with {len(picker.views)} tracked frames"):
        model = extended_model(tracker.model, picker.views)
    reporter.detail(f"extended model: {len(model.keyframes)} keyframes, {len(model.points)} points")
    if job.extended_model is not None:
        model.save(job.extended_model)
        reporter.echo(f"extend: the grown model written to {job.extended_model}")
    again = replace(job, tracker=Tracker(model, tracker.camera, tracker.base_settings))
    result = _run(again, axis_m, reporter, first=first.written)
    result.elapsed = first.elapsed + time.perf_counter() - t0  # both passes, the build
    result.added = len(picker.views)
    return result


def _outputs(job: TrackJob) -> list[tuple[str, str]]:
    return [(job.output, "csv")] + [(path, fmt) for fmt, path in job.formats.items() if path]


def _run(
    job: TrackJob,
    axis_m: float,
    reporter: Reporter,
    picker: ViewPicker | None = None,
    first: list[FrameRecord] | None = None,
) -> TrackResult:
    """Run the tracker over the frames and write every record to every output as it comes.
    An interrupt keeps the finished frames (outputs renamed into place with further signals
    held) and is returned. `picker`, `first`: `--extend`'s first and second pass (`_Passes`)."""
    src, tracker = job.source, job.tracker
    outputs = _outputs(job)
    total = None
    if src.count:
        stop = min(src.count, job.last) if job.last else src.count
        total = len(range(job.first, stop, job.every))
    done: list[tuple[str, int]] = []  # (status, inliers) per frame, for the summary
    decided: list[tuple] = []  # with -v: (frame, status, keyframe, inliers, matches, mode)
    verbose = reporter.verbose()
    interrupted = failed = None
    smoother = Smoother(job.smooth)
    t_start = time.perf_counter()
    with contextlib.ExitStack() as hold, contextlib.ExitStack() as stack:
        writers, ov, rrd = _open_outputs(stack, job, outputs, axis_m)
        bar = stack.enter_context(reporter.progress(total, "tracking"))
        keep = ov is not None or rrd is not None  # the overlays draw on the colour image
        # decoded and grayed in the reader thread, a few frames ahead; a video's gray straight
        # from its luma plane (1080p: no conversion to BGR and back), the same with overlays
        # (their colour from a second decoder): --overlay never changes the poses
        # (test_deterministic_with_overlay)
        frames = prefetch(src.frames(job.first, job.last, job.every, luma=True, colour=keep))
        passes = _Passes(picker, first)
        frames = passes.holding(frames)

        def emit(records):
            for rec in passes(records):
                # a record goes to every output or to none: a signal waits until it is out
                # (else the overlay could hold a frame fewer than the CSV)
                with signals.deferred():
                    for w in writers:
                        w.write(rec)
                    if rrd is not None:  # before the overlay, which takes the image
                        rrd.write(rec)
                    if ov is not None:
                        ov.write(rec)
                    done.append((rec.status, rec.inliers))
                    if verbose:
                        decided.append((rec.frame, str(rec.status), rec.keyframe, rec.inliers,
                                        rec.matches, rec.mode, str(rec.cause),
                                        str(rec.reason or "")))  # fmt: skip
                        reporter.detail(frame_line(rec), 2)
                if len(done) % 10 == 0:
                    rate = len(done) / max(time.perf_counter() - t_start, 1e-9)
                    bar.update(10, f"{rate:.0f} frames/s")

        try:
            for rec in track_frames(frames, tracker, keep_images=keep):
                emit(smoother.push(rec))
            with signals.deferred():  # the last frames held back by the smoother
                emit(smoother.flush())
        except (KeyboardInterrupt, InputError) as e:  # (InputError: a damaged keyframe image)
            hold.enter_context(signals.deferred())  # a second signal waits for the files
            emit(smoother.flush())  # the frames already tracked are kept
            emit(passes.rest())  # --extend's second pass: the first's rows for the rest
            if not writers[0].rows:
                signals.note(e, f"no frame finished; {outputs[0][0]} not written")
                raise
            if isinstance(e, InputError):  # raised once the files are in place
                e.args, failed = (f"{e} (kept {writers[0].rows} frames in {outputs[0][0]})",), e
            else:
                interrupted = e
        if not done and interrupted is None:
            raise InputError("no frames in the selected range (check --start/--end)")
    if failed is not None:
        raise failed  # after the outputs are in place
    elapsed = time.perf_counter() - t_start
    if interrupted is not None:
        signals.note(interrupted, f"kept {writers[0].rows} frames in {outputs[0][0]}")
    return TrackResult(job.output, done, elapsed, interrupted, decided, passes.written)


def _open_outputs(stack, job: TrackJob, outputs, axis_m: float):
    """The trajectory writers (every format is offered the diagnostic columns; TUM's and
    KITTI's rows skip them), the overlay video and the Rerun recording (None: not asked)."""
    camera, src = job.tracker.camera, job.source
    writers = [stack.enter_context(TrajectoryWriter(p, f, TRACK_COLUMNS)) for p, f in outputs]
    fps = src.fps / job.every if src.fps else 10.0
    ov = rrd = None
    if job.overlay:
        ov = stack.enter_context(OverlayVideo(job.overlay, fps, camera, axis_m))
    if job.rerun:
        rrd = stack.enter_context(TrackRecording(job.rerun, job.tracker.model, camera))
    return writers, ov, rrd


class _Passes:
    """`--extend` in `_run`: the first pass offers each record with its grey frame to the
    picker and keeps it (without its images); the second writes the first's ok records
    in place of its own, and, when interrupted, the first's records for the rest."""

    def __init__(self, picker: ViewPicker | None, first: list[FrameRecord] | None):
        self.picker, self.first = picker, first
        self.written: list[FrameRecord] = []
        self.held: dict = {}  # the grey frames the smoother still holds
        self.n = 0

    def holding(self, frames: Iterable[Frame]) -> Iterable[Frame]:
        return frames if self.picker is None else _holding(frames, self.held)

    def __call__(self, records: Iterable[FrameRecord]) -> Iterator[FrameRecord]:
        for rec in records:
            if self.picker is not None:
                self.picker.offer(rec, self.held.pop(rec.frame, None))
                self.written.append(replace(rec, image=None, measurement=None))
            elif self.first is not None and self.n < len(self.first) and self.first[self.n].ok:
                rec = replace(self.first[self.n], image=rec.image)  # the first pass's stands
            self.n += 1
            yield rec

    def rest(self) -> list[FrameRecord]:
        return [] if self.first is None else self.first[self.n :]


def _holding(frames: Iterable[Frame], held: dict) -> Iterator[Frame]:
    """The frames, each one's grey image also kept in `held` by frame id."""
    for f in frames:
        held[f.id] = f.image
        yield f


def nothing_found(result: TrackResult) -> None:
    """No frame ok: say why in one line (exit 3), after the outputs are written."""
    status = [str(r[0]) for r in result.rows]
    if not status or Status.OK.value in status:
        return
    raise NothingFound(
        f"the landmark was not found in any of the {len(status)} frames ({result.output} "
        "written, no pose): check that --model is this landmark's model and --camera this "
        "video's camera"
    )


def frame_line(rec) -> str:
    """-vv: one line per frame, what was decided and from what."""
    why = f" ({rec.mode})" if getattr(rec, "mode", None) else ""
    if getattr(rec, "cause", ""):  # why it was detected rather than flowed
        why = f" ({rec.mode}: {rec.cause})"
    kf = f", keyframe {rec.keyframe}" if getattr(rec, "keyframe", None) else ""
    return (
        f"frame {rec.frame}: {rec.status}{why}{kf}, {rec.inliers or 0} inliers of "
        f"{rec.matches or 0} matches"
    )


class OverlayVideo:
    """The overlay video, opened at the first decoded frame (whose size it takes)."""

    def __init__(self, path, fps: float, camera, axis_m: float):
        # VideoWriter reports no write error: the video must read back with its frames (one
        # of slack: a signal can land between writing a frame and counting it)
        # (no suffix, e.g. /dev/null: an .mp4 temporary file, so that OpenCV picks a container)
        self._path = atomic_path(
            path,
            suffix=Path(path).suffix or ".mp4",
            verify=lambda p: video_frames_written(p) >= self.n - 1,
        )
        self.path = path
        self.fps, self.camera, self.axis_m = fps, camera, axis_m
        self.writer, self.n = None, 0

    def __enter__(self):
        self.tmp = self._path.__enter__()
        return self

    def write(self, rec) -> None:
        img, rec.image = rec.image, None
        if img is None:
            return
        if self.writer is None:
            self.writer = cv2.VideoWriter(
                str(self.tmp),
                cv2.VideoWriter_fourcc(*"mp4v"),
                self.fps,
                (img.shape[1], img.shape[0]),
            )
            if not self.writer.isOpened():
                raise overlay_failure(self.path, self.tmp)
        self.writer.write(draw_overlay(img, rec, self.camera, self.axis_m))
        self.n += 1

    def __exit__(self, *exc):
        if self.writer is not None:
            self.writer.release()
        return self._path.__exit__(*exc)


def overlay_failure(path, tmp) -> OutputError | EnvironmentFailure:
    """Why the overlay video did not open, naming the file: a full disk is the machine's
    failure (exit 1), anything else the output's (exit 2)."""
    with contextlib.suppress(OSError):
        fs = os.statvfs(Path(tmp).parent)
        if fs.f_bavail * fs.f_frsize < (1 << 20):
            return EnvironmentFailure(f"cannot write {path}: no space left on device")
    return OutputError(f"cannot write the overlay video {path} (OpenCV's mp4v writer did not open)")
