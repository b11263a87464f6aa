"""Detection scheduling: which features of which frame are detected, and where, on the one
background thread (OpenCV's detectors release the GIL). Once a frame is detected, the next
regular detection's features (`redetect_every` + 1 frames later, in the box its pose
predicts) are detected while the frames between are flowed; while lost, the coming frames'
searches (the last pose's box, the half-size probe, the whole frame) while this one is
matched. What is detected depends on the frames alone, never on timing. A mixin of
`Tracker` (state: `_pending`, `_held_box`, `_bg_detector`)."""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np

from ..features import detect, make_detector

_WORKER: ThreadPoolExecutor | None = None


def _worker() -> ThreadPoolExecutor:
    """The one background thread for detections (OpenCV's detectors release the GIL)."""
    global _WORKER
    if _WORKER is None:
        _WORKER = ThreadPoolExecutor(max_workers=1, thread_name_prefix="mirage-detect")
    return _WORKER


def _forget_worker() -> None:
    global _WORKER
    _WORKER = None  # a forked child has none of the parent's threads: start its own


os.register_at_fork(after_in_child=_forget_worker)


class DetectionSchedule:
    """Which features are detected when, and where (a mixin of Tracker)."""

    def _detect_ahead(self, ahead, shape, calm: bool = False) -> None:
        """A frame was just detected: if flow holds, the next detection comes
        `redetect_every` + 1 frames later, so start detecting that frame's features now, on
        the worker thread, in the box that covers the model both where it is now and where
        the constant-velocity prediction puts it then (a box too small to detect without
        upsampling, a far landmark, is left to its own frame: its scale must come from
        the box that frame predicts). Unless this detection was `calm` (within
        `flow_max_dev_sigma` - 2 sigmas of its prediction), the job starts only once the
        next frame has flowed: the flow's deviation check often asks for a detection right
        there (the velocity then spans the jump from the flowed poses to the detected one),
        which would leave the features unused, their time taken from that detection
        (sample orbit: after 14 of the 47 detections that were not calm, after 2 of the 48
        calm ones; a calm bound 1 sigma higher measured no faster)."""
        self._drop("box")
        self._held_box = None
        k = self.lookahead
        if not k or len(ahead) < k or ahead[k - 1] is None or ahead[k - 1].shape != shape:
            return
        if self.anchor_n >= 2 * self.settings.patch_refresh_min and self._refreshes(
            self._predicted(k)
        ):  # well placed by patches: they will place it again then; keypoints go unused
            return
        boxes = [self._model_box(p, shape) for p in (self.prev_pose, self._predicted(k))]
        box = None
        if all(b is not None for b in boxes):
            (a0, a1, a2, a3, ash), (b0, b1, b2, b3, bsh) = boxes
            if max(b2 - b0, b3 - b1, a2 - a0, a3 - a1) < self.settings.upsample_below_px:
                return
            box = (min(a0, b0), min(a1, b1), max(a2, b2), max(a3, b3), min(ash, bsh))
        self._held_box = (self._frame_no + k, "box", self._box_features, ahead[k - 1], box)
        if calm:
            self._start(*self._held_box)
            self._held_box = None

    def _search_ahead(self, ahead) -> None:
        """Lost: the coming frames, if they stay lost, are searched as `lost_run` says (in
        the box of the last pose while it is kept, then the whole frame or the half-size
        probe), so their features are queued on the worker, as far ahead as the frames
        are decoded, and detected while this frame is matched. What is searched depends
        on the frames and the last pose alone; a frame that is not processed
        (undecodable) does not count."""
        n, box = 0, None
        for gray in ahead[: self.lookahead]:
            if gray is None:
                continue
            n += 1
            lost_run, frame_no = self.lost_run + n, self._frame_no + n
            if (
                self.prev_pose is not None and lost_run <= self.PREDICT_LOST
                and (frame_no, "lostbox") not in self._pending
            ):  # fmt: skip
                if box is None:  # no velocity while lost: the same box for every frame
                    box = self._model_box(self.prev_pose, gray.shape) or ()
                if box:
                    self._start(frame_no, "lostbox", self._box_features, gray, box)
            kind = self._search(lost_run)
            if kind is not None and (frame_no, kind) not in self._pending:
                fn = self._probe_features if kind == "probe" else self._search_features
                self._start(frame_no, kind, fn, gray)

    def _drop(self, *kinds: str) -> None:
        """Forget the features of those kinds detected ahead (the plan changed); those not
        started yet are not detected at all."""
        for key in [k for k in self._pending if k[1] in kinds]:
            self._pending.pop(key).cancel()

    def cancel_pending(self) -> None:
        """The run ended or was interrupted: the detections queued ahead are not started.
        The interpreter's exit joins the worker, which would first run every search queued
        for frames that will never come (an interrupted run waited for them)."""
        self._drop(*{kind for _, kind in self._pending})
        self._held_box = None

    def _start(self, frame_no: int, kind: str, fn, gray, *args) -> None:
        if self._bg_detector is None:
            self._bg_detector = make_detector(self.model.detector)
        job = _worker().submit(fn, gray, *args, self._bg_detector)
        job.box = args[0] if args else None  # a box search: where (and at which scale)
        self._pending[frame_no, kind] = job

    def _features(self, kind: str, fn, gray, *args):
        """This frame's features of that kind: detected ahead when they were, else now."""
        job = self._pending.pop((self._frame_no, kind), None)
        return job.result() if job is not None else fn(gray, *args, self.detector)

    def _search(self, lost_run: int) -> str | None:
        """How a lost frame is searched: 'full' (the whole frame) every `relocalise_every`
        frames, a 'probe' between (half size: a quarter of the pixels; it goes on to the
        whole frame only when it finds the landmark, so a far one waits for the next full
        search). Lost for longer than `long_lost` frames (a look-away, not a dropout), the
        whole frame every 2N frames and the probe every other frame between (None: not
        searched), so a near landmark is found within a frame of its return."""
        long = lost_run > self.settings.long_lost
        if lost_run % (self.settings.relocalise_every * (2 if long else 1)) == 0:
            return "full"
        return None if long and lost_run % 2 else "probe"

    def _whole_scale(self) -> float:
        """The scale this frame's whole frame is detected at: a lost frame's search's, else
        a tracked frame's whose box would cover most of it."""
        return self.search_scale if self.lost_run > 0 else self.full_scale

    def _whole_frame(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """This frame's whole-frame features (`_search_features` while lost, detected ahead
        when they were, else `_full_features`), the pixel limits set to their scale."""
        self._at_scale(self._whole_scale())
        fn = self._search_features if self.lost_run > 0 else self._full_features
        return self._features("full", fn, gray)

    def _probe_features(self, gray: np.ndarray, detector) -> tuple[np.ndarray, np.ndarray]:
        return _scaled_detect(gray, 2 * self.search_scale, detector)

    def _search_features(self, gray: np.ndarray, detector) -> tuple[np.ndarray, np.ndarray]:
        """A lost frame's whole frame, at the keyframes' own scale when the video's camera
        is sharper than the model's (a 1080p video against a 640x480 model: 0.2 of the
        pixels): enough to find the landmark, and the frames after it are tracked at
        `full_scale`."""
        return _scaled_detect(gray, self.search_scale, detector)

    def _full_features(self, gray: np.ndarray, detector) -> tuple[np.ndarray, np.ndarray]:
        """A tracked frame's whole frame (its box would cover most of it), at the scale of
        the tracking boxes when the video's camera is sharper than the model's (the
        keyframes' scale with `SHRINK_MARGIN`: a 1080p video against a 640x480 model, 0.31
        of the pixels), upsampled to it when coarser (`detection_scales`)."""
        return _scaled_detect(gray, self.full_scale, detector)

    def _upsamples(self, box) -> bool:
        """Whether `_box_features` upsamples the box (None: the whole frame, never)."""
        if box is None or box[4] > 1:
            return False
        return max(box[2] - box[0], box[3] - box[1]) < self.settings.upsample_below_px

    def _box_features(self, gray: np.ndarray, box, detector) -> tuple[np.ndarray, np.ndarray]:
        """Features in the pixel box (None: the whole frame): shrunk first when the landmark
        looks larger than from its keyframes, else upsampled when the box is small or the
        camera coarser than the model's (`detection_scales`)."""
        if box is None:
            return self._full_features(gray, detector)
        x0, y0, x1, y1, shrink = box
        crop = gray[y0:y1, x0:x1]
        if shrink > 1:  # the landmark larger than in its keyframes: at their scale
            up = 1 / shrink
            crop = cv2.resize(crop, None, fx=up, fy=up, interpolation=cv2.INTER_AREA)
        else:  # small and far, or a coarser camera than the model's: finer features
            small = self.settings.upsample_to_px / max(crop.shape) if self._upsamples(box) else 1
            up = max(small, 1 / self.full_scale, 1.0)
            if up > 1:
                crop = cv2.resize(crop, None, fx=up, fy=up, interpolation=cv2.INTER_CUBIC)
        kps, desc = detect(crop, detector)
        return kps / np.float32(up) + np.array([x0, y0], np.float32), desc


def _scaled_detect(gray: np.ndarray, scale: float, detector) -> tuple[np.ndarray, np.ndarray]:
    """Features of `gray` shrunk by `scale` (below 1: upsampled), in `gray`'s pixels."""
    if scale == 1:
        return detect(gray, detector)
    interp = cv2.INTER_AREA if scale > 1 else cv2.INTER_CUBIC
    small = cv2.resize(gray, None, fx=1 / scale, fy=1 / scale, interpolation=interp)
    kps, desc = detect(small, detector)
    # pixel centres: (u + 0.5) * scale - 0.5
    return kps * np.float32(scale) + np.float32((scale - 1) / 2), desc
