"""Training on the device at hand: ``--device`` is resolved (a GPU that is not there is refused),
checkpoints hold only CPU tensors and the random generators' states, so a run interrupted on
one device resumes on another (here: saved under ``cpu``, resumed under ``auto``, which is the
GPU on a machine that has one) exactly where the uninterrupted run would be, and each leg is
recorded with where and how long it trained."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="training needs torch (train extra)")

from training.data import Geometry, RenderedSet, SetSpec  # noqa: E402
from training.nets import KeypointNet  # noqa: E402
from training.train import (  # noqa: E402
    TrainConfig,
    TrainingError,
    resolve_device,
    run_training,
)

GEOM = Geometry(det_w=32, det_h=32, crop_w=64, crop_h=96)
K = 4


def _data(n: int = 24) -> RenderedSet:
    """A small keypoint set: textured crops with a bright square at each labelled keypoint."""
    rng = np.random.default_rng(3)
    crops = rng.integers(0, 60, (n, GEOM.crop_h, GEOM.crop_w, 3)).astype(np.uint8)
    kp = np.stack([rng.uniform(4, GEOM.crop_w - 5, (n, K)),
                   rng.uniform(4, GEOM.crop_h - 5, (n, K))], -1).astype(np.float32)
    for i in range(n):
        for u, v in kp[i].astype(int):
            crops[i, v - 1:v + 2, u - 1:u + 2] = 255
    return RenderedSet(
        det_images=np.zeros((n, GEOM.det_h, GEOM.det_w, 3), np.uint8),
        boxes=np.zeros((n, 4)), frame_size=np.full((n, 2), 64, np.int32),
        crops=crops, crop_kp=kp, crop_in_image=np.ones((n, K), bool),
        crop_visible=np.ones((n, K), bool), crop_scale=np.ones(n, np.float32),
        crop_view=np.arange(n), seg_labels=np.zeros((n, 0, 0), np.uint8))


def _cfg(steps: int, device: str, leg_steps: int | None = None) -> TrainConfig:
    return TrainConfig("keypoints", (SetSpec("randomized", 1, 1),),
                       (SetSpec("randomized", 1001, 1),), GEOM, steps=steps, batch=4,
                       threads=1, device=device, checkpoint_every=1000, leg_steps=leg_steps)


def _train(folder: Path, steps: int, device: str, leg_steps: int | None = None
           ) -> tuple[KeypointNet, dict]:
    folder.mkdir(exist_ok=True)
    torch.manual_seed(0)
    model = KeypointNet(K, GEOM.crop_w, GEOM.crop_h, hidden=32)
    state = run_training(_cfg(steps, device, leg_steps), model, _data(), folder / "keypoints.ckpt",
                         say=lambda line: None)
    return model, state


def test_device_names_are_resolved_and_a_missing_gpu_is_refused() -> None:
    assert resolve_device("cpu").type == "cpu"
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(TrainingError, match="device 'tpu'"):
        resolve_device("tpu")
    with pytest.raises(TrainingError, match="expected auto, cpu or cuda"):
        _cfg(1, "mps")
    if not torch.cuda.is_available():
        with pytest.raises(TrainingError, match="no CUDA GPU"):
            resolve_device("cuda")


def test_checkpoint_saved_on_one_device_resumes_on_another(tmp_path: Path) -> None:
    """6 steps in one go == a 3-step leg under ``cpu`` + 3 more resumed under ``auto`` (the random
    streams continue from the checkpoint, so the batches and augmentations are the same); the
    checkpoint holds CPU tensors only and the record lists both legs with their device."""
    whole, _ = _train(tmp_path / "whole", 6, "cpu")
    _train(tmp_path / "split", 6, "cpu", leg_steps=3)
    saved = torch.load(tmp_path / "split" / "keypoints.ckpt", map_location="cpu",
                       weights_only=False)
    tensors = [v for v in saved["model"].values()]
    tensors += [t for s in saved["opt"]["state"].values() for t in s.values()
                if isinstance(t, torch.Tensor)]
    assert tensors and all(t.device.type == "cpu" for t in tensors)
    assert saved["rng"] is not None and saved["state"]["step"] == 3
    resumed, state = _train(tmp_path / "split", 6, "auto")
    assert state["step"] == 6
    want = {k: v.float() for k, v in whole.state_dict().items()}
    got = {k: v.detach().cpu().float() for k, v in resumed.state_dict().items()}
    # on a GPU the resumed leg runs in bf16: same trajectory, not the same bits
    tol = 0.05 if torch.cuda.is_available() else 1e-5
    for name, w in want.items():
        np.testing.assert_allclose(got[name].numpy(), w.numpy(), atol=tol, rtol=tol,
                                   err_msg=name)
    legs = state["phases"]
    assert [leg["steps"] for leg in legs] == [[0, 3], [3, 6]]
    assert legs[0]["device"] == "cpu" and legs[0]["where"].startswith("cpu (")
    assert legs[1]["device"] == resolve_device("auto").type
    assert all(leg["wall_s"] >= 0 for leg in legs)
    assert len(state["history"]) == 2 and "cpu (" in state["history"][0]


def test_resumed_run_differs_when_the_random_streams_are_not_restored(tmp_path: Path) -> None:
    """The equality above is not vacuous: a resume whose checkpoint lost its generator states
    (an older checkpoint) draws other batches and ends elsewhere."""
    whole, _ = _train(tmp_path / "whole", 6, "cpu")
    _train(tmp_path / "split", 6, "cpu", leg_steps=3)
    path = tmp_path / "split" / "keypoints.ckpt"
    saved = torch.load(path, map_location="cpu", weights_only=False)
    saved["rng"] = None
    torch.save(saved, path)
    resumed, _ = _train(tmp_path / "split", 6, "cpu")
    diff = max(float((a - b).abs().max()) for a, b in
               zip(whole.state_dict().values(), resumed.state_dict().values(), strict=True)
               if a.dtype.is_floating_point)
    assert diff > 1e-4


def test_mirrored_crops_carry_their_labels() -> None:
    """A crop with a bright dot at each keypoint, mirrored: every keypoint label lands on a
    dot again, each keypoint on its partner's dot, mirrored; unflipped rows are untouched."""
    from training.targets import mirror_crops

    data = _data(4)
    x = torch.from_numpy(data.crops).permute(0, 3, 1, 2).float()
    perm = np.array([0, 3, 2, 1])  # 1 <-> 3 are a left/right pair
    wgt = np.tile(np.array([1.0, 1.0, 0.0, 1.0], np.float32), (4, 1))
    flip = np.array([True, False, True, False])
    xm, kp, wm = mirror_crops(x, data.crop_kp.copy(), wgt, flip, perm)
    for i in range(4):
        for j in range(K):
            u, v = np.rint(kp[i, j]).astype(int)
            assert xm[i, 0, v, u] == 255, (i, j)
    np.testing.assert_array_equal(xm[1], x[1])
    np.testing.assert_allclose(kp[1], data.crop_kp[1])
    np.testing.assert_allclose(kp[0, 1, 0], GEOM.crop_w - 1 - data.crop_kp[0, 3, 0])
    assert wm[0, 2] == 0 and wm[0, 1] == wgt[0, 3]


def test_tiny_mirror_run_asks_for_the_flip_in_its_card(tmp_path: Path) -> None:
    """``smartedge train keypoints --mirror`` (tiny) writes a card that asks the edge for the
    test-time flip and records the mirrored training and the leg's device."""
    pytest.importorskip("moderngl", reason="rendering the training views needs moderngl")
    from edge_agent.model_cards import KeypointCard
    from smartedge.cli import main
    from tests.edge_agent.conftest import TINY_ARGS

    assert main(["train", "keypoints", "--out", str(tmp_path), *TINY_ARGS, "--mirror",
                 "--device", "cpu"]) == 0
    card = KeypointCard.read(tmp_path / "keypoints.json")
    assert card.flip_tta is True and card.training["mirror_augmentation"] is True
    assert card.training["device"] == "cpu"
    assert card.training["phases"][0]["where"].startswith("cpu (")
    assert "Test-time flip" in (tmp_path / "keypoints.md").read_text()


def test_a_finished_run_keeps_the_weights_its_selection_scored_best(tmp_path: Path) -> None:
    """``select`` scores every checkpoint (here: 3, 1, 2 at steps 2, 4, 6): the finished run
    keeps step 4's weights, says so in its history, and its checkpoint resumes with them."""
    scores = iter([3.0, 1.0, 2.0])
    weights: dict[int, dict] = {}
    model = KeypointNet(K, GEOM.crop_w, GEOM.crop_h, hidden=32)

    def select(m: torch.nn.Module) -> float:
        step = 2 * (len(weights) + 1)
        weights[step] = {k: v.detach().clone() for k, v in m.state_dict().items()}
        return next(scores)

    cfg = dataclasses.replace(_cfg(6, "cpu"), checkpoint_every=2)
    torch.manual_seed(0)
    state = run_training(cfg, model, _data(), tmp_path / "keypoints.ckpt", say=lambda line: None,
                         select=select)
    assert state["best"] == {"step": 4, "score": 1.0} and "best_weights" not in state
    assert any("kept the weights of step 4" in line for line in state["history"])
    for name, tensor in model.state_dict().items():
        assert torch.equal(tensor, weights[4][name]), name
    assert not all(torch.equal(model.state_dict()[n], weights[6][n]) for n in weights[6])
