"""Test-time flip augmentation of the keypoint network: the left/right partner of every keypoint
is found by name, and with flip on, a mirrored render gives the mirrored keypoints (each
left keypoint where its right partner was, mirrored), which fails if the swap were wrong."""

from __future__ import annotations

import numpy as np
import pytest

from edge_agent.models import KeypointEstimator, ModelError, default_model_dir, mirror_permutation


def test_mirror_permutation_pairs_left_and_right() -> None:
    names = ["front_top", "front_left_top", "left_top", "right_top", "front_right_top"]
    perm = mirror_permutation(names)
    assert [names[i] for i in perm] == ["front_top", "front_right_top", "right_top",
                                        "left_top", "front_left_top"]
    np.testing.assert_array_equal(perm[perm], np.arange(len(names)))  # an involution
    with pytest.raises(ModelError, match="no mirror partner 'right_top'"):
        mirror_permutation(["front_top", "left_top"])
    # "leftover" is not a side: only whole words count
    np.testing.assert_array_equal(mirror_permutation(["leftover", "rightmost"]), [0, 1])


def _mirror(kp: np.ndarray, width: int, perm: np.ndarray) -> np.ndarray:
    """Keypoints (n, K, 2) of a frame → those of its mirror image."""
    out = kp[:, perm].copy()
    out[..., 0] = width - 1 - out[..., 0]
    return out


@pytest.fixture(scope="module")
def site_view():  # type: ignore[no-untyped-def]
    pytest.importorskip("moderngl", reason="rendering needs moderngl")
    from simulation.dataset import SampleGenerator
    from simulation.scenario import load_scenario

    gen = SampleGenerator(load_scenario(), "site", seed=5)
    for i in range(20):
        s = gen(i)
        box = s.robots[0].bbox_xyxy if s.robots else None
        if box is not None and (box[2] - box[0]) > 60 and s.robots[0].in_image.all():
            return s
    pytest.fail("no site view with the whole robot in 20 renders")


def test_mirrored_render_gives_mirrored_keypoints_with_flip(site_view) -> None:  # type: ignore[no-untyped-def]
    image = site_view.image_rgb
    w = image.shape[1]
    box = np.asarray(site_view.robots[0].bbox_xyxy, np.float64)
    box_m = np.array([w - 1 - box[2], box[1], w - 1 - box[0], box[3]])
    mirrored = np.ascontiguousarray(image[:, ::-1])
    path = default_model_dir() / "keypoints.onnx"
    tta = KeypointEstimator(path, threads=1, flip=True)
    perm = mirror_permutation(tta.card.keypoint_names)
    kp, conf = tta.estimate(image, box[None])
    kp_m, conf_m = tta.estimate(mirrored, box_m[None])
    np.testing.assert_allclose(kp_m, _mirror(kp, w, perm), atol=0.02)
    np.testing.assert_allclose(conf_m, conf[:, perm], atol=1e-4)
    # the keypoints are near the truth, so the check above is about real keypoints
    true = np.asarray(site_view.robots[0].keypoints_px)
    assert np.median(np.linalg.norm(kp[0] - true, axis=1)) < 3.0
    # without the left/right swap the mirrored estimate is far off: the swap is what is tested
    wrong = kp.copy()
    wrong[..., 0] = w - 1 - wrong[..., 0]
    assert np.max(np.linalg.norm(kp_m - wrong, axis=-1)) > 5.0
    # without the flip the network is not mirror-consistent by itself (the robot is not
    # left/right symmetric)
    plain = KeypointEstimator(path, threads=1, flip=False)
    p, _ = plain.estimate(image, box[None])
    p_m, _ = plain.estimate(mirrored, box_m[None])
    assert np.max(np.linalg.norm(p_m - _mirror(p, w, perm), axis=-1)) > 0.05


def test_the_card_decides_the_default(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """The estimator flips when its card says the model was trained for it (the shipped one),
    not otherwise; a card written before the field existed reads as no flip."""
    import json
    import shutil

    shipped = default_model_dir()
    assert KeypointEstimator(shipped / "keypoints.onnx", threads=1).flip is True
    for f in ("keypoints.onnx", "keypoints.json"):
        shutil.copy(shipped / f, tmp_path / f)
    doc = json.loads((tmp_path / "keypoints.json").read_text())
    doc.pop("flip_tta")
    (tmp_path / "keypoints.json").write_text(json.dumps(doc))
    old = KeypointEstimator(tmp_path / "keypoints.onnx", threads=1)
    assert old.flip is False and old.card.flip_tta is False
    assert KeypointEstimator(tmp_path / "keypoints.onnx", threads=1, flip=True).flip is True
