"""Training starts from an exported ONNX model (the shipped ones carry no checkpoint): the loaded
network reproduces the file, its batch norms behave in training mode, keypoints are matched by
name (new ones start from their neighbours), and a file that does not fit is refused by name."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="training needs torch (train extra)")
pytest.importorskip("onnx", reason="reading an ONNX file's weights needs onnx (train extra)")

from edge_agent.flip import mirror_permutation  # noqa: E402
from edge_agent.model_cards import KeypointCard, default_model_dir, reference_path  # noqa: E402
from tests.edge_agent.conftest import TINY_ARGS  # noqa: E402
from training.nets import KeypointNet, RobotDetector  # noqa: E402
from training.onnx_init import (  # noqa: E402
    OnnxInitError,
    init_from_onnx,
    keypoint_map,
)

SHIPPED = default_model_dir()
KP_ONNX = SHIPPED / "keypoints.onnx"
DET_ONNX = SHIPPED / "detector.onnx"
RIM_R, RIM_Z = 0.215, 0.345


def _hsr_keypoints() -> dict[str, tuple[float, float, float]]:
    """The paper site's HSR keypoints (simulation/sites/paper_lab.yaml) and four more top-rim
    points between them (67.5 / 112.5 deg each side)."""
    from simulation.scenario import PAPER_SCENARIO, load_scenario

    scenario = load_scenario(PAPER_SCENARIO)
    model = scenario.site.robot_model(scenario.robot_id)
    xyz = {n: tuple(p) for n, p in zip(model.keypoint_names, model.keypoints_base_m,
                                       strict=True)}
    for name, deg in (("left_fore_top", 67.5), ("left_aft_top", 112.5),
                      ("right_aft_top", 247.5), ("right_fore_top", 292.5)):
        a = math.radians(deg)
        xyz[name] = (RIM_R * math.cos(a), RIM_R * math.sin(a), RIM_Z)
    return xyz


def _inputs(path: Path) -> tuple[torch.Tensor, dict[str, np.ndarray]]:
    ref = dict(np.load(reference_path(path)))
    x = torch.from_numpy(ref["inputs"]).permute(0, 3, 1, 2).float() / 255.0
    return x, ref


def test_the_shipped_keypoint_network_loads_and_reproduces_its_reference() -> None:
    """Same keypoints: every output equals the file's reference outputs; in training mode the
    unfolded batch norms give (on the calibration batch) what evaluation mode gives."""
    x, ref = _inputs(KP_ONNX)
    names = list(KeypointCard.read(SHIPPED / "keypoints.json").keypoint_names)
    xyz = _hsr_keypoints()
    net = KeypointNet(len(names))
    info = init_from_onnx(net, KP_ONNX, x, keypoint_names=names,
                          keypoints_base_m=np.array([xyz[n] for n in names]))
    assert info.kept_keypoints == tuple(names) and not info.added_keypoints
    assert info.unfolded_norms > 20 and info.max_rel_diff < 1e-4
    net.eval()
    with torch.no_grad():
        kp, conf = net(x)
    assert np.abs(kp.numpy() - ref["keypoints"]).max() < 1e-2  # crop pixels
    assert np.abs(conf.numpy() - ref["confidence"]).max() < 1e-4
    net.train()
    with torch.no_grad():
        kp_train, _ = net(x)
    assert np.abs(kp_train.numpy() - kp.numpy()).max() < 1e-2


def test_new_keypoints_start_from_their_two_nearest_neighbours() -> None:
    """A 16-keypoint network from the 12-keypoint file: the 12 keep their outputs exactly, each
    new rim point starts from the two rim keypoints beside it, the left/right pairs mirror."""
    x, ref = _inputs(KP_ONNX)
    xyz = _hsr_keypoints()
    names = list(xyz)
    assert len(names) == 16
    mirror_permutation(names)  # the new points are left/right pairs
    net = KeypointNet(len(names))
    info = init_from_onnx(net, KP_ONNX, x, keypoint_names=names,
                          keypoints_base_m=np.array([xyz[n] for n in names]))
    added = dict(info.added_keypoints)
    assert set(added) == {"left_fore_top", "left_aft_top", "right_aft_top", "right_fore_top"}
    assert set(added["left_fore_top"]) == {"front_left_top", "left_top"}
    assert set(added["right_aft_top"]) == {"rear_right_top", "right_top"}
    net.eval()
    with torch.no_grad():
        kp, conf = net(x)
    assert np.abs(kp[:, :12].numpy() - ref["keypoints"]).max() < 1e-2
    assert np.abs(conf[:, :12].numpy() - ref["confidence"]).max() < 1e-4
    assert np.isfinite(kp.numpy()).all()


def test_keypoint_map_by_name() -> None:
    xyz = np.array([[0, 0, 0], [1, 0, 0], [0.9, 0.1, 0], [3, 0, 0]], dtype=float)
    m = keypoint_map(["a", "b", "c", "gone"], ["c", "a", "new", "b"], xyz[[0, 1, 2, 3]])
    # new (0.9, 0.1, 0) is nearest to a (1, 0, 0), then c (0, 0, 0); b (3, 0, 0) is farther
    assert m.rows[0] == [2] and m.rows[1] == [0] and m.rows[3] == [1]
    assert m.added == (("new", ("a", "c")),) and sorted(m.rows[2]) == [0, 2]
    assert m.dropped == ("gone",)
    with pytest.raises(OnnxInitError, match="fewer than two names"):
        keypoint_map(["a", "b"], ["a", "x"], np.zeros((2, 3)))


def test_the_shipped_detector_loads_at_its_size_and_at_another() -> None:
    x, ref = _inputs(DET_ONNX)
    det = RobotDetector()
    info = init_from_onnx(det, DET_ONNX, x)
    assert info.max_rel_diff < 1e-4 and info.linears == 0
    det.eval()
    with torch.no_grad():
        _peaks, size, off = det(x)
    assert np.abs(size.numpy() - ref["size"]).max() < 1e-3
    assert np.abs(off.numpy() - ref["offset"]).max() < 1e-3
    # fully convolutional: the same file starts a 640x360 detector (checked against onnxruntime
    # at that size inside init_from_onnx)
    wide = torch.nn.functional.interpolate(x, size=(360, 640), mode="bilinear")
    assert init_from_onnx(RobotDetector(), DET_ONNX, wide).max_rel_diff < 1e-4


def test_a_file_that_does_not_fit_is_refused_by_name(tmp_path: Path) -> None:
    x, _ = _inputs(KP_ONNX)
    names = list(KeypointCard.read(SHIPPED / "keypoints.json").keypoint_names)
    xyz = np.array([_hsr_keypoints()[n] for n in names])
    with pytest.raises(OnnxInitError, match=r"detector.onnx: keypoint models are matched by "
                       r"keypoint name.*not a keypoints model card"):
        init_from_onnx(KeypointNet(12), DET_ONNX, x, keypoint_names=names, keypoints_base_m=xyz)
    with pytest.raises(OnnxInitError, match=r"keypoints.onnx: 54 convolution / linear layers in "
                       r"the file, 65 in the network: another architecture"):
        init_from_onnx(RobotDetector(), KP_ONNX, torch.rand(2, 3, 96, 128))
    with pytest.raises(OnnxInitError, match="not found"):
        init_from_onnx(KeypointNet(12), tmp_path / "none.onnx", x, keypoint_names=names,
                       keypoints_base_m=xyz)
    lonely = tmp_path / "keypoints.onnx"
    shutil.copy(KP_ONNX, lonely)  # without its card: no keypoint names to match
    with pytest.raises(OnnxInitError, match=r"matched by keypoint name.*card not found"):
        init_from_onnx(KeypointNet(12), lonely, x, keypoint_names=names, keypoints_base_m=xyz)
    (tmp_path / "junk.onnx").write_bytes(b"not a model")
    with pytest.raises(OnnxInitError, match=r"junk.onnx: not a readable ONNX file"):
        init_from_onnx(RobotDetector(), tmp_path / "junk.onnx", x)
    # another crop size: the keypoint head's linear layer does not fit
    small = torch.nn.functional.interpolate(x, size=(128, 96), mode="bilinear")
    with pytest.raises(OnnxInitError, match=r"mlp.0.weight.*another architecture or size"):
        init_from_onnx(KeypointNet(12, input_w=96, input_h=128), KP_ONNX, small,
                       keypoint_names=names, keypoints_base_m=xyz)


def test_smartedge_train_starts_from_an_onnx_file(tiny_models: Path, tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    """`smartedge train keypoints --init-from keypoints.onnx`: the run says what it loaded,
    and the new card's history carries the file's card's history, then the start from it."""
    from smartedge.cli import main

    out, bad = tmp_path / "from_onnx", tmp_path / "bad"
    for folder in (out, bad):  # the tiny run's renders: these runs render nothing
        shutil.copytree(tiny_models / "cache", folder / "cache")
    code = main(["train", "keypoints", "--out", str(out), *TINY_ARGS,
                 "--init-from", str(tiny_models / "keypoints.onnx")])
    assert code == 0
    said = capsys.readouterr().out
    assert "initialized from keypoints.onnx" in said and "batch norms unfolded" in said
    before = json.loads((tiny_models / "keypoints.json").read_text())["training"]["history"]
    history = KeypointCard.read(out / "keypoints.json").training["history"]
    assert history[:len(before)] == before
    assert any(line.startswith("fine-tuned from the exported keypoints.onnx") for line in history)
    # a detector file given to the keypoint network is refused with the file's name
    code = main(["train", "keypoints", "--out", str(bad), *TINY_ARGS,
                 "--init-from", str(tiny_models / "detector.onnx")])
    assert code == 1
    assert "detector.onnx" in capsys.readouterr().err
