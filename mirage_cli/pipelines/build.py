"""`mirage build-model`'s pipeline: views with poses (a pose CSV or a board in view) ->
the landmark model -> the model file (with where it came from)."""

from __future__ import annotations

from collections.abc import Callable

from .. import runtime
from ..boards import Board
from ..build_model import (
    BuildResult,
    BuildSettings,
    build_model,
    coverage_warning,
    views_from_inputs,
)
from ..camera import Camera
from ..errors import InputError
from ..logs import log


def build(
    sources,
    camera: Camera,
    settings: BuildSettings,
    poses_csv=None,
    board: Board | None = None,
    progress: Callable[[str, int, int], None] | None = None,
) -> BuildResult:
    """The model from the views of `sources` (images, folders, globs, a video or a bag);
    `progress(stage, k, n)` sees each stage's steps."""
    runtime.return_freed_memory()  # each stage's big arrays back to the kernel when freed
    views = views_from_inputs(
        sources, camera, settings, poses_csv, board,
        (lambda k, n: progress("views", k, n)) if progress else None,
    )  # fmt: skip
    return build_model(views, camera, settings, progress)


def save_model(res: BuildResult, output, source: dict) -> None:
    """Write a built model (with where it came from) and warn about its weak parts."""
    model = res.model
    if len(model.points) == 0:
        raise InputError(
            "no 3D points could be triangulated: are the views close enough in direction "
            "(see --spacing-deg) and the poses right? (try --roi none)"
        )
    model.meta["source"] = source
    model.save(output)
    weak = [kf.name for kf in model.keyframes if kf.n_linked < 30]
    if weak:
        log.warning(
            f"{len(weak)} keyframe(s) have fewer than 30 3D points ({', '.join(weak[:5])}); "
            "tracking from those directions will be weak"
        )
    gap = coverage_warning(model)
    if gap:
        log.warning(gap)
    suspects = (model.meta.get("check") or {}).get("suspects") or []
    if suspects:
        log.warning(
            f"keyframe(s) {', '.join(suspects[:5])} disagree with the points the other keyframes "
            "see by over 4 sigma: check their rows in the pose file"
        )
