"""boards.py: the one board description (round trips through the board file), its printed
image against its object points, and the board pose recovered from rendered views."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import yaml

from mirage_cli.boards import Board, BoardPoser, load_board, parse_size
from mirage_cli.errors import InputError
from mirage_cli.pose import look_at
from mirage_cli.render import Renderer, Scene
from mirage_cli.synth import GROUND_BOARD, add_ground_board, default_camera

# What `mirage synth --ground-board` has always written (after its comment line).
GROUND_BOARD_YAML = """\
type: charuco
squares: [10, 10]
square_m: 0.14
marker_m: 0.105
dictionary: DICT_4X4_250
legacy_pattern: false
origin_m: [-0.7, 0.7, 0.0005]
yaw_deg: 0.0
placement: ground
"""

GRID = Board(
    4, 3, 0.0, "aruco_grid", marker_m=0.08, dictionary="DICT_4X4_50", separation_m=0.02,
    origin_m=(0.1, -0.2, 0.0), yaw_deg=30.0, placement="board",
)  # fmt: skip


def _dump(board: Board) -> str:
    return yaml.safe_dump(board.to_yaml(), sort_keys=False, default_flow_style=None)


@pytest.mark.parametrize(
    "board",
    [
        GROUND_BOARD,
        GRID,
        Board(7, 6, 0.05, "charuco", 0.035, "DICT_5X5_100", legacy_pattern=True, yaw_deg=-45),
    ],
)
def test_board_file_round_trip(board, tmp_path):
    f = tmp_path / "board.yaml"
    f.write_text(_dump(board))
    again = load_board(f)
    assert again == board
    assert _dump(again) == f.read_text()


def test_ground_board_file_is_unchanged():
    assert _dump(GROUND_BOARD) == GROUND_BOARD_YAML
    assert yaml.safe_load(GROUND_BOARD_YAML)["marker_m"] == GROUND_BOARD.marker_size_m


def test_board_file_defaults_and_dictionary_spelling(tmp_path):
    f = tmp_path / "b.yaml"
    f.write_text("squares: [5, 7]\nsquare_m: 0.04\nmarker_m: 0.03\n")
    b = load_board(f)
    assert (b.pattern, b.squares, b.dictionary, b.placement) == (
        "charuco", (5, 7), "DICT_4X4_50", "ground",
    )  # fmt: skip
    assert b.origin_m == (0.0, 0.0, 0.0) and b.yaw_deg == 0.0 and not b.legacy_pattern
    f.write_text("squares: [5, 7]\nsquare_m: 0.04\nmarker_m: 0.03\ndictionary: 5x5_100\n")
    assert load_board(f).cv_board().getDictionary().bytesList.shape[0] == 100


@pytest.mark.parametrize(
    "text, words",
    [
        ("- 1\n- 2\n", "mapping"),
        ("type: chessboard\nsquares: [9, 6]\nsquare_m: 0.02\nmarker_m: 0.01\n", "charuco or"),
        ("squares: [5, 7]\nsquare_m: 0.04\n", "missing key 'marker_m'"),
        ("squares: [5, 7]\nsquare_m: 0.04\nmarker_m: abc\n", "bad value"),
        ("squares: [5, 7]\nsquare_m: 0.04\nmarker_m: 0.05\n", "marker size"),
        ("squares: [1, 7]\nsquare_m: 0.04\nmarker_m: 0.03\n", "at least 2x2"),
        ("squares: [5, 7]\nsquare_m: 0.04\nmarker_m: 0.03\ndictionary: DICT_9\n", "dictionary"),
        ("squares: [5, 7]\nsquare_m: 0.04\nmarker_m: 0.03\norigin_m: [1, 2]\n", "origin_m"),
        ("squares: [5, 7]\nsquare_m: 0.04\nmarker_m: 0.03\nplacement: wall\n", "placement"),
        ("type: aruco_grid\nsquares: [5, 7]\nmarker_m: 0\n", "marker size"),
    ],
)
def test_bad_board_file_is_one_clear_error(text, words, tmp_path):
    f = tmp_path / "b.yaml"
    f.write_text(text)
    with pytest.raises(InputError) as e:
        load_board(f)
    msg = str(e.value)
    assert msg.startswith(f"board file {f}: ") and words in msg and "\n" not in msg


def test_parse_size():
    assert parse_size("9x6") == (9, 6)
    assert parse_size(" 7 X 5 ") == (7, 5)
    assert parse_size("4*3") == (4, 3) and parse_size("4,3") == (4, 3)
    for bad, why in (("9", "COLSxROWS"), ("9x6x2", "COLSxROWS"), ("1x6", ">= 2")):
        with pytest.raises(ValueError, match=why):
            parse_size(bad)


def test_calibration_board_defaults():
    b = Board(7, 5, 0.04, "charuco")
    assert b.marker_size_m == pytest.approx(0.03) and b.dictionary == "DICT_5X5_100"
    assert len(b.object_points) == 6 * 4  # inner corners of 7x5 squares
    with pytest.raises(InputError, match="marker size"):
        Board(7, 5, 0.04, "charuco", marker_m=0.04)
    with pytest.raises(InputError, match="unknown ArUco dictionary"):
        Board(7, 5, 0.04, "charuco", dictionary="nope")
    Board(9, 6, 0.025, dictionary="nope")  # a chessboard has no dictionary to check
    with pytest.raises(InputError, match="square size"):
        Board(9, 6, 0.0)


@pytest.mark.parametrize("board", [Board(9, 6, 0.025), Board(7, 5, 0.04, "charuco", 0.03)])
def test_printed_image_agrees_with_object_points(board):
    """Corners found in the printed image sit where object_points put them (px = m / square
    * px_per_square, plus the margin)."""
    px, margin = 40, 1
    img = board.image(px, margin)
    w, h = board.size_m
    size = (
        round((h / board.square_m + 2 * margin) * px),
        round((w / board.square_m + 2 * margin) * px),
    )
    assert img.shape == size
    if board.pattern == "chessboard":
        ok, found = cv2.findChessboardCorners(img, board.squares)
        assert ok
        found = found.reshape(-1, 2)
        cv2.cornerSubPix(img, found, (5, 5), (-1, -1), (3, 40, 1e-3))
        ids = np.arange(len(found))
        if np.linalg.norm(found[0]) > np.linalg.norm(found[-1]):  # OpenCV may start at the end
            found = found[::-1]
        offset = (1 + margin) * px  # one square of the pattern before the first inner corner
    else:
        found, ids, _, _ = board.cv_detector().detectBoard(img)
        found, ids = found.reshape(-1, 2), ids.ravel()
        assert len(ids) == 24
        offset = margin * px
    expect = board.object_points[ids, :2] / board.square_m * px + offset - 0.5
    assert np.abs(found - expect).max() < 0.2


@pytest.mark.parametrize("board, tol_m, tol_deg", [(GROUND_BOARD, 0.003, 0.1), (GRID, 0.005, 0.3)])
def test_poser_recovers_rendered_board_pose(board, tol_m, tol_deg):
    """The board rendered by synth's ray caster (distorted camera) gives back the camera
    pose, in W as the board's placement defines it. ChArUco corners are refined to
    sub-pixel; the ArUco grid's marker corners are not (0.7 px RMS here), hence its
    looser bound."""
    cam = default_camera()
    renderer = Renderer(add_ground_board(Scene([]), board), cam)
    poser = BoardPoser(board, cam)
    centre = board.T_wb.transform(np.r_[np.array(board.size_m) / 2, 0.0])
    if board.placement == "ground":
        views = [look_at([1.2 * np.cos(a), 1.2 * np.sin(a), 0.9], centre) for a in (0.3, 2.5)]
    else:  # W = board frame: the camera looks from z < 0, "up" is -y
        offsets = ([0.2, 0.1, -0.7], [-0.25, 0.05, -0.6])
        views = [look_at(centre + d, centre, up=(0, -1, 0)) for d in offsets]
    for truth in views:
        img = cv2.cvtColor(renderer.render(truth), cv2.COLOR_BGR2GRAY)
        pose, why = poser.pose(img)
        assert pose is not None, why
        assert pose.distance_to(truth) < tol_m and pose.angle_to(truth) < tol_deg, why


def test_poser_says_why_without_a_board():
    poser = BoardPoser(GROUND_BOARD, default_camera())
    pose, why = poser.pose(np.full((480, 640), 128, np.uint8))
    assert pose is None and why.startswith("board not found")
