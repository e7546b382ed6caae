"""Start a training run from an exported ONNX model: the shipped models carry no checkpoint.

``smartedge train <kind> --init-from edge_agent/models/<kind>.onnx`` fine-tunes the model a
site already runs (its own robot's look, more keypoints) without the GPU run that made it.

The exporter folds every batch norm into the convolution before it (``W' = W * gamma / std``,
``b' = beta + (b - mean) * gamma / std``), so the file holds one weight and one bias per
convolution and no normalisation statistics. Loading puts the folded weight into the
convolution and *unfolds* the batch norm so that both modes of the network stay right:

* in evaluation mode the pair computes ``conv(x) + b'``, exactly the file's result;
* in training mode a batch norm normalises by the batch's own statistics, so its running
  statistics and affine parameters are set from the convolution's output on calibration images
  of the training set (``mean = mu``, ``var = s^2``, ``gamma = sqrt(s^2 + eps)``,
  ``beta = mu + b'``): on batches like those, training starts where the file's model stands.

Convolutions and linear layers are matched in execution order (the exporter writes the graph in
the order ``forward`` runs), each checked by the module name the exporter records in the node's
scope and by shape. Keypoint networks are matched by keypoint *name* (the card beside the
file): kept keypoints keep their head channels, a keypoint the file lacks starts from the mean
of the two nearest kept keypoints on the robot (its base-frame position), removed ones are
dropped. The loaded network is checked against onnxruntime on the calibration images before
training starts.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

import numpy as np
import torch
from torch import nn

from edge_agent.model_cards import KeypointCard, ModelError, card_path
from protocol.errors import SmartedgeError

log = logging.getLogger(__name__)

#: onnxruntime and the loaded torch network may differ by this much relative to the output's
#: magnitude (float32 summation order) before loading is refused
MATCH_TOLERANCE: float = 1e-3


class OnnxInitError(SmartedgeError):
    """The ONNX file does not fit the network being trained (kind, layers, keypoints)."""


@dataclasses.dataclass(frozen=True)
class OnnxInit:
    """What :func:`init_from_onnx` loaded."""

    source: Path
    convolutions: int
    linears: int
    #: batch norms given back their statistics from the calibration images
    unfolded_norms: int
    calibration_images: int
    #: keypoints kept from the file, in the network's order
    kept_keypoints: tuple[str, ...]
    #: (new keypoint, the two kept keypoints it starts from)
    added_keypoints: tuple[tuple[str, tuple[str, str]], ...]
    dropped_keypoints: tuple[str, ...]
    #: largest difference to onnxruntime on the calibration images (kept outputs), relative
    max_rel_diff: float

    def summary(self) -> str:
        text = (f"initialized from {self.source.name} ({self.convolutions} convolutions, "
                f"{self.linears} linear layers, {self.unfolded_norms} batch norms unfolded on "
                f"{self.calibration_images} training images; matches onnxruntime to "
                f"{self.max_rel_diff:.1e})")
        if self.added_keypoints:
            text += ", keypoints added: " + ", ".join(
                f"{n} (from {a} + {b})" for n, (a, b) in self.added_keypoints)
        if self.dropped_keypoints:
            text += f", keypoints dropped: {', '.join(self.dropped_keypoints)}"
        return text


def _load_graph(path: Path) -> tuple[object, dict[str, np.ndarray]]:
    import onnx
    from onnx import numpy_helper

    if not path.is_file():
        raise OnnxInitError(f"{path}: --init-from model not found")
    try:
        graph = onnx.load(str(path)).graph
    except Exception as exc:  # onnx raises protobuf's and its own errors
        raise OnnxInitError(f"{path}: not a readable ONNX file ({exc})") from None
    return graph, {i.name: numpy_helper.to_array(i) for i in graph.initializer}


def _forward_watching(model: nn.Module, x: torch.Tensor,
                      modules: Iterable[tuple[str, nn.Module]],
                      see: Callable[[str, nn.Module, torch.Tensor], object]) -> None:
    """Run ``model`` on ``x`` (no gradients), calling ``see(name, module, output)`` after each
    of ``modules`` runs; the hooks are removed afterwards."""
    hooks = [m.register_forward_hook(lambda mod, _i, out, n=n: see(n, mod, out))
             for n, m in modules]
    try:
        with torch.no_grad():
            model(x)
    finally:
        for h in hooks:
            h.remove()


def _execution_order(model: nn.Module, sample: torch.Tensor) -> list[tuple[str, nn.Module]]:
    """(qualified name, module) of every Conv2d and Linear in the order ``forward`` runs them."""
    order: list[tuple[str, nn.Module]] = []
    _forward_watching(model, sample, ((n, m) for n, m in model.named_modules()
                                      if isinstance(m, nn.Conv2d | nn.Linear)),
                      lambda n, m, _out: order.append((n, m)))
    return order


def _norm_after(model: nn.Module) -> dict[str, tuple[str, nn.BatchNorm2d]]:
    """Conv2d name → (name, module) of the BatchNorm2d right after it in the same Sequential."""
    out: dict[str, tuple[str, nn.BatchNorm2d]] = {}
    for name, mod in model.named_modules():
        if not isinstance(mod, nn.Sequential):
            continue
        kids = list(mod.named_children())
        prefix = f"{name}." if name else ""
        for (a, ma), (b, mb) in itertools.pairwise(kids):
            if isinstance(ma, nn.Conv2d) and isinstance(mb, nn.BatchNorm2d):
                out[prefix + a] = (prefix + b, mb)
    return out


def _scope_matches(node_name: str, module_name: str) -> bool:
    """The exporter names a node ``/a/b/b.0/Conv``: its last scope (``b.0``) ends the module's
    qualified name. A node without a scope (another exporter) is not checked."""
    parts = node_name.strip("/").split("/")
    if len(parts) < 2:
        return True
    last = parts[-2]
    return module_name == last or module_name.endswith("." + last)


@dataclasses.dataclass(frozen=True)
class KeypointMap:
    """How a keypoint network's keypoints take the file's head channels
    (:func:`keypoint_map`)."""

    rows: list[list[int]]  # per network keypoint: the file's keypoints whose channels it takes
    kept: tuple[str, ...]
    added: tuple[tuple[str, tuple[str, str]], ...]
    dropped: tuple[str, ...]
    kept_index: tuple[tuple[int, int], ...]  # (network index, file index)


def keypoint_map(file_names: Sequence[str], names: Sequence[str], xyz_m: np.ndarray
                 ) -> KeypointMap:
    """How the network's keypoints ``names`` (base-frame positions ``xyz_m``, (K, 3)) take the
    head channels of the file's keypoints ``file_names``: by name; a new keypoint from the
    two nearest kept keypoints."""
    index = {n: i for i, n in enumerate(file_names)}
    kept = [(j, n) for j, n in enumerate(names) if n in index]
    if len(kept) < 2:
        raise OnnxInitError(f"the network's keypoints {list(names)} share fewer than two names "
                            f"with the file's {list(file_names)}: nothing to start from")
    xyz = np.asarray(xyz_m, dtype=np.float64).reshape(len(names), 3)
    rows: list[list[int]] = []
    added = []
    for j, n in enumerate(names):
        if n in index:
            rows.append([index[n]])
            continue
        dist = sorted((float(np.linalg.norm(xyz[j] - xyz[k])), k) for k, _ in kept)
        a, b = dist[0][1], dist[1][1]
        rows.append([index[names[a]], index[names[b]]])
        added.append((n, (names[a], names[b])))
    dropped = tuple(n for n in file_names if n not in set(names))
    return KeypointMap(rows, tuple(n for _, n in kept), tuple(added), dropped,
                        tuple((j, index[n]) for j, n in kept))


def _remap_head(w: np.ndarray, per_keypoint: int, rows: list[list[int]]) -> np.ndarray:
    """Output channels grouped per keypoint (``per_keypoint`` each) → the network's keypoints."""
    groups = w.reshape(-1, per_keypoint, *w.shape[1:])
    return np.concatenate([groups[r].mean(axis=0) for r in rows]).astype(w.dtype)


def init_from_onnx(model: nn.Module, path: Path, calibration: torch.Tensor, *,
                   keypoint_names: Sequence[str] | None = None,
                   keypoints_base_m: np.ndarray | None = None) -> OnnxInit:
    """Load the ONNX file ``path`` (exported by ``smartedge train``) into ``model`` (same
    architecture; a keypoint network may have other keypoints, matched by name through the
    card beside the file, see the module text). ``calibration``: (N, 3, H, W) float inputs from
    the training set (the batch norms' statistics). Raises :class:`OnnxInitError` naming the
    file and the layer when the file does not fit."""
    path = Path(path)
    graph, inits = _load_graph(path)
    device = next(model.parameters()).device
    calibration = calibration.to(device)
    kp_map: KeypointMap | None = None
    per_keypoint = getattr(model, "per_keypoint", None)
    if per_keypoint is not None:
        if keypoint_names is None or keypoints_base_m is None:
            raise OnnxInitError("a keypoint network needs its keypoint names and positions")
        try:
            card = KeypointCard.read(card_path(path))
        except ModelError as exc:
            raise OnnxInitError(f"{path}: keypoint models are matched by keypoint name: {exc}"
                                ) from None
        kp_map = keypoint_map(card.keypoint_names, keypoint_names, keypoints_base_m)
    model.eval()
    order = _execution_order(model, calibration[:1])
    norms = _norm_after(model)
    nodes = [n for n in graph.node if n.op_type in ("Conv", "MatMul", "Gemm")]
    if len(nodes) != len(order):
        raise OnnxInitError(f"{path}: {len(nodes)} convolution / linear layers in the file, "
                            f"{len(order)} in the network: another architecture")
    state = model.state_dict()
    loaded: set[str] = set()
    unfold: dict[str, tuple[nn.Conv2d, tuple[str, nn.BatchNorm2d], np.ndarray]] = {}
    n_conv = n_lin = 0

    def put(key: str, value: np.ndarray, node: str) -> None:
        want = tuple(state[key].shape)
        if tuple(value.shape) != want:
            raise OnnxInitError(f"{path}: layer {node} holds {tuple(value.shape)} for {key}, "
                                f"the network wants {want}: another architecture or size")
        with torch.no_grad():
            state[key].copy_(torch.from_numpy(np.array(value)))  # a writable copy
        loaded.add(key)

    for node, (name, mod) in zip(nodes, order, strict=True):
        if not _scope_matches(node.name, name):
            raise OnnxInitError(f"{path}: node {node.name} stands where the network runs "
                                f"{name}: another architecture")
        inputs = list(node.input)
        if isinstance(mod, nn.Conv2d):
            if node.op_type != "Conv":
                raise OnnxInitError(f"{path}: node {node.name} ({node.op_type}) where the "
                                    f"network runs the convolution {name}")
            n_conv += 1
            w = inits[inputs[1]]
            b = inits[inputs[2]] if len(inputs) > 2 and inputs[2] in inits else None
            if kp_map is not None and name == "to_kp":
                w = _remap_head(w, per_keypoint, kp_map.rows)
                b = None if b is None else _remap_head(b, per_keypoint, kp_map.rows)
            put(f"{name}.weight", w, node.name)
            if name in norms:
                bias = np.zeros(w.shape[0], np.float32) if b is None else b
                unfold[name] = (mod, norms[name], bias)
            elif mod.bias is not None:
                if b is None:
                    raise OnnxInitError(f"{path}: layer {node.name} has no bias for {name}")
                put(f"{name}.bias", b, node.name)
        else:
            n_lin += 1
            if node.op_type == "MatMul":
                w = inits[inputs[1]].T
            elif node.op_type == "Gemm":
                trans_b = next((a.i for a in node.attribute if a.name == "transB"), 0)
                w = inits[inputs[1]] if trans_b else inits[inputs[1]].T
            else:
                raise OnnxInitError(f"{path}: node {node.name} ({node.op_type}) where the "
                                    f"network runs the linear layer {name}")
            put(f"{name}.weight", w, node.name)
            if mod.bias is not None:
                b = inits.get(f"{name}.bias")
                if b is None and node.op_type == "Gemm" and len(inputs) > 2:
                    b = inits.get(inputs[2])
                if b is None:
                    raise OnnxInitError(f"{path}: no bias for the linear layer {name}")
                put(f"{name}.bias", b, node.name)
    for key, value in inits.items():  # named constants (normalisation buffers)
        if key in state and key not in loaded and value.shape == tuple(state[key].shape):
            put(key, value, key)
    # the batch norms first as identity + the folded bias (eval mode then equals the file) ...
    with torch.no_grad():
        for _conv, (bn_name, bn), bias in unfold.values():
            bn.running_mean.zero_()
            bn.running_var.fill_(1.0 - bn.eps)
            bn.weight.fill_(1.0)
            bn.bias.copy_(torch.from_numpy(bias))
            loaded.update(f"{bn_name}.{k}" for k in ("weight", "bias", "running_mean",
                                                     "running_var", "num_batches_tracked"))
    missing = sorted(k for k in state if k not in loaded)
    if missing:
        raise OnnxInitError(f"{path}: the file sets no value for {missing[:5]}"
                            f"{' ...' if len(missing) > 5 else ''}")
    # ... then their statistics from the convolutions' outputs on the calibration images
    stats: dict[str, tuple[torch.Tensor, torch.Tensor]] = {}
    _forward_watching(model, calibration, ((n, conv) for n, (conv, _, _) in unfold.items()),
                      lambda n, _m, out: stats.__setitem__(
                          n, (out.mean(dim=(0, 2, 3)), out.var(dim=(0, 2, 3), unbiased=False))))
    with torch.no_grad():
        for name, (_conv, (_, bn), bias) in unfold.items():
            mu, var = stats[name]
            bn.running_mean.copy_(mu)
            bn.running_var.copy_(var)
            bn.weight.copy_(torch.sqrt(var + bn.eps))
            bn.bias.copy_(mu + torch.from_numpy(bias).to(mu))
    rel = _compare_with_onnxruntime(path, model, calibration[:8], kp_map)
    return OnnxInit(path, n_conv, n_lin, len(unfold), len(calibration),
                    kp_map.kept if kp_map else (), kp_map.added if kp_map else (),
                    kp_map.dropped if kp_map else (), rel)


def _compare_with_onnxruntime(path: Path, model: nn.Module, x: torch.Tensor,
                              kp_map: KeypointMap | None) -> float:
    import onnxruntime as ort

    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    shape = sess.get_inputs()[0].shape
    size = tuple(shape[2:]) if len(shape) == 4 else ()
    if all(isinstance(d, int) for d in size) and len(size) == 2 and size != tuple(x.shape[2:]):
        # a fully convolutional network trained at another input size: compare at the file's
        x = torch.nn.functional.interpolate(x, size=size, mode="bilinear", align_corners=False)
    xs = x.detach().cpu().numpy()
    got = sess.run(None, {sess.get_inputs()[0].name: xs})
    with torch.no_grad():
        ref = [t.detach().cpu().numpy() for t in model.eval()(x)]
    worst = 0.0
    for name, a, b in zip([o.name for o in sess.get_outputs()], got, ref, strict=True):
        if kp_map is not None:  # keypoints (N, K, 2) / confidence (N, K): the kept keypoints
            net_idx = [j for j, _ in kp_map.kept_index]
            file_idx = [i for _, i in kp_map.kept_index]
            a, b = a[:, file_idx], b[:, net_idx]
        if a.shape != b.shape:
            raise OnnxInitError(f"{path}: output {name} is {a.shape} from onnxruntime, "
                                f"{b.shape} from the loaded network")
        diff = np.abs(a.astype(np.float64) - b)
        scale = max(1.0, float(np.abs(a).max()))
        # a detector's peak output keeps a cell only where it is a local maximum: a tie may go
        # either way in two runtimes, so a few cells are allowed to differ
        value = float(np.quantile(diff, 0.999)) / scale
        worst = max(worst, value)
        if value > MATCH_TOLERANCE:
            raise OnnxInitError(f"{path}: the loaded network differs from onnxruntime on "
                                f"output {name} by {value:.2e} (relative): loading failed")
    log.info("%s: loaded network matches onnxruntime to %.1e", path, worst)
    return worst
