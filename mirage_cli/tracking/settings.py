"""`mirage track`'s settings: the tracker's own, and the solver's option objects it passes on."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from ..solver import RansacOptions, RefineOptions


@dataclass
class TrackSettings:
    method: str = "mirage-s"
    redetect_every: int = 5  # frames between full detections while flow holds
    detect_ahead: bool = True  # the next regular detection's features are detected on
    # the second core while the frames before it are flowed (False: in its own frame)
    min_inliers: int = 15  # fewer consistent points without a prediction: lost
    min_track_inliers: int = 6  # while tracking (a prediction to match around and start
    # Mirage-S from) the pose's uncertainty decides, so a few well-spread points suffice
    max_false_alarms: float = 1e-3  # the inliers must rule out chance: at most this many
    # of RANSAC's hypotheses would gather as much support from wrong matches (evidence.py)
    min_landmark_inliers: int = 10  # inliers on the landmark itself, not the ground
    max_ok_rmse_px: float = 2.0  # an ok frame's largest reprojection RMS (--max-rmse)
    max_roll_deg: float = 45.0  # a pose rolled this much beyond every keyframe (W's up
    # in the image) is `implausible` (--max-roll; 180: never)
    max_leverage: float = 0.9  # a point that carries more of a direction of the pose on
    # its own is dropped and the pose fitted without it (solver.verifiable)
    # RANSAC's inlier threshold and seed: 3 px, seed 0
    ransac: RansacOptions = field(default_factory=lambda: RansacOptions(threshold_px=3.0))
    # the fit drops points beyond max(reject_px, 5 sigma); Mirage-S's Huber floor: residuals
    # beyond max(huber_px, 2.5 sigma) weigh less (a model point or keypoint that is off by a
    # pixel pulls the pose less)
    refine: RefineOptions = field(
        default_factory=lambda: RefineOptions(reject_px=2.0, huber_px=0.5)
    )
    ratio: float = 0.8
    flow: bool = True
    min_flow_points: int = 30  # the flow needs this many of the detected points, or
    flow_keep_few: float = 0.8  # this share of a detection with fewer (a small view), and
    flow_keep: float = 0.5  # this share of any detection: else detect afresh
    flow_fb_px: float = 0.7  # forward-backward consistency of Lucas-Kanade
    flow_window_px: int = 7  # Lucas-Kanade window: small, so it stays on one surface
    flow_levels: int = 1  # pyramid levels above the image: each point starts where the
    # predicted pose puts it (forward) or at its anchor (backward), so one suffices
    flow_shift_retry: bool = True  # too few points flowed: measure the image shift they
    # agree on (a coarse pass) and flow again from it, before detecting afresh
    flow_max_dev_sigma: float = 4.0  # flowed pose this many sigmas off the prediction: detect
    flow_max_rmse_px: float = 1.0  # a worse flowed fit (large motion, drift) -> detect,
    flow_rmse_growth: float = 1.5  # unless within this many times its detection's RMS
    flow_gain_tol: float = 0.05  # the exposure changed more since the anchor: flow again
    # in the frame scaled to the anchor's brightness (Lucas-Kanade assumes it constant)
    local_keyframes: int = 4  # keyframes near the previous pose to match against
    global_keyframes: int = 3  # keyframes proposed by recognition when lost
    relocalise_every: int = 3  # while lost: the whole frame every N frames, a half-size
    # probe between (1: the whole frame every time)
    long_lost: int = 12  # lost longer than this (a look-away, not a dropout): the whole
    # frame every 2N frames, the probe every other frame between
    max_jump_m: float = 0.5  # a pose this far from the previous ok pose (per frame)...
    max_jump_deg: float = 30.0  # ...or turned this much is distrusted (needs detection)
    guided_radius_px: float = 40.0  # while tracking: match only near the predicted pixel
    detect_margin_px: int = 32  # while tracking: detect only in the predicted box of the
    # model's points plus this margin (-1: always the whole frame)
    upsample_below_px: int = 320  # a smaller detection box (longer side, px; 0: never)...
    upsample_to_px: int = 480  # ...is upsampled to this size before detection
    patch_refine: str = "small"  # place points by keyframe patches: off | small | all
    patch_keyframes: int = 2
    patch_reach_px: int = 4
    patch_max_angle_deg: float = 20.0  # between the keyframe's and the frame's rays
    patch_max_angle_normal_deg: float = 60.0  # the same for a point on a face (its normal)
    patch_max_slant_deg: float = 75.0  # a face seen more obliquely gives no template
    patch_flat_max: float = 0.05  # a point's neighbours this flat make a face (patches.py)
    patch_coarse_level: int = 2  # patches alone, off the prediction: from this level down
    patch_refresh: bool = True  # from above: regular detections by patches alone
    patch_refresh_min: int = 60  # points they must place (else keypoints as usual)
    patch_min_ncc: float = 0.8
    patch_min_gain: float = 2.0  # patch inliers at least this x the keypoints' to be used
    patch_dispute: float = 3.0  # sigmas apart (the two centres) at which the keypoints'
    # pose must cover the patches' (`_patch_verdict`; far tuning seeds: 23 of ~7000 ok
    # frames, 3 of them wrong, were kept by keypoints the patches put 3 sigma or more away)
    ground_dispute_max: int = 3  # a detected or flowed pose with at most this many inliers
    # off the landmark is fitted again without them (`_ground_dispute`; 0: never)
    patch_max_points: int = 300  # per keyframe
    patch_error_points: float = 60.0  # patch errors average like this many points
    patch_error_floor: float = 3.0  # and a patched pose's covariance is at least this many
    # times what its residuals show, in a view shrunk `patch_floor_ratio` or more from its
    # keyframe's: each patch is placed within a few pixels of the pose it measures, from
    # a template warped by that pose (far tuning seeds 58-99: patched poses that passed
    # the gate were 1.85x / 1.44x / 1.25x as far off as their sigma at 30-60 / 60-100 /
    # 100-200 patch inliers, 0.95x beyond)
    patch_floor_ratio: float = 1.5  # (far tuning seeds: honest below 1.5x, not above)
    patch_ransac: RansacOptions = field(default_factory=lambda: RansacOptions(threshold_px=2.0))
    shrink_above: float = 1.5  # the landmark looks this many times larger than from its
    # nearest keyframe (a sharper camera than the model's, or nearer): the detection box
    # is shrunk by that factor / SHRINK_MARGIN first (the keyframes hold no finer
    # features; SIFT's time goes with the pixels)
    proposals: int = 2  # relocalisation that found nothing: RANSAC proposals from looser
    # matches, each checked by guided matching around it (0: none; relocalise.py)
    second_hypothesis: float = 0.5  # relocalisation: a distinct pose with this share of the
    # first's inliers makes the frame ambiguous (lost)
    distinct_m: float = 0.10  # two poses further apart than this (or distinct_deg) are
    distinct_deg: float = 5.0  # different hypotheses
    model_error_points: float = 300.0  # model/keypoint errors average like this many points
    max_sigma_pos_m: float = 0.10  # a larger 1-sigma uncertainty is `uncertain`, not ok
    max_sigma_rot_deg: float = 1.5
    max_sigma_range: float = 0.01  # ...or larger than this share of the landmark's distance,
    sigma_range_floor_m: float = 0.0  # which is never below this (a near landmark)

    def distinct(self, a, b) -> bool:
        """Two poses are different hypotheses (`distinct_m` apart or `distinct_deg` turned)."""
        return a.distance_to(b) > self.distinct_m or a.angle_to(b) > self.distinct_deg

    def at_scale(self, f: float) -> TrackSettings:
        """These settings for features detected on an image shrunk by `f` (>= 1; a video
        sharper than the model's keyframes): the limits that measure a keypoint's or a
        model point's error in pixels grow with the pixels (a model point 0.5 px off in
        its keyframes is 1.1 px off in a 1080p frame against them), and so does the
        prediction's reach (the radius of guided matching)."""
        if f <= 1:
            return self
        r = self.refine
        return replace(
            self,
            max_ok_rmse_px=self.max_ok_rmse_px * f,
            flow_max_rmse_px=self.flow_max_rmse_px * f,
            guided_radius_px=self.guided_radius_px * f,
            ransac=replace(self.ransac, threshold_px=self.ransac.threshold_px * f),
            refine=replace(
                r,
                huber_px=r.huber_px * f,
                reject_px=None if r.reject_px is None else r.reject_px * f,
            ),
        )
