"""mirage-cli: offline 6-DOF camera pose analysis around a known landmark."""

__version__ = "0.1.0"

from .camera import Camera  # noqa: E402
from .errors import MirageError  # noqa: E402
from .pose import Pose  # noqa: E402
from .solver import PoseEstimate, RansacOptions, RefineOptions, solve_pose  # noqa: E402

__all__ = [
    "Camera",
    "MirageError",
    "Pose",
    "PoseEstimate",
    "RansacOptions",
    "RefineOptions",
    "__version__",
    "solve_pose",
]
