"""Rerun recordings (`.rrd`) of a track run or a landmark model, for looking, not reading.

The only module that imports rerun-sdk (the optional `[viz]` extra), and only when a
recording is asked for, so mirage runs without it. Entities, in W (z up; cameras in
OpenCV's right-down-forward convention):

- `world/model/points`: the model's 3D points, grey from the keyframe pixels that see them
- `world/model/keyframes/NNN`: each keyframe camera (camera-to-world transform), with its
  frustum and thumbnail in `.../image`
- `world/camera`: the tracked camera per ok frame; `world/camera/image` its frame (JPEG)
  and `world/camera/image/inliers` the inlier pixels (empty when the frame is not ok)
- `world/trajectory/NNNN`: the camera path so far, in blocks of TRAJECTORY_BLOCK poses so
  that each frame logs at most one block (the file grows linearly, not quadratically);
  lost stretches break the line
- `track/ok`, `track/inliers`, `track/sigma_pos_m`, `track/sigma_rot_deg`: time series;
  `track/status`: a text log line whenever the status changes

Timelines: `frame` (the video frame number, or the running index for image sets) and
`time` (the frame's time_s).
"""

from __future__ import annotations

import math
import os
import warnings
from pathlib import Path

import cv2
import numpy as np

from .errors import EnvironmentFailure, InputError, OutputError, cv_message
from .fileio import atomic_path, write_failure
from .model import LandmarkModel
from .records import FrameRecord

RERUN_MISSING = "--rerun needs rerun-sdk: pip install -e '.[viz]' in the mirage-cli checkout"
APP_ID = "mirage"
JPEG_QUALITY = 80  # 640x480 frames: ~40 kB instead of 900 kB raw
TRAJECTORY_BLOCK = 100  # poses per trajectory entity
FLUSH_TIMEOUT_S = 120.0  # rerun's flush waits forever when its file writer died (full disk)
# rerun 0.41's file writer does not survive a full disk: its thread dies and closing the
# recording can then block for ever. So we stop, with one clear line, while this much room
# is left (more than rerun buffers before it writes)
MIN_FREE_BYTES = 16 * 1024 * 1024
POINTS = "world/model/points"
KEYFRAMES = "world/model/keyframes"
CAMERA = "world/camera"
IMAGE = "world/camera/image"
INLIERS = "world/camera/image/inliers"
TRAJECTORY = "world/trajectory"


def rerun_module():
    """`import rerun`, or the one-line error that says how to get it."""
    # rerun's Rust logger prints its own lines on stderr (four for a full disk) while the
    # failure also comes back as an exception, which is our one line; a user's RUST_LOG wins
    os.environ.setdefault("RUST_LOG", "off")
    try:
        import rerun
    except ImportError:
        raise InputError(RERUN_MISSING) from None
    return rerun


def check_room(path) -> None:
    """Fail, while a recording can still be closed, before its disk is full (see
    MIN_FREE_BYTES); the CLI calls it before any work too."""
    st = os.statvfs(Path(path).parent)
    if st.f_bavail * st.f_frsize < MIN_FREE_BYTES:
        raise EnvironmentFailure(
            f"cannot write {path}: less than {MIN_FREE_BYTES >> 20} MB left on its disk "
            "(disk full?)"
        )


def _reads_back(path) -> bool:
    """A finished recording has its footer (manifest); a truncated one does not."""
    rr = rerun_module()
    with warnings.catch_warnings():  # "no footer: legacy format": it is a failed write
        warnings.simplefilter("ignore")
        rr.chunk.RrdReader(path).store()
    return True


def _jpeg(img: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        raise OutputError("cannot encode a frame as JPEG for the Rerun recording")
    return buf.tobytes()


def point_greys(model: LandmarkModel) -> np.ndarray:
    """(P,) uint8: each 3D point's mean grey in the keyframe thumbnails that observe it
    (the model stores no colour; grey shows the landmark's texture in 3D)."""
    total = np.zeros(len(model.points))
    count = np.zeros(len(model.points))
    for kf in model.keyframes:
        kp, _, pid = kf.linked()
        th = kf.thumbnail
        if not len(pid) or th is None or th.size == 0:
            continue
        s = th.shape[1] / model.camera.width
        ij = np.rint(kp * s).astype(int)
        x = np.clip(ij[:, 0], 0, th.shape[1] - 1)
        y = np.clip(ij[:, 1], 0, th.shape[0] - 1)
        total += np.bincount(pid, th[y, x].astype(float), len(model.points))
        count += np.bincount(pid, minlength=len(model.points))
    grey = np.where(count > 0, total / np.maximum(count, 1), 160.0)
    return np.rint(grey).astype(np.uint8)


def frustum_m(model: LandmarkModel) -> float:
    """Frustum depth drawn in the viewer: a tenth of the landmark's extent."""
    pts = model.points
    return float(np.ptp(pts, axis=0).max() * 0.1) if len(pts) > 1 else 0.1


def _log_model(rr, rec, model: LandmarkModel) -> None:
    """Static: view coordinates, the 3D points and the keyframe cameras with thumbnails."""
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    M = model.world_from_model
    if not np.array_equal(M, np.eye(3)):  # a model kept levelled: its points into W
        rec.log("world/model", rr.Transform3D(mat3x3=M), static=True)
    g = point_greys(model)
    rec.log(POINTS, rr.Points3D(model.points, colors=np.stack([g, g, g], 1)), static=True)
    depth, cam = frustum_m(model), model.camera
    for i, kf in enumerate(model.keyframes):
        path = f"{KEYFRAMES}/{i:03d}"
        rec.log(path, rr.Transform3D(translation=kf.pose.center, mat3x3=kf.pose.R_wc), static=True)
        th = kf.thumbnail
        has_thumb = th is not None and th.size > 0
        s = th.shape[1] / cam.width if has_thumb else 1.0
        K = cam.K.copy()
        K[:2] *= s  # the thumbnail's pixels
        size = [th.shape[1], th.shape[0]] if has_thumb else [cam.width, cam.height]
        rec.log(
            f"{path}/image",
            rr.Pinhole(
                image_from_camera=K,
                resolution=size,
                camera_xyz=rr.ViewCoordinates.RDF,
                image_plane_distance=depth,
            ),
            static=True,
        )
        if has_thumb:
            rec.log(
                f"{path}/image",
                rr.EncodedImage(contents=_jpeg(th), media_type="image/jpeg"),
                static=True,
            )


_ABANDONED: list = []  # recordings whose file writer failed (see _Recording.__exit__)


class _Recording:
    """A recording written to a temporary file and renamed into place on success."""

    def __init__(self, path):
        self._target = path
        self._path = atomic_path(path, verify=_reads_back)
        self.rr = rerun_module()

    def blueprint(self):
        """The viewer's default layout (None: Rerun's automatic one)."""
        return None

    def __enter__(self):
        self.tmp = self._path.__enter__()
        try:
            check_room(self._target)
        except EnvironmentFailure as err:
            self._path.__exit__(type(err), err, None)  # drops the temp file
            raise
        self.rec = self.rr.RecordingStream(APP_ID)
        try:
            self.rec.save(str(self.tmp), default_blueprint=self.blueprint())
        except RuntimeError as e:  # rerun's OS errors (a full disk) come as RuntimeError
            self.rec.disconnect()  # else it warns about the data it drops
            err = write_failure(self._target, OSError(cv_message(e)))
            self._path.__exit__(type(err), err, None)
            raise err from None
        return self

    def __exit__(self, *exc):
        try:
            self.rec.flush(timeout_sec=FLUSH_TIMEOUT_S)
            self.rec.disconnect()  # closes the file, writing its footer
        except RuntimeError as e:  # rerun's write errors, or a flush that does not end
            # rerun 0.41 blocks for ever disconnecting, or garbage-collecting, a recording
            # whose file writer died (a full disk): keep it referenced, never disconnected
            _ABANDONED.append(self.rec)
            if exc[0] is None:
                err = write_failure(self._target, OSError(f"{cv_message(e)} (disk full?)"))
                self._path.__exit__(type(err), err, None)  # drops the temp file
                raise err from None
        return self._path.__exit__(*exc)


def record_model(path, model: LandmarkModel) -> None:
    """`mirage inspect --rerun`: the model's points and keyframe cameras, all static."""
    with _Recording(path) as r:
        _log_model(r.rr, r.rec, model)
        check_room(r._target)


class TrackRecording(_Recording):
    """`mirage track --rerun`: the model once, then every frame as it is tracked. An
    interrupted run keeps the finished frames (the CLI exits this normally then)."""

    def __init__(self, path, model: LandmarkModel, camera):
        super().__init__(path)
        self.model, self.camera = model, camera
        self.n = 0
        self._blocks: list[list[list[np.ndarray]]] = [[]]  # block -> runs -> centres
        self._in_block = 0
        self._run_open = False
        self._status = None

    def blueprint(self):
        """3D scene | the frame with its inliers over the time series, one plot each (their
        scales differ by five orders of magnitude)."""
        import rerun.blueprint as rrb

        plots = [
            rrb.TimeSeriesView(origin=f"track/{name}", name=name)
            for name in ("inliers", "sigma_pos_m", "sigma_rot_deg", "ok")
        ]
        return rrb.Blueprint(
            rrb.Horizontal(
                rrb.Spatial3DView(origin="world", name="landmark and camera"),
                rrb.Vertical(
                    rrb.Spatial2DView(origin=IMAGE, name="frame and inliers"),
                    rrb.Tabs(*plots, rrb.TextLogView(origin="track/status", name="status")),
                    row_shares=[3, 2],
                ),
                column_shares=[3, 2],
            )
        )

    def __enter__(self):
        super().__enter__()
        rr, rec = self.rr, self.rec
        _log_model(rr, rec, self.model)
        c = self.camera
        rec.log(
            IMAGE,
            rr.Pinhole(
                image_from_camera=c.K,
                resolution=[c.width, c.height],
                camera_xyz=rr.ViewCoordinates.RDF,
                image_plane_distance=frustum_m(self.model) * 2,
            ),
            static=True,
        )
        return self

    def write(self, fr: FrameRecord) -> None:
        check_room(self._target)
        rr, rec = self.rr, self.rec
        rec.set_time("frame", sequence=fr.frame if isinstance(fr.frame, int) else self.n)
        if math.isfinite(fr.time_s):
            rec.set_time("time", duration=float(fr.time_s))
        if fr.image is not None:
            rec.log(IMAGE, rr.EncodedImage(contents=_jpeg(fr.image), media_type="image/jpeg"))
        px = fr.inlier_px if fr.ok and fr.inlier_px is not None else np.zeros((0, 2))
        rec.log(INLIERS, rr.Points2D(px, colors=[0, 220, 0], radii=rr.Radius.ui_points(2.5)))
        if fr.ok and fr.pose is not None:
            rec.log(CAMERA, rr.Transform3D(translation=fr.pose.center, mat3x3=fr.pose.R_wc))
            self._extend(fr.pose.center)
        else:
            self._run_open = False
        if fr.status != self._status:
            rec.log("track/status", rr.TextLog(f"{fr.frame}: {fr.status}"))
            self._status = fr.status
        rec.log("track/ok", rr.Scalars(float(fr.ok)))
        rec.log("track/inliers", rr.Scalars(float(fr.inliers)))
        for name in ("sigma_pos_m", "sigma_rot_deg"):
            v = getattr(fr, name)
            if fr.ok and math.isfinite(v):
                rec.log(f"track/{name}", rr.Scalars(float(v)))
        self.n += 1

    def _extend(self, centre: np.ndarray) -> None:
        """Add a pose to the path; log the current block of it (the earlier blocks stay)."""
        runs = self._blocks[-1]
        if self._in_block >= TRAJECTORY_BLOCK:  # a new block, joined to the last one
            last = runs[-1][-1] if self._run_open else None
            runs = [[last]] if last is not None else []
            self._blocks.append(runs)
            self._in_block = 0
        if not self._run_open or not runs:
            runs.append([])
        runs[-1].append(np.asarray(centre, float))
        self._in_block += 1
        self._run_open = True
        strips = [np.array(r) for r in runs]
        self.rec.log(
            f"{TRAJECTORY}/{len(self._blocks) - 1:04d}",
            self.rr.LineStrips3D(strips, colors=[255, 140, 0]),
        )
