"""mirage-cli: offline 6-DOF camera pose analysis around a known landmark."""

__version__ = "0.1.0"

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

_LAZY = {
    "Camera": "camera",
    "MirageError": "errors",
    "Pose": "pose",
    "PoseEstimate": "solver",
    "RansacOptions": "solver",
    "RefineOptions": "solver",
    "solve_pose": "solver",
}


def __getattr__(name):
    """Import the public names on first use: `python -m mirage_cli` must get its signal
    handlers in before OpenCV and numba load (a Ctrl-C at start-up is then one line)."""
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
