"""The detector registry: every entry detects what its spec says, descriptors keep their
dtype through a model file, and RootSIFT (one entry + one function) tracks like SIFT."""

import cv2
import numpy as np
import pytest
from conftest import SAMPLE, run_mirage
from test_track import assert_accuracy, errors  # errors of the ok rows; limits

from mirage_cli.camera import Camera
from mirage_cli.errors import InputError
from mirage_cli.features import (
    DETECTORS,
    REGISTRY,
    DetectorSettings,
    detect,
    make_detector,
    root_sift,
)
from mirage_cli.model import Keyframe, LandmarkModel, make_thumbnail
from mirage_cli.trajectory import read_pose_csv, row_pose

KF = SAMPLE / "keyframes"


def _image(i=0):
    return cv2.imread(str(sorted(KF.glob("*.jpg"))[i]), cv2.IMREAD_GRAYSCALE)


def test_root_sift_is_the_hellinger_map():
    d = np.random.default_rng(0).integers(0, 256, (50, 128)).astype(np.float32)
    r = root_sift(d)
    assert r.dtype == np.float32
    np.testing.assert_allclose(np.sum(r**2, axis=1), 1.0, rtol=1e-5)  # unit L2 norm
    np.testing.assert_allclose(r, np.sqrt(d / d.sum(axis=1, keepdims=True)), rtol=1e-6)
    # L2 distance of RootSIFT = Hellinger distance of the L1-normalised histograms
    p, q = d[0] / d[0].sum(), d[1] / d[1].sum()
    hell = np.sqrt(np.sum((np.sqrt(p) - np.sqrt(q)) ** 2))
    assert np.linalg.norm(r[0] - r[1]) == pytest.approx(hell, rel=1e-5)
    assert np.all(root_sift(np.zeros((2, 128), np.float32)) == 0)  # no division by zero


@pytest.mark.parametrize("name", DETECTORS)
def test_each_detector_gives_its_spec(name):
    spec = REGISTRY[name]
    det = make_detector(DetectorSettings(name, 500))
    kp, desc = detect(_image(), det)
    assert 100 <= len(kp) <= 500 and kp.dtype == np.float32
    assert desc.dtype == spec.dtype and desc.shape == (len(kp), spec.width)
    kp0, desc0 = detect(np.zeros((64, 64), np.uint8), det)  # nothing to find
    assert kp0.shape == (0, 2) and desc0.dtype == spec.dtype and desc0.shape[1] == spec.width


def test_unknown_detector_is_an_input_error():
    with pytest.raises(InputError, match="unknown detector 'surf'.*rootsift"):
        DetectorSettings.from_dict({"name": "surf"})
    with pytest.raises(InputError, match="unknown detector"):
        make_detector(DetectorSettings("surf"))


@pytest.mark.parametrize("name", DETECTORS)
def test_descriptors_keep_dtype_and_values_through_the_model_file(name, tmp_path):
    settings = DetectorSettings(name, 300)
    det = make_detector(settings)
    truth = {r["frame"]: row_pose(r) for _, r in read_pose_csv(KF / "poses.csv").iterrows()}
    kfs = []
    for i in range(2):
        img = _image(i)
        kp, desc = detect(img, det)
        ids = np.full(len(kp), -1, np.int32)
        ids[::2] = np.arange(len(ids[::2])) + 1000 * i  # half the features linked
        name_i = sorted(KF.glob("*.jpg"))[i].name
        kfs.append(Keyframe(name_i, truth[name_i], kp, desc, ids, make_thumbnail(img)))
    model = LandmarkModel(
        Camera.load(SAMPLE / "camera_truth.yaml"), settings, kfs, np.zeros((2000, 3))
    )
    model.save(tmp_path / "m.mirage")
    back = LandmarkModel.load(tmp_path / "m.mirage")
    assert back.detector == settings
    for a, b in zip(back.keyframes, kfs, strict=True):
        assert a.descriptors.dtype == REGISTRY[name].dtype
        assert np.array_equal(a.descriptors, b.descriptors)
    assert back.recognize(kfs[1].descriptors, top_k=1)[0][0] == 1


def _sample_model(tmp_path, detector: str):
    """`mirage build-model` of the sample keyframes with this detector."""
    model = tmp_path / f"{detector}.mirage"
    p = run_mirage(
        "-q", "build-model", KF, "--detector", detector, "--poses", KF / "poses.csv",
        "--camera", SAMPLE / "camera_truth.yaml", "-o", model,
    )  # fmt: skip
    assert p.returncode == 0, p.stderr
    return model


def test_rootsift_model_tracks_the_orbit(tmp_path):
    """`--detector rootsift` end to end: as accurate as SIFT (its own measured figures,
    with test_track's margins)."""
    model = _sample_model(tmp_path, "rootsift")
    m = LandmarkModel.load(model)
    assert m.detector.name == "rootsift" and len(m.points) > 3000
    d = m.keyframes[0].descriptors
    assert d.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, rtol=1e-4)  # RootSIFT kept
    csv = tmp_path / "p.csv"
    p = run_mirage("-q", "track", SAMPLE / "orbit.mp4", "--model", model, "--every", "2", "-o", csv)
    assert p.returncode == 0, p.stderr
    est = read_pose_csv(csv)
    truth = read_pose_csv(SAMPLE / "orbit_truth.csv").set_index("frame").loc[est["frame"]]
    vis = truth["landmark_visible"].to_numpy()
    ok = (est["status"] == "ok").to_numpy()
    assert ok[vis >= 0.3].mean() >= 0.99 and not ok[vis == 0].any()
    pos, rot, _ = errors(est, truth.reset_index())
    # measured at dc25f7f (every 2nd frame): 1.46 / 3.40 / 5.63 mm, 0.059 / 0.133 / 0.230 deg
    assert_accuracy(pos, rot, (1.46, 3.40, 5.63), (0.059, 0.133, 0.230))


def test_orb_model_tracks_the_start_of_the_orbit(tmp_path):
    """Binary descriptors through guided matching (Hamming distances; once an OpenCV
    assertion on the first tracked frame)."""
    model = _sample_model(tmp_path, "orb")
    csv = tmp_path / "p.csv"
    p = run_mirage("-q", "track", SAMPLE / "orbit.mp4", "--model", model, "--end", "60", "-o", csv)
    assert p.returncode == 0, p.stderr
    est = read_pose_csv(csv)
    assert (est["status"] == "ok").mean() >= 0.95
    truth = read_pose_csv(SAMPLE / "orbit_truth.csv").set_index("frame").loc[est["frame"]]
    pos, rot, _ = errors(est, truth.reset_index())
    # measured at dc25f7f (60 frames): 3.11 / 6.24 / 7.93 mm, 0.128 / 0.219 / 0.271 deg
    assert_accuracy(pos, rot, (3.11, 6.24, 7.93), (0.128, 0.219, 0.271))
