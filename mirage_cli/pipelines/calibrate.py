"""`mirage calibrate`'s pipeline: board detections -> calibration -> the camera file (and
the report plot)."""

from __future__ import annotations

from ..boards import Board
from ..calibrate import CalibOptions, Calibration, Detections
from ..calibrate import calibrate as run_calibration
from ..camera import Camera
from ..logs import log
from ..plotting import CALIBRATION_DPI, calibration_figure, save_png

_K_NAMES = ("fx", "fy", "cx", "cy")


def calibrate_to_file(
    det: Detections, target: Board, opts: CalibOptions, output, report=None
) -> Calibration:
    """Calibrate from detected views; write the camera YAML (and the plot)."""
    for w in det.warnings:
        log.warning(w)
    calib = run_calibration(det, target, opts)
    cam = Camera(calib.K, calib.dist, *calib.image_size, calib.rms_px, _meta(calib, det, target))
    cam.save(output)
    if report:
        save_png(calibration_figure(calib), report, CALIBRATION_DPI)
    return calib


def _meta(c: Calibration, det: Detections, b: Board) -> dict:
    meta = {
        "pattern": b.pattern,
        "board": b.label,
        "square_m": float(b.square_m),
        "views_found": len(det.views),
        "views_used": len(c.views),
        "views_rejected": len(c.rejected),
        "view_names": ",".join(v.name for v in c.views),
        "per_view_errors_px": [round(float(e), 4) for e in c.view_errors_px],
        "std_intrinsics": [c.std_intrinsics[k] for k in _K_NAMES],
        "std_distortion": [v for k, v in c.std_intrinsics.items() if k not in _K_NAMES],
    }
    if b.pattern == "charuco":
        meta["marker_m"] = float(b.marker_size_m)
        meta["dictionary"] = b.dictionary
    return meta
