import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from mirage_cli.pose import (
    Pose,
    look_at,
    matrix_from_quat,
    matrix_from_rpy,
    quat_from_matrix,
    rodrigues,
    rotvec,
    rpy_from_matrix,
)

angle = st.floats(-np.pi, np.pi, allow_nan=False)
pitch = st.floats(-np.radians(89), np.radians(89), allow_nan=False)
coord = st.floats(-50, 50, allow_nan=False)
quat = st.lists(st.floats(-1, 1, allow_nan=False), min_size=4, max_size=4).filter(
    lambda q: np.linalg.norm(q) > 0.1
)


@given(quat)
def test_quaternion_matrix_round_trip(q):
    q = np.asarray(q) / np.linalg.norm(q)
    q = q if q[0] >= 0 else -q
    R = matrix_from_quat(q)
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.isclose(np.linalg.det(R), 1.0)
    q2 = quat_from_matrix(R)
    # q and -q are the same rotation; with w == 0 both signs are canonical
    assert np.allclose(q2, q, atol=1e-9) or np.allclose(q2, -q, atol=1e-9)
    assert np.allclose(matrix_from_quat(q2), R, atol=1e-9)


@given(angle, pitch, angle)
def test_rpy_matrix_round_trip(r, p, y):
    R = matrix_from_rpy(r, p, y)
    r2, p2, y2 = rpy_from_matrix(R)
    assert np.allclose(matrix_from_rpy(r2, p2, y2), R, atol=1e-9)
    assert abs(p2 - p) < 1e-9
    assert abs(np.angle(np.exp(1j * (r2 - r)))) < 1e-9
    assert abs(np.angle(np.exp(1j * (y2 - y)))) < 1e-9


@given(st.lists(st.floats(-3, 3, allow_nan=False), min_size=3, max_size=3))
def test_rotvec_round_trip(v):
    v = np.asarray(v)
    R = rodrigues(v)
    assert np.allclose(rodrigues(rotvec(R)), R, atol=1e-9)


@settings(max_examples=200)
@given(angle, pitch, angle, coord, coord, coord)
def test_pose_center_quat_rpy_round_trip(r, p, y, x, yy, z):
    pose = Pose.from_center_rpy([x, yy, z], *np.degrees([r, p, y]))
    assert np.allclose(pose.rpy_deg, np.degrees([r, p, y]), atol=1e-7) or np.allclose(
        matrix_from_rpy(*np.radians(pose.rpy_deg)), matrix_from_rpy(r, p, y), atol=1e-9
    )
    again = Pose.from_center_quat(pose.center, pose.quat_wxyz)
    assert np.allclose(again.R, pose.R, atol=1e-9)
    assert np.allclose(again.t, pose.t, atol=1e-9 * max(1, abs(x) + abs(yy) + abs(z)))
    assert np.allclose(pose.center, [x, yy, z], atol=1e-9)
    # T_CW <-> centre: the centre maps to the camera origin
    assert np.allclose(pose.transform(pose.center[None]), 0, atol=1e-9)
    # rvec/tvec round trip
    p2 = Pose.from_rvec_tvec(pose.rvec, pose.tvec)
    assert np.allclose(p2.R, pose.R, atol=1e-9)


@given(angle, pitch, angle, coord, coord, coord)
def test_compose_inverse(r, p, y, x, yy, z):
    a = Pose.from_center_rpy([x, yy, z], *np.degrees([r, p, y]))
    ident = a @ a.inverse()
    assert np.allclose(ident.R, np.eye(3), atol=1e-9)
    assert np.allclose(ident.t, 0, atol=1e-8)
    assert a.distance_to(a) == 0
    assert a.angle_to(a) < 1e-5


def test_rep103_conventions():
    # a level camera looking along +X has roll = pitch = yaw = 0
    level = look_at([-2, 0, 0.5], [0, 0, 0.5])
    assert np.allclose(level.rpy_deg, 0, atol=1e-9)
    assert np.allclose(level.quat_wxyz @ level.quat_wxyz, 1)
    # looking along +Y: yaw = +90 (counter-clockwise seen from above)
    assert np.isclose(look_at([0, -2, 0.5], [0, 0, 0.5]).rpy_deg[2], 90)
    # looking down at the ground: REP-103 pitch is positive nose-down
    down = look_at([-2, 0, 2.0], [0, 0, 0.0])
    assert np.isclose(down.rpy_deg[1], 45)
    # the optical axis (camera z) is the body's x axis
    assert np.allclose(level.R_wc[:, 2], [1, 0, 0])
    # azimuth of the camera centre around the origin
    assert np.isclose(look_at([0, 2, 0], [0, 0, 0]).azimuth_deg, 90)
    assert look_at([-2, 0, 0], [0, 0, 0]).azimuth_deg == 180.0


def test_angle_and_distance():
    a = Pose.from_center_rpy([1, 0, 0], 0, 0, 0)
    b = Pose.from_center_rpy([1, 3, 4], 0, 0, 30)
    assert np.isclose(a.distance_to(b), 5)
    assert np.isclose(a.angle_to(b), 30)
