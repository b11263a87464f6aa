"""`mirage track --extend`: tracked frames from new views join the model (extend.py)."""

from dataclasses import replace
from types import SimpleNamespace

import cv2
import numpy as np
import pandas as pd
import pytest
from conftest import SAMPLE, assert_one_line_error, run_mirage

from mirage_cli.camera import Camera
from mirage_cli.extend import ViewPicker, can_extend, inherited_sigmas
from mirage_cli.frames import Frame, FrameSource
from mirage_cli.model import INHERITED_TABLE, LandmarkModel
from mirage_cli.pipelines.track import extended_records, tracked_records
from mirage_cli.pose import look_at
from mirage_cli.records import FrameRecord, Status
from mirage_cli.synth import LANDMARK_TARGET
from mirage_cli.tracking import Tracker, TrackSettings
from mirage_cli.tracking.smooth import SmoothSettings
from mirage_cli.trajectory import row_pose


def test_points_only_the_added_frames_triangulate_carry_their_sigma():
    """Keyframes 0-1 are the model's own, 2-3 the added frames (sigma 4 / 2 mm, 0.2 / 0.1
    deg), all 1 m from the points. A point two own keyframes see carries nothing, whoever
    else sees it; one own keyframe and an added frame: that frame's sigma; two added
    frames: their mean. Seen from directions 10 deg apart or more (25 here) the sigma is
    as it is; 5 deg apart, it grows by sin(10) / sin(5) along the rays (`_depth_gain`)."""

    def view(deg):
        a = np.radians(deg)
        return SimpleNamespace(pose=SimpleNamespace(center=np.array([np.sin(a), -np.cos(a), 0])))

    obs = {
        "point": np.array([0, 0, 0, 1, 1, 2, 2, 3, 3]),
        "keyframe": np.array([0, 1, 2, 0, 3, 2, 3, 1, 0]),
    }
    model = SimpleNamespace(points=np.zeros((4, 3)), point_observations=obs,
                            keyframes=[view(0), view(30), view(60), view(35)])  # fmt: skip
    views = [SimpleNamespace(sigma_pos_m=0.004, sigma_rot_deg=0.2),
             SimpleNamespace(sigma_pos_m=0.002, sigma_rot_deg=0.1)]  # fmt: skip
    got = inherited_sigmas(model, 2, views)
    want = np.array([[0, 0], [0.002, np.radians(0.1)], [0.003, np.radians(0.15)], [0, 0]])
    np.testing.assert_allclose(got, want, atol=1e-12)
    model.keyframes[3] = view(55)  # 5 deg from frame 2
    narrow = inherited_sigmas(model, 2, views)[2]
    gain = np.sin(np.radians(10)) / np.sin(np.radians(5))  # 1.99
    np.testing.assert_allclose(narrow, want[2] * gain, rtol=1e-9)


def _ok(pose, sigma=0.001, frame=0):
    return FrameRecord(Status.OK, pose, frame, sigma_pos_m=sigma, sigma_rot_deg=0.05)


def test_the_picker_keeps_well_tracked_frames_from_new_views(sample_model):
    """A frame joins when it is ok, its sigma at most 1% of its range, its view 6 deg or
    more from every keyframe's and every frame already taken (`view_change`), and only
    once its run of ok frames is 10 long: a single ok frame (a wrong relocalisation
    looks like one) never joins."""
    model = LandmarkModel.load(sample_model)
    picker = ViewPicker(model)
    gray = np.zeros((480, 640), np.uint8)
    up = look_at(LANDMARK_TARGET + np.array([0.9, 0.3, 1.2]), LANDMARK_TARGET)
    near = look_at(LANDMARK_TARGET + np.array([0.92, 0.3, 1.2]), LANDMARK_TARGET)
    picker.offer(_ok(up, frame=1), gray)  # new, but its run ends at 1 frame
    picker.offer(FrameRecord(Status.UNCERTAIN, up, 2), gray)
    picker.offer(_ok(model.keyframes[3].pose, frame=3), gray)  # a keyframe's own view
    picker.offer(_ok(up, sigma=0.05, frame=4), gray)  # 3% of a 1.5 m range
    picker.offer(_ok(up, frame=5), None)  # no image
    picker.offer(_ok(up, frame=6), gray)
    for k in range(7, 12):
        picker.offer(_ok(near, frame=k), gray)  # a degree from frame 6
        assert not picker.views  # the run is 9 long at frame 11
    picker.offer(_ok(near, frame=12), gray)
    assert [v.name for v in picker.views] == ["frame 6"]
    assert picker.views[0].pose.distance_to(up) < 1e-12


def _climb(elevations, azimuth_deg=40.0, dist=1.5):
    """The sample's landmark rendered by a camera climbing at one azimuth (grey frames)."""
    from mirage_cli.render import Renderer
    from mirage_cli.synth import landmark_scene

    cam = Camera.load(SAMPLE / "camera_truth.yaml")
    r = Renderer(landmark_scene(0), cam, aa=1)
    poses, grays = [], []
    for k, e in enumerate(np.radians(elevations)):
        a = np.radians(azimuth_deg) + 0.01 * k
        d = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
        poses.append(look_at(LANDMARK_TARGET + dist * d, LANDMARK_TARGET))
        img = r.render(poses[-1], 1.5, np.random.default_rng(k))
        grays.append(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY))
    return cam, poses, grays


@pytest.fixture(scope="module")
def climb(sample_model, tmp_path_factory):
    """A camera climbing from 20 to 80 deg above the landmark (the sample's keyframes look
    from 13 deg), as an image folder: tracked plainly (the API), then by `mirage track
    --extend --extended-model` (one build of the grown model for the module)."""
    elevations = np.linspace(20, 80, 13)
    cam, poses, grays = _climb(elevations)
    model = LandmarkModel.load(sample_model)
    frames = (Frame(i, i, i / 30, g) for i, g in enumerate(grays))
    plain = list(tracked_records(frames, Tracker(model, cam, TrackSettings()), SmoothSettings()))
    tmp = tmp_path_factory.mktemp("climb")
    (tmp / "frames").mkdir()
    for i, g in enumerate(grays):
        cv2.imwrite(str(tmp / "frames" / f"{i:06d}.png"), g)
    args = ("track", tmp / "frames", "--model", sample_model, "--camera",
            SAMPLE / "camera_truth.yaml", "--fps", "30")  # fmt: skip
    p = run_mirage(*args, "-o", tmp / "poses.csv", "--extend", "--extended-model", tmp / "g.mirage")
    return SimpleNamespace(elevations=elevations, poses=poses, plain=plain, run=p, args=args,
                           rows=pd.read_csv(tmp / "poses.csv") if p.returncode == 0 else None,
                           grown=tmp / "g.mirage")  # fmt: skip


def test_a_camera_climbing_past_the_keyframes_reach_is_tracked_with_extend(climb):
    """Above 65 deg the plain run loses the landmark (its top and foreshortened sides are
    no keyframe's view); with the frames it tracked on the way up joined to the model,
    every frame is ok within 1 cm and 0.5 deg, and those found only now within 3 of their
    own sigmas: the points only the added frames see carry their pose error
    (`inherited_sigmas`). The first pass's ok poses stand as they were."""
    assert climb.run.returncode == 0, climb.run.stderr
    assert "tracked frames joined the model (--extend)" in climb.run.stdout, climb.run.stdout
    plain_ok = np.array([r.ok for r in climb.plain])
    assert not plain_ok[climb.elevations >= 70].any(), plain_ok
    assert plain_ok[climb.elevations <= 50].all(), plain_ok
    rows = climb.rows
    assert len(rows) == len(climb.poses) and (rows["status"] == "ok").all(), rows["status"]
    for (_, row), truth, before in zip(rows.iterrows(), climb.poses, climb.plain, strict=True):
        pose = row_pose(row)
        pos, rot = pose.distance_to(truth), pose.angle_to(truth)
        assert pos < 0.01 and rot < 0.5, (pos, rot)
        if before.ok:  # the first pass's stands
            assert pose.distance_to(before.pose) < 1e-5 and pose.angle_to(before.pose) < 1e-3
        else:  # found against the added frames' points: as uncertain as they are
            assert pos < 3 * row["sigma_pos_m"] and rot < 3 * row["sigma_rot_deg"], (pos, row)


def test_an_extended_model_keeps_its_inherited_sigmas_in_its_file(climb, sample_model, tmp_path):
    model = LandmarkModel.load(climb.grown)
    n_own = len(LandmarkModel.load(sample_model).keyframes)
    assert model.meta["extended"]["keyframes"] == n_own < len(model.keyframes)
    table = model.tables[INHERITED_TABLE]
    assert (table[:, 0] > 0).any() and (table[:, 0] == 0).any()
    model.save(tmp_path / "again.mirage")
    back = LandmarkModel.load(tmp_path / "again.mirage")
    np.testing.assert_array_equal(back.tables[INHERITED_TABLE], table)
    assert back.meta["extended"]["frames"] == model.meta["extended"]["frames"]


def test_the_extended_model_option_needs_extend(climb, tmp_path):
    bad = run_mirage(*climb.args, "-o", tmp_path / "p.csv", "--extended-model", tmp_path / "m")
    assert_one_line_error(bad, 2, "--extend")
    assert not (tmp_path / "p.csv").exists()


def test_a_model_without_keyframe_images_cannot_be_extended(sample_model):
    model = LandmarkModel.load(sample_model)
    assert can_extend(model, model.camera) is None
    other = replace(model.camera, K=model.camera.K * [[1.1], [1.1], [1]])
    assert "camera" in can_extend(model, other)
    for kf in model.keyframes:
        kf.image = None
    assert "keyframe images" in can_extend(model, model.camera)


def test_extending_footage_the_keyframes_already_cover_changes_nothing(sample_model):
    """The sample orbit's first 60 frames fly where the keyframes were taken, every one
    ok: `extended_records` builds nothing and gives the plain run's records."""
    cam = Camera.load(SAMPLE / "camera_truth.yaml")
    model = LandmarkModel.load(sample_model)
    src = FrameSource([SAMPLE / "orbit.mp4"])
    images = [f.image for f in src.frames(0, 60)]

    def frames():
        return (Frame(i, i, i / 30, g) for i, g in enumerate(images))

    plain = list(tracked_records(frames(), Tracker(model, cam, TrackSettings())))
    got, grown = extended_records(frames, Tracker(model, cam, TrackSettings()))
    assert grown is None and all(r.ok for r in plain)
    for a, b in zip(plain, got, strict=True):
        assert a.pose.distance_to(b.pose) == 0.0 and a.sigma_pos_m == b.sigma_pos_m
