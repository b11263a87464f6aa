"""`mirage synth`: write a synthetic data set with exact ground truth."""

from __future__ import annotations

import multiprocessing as mp
import time
from pathlib import Path

import click
import cv2
import numpy as np
import yaml

from .. import families, signals, synth
from ..camera import Camera
from ..errors import InputError, OutputError
from ..fileio import (
    atomic_path,
    atomic_write,
    ensure_dir,
    refuse_overwrite,
    video_frames_written,
)
from ..records import FrameRecord, Status
from ..render import Renderer, stable_rng
from ..trajectory import write_trajectory
from . import ui
from .calibrate import parse_board
from .config import default_of
from .options import FOLDER, BoundedInt, FiniteFloat, camera_option, float_list, shown

MAX_SIDE = 8192  # px: an 8K frame; larger renders exhaust memory (rays per pixel)

PARTS = ("calibration", "keyframes", "orbit")

_worker: dict = {}


def _render_job(args):
    """Render one frame in a worker (the Renderer is inherited through fork)."""
    i, poses = args
    r: Renderer = _worker["renderer"]
    rng = stable_rng(_worker["seed"], f"{_worker['name']}-noise-{i}")
    return r.render(poses[0], _worker["noise"], rng, blur_poses=poses if len(poses) > 1 else None)


def _render_all(
    renderer: Renderer, pose_lists, noise: float, seed: int, name: str, jobs: int, label: str
):
    """Yield rendered frames in order, on `jobs` processes when the platform can fork."""
    _worker.update(renderer=renderer, noise=noise, seed=seed, name=name)
    items = list(enumerate(pose_lists))
    with ui.progress(len(items), label) as bar:
        if jobs > 1 and "fork" in mp.get_all_start_methods() and len(items) > 2:
            with mp.get_context("fork").Pool(jobs, signals.worker_init) as pool:
                for img in pool.imap(_render_job, items, chunksize=2):
                    bar.update(1)
                    yield img
        else:
            for it in items:
                bar.update(1)
                yield _render_job(it)


def _write_jpeg(path: Path, img: np.ndarray, quality: int) -> None:
    with atomic_write(path, "wb") as f:
        f.write(synth.encode_jpeg(img, quality))


@click.command("synth")
@click.argument("outdir", type=FOLDER)
@shown("--seed", type=BoundedInt(min=0), default=0, help="Random seed.")
@camera_option("Camera YAML to render with (default: a 640x480 webcam with distortion).")
@click.option(
    "--width",
    type=BoundedInt(min=16, max=MAX_SIDE),
    help="Image width (scales the camera).",
)
@click.option("--height", type=BoundedInt(min=16, max=MAX_SIDE), help="Image height.")
@shown(
    "--only",
    default=",".join(PARTS),
    help="Comma-separated parts to write: calibration, keyframes, orbit.",
)
@shown("--board", default="{}x{}".format(*synth.CALIB_BOARD), help="Inner corners COLSxROWS.")
@shown(
    "--square",
    type=FiniteFloat(min=0, min_open=True),
    default=synth.CALIB_SQUARE_M,
    help="Chessboard square size (m).",
)
@shown("--calib-views", type=BoundedInt(min=1, max=1000), default=20)
@shown(
    "--keyframe-step",
    type=FiniteFloat(min=1, max=180),
    default=default_of(synth.keyframe_poses, "step_deg"),
    help="Keyframe spacing in azimuth (deg).",
)
@shown(
    "--heights",
    default=",".join(map(str, default_of(synth.keyframe_poses, "heights"))),
    help="Keyframe camera heights (m), comma-separated.",
)
@shown(
    "--radius",
    type=FiniteFloat(min=0.8),
    default=default_of(synth.keyframe_poses, "radius"),
    help="Keyframe circle radius (m).",
)
@shown(
    "--duration",
    type=FiniteFloat(min=0.1),
    default=synth.OrbitPath.duration_s,
    help="Orbit video length (s).",
)
@shown("--fps", type=FiniteFloat(min=1), default=30.0)
@shown("--noise", type=FiniteFloat(min=0), default=1.5, help="Sensor noise sigma (grey levels).")
@shown(
    "--motion-blur",
    type=BoundedInt(min=1),
    default=1,
    help="Sub-frame renders averaged over the exposure, centred on the frame's time (1 = off).",
)
@shown(
    "--exposure",
    type=FiniteFloat(min=0, max=1, min_open=True),
    default=0.5,
    help="Shutter time as a share of the frame interval (the span --motion-blur averages).",
)
@shown(
    "--jpeg-quality",
    type=BoundedInt(50, 100),
    default=default_of(synth.encode_jpeg, "quality"),
)
@shown("--jobs", type=BoundedInt(min=1), default=2, help="Render processes.")
@click.option(
    "--ground-board",
    is_flag=True,
    help="Lay a ChArUco board on the ground around the landmark (for build-model --board); "
    "writes OUTDIR/board.yaml. Off by default: the default output does not change.",
)
@click.option(
    "--floor-tiles",
    type=FiniteFloat(min=0.05),
    metavar="PERIOD_M",
    help="Stress: the ground is one texture tile repeated every PERIOD_M metres (floor "
    "features have exact twins one period apart).",
)
@click.option(
    "--lookalike",
    is_flag=True,
    help="Stress: opposite sides of the landmark carry the same texture.",
)
@click.option(
    "--weak-texture",
    is_flag=True,
    help="Stress: the landmark is plain paint with a few textured patches per face.",
)
@click.option(
    "--dusk",
    is_flag=True,
    help="Stress: the light falls to 25% over the orbit video and the sensor noise rises "
    "(+3 grey levels at the end), as an auto-gain camera at dusk.",
)
@click.option(
    "--pole",
    is_flag=True,
    help="Stress: a textured pole (8 cm wide) stands between the orbit and the landmark at "
    "azimuth 60 deg, 0.95 m from it, and passes in front of the landmark during the orbit. "
    "In the orbit video only (not in the keyframes); landmark_visible counts it.",
)
@shown(
    "--video-radius",
    type=FiniteFloat(min=0.8),
    default=default_of(synth.OrbitPath, "radius_m"),
    help="Orbit video circle radius (m); the keyframes keep --radius.",
)
@shown(
    "--video-height",
    type=FiniteFloat(min=0.1, max=20.0),
    default=default_of(synth.OrbitPath, "height_m"),
    help="Orbit video camera height (m; it looks at the landmark from there): 2.2 with the "
    "default radius is a drone's view from 50 deg above.",
)
@shown(
    "--aa",
    type=click.IntRange(1, 4),
    default=default_of(Renderer, "aa"),
    help="Rays per pixel side (anti-aliasing); 1 renders about 4x faster.",
)
@shown(
    "--turns",
    type=FiniteFloat(min=0, min_open=True),
    default=default_of(synth.OrbitPath, "turns"),
    help="Orbit video: turns around the landmark over --duration (sets the speed).",
)
@click.option(
    "--look-away",
    metavar="SECONDS|START,END",
    help="The look-away stretch: its length (starting at 78% of the video; 0 = none) or its "
    "start and end times in seconds. Default: min(2.2 s, 11% of the video) at 78%.",
)
@click.option(
    "--random",
    "random_seed",
    type=BoundedInt(min=0),
    metavar="SEED",
    help="Draw the whole scene at random from SEED within --family (landmark, photographs "
    "on its faces, floor, light drift, occluder, blur, noise, camera, keyframe and video "
    "distances); writes OUTDIR/scene.yaml with what was drawn.",
)
@shown(
    "--family",
    type=click.Choice(families.FAMILIES),
    default=families.FAMILIES[0],
    help="With --random: near (video 0.8-2 m away), far (3-5 m, landmark 50-120 px tall, "
    "keyframes 1-1.5 m), above (video 30-60 deg above the horizon, keyframes 0-20 deg).",
)
def synth_cmd(
    outdir,
    random_seed,
    family,
    seed,
    camera_path,
    width,
    height,
    only,
    board,
    square,
    calib_views,
    keyframe_step,
    heights,
    radius,
    duration,
    fps,
    noise,
    motion_blur,
    jpeg_quality,
    jobs,
    ground_board,
    exposure,
    floor_tiles,
    lookalike,
    weak_texture,
    dusk,
    pole,
    video_radius,
    video_height,
    look_away,
    turns,
    aa,
):
    """Render a synthetic data set with exact ground truth into OUTDIR.

    Writes camera_truth.yaml, calibration/ (chessboard views), keyframes/ (views
    circling the landmark + poses.csv), orbit.mp4 + orbit_truth.csv and
    desired_path.yaml. The same --seed gives byte-identical images.

    Example: mirage synth sample_data --seed 0
    """
    parts = _parts(only)
    if random_seed is not None:
        _refuse_scene_options()
        _random_scene(outdir, family, random_seed, parts, duration, fps, exposure, jobs, aa)
        return
    away_s, (cols, rows), hs = _scene_values(look_away, duration, board, heights)
    cam = _camera(camera_path, width, height)
    if camera_path:
        refuse_overwrite({"OUTDIR": Path(outdir) / "camera_truth.yaml"}, {"--camera": camera_path})
    out = ensure_dir(outdir)
    t0 = time.perf_counter()
    cam.save(out / "camera_truth.yaml")

    if "calibration" in parts:
        _calibration(out / "calibration", cam, cols, rows, square, calib_views, seed, noise,
                     jpeg_quality, jobs)  # fmt: skip
    if "keyframes" in parts or "orbit" in parts:
        scene = synth.landmark_scene(
            seed, floor_tile_m=floor_tiles, lookalike=lookalike, weak=weak_texture
        )
        if ground_board:
            scene = _with_ground_board(scene, out)
        renderer = Renderer(scene, cam, aa=aa)
        if "keyframes" in parts:
            _keyframes(out / "keyframes", renderer, keyframe_step, radius, hs, seed, noise,
                       jpeg_quality, jobs)  # fmt: skip
        if "orbit" in parts:
            path = synth.OrbitPath(
                duration_s=duration, radius_m=video_radius, height_m=video_height, turns=turns,
                look_away_s=away_s,
            )  # fmt: skip
            _landmark_orbit(out, scene, cam, aa, path, pole, fps, seed, noise, motion_blur,
                            exposure, jobs, dusk)  # fmt: skip
    ui.echo(f"synth: wrote {', '.join(parts)} to {out} in {time.perf_counter() - t0:.1f} s")


def _scene_values(look_away, duration, board, heights):
    """The default scene's options that need parsing, checked before any rendering."""
    away_s = _parse_look_away(look_away, duration)
    try:
        board_size = parse_board(None, None, board)
    except click.BadParameter as e:
        e.param_hint = "'--board'"
        raise
    return away_s, board_size, float_list(heights, "--heights")


def _landmark_orbit(out, scene, cam, aa, path, pole, fps, seed, noise, blur, exposure, jobs,
                    dusk) -> None:  # fmt: skip
    """The default landmark's orbit video, with the pole in front of it if asked."""
    occluders = [synth.pole(seed)] if pole else []
    if occluders:
        scene = synth.add_occluder(scene, occluders[0])
    _orbit(out, Renderer(scene, cam, aa=aa), path, fps, seed, noise, blur, exposure, jobs,
           occluders, dusk=dusk)  # fmt: skip


def _parts(only: str) -> list[str]:
    """`--only`: the parts to write, each one of PARTS."""
    parts = [p.strip() for p in only.split(",") if p.strip()]
    bad = [p for p in parts if p not in PARTS]
    if bad or not parts:
        raise click.BadParameter(
            f"unknown part(s) {', '.join(bad) or '(none)'}; choose from {', '.join(PARTS)}",
            param_hint="'--only'",
        )
    return parts


def _camera(camera_path, width, height) -> Camera:
    """The camera to render with: the file's or the default webcam, scaled to the size."""
    cam = Camera.load(camera_path) if camera_path else synth.default_camera()
    if width or height:
        w = width or round(cam.width * height / cam.height)
        h = height or round(cam.height * width / cam.width)
        if max(w, h) > MAX_SIDE:
            raise click.BadParameter(
                f"the image would be {w}x{h}; at most {MAX_SIDE} px a side",
                param_hint="'--width' / '--height'",
            )
        cam = cam.scaled(w, h)
    return cam


def _with_ground_board(scene, out: Path):
    """The scene with the ChArUco board on the ground, and OUTDIR/board.yaml describing it."""
    scene = synth.add_ground_board(scene)
    with atomic_write(out / "board.yaml") as f:
        f.write("# The ChArUco board on the ground (mirage synth --ground-board).\n")
        yaml.safe_dump(synth.GROUND_BOARD.to_yaml(), f, sort_keys=False, default_flow_style=None)
    return scene


# options that shape the default scene; a --random scene draws all of them itself
SCENE_OPTIONS = (
    "seed", "camera_path", "width", "height", "keyframe_step", "heights", "radius", "noise",
    "motion_blur", "ground_board", "floor_tiles", "lookalike", "weak_texture", "dusk", "pole",
    "video_radius", "video_height",
    "turns", "look_away", "jpeg_quality",
)  # fmt: skip


def _refuse_scene_options() -> None:
    ctx = click.get_current_context()
    given = [
        p.opts[0]
        for p in ctx.command.params
        if p.name in SCENE_OPTIONS
        and ctx.get_parameter_source(p.name) is not click.core.ParameterSource.DEFAULT
    ]
    if given:
        raise click.UsageError(
            f"--random draws the scene itself; drop {', '.join(given)} (or --random)"
        )


def _random_scene(outdir, family, seed, parts, duration, fps, exposure, jobs, aa) -> None:
    """`synth --random SEED --family F`: the family's scene, written as the default one."""
    t0 = time.perf_counter()
    try:
        fs = families.family_scene(family, seed, duration)
    except RuntimeError as e:  # scikit-image missing
        raise InputError(str(e)) from None
    out = ensure_dir(outdir)
    fs.camera.save(out / "camera_truth.yaml")
    with atomic_write(out / "scene.yaml") as f:
        f.write(f"# mirage synth --random {seed} --family {family}: what was drawn\n")
        yaml.safe_dump(_plain(fs.recipe), f, sort_keys=False, default_flow_style=None)
    if "calibration" in parts:
        cols, rows = synth.CALIB_BOARD
        _calibration(
            out / "calibration", fs.camera, cols, rows, synth.CALIB_SQUARE_M, 20, seed,
            fs.noise, 95, jobs,
        )  # fmt: skip
    if "keyframes" in parts:
        _keyframe_views(
            out / "keyframes", Renderer(fs.scene, fs.camera, aa=aa), fs.keyframes, seed,
            fs.noise, 95, jobs,
        )  # fmt: skip
    if "orbit" in parts:
        _orbit(
            out, Renderer(fs.video_scene, fs.camera, aa=aa), fs.path, fps, seed, fs.noise,
            fs.motion_blur, exposure, jobs, fs.occluders, fs.samples(), fs.gain_at,
        )  # fmt: skip
    ui.echo(
        f"synth: random {family} scene {seed} ({', '.join(parts)}) in {out} in "
        f"{time.perf_counter() - t0:.1f} s"
    )


def _plain(v):
    """numpy scalars and arrays as YAML-safe Python values."""
    if isinstance(v, dict):
        return {k: _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple, np.ndarray)):
        return [_plain(x) for x in v]
    if isinstance(v, np.generic):
        return v.item()
    return v


def _calibration(folder, cam, cols, rows, square, n, seed, noise, quality, jobs):
    folder = ensure_dir(folder)
    renderer = Renderer(synth.board_scene(cols, rows, square, seed), cam)
    try:
        poses = synth.calibration_poses(cam, cols, rows, square, n, stable_rng(seed, "calib"))
    except RuntimeError as e:
        raise InputError(f"{e} (board {cols}x{rows}, square {square} m)") from None
    names = [f"calib_{i:03d}.jpg" for i in range(n)]
    for name, img in zip(
        names,
        _render_all(renderer, [[p] for p in poses], noise, seed, "calib", jobs, "calibration"),
        strict=True,
    ):
        _write_jpeg(folder / name, img, quality)
    write_trajectory(  # camera poses in the board frame
        folder / "poses.csv",
        [FrameRecord(Status.OK, p, name) for name, p in zip(names, poses, strict=True)],
    )
    ui.echo(
        f"synth: {n} chessboard views ({cols}x{rows} inner corners, {square * 1000:g} mm "
        f"squares) in {folder}"
    )


def _keyframes(folder, renderer, step, radius, heights, seed, noise, quality, jobs):
    views = synth.keyframe_poses(step, radius, heights)
    _keyframe_views(folder, renderer, views, seed, noise, quality, jobs)
    ui.echo(f"synth: {len(views)} keyframes every {step:g} deg in {folder}")


def _keyframe_views(folder, renderer, views, seed, noise, quality, jobs):
    folder = ensure_dir(folder)
    imgs = _render_all(
        renderer, [[p] for _, p in views], noise, seed, "keyframes", jobs, "keyframes"
    )
    for (name, _), img in zip(views, imgs, strict=True):
        _write_jpeg(folder / f"{name}.jpg", img, quality)
    write_trajectory(
        folder / "poses.csv", [FrameRecord(Status.OK, p, f"{name}.jpg") for name, p in views]
    )


def _orbit(
    out: Path, renderer, path, fps, seed, noise, blur, exposure, jobs, occluders, samples=None,
    gain=None, dusk=False,
):  # fmt: skip
    """The video along `path`; `samples` are the landmark's surface points (visibility),
    `gain(t)` the lighting's drift (a factor on every pixel); `dusk` dims the light to 25%
    over the video and adds noise as it falls."""
    cam = renderer.camera
    n = int(round(path.duration_s * fps))
    times = np.arange(n) / fps
    poses = [path.pose(t) for t in times]
    pose_lists = [
        path.exposure_poses(t, blur, exposure / fps) if blur > 1 else [p]
        for t, p in zip(times, poses, strict=True)
    ]
    samples = synth.landmark_surface_samples() if samples is None else samples
    vis = [synth.landmark_visibility(cam, p, samples, occluders) for p in poses]
    with atomic_path(out / "orbit.mp4", verify=lambda p: video_frames_written(p) == n) as tmp:
        writer = cv2.VideoWriter(
            str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), fps, (cam.width, cam.height)
        )
        if not writer.isOpened():
            raise OutputError("this OpenCV build cannot write mp4 (mp4v) video")
        frames = _render_all(renderer, pose_lists, noise, seed, "orbit", jobs, "orbit video")
        for i, (t, img) in enumerate(zip(times, frames, strict=True)):
            if gain is not None:
                img = cv2.convertScaleAbs(img, alpha=gain(t))
            if dusk:
                img = synth.dusk_frame(img, t / max(path.duration_s, 1e-9), seed, i)
            writer.write(img)
        writer.release()
    write_trajectory(
        out / "orbit_truth.csv",
        [
            FrameRecord(Status.OK, p, i, t, extra={"landmark_visible": round(v, 4)})
            for i, (t, p, v) in enumerate(zip(times, poses, vis, strict=True))
        ],
        extra_columns=["landmark_visible"],
    )
    with atomic_write(out / "desired_path.yaml") as f:
        f.write("# Desired path of the orbit (mirage synth); see the brief, section 3.\n")
        yaml.safe_dump(path.desired_path(), f, sort_keys=False, default_flow_style=None)
    away = sum(v == 0 for v in vis)
    ui.echo(
        f"synth: orbit.mp4 {n} frames at {fps:g} fps, {cam.width}x{cam.height}; landmark "
        f"out of view in {away} frames"
    )


def _parse_look_away(text: str | None, duration: float) -> tuple[float, float]:
    """`--look-away`: None, a length in seconds, or START,END in seconds."""
    if text is None:
        return _look_away(duration)
    try:
        vals = [float(v) for v in str(text).split(",")]
    except ValueError:
        vals = []
    if len(vals) == 1 and vals[0] >= 0:
        return _look_away(duration, vals[0])
    if len(vals) == 2 and 0 <= vals[0] <= vals[1]:
        return vals[0], vals[1]
    raise click.BadParameter(
        f"{text!r} is not SECONDS or START,END (seconds, START <= END)",
        param_hint="'--look-away'",
    )


def _look_away(duration: float, length: float | None = None) -> tuple[float, float]:
    """The look-away stretch: 2.2 s starting at 78% of the video (scaled for short videos),
    where the path's last part repeats its start, so every azimuth is seen in view."""
    if length is None:
        length = min(2.2, 0.11 * duration)
    start = 0.78 * duration
    return start, start + length
