"""The ChArUco board: spec checks and its file, the printed image's geometry, detection on the
flat print (exact corner pixels known) and the reasons a view is refused."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from calibration.board import (
    BoardDetector,
    BoardSpecError,
    CharucoBoardSpec,
    board_image,
    draw_detection,
    load_board_spec,
)

SPEC = CharucoBoardSpec(9, 7, 0.06, 0.045, "DICT_5X5_100")


def test_spec_checks_name_what_is_wrong() -> None:
    with pytest.raises(ValueError, match="marker_length_m"):
        CharucoBoardSpec(7, 5, 0.04, 0.04)
    with pytest.raises(ValueError, match="unknown ArUco dictionary 'DICT_9X9'"):
        CharucoBoardSpec(7, 5, 0.04, 0.03, "DICT_9X9")
    with pytest.raises(ValueError, match="a 16x14 board needs 112 markers; DICT_4X4_50 has 50"):
        CharucoBoardSpec(16, 14, 0.04, 0.03, "DICT_4X4_50")
    with pytest.raises(ValueError, match="squares_x"):
        CharucoBoardSpec(2, 5, 0.04, 0.03)


def test_spec_file_round_trip_and_errors_name_the_key(tmp_path) -> None:
    path = SPEC.write(tmp_path / "board.yaml")
    assert load_board_spec(path) == SPEC
    path.write_text("charuco_board: {squares: [9, 7], square_length_m: 0.06, "
                    "marker_length_m: 0.07, dictionary: DICT_5X5_100}\n")
    with pytest.raises(BoardSpecError, match=r"board\.yaml: charuco_board\.marker_length_m"):
        load_board_spec(path)
    path.write_text("charuco_board: {squares: [9], square_length_m: 0.06, "
                    "marker_length_m: 0.04, dictionary: DICT_5X5_100}\n")
    with pytest.raises(BoardSpecError, match=r"charuco_board\.squares: expected"):
        load_board_spec(path)
    path.write_text("charuco_board: {squares: [9, 7], square_length_m: 0.06, "
                    "marker_length_m: 0.04}\n")
    with pytest.raises(BoardSpecError, match=r"charuco_board\.dictionary: required"):
        load_board_spec(path)


def test_detection_on_the_flat_print_is_exact() -> None:
    img = board_image(SPEC, px_per_square=40, margin_squares=0.5)
    assert img.image.shape == (7 * 40 + 40, 9 * 40 + 40)
    det = BoardDetector(SPEC).detect(img.image)
    assert det.usable and det.num_corners == SPEC.num_corners == 48
    # corner i sits on the pixel edge margin + (col + 1) * 40, i.e. at centre coordinate - 0.5
    ids = det.corner_ids
    expected = np.column_stack([20 + (ids % 8 + 1) * 40 - 0.5, 20 + (ids // 8 + 1) * 40 - 0.5])
    np.testing.assert_allclose(det.corners_px, expected, atol=0.05)
    # and the board frame agrees: board metres * px per metre + margin
    board_xy = SPEC.corners_board_m()[ids, :2] * img.px_per_m + img.margin_px - 0.5
    np.testing.assert_allclose(det.corners_px, board_xy, atol=0.05)
    assert img.extent_board_m == pytest.approx((-0.03, -0.03, 0.57, 0.45))


def test_refusals_carry_their_reason() -> None:
    det = BoardDetector(SPEC)
    img = board_image(SPEC, px_per_square=40).image
    blurred = cv2.GaussianBlur(img, (0, 0), 4.0)
    assert "blurred" in (det.detect(blurred).reason or "")
    assert det.detect(np.full((240, 320), 128, np.uint8)).reason == "no board found"
    few = img.copy()
    few[:, 110:] = 255  # only the first two columns of squares left
    reason = det.detect(few).reason or ""
    assert reason.startswith(("too few corners", "corners on one line", "no ChArUco")), reason
    overlay = draw_detection(blurred, det.detect(blurred))
    assert overlay.shape == (*blurred.shape, 3)
