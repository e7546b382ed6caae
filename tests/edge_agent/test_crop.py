"""Image geometry shared by training and inference: the crop transform is invertible, its
window has the network's aspect ratio and holds the padded box, the crop puts each image pixel
where ``to_crop`` says, the training jitter moves/zooms the window as documented, and the
detector resize and NCHW conversion give what the networks expect."""

from __future__ import annotations

import numpy as np
import pytest

from edge_agent.crop import (
    CROP_PADDING,
    CropTransform,
    crop_box,
    crop_transform,
    extract_crop,
    resize_for_detector,
    to_nchw,
)

CROP_W, CROP_H = 64, 96

#: (x0, y0, x1, y1) box edges: tall, wide, tiny, partly outside a 640x480 image
BOXES = (
    np.array([300.0, 100.0, 360.0, 330.0]),
    np.array([100.5, 200.25, 420.0, 260.0]),
    np.array([50.0, 50.0, 50.5, 50.5]),
    np.array([-40.0, 380.0, 90.0, 520.0]),
)


def _window(tf: CropTransform, crop_w: int = CROP_W, crop_h: int = CROP_H) -> np.ndarray:
    """The crop's window in image coordinates: (x0, y0, x1, y1) of its outer pixel edges."""
    lo = tf.to_image(np.array([-0.5, -0.5]))
    hi = tf.to_image(np.array([crop_w - 0.5, crop_h - 0.5]))
    return np.concatenate([lo, hi])


def _blob_image(centre: tuple[float, float], sigma: float, w: int = 640, h: int = 480
                ) -> np.ndarray:
    """Black RGB image with a bright Gaussian blob at the sub-pixel ``centre`` (OpenCV pixel
    centres) in the green channel only."""
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    g = np.exp(-((u - centre[0]) ** 2 + (v - centre[1]) ** 2) / (2 * sigma ** 2))
    image = np.zeros((h, w, 3), np.uint8)
    image[..., 1] = np.round(255 * g).astype(np.uint8)
    return image


def _centroid(channel: np.ndarray) -> np.ndarray:
    """Intensity-weighted (x, y) centroid of a 2-D array."""
    v, u = np.indices(channel.shape)
    m = channel.astype(np.float64)
    return np.array([(m * u).sum(), (m * v).sum()]) / m.sum()


@pytest.mark.parametrize("box", BOXES)
@pytest.mark.parametrize("jitter", [{}, {"shift": (0.07, -0.05), "zoom": 1.2},
                                    {"zoom": 0.85}])
def test_to_crop_and_to_image_are_inverse(box: np.ndarray, jitter: dict) -> None:
    """Image → crop → image (and crop → image → crop) returns the points, for any batch shape;
    the (2, 3) matrix for ``cv2.warpAffine`` is the same map as ``to_crop``."""
    tf = crop_transform(box, CROP_W, CROP_H, **jitter)
    rng = np.random.default_rng(0)
    pts = rng.uniform(-100, 700, (5, 3, 2))
    np.testing.assert_allclose(tf.to_image(tf.to_crop(pts)), pts, atol=1e-9)
    np.testing.assert_allclose(tf.to_crop(tf.to_image(pts)), pts, atol=1e-9)
    homog = np.concatenate([pts.reshape(-1, 2), np.ones((15, 1))], axis=1)
    np.testing.assert_allclose(homog @ tf.matrix().T, tf.to_crop(pts).reshape(-1, 2), atol=1e-9)


@pytest.mark.parametrize("box", BOXES)
def test_window_has_the_crop_aspect_and_holds_the_padded_box(box: np.ndarray) -> None:
    """The window is centred on the box, has the crop's aspect ratio, contains the box enlarged
    by ``CROP_PADDING`` and is tight along the box's limiting side; the box centre lands on the
    crop's centre pixel position."""
    tf = crop_transform(box, CROP_W, CROP_H)
    x0, y0, x1, y1 = _window(tf)
    ww, wh = x1 - x0, y1 - y0
    assert ww / wh == pytest.approx(CROP_W / CROP_H)
    assert wh == pytest.approx(CROP_H / tf.scale)
    centre = np.array([(box[0] + box[2]) / 2, (box[1] + box[3]) / 2])
    np.testing.assert_allclose([(x0 + x1) / 2, (y0 + y1) / 2], centre, atol=1e-9)
    np.testing.assert_allclose(tf.to_crop(centre), [(CROP_W - 1) / 2, (CROP_H - 1) / 2],
                               atol=1e-9)
    bw, bh = max(box[2] - box[0], 1.0), max(box[3] - box[1], 1.0)
    pw, ph = bw * CROP_PADDING, bh * CROP_PADDING
    assert ww >= pw - 1e-9 and wh >= ph - 1e-9
    assert ww == pytest.approx(pw) or wh == pytest.approx(ph)  # tight along one side
    # crop_box gives the same window as a centre and height
    c, height = crop_box(box, CROP_W, CROP_H)
    np.testing.assert_allclose(c, centre, atol=1e-9)
    assert height == pytest.approx(wh)


def test_padding_argument_scales_the_window() -> None:
    """``padding=1`` gives the plain aspect-corrected box; the default pads by CROP_PADDING."""
    box = BOXES[0]
    plain = _window(crop_transform(box, CROP_W, CROP_H, padding=1.0))
    padded = _window(crop_transform(box, CROP_W, CROP_H))
    assert plain[3] - plain[1] == pytest.approx(box[3] - box[1])  # tall box: height limits
    assert (padded[3] - padded[1]) / (plain[3] - plain[1]) == pytest.approx(CROP_PADDING)


def test_jitter_shift_moves_and_zoom_enlarges_the_window() -> None:
    """``shift`` moves the window centre by that fraction of the window's width/height;
    ``zoom`` > 1 enlarges the window about the same centre (a smaller scale)."""
    box = BOXES[1]
    base = crop_transform(box, CROP_W, CROP_H)
    bx0, by0, bx1, by1 = _window(base)
    bw, bh = bx1 - bx0, by1 - by0
    shifted = crop_transform(box, CROP_W, CROP_H, shift=(0.1, -0.05))
    sx0, sy0, sx1, sy1 = _window(shifted)
    assert shifted.scale == pytest.approx(base.scale)
    assert (sx0 + sx1) / 2 - (bx0 + bx1) / 2 == pytest.approx(0.1 * bw)
    assert (sy0 + sy1) / 2 - (by0 + by1) / 2 == pytest.approx(-0.05 * bh)
    zoomed = crop_transform(box, CROP_W, CROP_H, zoom=1.5)
    zx0, zy0, zx1, zy1 = _window(zoomed)
    assert zoomed.scale == pytest.approx(base.scale / 1.5)
    assert zy1 - zy0 == pytest.approx(1.5 * bh)
    np.testing.assert_allclose([(zx0 + zx1) / 2, (zy0 + zy1) / 2],
                               [(bx0 + bx1) / 2, (by0 + by1) / 2], atol=1e-9)
    shrunk = crop_transform(box, CROP_W, CROP_H, zoom=0.8)
    assert shrunk.scale == pytest.approx(base.scale / 0.8)


@pytest.mark.parametrize(("box", "what"), [
    (np.array([310.0, 200.0, 326.0, 224.0]), "enlarging"),  # ~3.2 crop px per image px
    (np.array([250.0, 100.0, 380.0, 330.0]), "shrinking"),  # ~0.33 crop px per image px
])
def test_extract_crop_puts_image_pixels_where_to_crop_says(box: np.ndarray, what: str) -> None:
    """A bright blob at a sub-pixel image position appears in the crop at ``to_crop`` of that
    position (centroid within 0.15 crop px), whether the crop enlarges or shrinks."""
    centre = (318.3, 211.7) if what == "enlarging" else (301.6, 240.2)
    image = _blob_image(centre, sigma=1.5 if what == "enlarging" else 4.0)
    tf = crop_transform(box, CROP_W, CROP_H)
    assert (tf.scale > 1.0) == (what == "enlarging")
    crop = extract_crop(image, tf, CROP_W, CROP_H)
    assert crop.shape == (CROP_H, CROP_W, 3) and crop.dtype == np.uint8
    assert not crop[..., 0].any() and not crop[..., 2].any()  # channels stay where they were
    expected = tf.to_crop(np.array(centre))
    np.testing.assert_allclose(_centroid(crop[..., 1]), expected, atol=0.15)
    peak = np.unravel_index(np.argmax(crop[..., 1]), crop.shape[:2])[::-1]
    assert np.all(np.abs(np.array(peak) - expected) <= 1.0)


def test_extract_crop_single_pixel_at_unit_scale() -> None:
    """At one crop pixel per image pixel with an integer origin, one bright image pixel lands
    exactly on the crop pixel ``to_crop`` names, and nothing else lights up."""
    tf = CropTransform(np.array([200.0, 150.0]), 1.0)
    image = np.zeros((480, 640, 3), np.uint8)
    image[171, 233] = (255, 128, 7)
    crop = extract_crop(image, tf, CROP_W, CROP_H)
    u, v = tf.to_crop(np.array([233.0, 171.0]))
    assert (u, v) == (33.0, 21.0)
    assert tuple(crop[21, 33]) == (255, 128, 7)
    assert np.count_nonzero(crop.any(axis=2)) == 1


def test_extract_crop_outside_the_image_is_black() -> None:
    """The part of the window beyond the image border is black; inside it is the image."""
    image = np.full((480, 640, 3), 200, np.uint8)
    tf = crop_transform(BOXES[3], CROP_W, CROP_H)  # the window sticks out left and bottom
    crop = extract_crop(image, tf, CROP_W, CROP_H)
    left_edge = tf.to_crop(np.array([-0.5, 0.0]))[0]
    bottom_edge = tf.to_crop(np.array([0.0, 479.5]))[1]
    assert 2 < left_edge < CROP_W - 2 and 2 < bottom_edge < CROP_H - 2
    assert not crop[:, : int(np.floor(left_edge)) - 1].any()
    assert not crop[int(np.ceil(bottom_edge)) + 1:].any()
    inner = crop[: int(bottom_edge) - 1, int(np.ceil(left_edge)) + 1:]
    assert inner.size and np.all(inner == 200)


def test_resize_for_detector_sizes() -> None:
    """Any frame comes back at the detector's input size as uint8 RGB; a frame already that
    size is returned unchanged; a uniform frame stays uniform when shrunk or enlarged."""
    frame = np.full((480, 848, 3), (10, 120, 250), np.uint8)
    small = resize_for_detector(frame, 424, 240)
    assert small.shape == (240, 424, 3) and small.dtype == np.uint8
    assert np.all(small == (10, 120, 250))
    big = resize_for_detector(frame[:96, :128], 256, 192)
    assert big.shape == (192, 256, 3) and np.all(big == (10, 120, 250))
    odd = resize_for_detector(frame, 128, 96)  # different aspect ratio: stretched, not padded
    assert odd.shape == (96, 128, 3)
    same = frame[:96, :128]
    assert resize_for_detector(same, 128, 96) is same


def test_resize_for_detector_keeps_positions() -> None:
    """A blob in the frame lands at the position the edge convention predicts:
    ``(x + 0.5) * input_w / frame_w - 0.5`` (the inverse of the detector's box scaling)."""
    image = _blob_image((500.3, 300.7), sigma=6.0)
    small = resize_for_detector(image, 320, 240)
    expected = (np.array([500.3, 300.7]) + 0.5) * 0.5 - 0.5
    np.testing.assert_allclose(_centroid(small[..., 1]), expected, atol=0.1)


def test_to_nchw_shape_dtype_and_range() -> None:
    """One image or a batch → (N, 3, H, W) float32 contiguous in [0, 1]: 0 → 0, 255 → 1,
    channel order and pixel positions kept."""
    image = np.zeros((5, 7, 3), np.uint8)
    image[1, 2] = (255, 0, 51)
    x = to_nchw(image)
    assert x.shape == (1, 3, 5, 7) and x.dtype == np.float32 and x.flags.c_contiguous
    assert x[0, 0, 1, 2] == 1.0 and x[0, 1, 1, 2] == 0.0
    assert x[0, 2, 1, 2] == pytest.approx(0.2)
    assert x.min() == 0.0 and x.max() == 1.0
    batch = np.random.default_rng(1).integers(0, 256, (4, 6, 8, 3), dtype=np.uint8)
    xb = to_nchw(batch)
    assert xb.shape == (4, 3, 6, 8) and xb.dtype == np.float32
    assert xb.min() >= 0.0 and xb.max() <= 1.0
    np.testing.assert_allclose(xb * 255, batch.transpose(0, 3, 1, 2), atol=1e-4)
    full = to_nchw(np.full((2, 2, 3), 255, np.uint8))
    assert np.all(full <= 1.0) and np.all(full == 1.0)


def test_training_crops_use_the_deployed_crop() -> None:
    """A rendered view's training rows (no jitter) hold exactly the crop the edge pipeline cuts
    for the labelled box, and keypoint labels at ``to_crop`` of the frame keypoints."""
    pytest.importorskip("moderngl", reason="rendering needs moderngl")
    from simulation.dataset import SampleGenerator
    from simulation.scenario import load_scenario
    from training.data import Geometry, view_records

    gen = SampleGenerator(load_scenario(), "randomized", seed=11, width=256, height=192)
    geometry = Geometry(det_w=128, det_h=96, crop_w=CROP_W, crop_h=CROP_H, crop_jitter=False)
    for i in range(6):
        sample = gen(i)
        robot = sample.robots[0]
        box = robot.bbox_xyxy
        if box is None or (box[2] - box[0]) * (box[3] - box[1]) < 64:
            continue
        rows = view_records(sample, geometry, np.random.default_rng(0))
        assert len(rows.crops) == 1
        tf = crop_transform(box, CROP_W, CROP_H, padding=CROP_PADDING)
        np.testing.assert_array_equal(rows.crops[0],
                                      extract_crop(sample.image_rgb, tf, CROP_W, CROP_H))
        np.testing.assert_allclose(rows.crop_kp[0], tf.to_crop(robot.keypoints_px), atol=1e-3)
        assert rows.crop_scale[0] == pytest.approx(tf.scale)
        np.testing.assert_array_equal(rows.det_images[0],
                                      resize_for_detector(sample.image_rgb, 128, 96))
        return
    pytest.fail("no view with a visible robot among the first 6 randomized views")
