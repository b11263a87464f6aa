"""The per-frame record of a trajectory and its status words: what tracking produces and
every output (trajectory.py's formats, the overlay, the Rerun recording) consumes."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum

import numpy as np

from .pose import Pose


class Status(str, Enum):
    """Every status word a frame can get; the str values are what files hold."""

    OK = "ok"  # a trusted pose
    LOST = "lost"  # not enough consistent evidence for a pose
    AMBIGUOUS = "ambiguous"  # relocalisation: two distinct poses explain the frame alike
    UNCERTAIN = "uncertain"  # a pose, but its uncertainty is too large to trust
    DECODE_ERROR = "decode_error"  # the frame could not be decoded
    SIZE_MISMATCH = "size_mismatch"  # a frame of another size than the sequence's camera

    def __str__(self) -> str:
        return self.value

    __format__ = str.__format__


class Reason(str, Enum):
    """Why a frame is not `ok` (the pose CSV's `reason` column; empty when ok)."""

    FEW_FEATURES = "few_features"  # too few keypoints in the frame (blank, dark, blurred)
    NOT_SEARCHED = "not_searched"  # long lost: this frame was skipped between searches
    NOT_RECOGNISED = "not_recognised"  # no keyframe shares its features
    FEW_MATCHES = "few_matches"  # too few matches to the model's points
    FEW_INLIERS = "few_inliers"  # too few matches agree on one pose
    CHANCE = "chance"  # the agreeing matches could be chance (evidence.py)
    AMBIGUOUS = "ambiguous"  # two distinct poses explain the matches alike
    OFF_LANDMARK = "off_landmark"  # the pose rests on the ground or background alone
    RESIDUAL = "residual"  # the reprojection RMS is above --max-rmse
    BEHIND = "behind"  # the landmark would be behind the camera
    IMPLAUSIBLE = "implausible"  # the camera would be rolled far beyond every keyframe
    JUMP = "jump"  # the pose jumped further from the last one than the motion allows
    UNCERTAIN = "uncertain"  # its 1-sigma uncertainty is above the limits

    def __str__(self) -> str:
        return self.value

    __format__ = str.__format__


class Cause(str, Enum):
    """Why a frame was detected (or relocalised) rather than flowed: what makes footage
    slow (`mirage track -v` counts them)."""

    SCHEDULED = "scheduled"  # the regular detection (every `redetect_every` + 1 frames)
    FLOW_FAILED = "flow_failed"  # Lucas-Kanade could not run (no points left in reach)
    FLOW_WEAK = "flow_weak"  # too few of the detection's points followed well
    FLOW_DRIFT = "flow_drift"  # the flowed points fit the pose worse than the detection
    FLOW_DEVIATION = "flow_deviation"  # the flowed pose is far from the predicted one
    FLOW_REFUSED = "flow_refused"  # the flowed pose did not pass the gate
    LOST = "lost"  # no pose to flow from (lost, or the first frame)
    NO_FLOW = "no_flow"  # flow is off (--no-flow)

    def __str__(self) -> str:
        return self.value

    __format__ = str.__format__


@dataclass
class Measurement:
    """What the tracker measured in a frame with a pose (ok or uncertain), for the smoother:
    the pose and its 6x6 covariance (the solver's parametrisation, see `PoseEstimate`) split
    into what this frame's residuals show (`cov`) and the model's own error, shared with
    every frame that sees the same points (`cov_shared`); the frame whose detection its
    points come from (`anchor`), and the gate's limits."""

    pose: Pose
    cov: np.ndarray
    cov_shared: np.ndarray
    anchor: int = 0
    max_sigma_pos_m: float = float("inf")
    max_sigma_rot_deg: float = float("inf")


@dataclass
class FrameRecord:
    """One frame of a trajectory: its id, time, status, pose and tracking diagnostics."""

    status: Status = Status.LOST
    pose: Pose | None = None  # T_CW; None unless ok
    frame: int | str = ""  # video frame number or image file name
    time_s: float = float("nan")
    keyframe: str = ""
    matches: int = 0
    inliers: int = 0
    rmse_px: float = float("nan")
    iterations: int = 0
    sigma_pos_m: float = float("nan")
    sigma_rot_deg: float = float("nan")
    ms: float = float("nan")  # processing time of the frame
    mode: str = ""  # detect | flow | relocalise
    reason: str = ""  # why not ok (a Reason); empty when ok
    cause: str = ""  # detect / relocalise: why the frame was not flowed (a Cause; -v)
    inlier_px: np.ndarray | None = field(default=None, repr=False)  # for overlays
    image: np.ndarray | None = field(default=None, repr=False)  # the frame, when kept
    extra: dict = field(default_factory=dict)  # other columns by name (landmark_visible)
    measurement: Measurement | None = field(default=None, repr=False)  # for the smoother

    @property
    def ok(self) -> bool:
        return self.status == Status.OK
