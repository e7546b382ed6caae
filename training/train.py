"""Train, validate and export the detector, the keypoint network and the segmentation network.

``smartedge train detector|keypoints|segmentation`` runs :func:`train`: render (or reuse) the
training and held-out sets, train with checkpoints (an interrupted run resumes), validate on the
held-out sets, export one self-contained ONNX file, check onnxruntime against torch, write the
model card (``<kind>.json`` read by the edge pipeline, ``<kind>.md`` for people).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import platform
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from edge_agent.flip import mirror_permutation
from edge_agent.metrics import (
    confusion_matrix,
    detection_ap,
    keypoint_metrics,
    segmentation_metrics,
)
from edge_agent.model_cards import (
    CARD_VERSION,
    KINDS,
    DetectorCard,
    KeypointCard,
    SegmentationCard,
    card_machine,
    card_path,
    export_differences,
    reference_path,
    usable_cores,
)
from edge_agent.networks import decode_detections
from protocol.errors import SmartedgeError
from protocol.semantic_classes import NUM_SEMANTIC_CLASSES, SEMANTIC_CLASSES
from training.data import Geometry, RenderedSet, SetSpec, ViewSource, real_set, render_set
from training.nets import PEAK_TIE, KeypointNet, RobotDetector, SemanticSegNet
from training.onnx_init import OnnxInitError, init_from_onnx
from training.targets import (
    class_weights,
    detector_targets,
    focal_loss,
    frame_to_input,
    keypoint_weights,
    mirror_crops,
    photometric,
    simcc_targets,
)

log = logging.getLogger(__name__)


class TrainingError(SmartedgeError):
    """Training cannot start or its result fails a check (export, onnxruntime mismatch)."""


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """What one training run does. ``train_sets`` / ``val_sets``: rendered sets (held-out
    sets must use other seeds); ``steps`` (or ``minutes``: a time budget, steps then set from
    the measured speed); ``batch``; ``lr`` (AdamW, cosine decay); ``threads``: torch CPU
    threads; ``workers``: render processes; ``sigma_px``: keypoint label width."""

    kind: str
    train_sets: tuple[SetSpec, ...]
    val_sets: tuple[SetSpec, ...]
    geometry: Geometry = dataclasses.field(default_factory=Geometry)
    steps: int = 4000
    minutes: float | None = None
    batch: int = 16
    lr: float = 2e-3
    weight_decay: float = 1e-4
    threads: int = 2
    workers: int = 2
    sigma_px: float = 1.5
    checkpoint_every: int = 200
    seed: int = 0
    #: fine-tune: start from the weights of this checkpoint (``<kind>.ckpt`` of an earlier run
    #: of the same kind and geometry) or exported model (``<kind>.onnx``, e.g. a shipped one:
    #: :mod:`training.onnx_init`) with a fresh optimizer and schedule
    init_from: str | None = None
    #: ``auto`` (CUDA when torch sees a GPU), ``cpu`` or ``cuda`` (``cuda:N``)
    device: str = "auto"
    #: bf16 autocast on CUDA (None: on where the GPU supports bf16; never on CPU)
    amp: bool | None = None
    #: keypoints: mirror half the crops left/right, keypoints swapped with their mirror
    #: partners (:func:`edge_agent.flip.mirror_permutation`): the network also sees the
    #: robot's mirror image (what flip test-time augmentation feeds it)
    mirror: bool = False
    #: stop this leg after so many steps (checkpointed; the same command resumes the schedule,
    #: here or on another machine); None: run to the end
    leg_steps: int | None = None
    #: a lab's labelled frames (COCO keypoints) trained on beside the renders, each row
    #: ``real_weight`` times; ``real_val``: held-out labelled frames validated on (``real``)
    real_train: Path | None = None
    real_val: Path | None = None
    real_weight: int = 1

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise TrainingError(f"kind {self.kind!r}: expected one of {KINDS}")
        train_seeds = {s.seed for s in self.train_sets}
        clash = train_seeds & {s.seed for s in self.val_sets}
        if clash:
            raise TrainingError(f"held-out sets reuse training seed(s) {sorted(clash)}")
        if self.device != "auto" and self.device.split(":")[0] not in ("cpu", "cuda"):
            raise TrainingError(f"device {self.device!r}: expected auto, cpu or cuda[:N]")
        if self.real_weight < 1:
            raise TrainingError(f"real weight {self.real_weight}: must be >= 1")
        if self.kind == "segmentation" and (self.real_train or self.real_val):
            raise TrainingError("labelled frames (--real) train the detector and the keypoint "
                                "network; the segmentation network needs class images")
        if self.steps < 1 or self.batch < 1:
            raise TrainingError(f"steps {self.steps}, batch {self.batch}: both must be >= 1")
        if self.kind == "segmentation":
            g, stride = self.geometry, SemanticSegNet.output_stride
            if g.det_w % 4 or g.det_h % 4:
                raise TrainingError(f"segmentation input {g.det_w}x{g.det_h}: both must be "
                                    "multiples of 4")
            if (g.seg_w, g.seg_h) != (g.det_w // stride, g.det_h // stride):
                raise TrainingError(f"segmentation labels {g.seg_w}x{g.seg_h}: the network's "
                                    f"output for a {g.det_w}x{g.det_h} input is "
                                    f"{g.det_w // stride}x{g.det_h // stride}")


# --------------------------------------------------------------------------------------------
# targets and losses
# --------------------------------------------------------------------------------------------


def _to_tensor(images: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(images)).permute(0, 3, 1, 2).float().div_(255.0)


# --------------------------------------------------------------------------------------------
# the training loop
# --------------------------------------------------------------------------------------------


def _build(cfg: TrainConfig, num_keypoints: int) -> torch.nn.Module:
    g = cfg.geometry
    if cfg.kind == "detector":
        return RobotDetector()
    if cfg.kind == "segmentation":
        return SemanticSegNet(NUM_SEMANTIC_CLASSES)
    return KeypointNet(num_keypoints, g.crop_w, g.crop_h)


def _images(data: np.ndarray, idx: np.ndarray, device: torch.device,
            resident: torch.Tensor | None = None) -> torch.Tensor:
    """Rows ``idx`` of (N, H, W, 3) uint8 images as (B, 3, H, W) float in [0, 1] on ``device``:
    gathered on the device from ``resident`` (the whole array already there) or copied there
    as uint8 (a quarter of the float bytes) and converted on the device."""
    if resident is not None:
        x = resident[torch.from_numpy(idx).to(resident.device)]
    else:
        x = torch.from_numpy(np.ascontiguousarray(data[idx])).to(device, non_blocking=True)
    return x.permute(0, 3, 1, 2).float().div_(255.0)


def _batch_loss(cfg: TrainConfig, model: torch.nn.Module, data: RenderedSet, idx: np.ndarray,
                gen: torch.Generator, rng: np.random.Generator, device: torch.device,
                weights: torch.Tensor | None = None,
                resident: torch.Tensor | None = None,
                mirror_perm: np.ndarray | None = None) -> torch.Tensor:
    """One batch's loss. Under autocast the losses are computed from float32 logits.
    ``mirror_perm`` (keypoints): mirror half the crops, keypoints to their partners."""
    g = cfg.geometry
    if cfg.kind == "segmentation":
        images, labels = data.det_images[idx], data.seg_labels[idx]
        flip = rng.uniform(size=len(idx)) < 0.5
        images = np.where(flip[:, None, None, None], images[:, :, ::-1], images)
        labels = np.where(flip[:, None, None], labels[:, :, ::-1], labels)
        x = photometric(_images(images, np.arange(len(idx)), device), gen)
        target = torch.from_numpy(labels.astype(np.int64)).to(device)
        return F.cross_entropy(model.forward_train(x).float(), target, weight=weights)
    if cfg.kind == "detector":
        boxes = frame_to_input(data.boxes[idx], data.frame_size[idx], g.det_w, g.det_h)
        flip = rng.uniform(size=len(idx)) < 0.5
        fx0 = g.det_w - 1 - boxes[:, 2]
        fx1 = g.det_w - 1 - boxes[:, 0]
        boxes = np.where(flip[:, None], np.stack([fx0, boxes[:, 1], fx1, boxes[:, 3]], 1), boxes)
        x = _images(data.det_images, idx, device, resident)
        f = torch.from_numpy(flip).to(x.device)[:, None, None, None]
        x = photometric(torch.where(f, x.flip(-1), x), gen)
        out = model.forward_train(x)
        h, w = out.heat_logits.shape[-2:]
        heat, size, off, mask = (torch.from_numpy(a).to(device)
                                 for a in detector_targets(boxes, w, h, RobotDetector.stride))
        n = mask.sum().clamp_min(1.0)
        l_size = (F.l1_loss(out.log_size.float(), size, reduction="none") * mask).sum() / n
        l_off = (F.l1_loss(out.offset.float(), off, reduction="none") * mask).sum() / n
        return focal_loss(out.heat_logits.float(), heat) + l_size + l_off
    kp = data.crop_kp[idx]
    wgt = keypoint_weights(kp, data.crop_in_image[idx], g.crop_w, g.crop_h)
    x = _images(data.crops, idx, device, resident)
    if mirror_perm is not None:
        flip = rng.uniform(size=len(idx)) < 0.5
        x, kp, wgt = mirror_crops(x, kp, wgt, flip, mirror_perm)
    wgt = torch.from_numpy(wgt).to(device)
    x = photometric(x, gen)
    out = model.forward_train(x)
    kp_t = torch.from_numpy(kp).to(device)
    logits_x, logits_y = out.logits_x.float(), out.logits_y.float()
    tx = simcc_targets(kp_t[..., 0], logits_x.shape[-1], model.split, cfg.sigma_px)
    ty = simcc_targets(kp_t[..., 1], logits_y.shape[-1], model.split, cfg.sigma_px)
    ce = (-(tx * F.log_softmax(logits_x, -1)).sum(-1)
          - (ty * F.log_softmax(logits_y, -1)).sum(-1))
    return (ce * wgt).sum() / wgt.sum().clamp_min(1.0)


def _rows(cfg: TrainConfig, data: RenderedSet) -> int:
    return len(data.crops) if cfg.kind == "keypoints" else len(data.det_images)


def _progress_line(step: int, total: int, loss: float, rate: float, eta_s: float) -> str:
    filled = int(30 * step / max(total, 1))
    return (f"  [{'#' * filled}{'.' * (30 - filled)}] step {step}/{total} loss {loss:.4f} "
            f"{rate:.1f} img/s eta {eta_s / 60:.1f} min")


def resolve_device(name: str = "auto") -> torch.device:
    """``auto``: the first CUDA device when torch sees one, else the CPU; ``cuda`` without a
    GPU is refused (:class:`TrainingError`) rather than silently trained on the CPU."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except (RuntimeError, ValueError) as exc:
        raise TrainingError(f"device {name!r}: {exc}") from None
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise TrainingError(f"device {name!r}: torch sees no CUDA GPU (torch "
                                f"{torch.__version__}); use --device cpu or auto")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise TrainingError(f"device {name!r}: only {torch.cuda.device_count()} GPU(s)")
    elif device.type != "cpu":
        raise TrainingError(f"device {name!r}: expected auto, cpu or cuda[:N]")
    return device


def device_description(device: torch.device) -> str:
    """Where a phase ran, for the model card: the GPU's name, or the CPU's model and cores."""
    if device.type == "cuda":
        return f"cuda ({torch.cuda.get_device_name(device)})"
    return f"cpu ({_cpu_name()}, {usable_cores()} cores)"


def _use_amp(cfg: TrainConfig, device: torch.device) -> bool:
    """bf16 autocast: only on CUDA (its range equals float32's, so no loss scaling), where the
    GPU supports it, unless ``cfg.amp`` says otherwise."""
    if device.type != "cuda" or cfg.amp is False:
        return False
    return bool(torch.cuda.is_bf16_supported())


def _to_cpu(obj: Any) -> Any:
    """Tensors of a (nested) state dict moved to the CPU: a checkpoint loads on any machine."""
    if isinstance(obj, torch.Tensor):
        return obj.detach().cpu()
    if isinstance(obj, dict):
        return {k: _to_cpu(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return type(obj)(_to_cpu(v) for v in obj)
    return obj


def _resident_images(cfg: TrainConfig, data: RenderedSet, device: torch.device,
                     say: Callable[[str], None]) -> torch.Tensor | None:
    """On a GPU, the training images (uint8: the keypoint crops, or the detector's frames) kept
    on the device when they take at most a quarter of its free memory: batches are then
    gathered (and flipped) there, not copied per step."""
    if device.type != "cuda" or cfg.kind not in ("keypoints", "detector"):
        return None
    images, what = ((data.crops, "crops") if cfg.kind == "keypoints"
                    else (data.det_images, "frames"))
    free, _ = torch.cuda.mem_get_info(device)
    if images.nbytes > free // 4:
        say(f"{what} ({images.nbytes / 1e9:.1f} GB) stay in host memory")
        return None
    say(f"{what} ({images.nbytes / 1e9:.2f} GB) copied to {device}")
    return torch.from_numpy(np.ascontiguousarray(images)).to(device)


def run_training(cfg: TrainConfig, model: torch.nn.Module, data: RenderedSet, ckpt: Path,
                 say: Callable[[str], None], render_s: float | None = None,
                 mirror_perm: np.ndarray | None = None, robot_model: Any = None,
                 real_data: dict[str, Any] | None = None,
                 select: Callable[[torch.nn.Module], float] | None = None) -> dict[str, Any]:
    """Train ``model`` on ``data``; resumes from ``ckpt`` when it exists, on any device (the
    checkpoint holds CPU tensors and the random generators' states). Returns the run's record
    (steps, training wall time, the first run's render time, losses, ``phases``: where and how
    long each leg trained). ``robot_model`` (keypoints, ``--init-from`` an ONNX file): the
    keypoints' names and positions, to match the file's keypoints by name. ``real_data``: the
    labelled frames trained on (content hash and weight); a checkpoint resumes only with the
    same ones. ``select(model)``: a score on held-out data (lower is better), taken at every
    checkpoint; a finished run keeps the weights of the best one (early stopping without
    cutting the schedule short), recorded as ``state["best"]``."""
    device = resolve_device(cfg.device)
    amp = _use_amp(cfg, device)
    torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    if device.type == "cuda":
        torch.backends.cudnn.benchmark = True
    model.to(device)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    rows = _rows(cfg, data)
    if rows < cfg.batch:
        raise TrainingError(f"{rows} training rows for batch {cfg.batch}: render more views")
    identity = {"kind": cfg.kind, "geometry": _geometry_identity(cfg.geometry)}
    state: dict[str, Any] = {"step": 0, "total_steps": cfg.steps, "wall_s": 0.0, "losses": [],
                             "identity": identity, "render_wall_s": render_s,
                             "real_data": real_data}
    if cfg.init_from and not ckpt.exists() and Path(cfg.init_from).suffix == ".onnx":
        state["history"] = _init_from_onnx(cfg, model, data, robot_model, say)
    elif cfg.init_from and not ckpt.exists():
        state["history"] = _init_weights(Path(cfg.init_from), model, identity, device, say)
    saved_rng: dict[str, Any] | None = None
    if ckpt.exists():
        try:
            # CPU first: a checkpoint saved on a GPU resumes on a CPU-only machine and back
            saved = torch.load(ckpt, map_location="cpu", weights_only=False)
            model.load_state_dict(saved["model"])
            opt.load_state_dict(saved["opt"])  # moves its state to the parameters' device
        except Exception as exc:  # torch raises many types for a bad or foreign file
            raise TrainingError(f"{ckpt}: cannot resume from this checkpoint ({exc}); "
                                "delete it or use another --out") from None
        state = saved["state"]
        saved_rng = saved.get("rng")
        state.setdefault("render_wall_s", None)  # checkpoints from before it was recorded
        if state.get("identity", identity) != identity:
            raise TrainingError(f"{ckpt}: checkpoint of another configuration "
                                f"({state['identity']}, now {identity}); use another --out")
        if state.get("real_data") != real_data:  # checkpoints from before it: None
            raise TrainingError(f"{ckpt}: checkpoint trained on other labelled frames "
                                f"({state.get('real_data')}, now {real_data}); use another "
                                "--out")
        if cfg.minutes is None and cfg.steps != state["total_steps"]:
            say(f"{ckpt}: --steps {cfg.steps} replaces the checkpoint's {state['total_steps']}")
            state["total_steps"] = cfg.steps
        say(f"resuming from {ckpt} at step {state['step']}/{state['total_steps']}")
    history = state.setdefault("history", [])
    phases = state.setdefault("phases", [])
    weights = None
    if cfg.kind == "segmentation":
        state.setdefault("class_weights", class_weights(data.seg_labels,
                                                        NUM_SEMANTIC_CLASSES).tolist())
        weights = torch.tensor(state["class_weights"], dtype=torch.float32, device=device)
    first_step = state["step"]
    gen = torch.Generator().manual_seed(cfg.seed + state["step"])
    rng = np.random.default_rng([cfg.seed, state["step"]])
    if saved_rng is not None:  # continue the very same random streams
        gen.set_state(saved_rng["torch"])
        rng.bit_generator.state = saved_rng["numpy"]
    resident = _resident_images(cfg, data, device, say)
    where = device_description(device)
    say(f"training on {where}{', bf16 autocast' if amp else ''}")
    model.train()
    t_last = time.perf_counter()
    t_phase = time.perf_counter()
    window: list[float] = []
    step_times: list[float] = []

    def save() -> None:
        _save_checkpoint(ckpt, model, opt, state, {"torch": gen.get_state(),
                                                   "numpy": rng.bit_generator.state})

    def score_now() -> None:
        assert select is not None
        score = float(select(model))
        model.to(device)
        model.train()
        best = state.get("best")
        if not math.isfinite(score):
            score = math.inf
        if best is None or score < best["score"]:
            state["best"] = {"step": state["step"], "score": score}
            state["best_weights"] = {k: v.detach().cpu().clone()  # a copy, not the live ones
                                     for k, v in model.state_dict().items()}
        say(f"step {state['step']}: held-out selection score {score:.4g} (best "
            f"{state['best']['score']:.4g} at step {state['best']['step']})")

    while state["step"] < state["total_steps"] and (
            cfg.leg_steps is None or state["step"] - first_step < cfg.leg_steps):
        step = state["step"]
        warmup = min(1.0, (step + 1) / 100)
        lr = cfg.lr * warmup * 0.5 * (1 + math.cos(math.pi * step / state["total_steps"]))
        for group in opt.param_groups:
            group["lr"] = lr
        idx = rng.choice(rows, cfg.batch, replace=False)
        t0 = time.perf_counter()
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=amp):
            loss = _batch_loss(cfg, model, data, idx, gen, rng, device, weights, resident,
                               mirror_perm if cfg.mirror else None)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 5.0)
        opt.step()
        loss_value = float(loss.detach())  # waits for the GPU: the step time is its own
        dt = time.perf_counter() - t0
        step_times.append(dt)
        state["wall_s"] += dt
        state["step"] += 1
        window.append(loss_value)
        if cfg.minutes is not None and state["step"] == 20 and state.get("budgeted") is None:
            per_step = float(np.median(step_times[5:])) * 1.05
            state["total_steps"] = max(40, int(cfg.minutes * 60 / per_step))
            state["budgeted"] = True
            say(f"time budget {cfg.minutes:.0f} min at {per_step * 1000:.0f} ms/step: "
                f"{state['total_steps']} steps")
        if state["step"] % 25 == 0 or state["step"] == state["total_steps"]:
            mean = float(np.mean(window))
            state["losses"].append([state["step"], mean])
            window = []
            rate = cfg.batch / max(float(np.median(step_times[-25:])), 1e-9)
            eta = (state["total_steps"] - state["step"]) * cfg.batch / rate
            say(_progress_line(state["step"], state["total_steps"], mean, rate, eta))
        if select is not None and (state["step"] % cfg.checkpoint_every == 0
                                   or state["step"] == state["total_steps"]):
            score_now()
        if state["step"] % cfg.checkpoint_every == 0 or time.perf_counter() - t_last > 300:
            save()
            t_last = time.perf_counter()
    if state["step"] > first_step:
        leg_s = time.perf_counter() - t_phase
        phases.append({"steps": [first_step, state["step"]], "device": device.type,
                       "where": where, "amp": "bf16" if amp else None,
                       "batch": cfg.batch, "wall_s": round(leg_s, 1)})
        history.append(f"steps {first_step}-{state['step']} of a {state['total_steps']}-step "
                       f"cosine schedule on {where}"
                       f"{', bf16 autocast' if amp else ''}, {cfg.threads} thread(s), "
                       f"{leg_s:.0f} s")
    best = state.get("best")
    if (select is not None and best is not None and state["step"] >= state["total_steps"]
            and best["step"] != state["step"] and state.get("best_weights") is not None):
        model.load_state_dict(state["best_weights"])
        history.append(f"kept the weights of step {best['step']}: the best held-out selection "
                       f"score ({best['score']:.4g}) of the run's checkpoints")
        say(f"keeping the weights of step {best['step']} (best held-out score "
            f"{best['score']:.4g})")
    save()
    model.eval()
    return {k: v for k, v in state.items() if k != "best_weights"}


def _geometry_identity(geometry: Geometry) -> dict[str, Any]:
    """The geometry as a checkpoint records it; without the segmentation label size when there
    is none, so checkpoints from before it existed still resume."""
    doc = dataclasses.asdict(geometry)
    if not geometry.seg_w and not geometry.seg_h:
        doc.pop("seg_w")
        doc.pop("seg_h")
    return doc


def _init_weights(path: Path, model: torch.nn.Module, identity: dict[str, Any],
                  device: torch.device, say: Callable[[str], None]) -> list[str]:
    """Load the weights of the checkpoint ``path`` (fine-tuning); returns its history lines."""
    if not path.is_file():
        raise TrainingError(f"{path}: --init-from checkpoint not found")
    try:
        saved = torch.load(path, map_location="cpu", weights_only=False)
        other = saved["state"]
        theirs = other.get("identity", identity)  # older checkpoints have none
        resized = _input_resize(theirs, identity)
        if theirs != identity and resized is None:
            raise TrainingError(f"{path}: checkpoint of another configuration "
                                f"({theirs}, now {identity})")
        model.load_state_dict(saved["model"])
    except TrainingError:
        raise
    except Exception as exc:  # torch raises many types for a bad or foreign file
        raise TrainingError(f"{path}: cannot initialize from this checkpoint ({exc})") from None
    note = f", input {resized}" if resized else ""
    say(f"initialized from {path.name} ({other['step']} steps{note})")
    return [*other.get("history", []),
            f"fine-tuned from that checkpoint ({other['step']} steps{note}) with a fresh "
            "optimizer"]


#: training images the batch norms of an ONNX starting point are unfolded on
ONNX_CALIBRATION_IMAGES: int = 64


def _init_from_onnx(cfg: TrainConfig, model: torch.nn.Module, data: RenderedSet,
                    robot_model: Any, say: Callable[[str], None]) -> list[str]:
    """Start from an exported model (:mod:`training.onnx_init`); returns the history
    lines: the file's card's history, when there is one, then this start."""
    path = Path(cfg.init_from or "")
    images = data.crops if cfg.kind == "keypoints" else data.det_images
    pick = np.random.default_rng(cfg.seed).choice(
        len(images), size=min(ONNX_CALIBRATION_IMAGES, len(images)), replace=False)
    names = xyz = None
    if robot_model is not None:
        names, xyz = robot_model.keypoint_names, np.asarray(robot_model.keypoints_base_m)
    try:
        info = init_from_onnx(model, path, _to_tensor(images[np.sort(pick)]),
                              keypoint_names=names, keypoints_base_m=xyz)
    except OnnxInitError as exc:
        raise TrainingError(str(exc)) from None
    say(info.summary())
    history: list[str] = []
    try:
        history = list(json.loads(card_path(path).read_text(encoding="utf-8"))
                       .get("training", {}).get("history", []))
    except (OSError, ValueError, AttributeError):
        say(f"{card_path(path)}: no readable model card, the new card's history starts here")
    return [*history, f"fine-tuned from the exported {path.name} with a fresh optimizer: "
            + info.summary().removeprefix(f"initialized from {path.name} ")]


def _input_resize(theirs: dict[str, Any], ours: dict[str, Any]) -> str | None:
    """``"424x240 -> 640x360"`` when two checkpoint identities differ only in the whole-frame
    input size of a fully convolutional network (detector, segmentation: the same weights run
    at any size), else None."""
    if theirs.get("kind") != ours.get("kind") or ours.get("kind") == "keypoints":
        return None
    a, b = dict(theirs.get("geometry", {})), dict(ours.get("geometry", {}))
    size_keys = ("det_w", "det_h", "seg_w", "seg_h")
    if ({k: v for k, v in a.items() if k not in size_keys}
            != {k: v for k, v in b.items() if k not in size_keys}):
        return None
    if (a.get("det_w"), a.get("det_h")) == (b.get("det_w"), b.get("det_h")):
        return None
    return f"{a.get('det_w')}x{a.get('det_h')} -> {b.get('det_w')}x{b.get('det_h')}"


def _save_checkpoint(path: Path, model: torch.nn.Module, opt: Any, state: dict[str, Any],
                     rng: dict[str, Any] | None = None) -> None:
    """Weights, optimizer, the run's record and the random generators' states, all on the CPU
    (device-independent: resumes on another machine, GPU or not)."""
    tmp = path.with_suffix(".tmp")
    torch.save({"model": _to_cpu(model.state_dict()), "opt": _to_cpu(opt.state_dict()),
                "state": state, "rng": rng}, tmp)
    tmp.replace(path)


# --------------------------------------------------------------------------------------------
# validation (torch, on the held-out sets)
# --------------------------------------------------------------------------------------------


@torch.no_grad()
def predict_detector(model: RobotDetector, det_images: np.ndarray, batch: int = 16
                     ) -> list[np.ndarray]:
    """Detections (n, 5: x0, y0, x1, y1 in input pixels, score) per image."""
    model.eval()
    out = []
    for i in range(0, len(det_images), batch):
        peaks, size, off = model(_to_tensor(det_images[i:i + batch]))
        for p, s, o in zip(peaks.numpy(), size.numpy(), off.numpy(), strict=True):
            out.append(decode_detections(p, s, o, RobotDetector.stride, min_score=0.05))
    return out


@torch.no_grad()
def predict_segmentation(model: SemanticSegNet, images: np.ndarray, batch: int = 16
                         ) -> tuple[np.ndarray, np.ndarray]:
    """(N, h, w) uint8 class ids and float32 confidences of (N, H, W, 3) uint8 inputs."""
    model.eval()
    ids, confs = [], []
    for i in range(0, len(images), batch):
        c, p = model(_to_tensor(images[i:i + batch]))
        ids.append(c.numpy())
        confs.append(p.numpy())
    return np.concatenate(ids), np.concatenate(confs)


@torch.no_grad()
def predict_keypoints(model: KeypointNet, crops: np.ndarray, batch: int = 32
                      ) -> tuple[np.ndarray, np.ndarray]:
    model.eval()
    kps, confs = [], []
    for i in range(0, len(crops), batch):
        kp, conf = model(_to_tensor(crops[i:i + batch]))
        kps.append(kp.numpy())
        confs.append(conf.numpy())
    return np.concatenate(kps), np.concatenate(confs)


def validate(cfg: TrainConfig, model: torch.nn.Module, sets: dict[str, RenderedSet]
             ) -> dict[str, dict[str, float]]:
    """Held-out metrics per set name."""
    g = cfg.geometry
    model = model.cpu()
    result: dict[str, dict[str, float]] = {}
    for name, data in sets.items():
        if cfg.kind == "detector":
            dets = predict_detector(model, data.det_images)  # type: ignore[arg-type]
            gt = frame_to_input(data.boxes, data.frame_size, g.det_w, g.det_h)
            result[name] = detection_ap(dets, gt)
        elif cfg.kind == "segmentation":
            ids, _ = predict_segmentation(model, data.det_images)  # type: ignore[arg-type]
            cm = confusion_matrix(data.seg_labels, ids, NUM_SEMANTIC_CLASSES)
            result[name] = segmentation_metrics(cm, SEMANTIC_CLASSES)
        else:
            kp, conf = predict_keypoints(model, data.crops)  # type: ignore[arg-type]
            # errors in frame pixels: crop error / crop scale
            err = np.linalg.norm(kp - data.crop_kp, axis=-1) / data.crop_scale[:, None]
            wgt = keypoint_weights(data.crop_kp, data.crop_in_image, g.crop_w, g.crop_h) > 0
            result[name] = keypoint_metrics(err, conf, wgt, data.crop_visible)
    return result


# --------------------------------------------------------------------------------------------
# export
# --------------------------------------------------------------------------------------------


def export_onnx(cfg: TrainConfig, model: torch.nn.Module, path: Path) -> None:
    g = cfg.geometry
    model = model.cpu().eval()
    if cfg.kind == "detector":
        dummy = torch.rand(1, 3, g.det_h, g.det_w)
        names_in, names_out = ["image"], ["peaks", "size", "offset"]
        # a free input size: the edge runs the whole frame at the card's size and a camera's
        # far band at its own (edge_agent/far_band.py)
        out_dims = {0: "batch", 2: "out_height", 3: "out_width"}
        dyn = {"image": {0: "batch", 2: "height", 3: "width"}, "peaks": out_dims,
               "size": out_dims, "offset": out_dims}
    elif cfg.kind == "segmentation":
        dummy = torch.rand(1, 3, g.det_h, g.det_w)
        names_in, names_out = ["image"], ["class_ids", "confidence"]
        dyn = {"image": {0: "batch"}, "class_ids": {0: "batch"}, "confidence": {0: "batch"}}
    else:
        dummy = torch.rand(1, 3, g.crop_h, g.crop_w)
        names_in, names_out = ["crop"], ["keypoints", "confidence"]
        dyn = {"crop": {0: "batch"}, "keypoints": {0: "batch"}, "confidence": {0: "batch"}}
    tmp = path.with_suffix(".tmp.onnx")
    torch.onnx.export(model, (dummy,), str(tmp), dynamo=False, opset_version=17,
                      input_names=names_in, output_names=names_out, dynamic_axes=dyn)
    tmp.replace(path)


def check_onnxruntime(cfg: TrainConfig, model: torch.nn.Module, path: Path,
                      samples: np.ndarray) -> dict[str, float]:
    """Run the exported file with onnxruntime on ``samples`` (N, H, W, 3 uint8 inputs) and
    compare with torch; raises :class:`TrainingError` past the tolerance."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = cfg.threads
    sess = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
    x = _to_tensor(samples)
    with torch.no_grad():
        ref = [t.numpy() for t in model.cpu().eval()(x)]
    got = sess.run(None, {sess.get_inputs()[0].name: x.numpy()})
    names = [o.name for o in sess.get_outputs()]
    if cfg.kind == "detector":
        # a cell whose heat sits at the peak test's threshold may go either way in two
        # runtimes (float noise): compare the peaks everywhere else
        with torch.no_grad():
            heat = torch.sigmoid(model.forward_train(x).heat_logits)  # type: ignore[operator]
            gap = (F.max_pool2d(heat, 3, 1, 1) - heat).numpy()
        ambiguous = np.abs(gap - PEAK_TIE) < 1e-6
        got[0] = np.where(ambiguous, ref[0], got[0])
        extra = {"peaks_ambiguous": ambiguous}
    else:
        extra = {}
    diffs = {}
    for name, r, o in zip(names, ref, got, strict=True):
        if name == "class_ids":  # the share of pixels whose class differs
            diffs[name] = float(np.mean(r != o)) if r.size else 0.0
        else:
            diffs[name] = (float(np.max(np.abs(r.astype(np.float64) - o))) if r.size
                           else 0.0)
    ratios = export_differences({**dict(zip(names, ref, strict=True)), **extra},
                                dict(zip(names, got, strict=True)))
    bad = {k: diffs[k] for k, v in ratios.items() if v > 1.0}
    if bad:
        raise TrainingError(f"{path}: onnxruntime differs from torch: {bad}")
    np.savez_compressed(reference_path(path), inputs=np.asarray(samples, np.uint8),
                        **dict(zip(names, ref, strict=True)), **extra)
    return diffs


# --------------------------------------------------------------------------------------------
# the whole run
# --------------------------------------------------------------------------------------------


def train(cfg: TrainConfig, views: ViewSource, out_dir: Path, *,
          robot_mesh_name: str = "built-in HSR-like mesh",
          say: Callable[[str], None] = print) -> Path:
    """Render (from ``views``), train, validate, export, check, write the model card. Returns
    the ONNX path."""
    out_dir.mkdir(parents=True, exist_ok=True)
    model_def = views.robot_model
    cache = out_dir / "cache"
    t_start = time.perf_counter()
    say(f"{cfg.kind}: training sets {[s.name for s in cfg.train_sets]}, "
        f"held-out {[s.name for s in cfg.val_sets]}")
    data = render_set(views, cfg.train_sets, cfg.geometry, cache, workers=cfg.workers,
                      progress=say)
    eval_geom = dataclasses.replace(cfg.geometry, crop_jitter=False)
    val = {s.name: render_set(views, [s], eval_geom, cache, workers=cfg.workers,
                              augment_clean=False, progress=say)
           for s in cfg.val_sets}
    real: dict[str, Any] = {}
    if cfg.real_train is not None:
        rows, info = real_set(cfg.real_train, cfg.geometry, model_def.keypoint_names,
                              np.random.default_rng(cfg.seed), views.augment)
        data = RenderedSet.concatenate([data, *[rows] * cfg.real_weight])
        real["train"] = {**dataclasses.asdict(info), "weight": cfg.real_weight}
        say(f"{cfg.kind}: {info.frames} labelled frames of {cfg.real_train} x "
            f"{cfg.real_weight} beside the renders (left out: {info.left_out or 'none'})")
    if cfg.real_val is not None:
        val["real"], info = real_set(cfg.real_val, eval_geom, model_def.keypoint_names,
                                     np.random.default_rng(cfg.seed + 1))
        real["val"] = dataclasses.asdict(info)
    render_s = time.perf_counter() - t_start
    torch.manual_seed(cfg.seed)  # the initial weights too
    model = _build(cfg, model_def.num_keypoints)
    n_params = sum(p.numel() for p in model.parameters())
    say(f"{cfg.kind}: {n_params / 1e6:.2f} M parameters, {_rows(cfg, data)} training rows, "
        f"device {device_description(resolve_device(cfg.device))}")
    perm = (mirror_permutation(model_def.keypoint_names)
            if cfg.mirror and cfg.kind == "keypoints" else None)
    real_identity = ({"sha256": real["train"]["sha256"], "weight": cfg.real_weight}
                     if "train" in real else None)
    select = None
    if "real" in val:  # keep the weights that do best on the lab's held-out frames
        def select(m: torch.nn.Module) -> float:
            figures = validate(cfg, m, {"real": val["real"]})["real"]
            if cfg.kind == "detector":
                return -float(figures.get("AP@0.5", float("nan")))
            return float(figures.get("median error px", float("nan")))

    state = run_training(cfg, model, data, out_dir / f"{cfg.kind}.ckpt", say, render_s, perm,
                         robot_model=model_def, real_data=real_identity, select=select)
    t_eval = time.perf_counter()
    metrics = validate(cfg, model, val)
    for name, figures in metrics.items():
        say(f"held-out {name}: " + ", ".join(f"{k} {v:.3g}" for k, v in figures.items()))
    onnx_path = out_dir / f"{cfg.kind}.onnx"
    for stale in (onnx_path, reference_path(onnx_path), card_path(onnx_path)):
        stale.unlink(missing_ok=True)  # never leave a new model beside an old card
    export_onnx(cfg, model, onnx_path)
    first = next(iter(val.values()))
    probe = first.crops[:4] if cfg.kind == "keypoints" else first.det_images[:2]
    try:
        diffs = check_onnxruntime(cfg, model, onnx_path, probe)
    except TrainingError:
        onnx_path.unlink(missing_ok=True)
        raise
    say(f"onnxruntime matches torch: max abs diff {diffs}")
    first_render_s = state.get("render_wall_s")
    total_s = (first_render_s or 0.0) + state["wall_s"] + (time.perf_counter() - t_eval)
    card = _card(cfg, model_def, robot_mesh_name, state, metrics, diffs, n_params,
                 first_render_s, total_s, onnx_path, real)
    card.write(out_dir)
    say(f"wrote {onnx_path} ({onnx_path.stat().st_size / 1e6:.2f} MB) and its model card")
    return onnx_path


def _card(cfg: TrainConfig, model_def: Any, mesh_name: str, state: dict[str, Any],
          metrics: dict[str, dict[str, float]], diffs: dict[str, float], n_params: int,
          render_s: float | None, total_s: float, onnx_path: Path,
          real: dict[str, Any] | None = None
          ) -> DetectorCard | KeypointCard | SegmentationCard:
    g = cfg.geometry
    training = {
        "train_sets": [dataclasses.asdict(s) for s in cfg.train_sets],
        "val_sets": [dataclasses.asdict(s) for s in cfg.val_sets],
        "steps": state["step"], "batch": cfg.batch, "lr": cfg.lr, "sigma_px": cfg.sigma_px,
        "mirror_augmentation": cfg.mirror,
        "train_wall_s": round(state["wall_s"], 1),
        "render_wall_s": None if render_s is None else round(render_s, 1),
        "total_wall_s": round(total_s, 1),
        # where the last leg trained (every leg: ``phases``)
        "device": (state["phases"][-1]["device"] if state.get("phases")
                   else resolve_device(cfg.device).type),
        "machine": card_machine(),
        "phases": list(state.get("phases", [])),
        "torch": torch.__version__,
        "final_loss": round(state["losses"][-1][1], 4) if state["losses"] else None,
        "parameters": n_params, "robot_mesh": mesh_name,
        "history": list(state.get("history", [])),
    }
    if state.get("best"):
        # the checkpoint kept: the best on the labelled held-out frames ("real")
        training["selected"] = {"step": state["best"]["step"],
                                "score": round(state["best"]["score"], 5)}
    if real:
        # a lab's labelled frames beside the renders: file, content hash, frames, cameras,
        # where the labels came from
        training["real_data"] = real
    if cfg.kind == "segmentation":
        training["class_weights"] = [round(w, 3) for w in state.get("class_weights", [])]
        training.pop("sigma_px")
    common = {"version": CARD_VERSION, "onnx": onnx_path.name, "robot_model": model_def.name,
              "keypoint_names": list(model_def.keypoint_names), "metrics": metrics,
              "onnx_check": diffs, "training": training}
    if cfg.kind == "detector":
        # every detector trains on mirrored frames too (_batch_loss), so it runs with flip
        # test-time augmentation by default
        return DetectorCard(input_w=g.det_w, input_h=g.det_h, stride=RobotDetector.stride,
                            flip_tta=True, **common)
    if cfg.kind == "segmentation":
        return SegmentationCard(input_w=g.det_w, input_h=g.det_h, output_w=g.seg_w,
                                output_h=g.seg_h, classes=list(SEMANTIC_CLASSES), **common)
    # a model that saw mirrored crops runs with flip test-time augmentation by default
    return KeypointCard(input_w=g.crop_w, input_h=g.crop_h, flip_tta=cfg.mirror, **common)


def _cpu_name() -> str:
    """The CPU's model name (Linux), else the architecture."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.machine() or "unknown CPU"

