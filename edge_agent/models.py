"""The edge's networks at run time: model cards, onnxruntime sessions, decoding (no torch).

A model is an ONNX file with its card beside it (same name, ``.json``: :class:`DetectorCard` /
:class:`KeypointCard` / :class:`SegmentationCard`: input size, robot model and keypoint names,
the segmentation's classes and output size, training record, held-out metrics); ``.md`` is the
same card for people and ``.reference.npz`` holds torch's outputs on fixed inputs (the export
check). The shipped models for the built-in robot live in
``edge_agent/models/`` (:func:`default_model_dir`); a site file's robot model may name others.

:class:`RobotKeypointPipeline` runs detector → crop → keypoints on a full frame and returns raw
(distorted) pixel keypoints with confidences per detected robot. :class:`RobotTypesPipeline` does
it for every robot model (type) of a site, one :class:`RobotKeypointPipeline` each, and removes
the duplicate boxes two types' detectors put on one robot; :func:`models_for_site` picks the one
or the other for a site file. :class:`SemanticSegmenter`
turns a whole frame into per-pixel classes of :mod:`protocol.semantic_classes` with confidences.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, ClassVar, Final

import numpy as np

from edge_agent.boxes import box_iou, iou_matrix, same_robot
from edge_agent.crop import CROP_PADDING, crop_transform, extract_crop, resize_for_detector, to_nchw
from edge_agent.far_band import FarBand
from edge_agent.metrics import sigma_from_confidence
from protocol.errors import SmartedgeError
from protocol.semantic_classes import SEMANTIC_CLASSES

log = logging.getLogger(__name__)

CARD_VERSION: Final = 1
KINDS: Final = ("detector", "keypoints", "segmentation")


class ModelError(SmartedgeError):
    """A model file or card is missing, corrupt or does not fit the site's robot model."""


def usable_cores() -> int:
    """The CPU cores this process may run on (its affinity where the OS says, else all)."""
    import os

    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def card_machine() -> str:
    """This machine as a model card names it (architecture, cores, OS): where a model
    trained, or where its figures were measured."""
    import platform

    return f"{platform.machine()}, {usable_cores()} cores, {platform.system()}"


def default_model_dir() -> Path:
    """The folder of the shipped models for the built-in robot (package data)."""
    return Path(__file__).resolve().parent / "models"


@dataclasses.dataclass(frozen=True)
class ModelCard:
    """What the edge pipeline needs to know about a model, and how it was made."""

    KIND: ClassVar[str] = ""
    version: int
    onnx: str
    robot_model: str
    keypoint_names: list[str]
    input_w: int
    input_h: int
    metrics: dict[str, dict[str, float]]
    onnx_check: dict[str, float]
    training: dict[str, Any]
    #: figures measured through the deployed pipeline after training (``smartedge evaluate
    #: keypoints --record``): what was run → {"command", "date", "machine", "views",
    #: "figures": {set: {name: value}}}
    evaluations: dict[str, dict[str, Any]] = dataclasses.field(default_factory=dict,
                                                               kw_only=True)

    def with_evaluation(self, name: str, entry: dict[str, Any]) -> ModelCard:
        """This card with ``entry`` recorded as evaluation ``name`` (an earlier one of that
        name replaced)."""
        return dataclasses.replace(self, evaluations={**self.evaluations, name: entry})

    def to_json(self) -> dict[str, Any]:
        return {"kind": self.KIND, **dataclasses.asdict(self)}

    def write(self, folder: Path) -> None:
        (folder / f"{self.KIND}.json").write_text(json.dumps(self.to_json(), indent=2) + "\n",
                                                  encoding="utf-8")
        (folder / f"{self.KIND}.md").write_text(self.markdown(), encoding="utf-8")

    @classmethod
    def read(cls, path: Path) -> ModelCard:
        try:
            doc = json.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise ModelError(f"{path}: model card not found (train the model with "
                             f"`smartedge train {cls.KIND}`; the card sits beside the .onnx "
                             "file)") from None
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ModelError(f"{path}: cannot read the model card: {exc}") from None
        if not isinstance(doc, dict) or doc.get("kind") != cls.KIND:
            raise ModelError(f"{path}: not a {cls.KIND} model card "
                             f"(kind {doc.get('kind') if isinstance(doc, dict) else None!r})")
        if doc.get("version") != CARD_VERSION:
            raise ModelError(f"{path}: card version {doc.get('version')!r}, "
                             f"this smartedge reads {CARD_VERSION}")
        doc.pop("kind")
        names = {f.name for f in dataclasses.fields(cls)}
        required = {f.name for f in dataclasses.fields(cls)
                    if f.default is dataclasses.MISSING
                    and f.default_factory is dataclasses.MISSING}
        missing = sorted(required - doc.keys())
        if missing:
            raise ModelError(f"{path}: model card lacks {missing}")
        evaluations = doc.get("evaluations", {})
        if not isinstance(evaluations, dict) or not all(
                isinstance(e, dict) for e in evaluations.values()):
            raise ModelError(f"{path}: bad model card: 'evaluations' must map a name to an "
                             "object (command, date, machine, views, figures)")
        try:
            return cls(**{k: v for k, v in doc.items() if k in names})
        except (TypeError, ValueError) as exc:
            raise ModelError(f"{path}: bad model card: {exc}") from None

    def _loss_lines(self) -> list[str]:
        return []

    def _model_lines(self) -> list[str]:
        """The card's first bullet points after the file: what the model is for."""
        return [f"- robot model: `{self.robot_model}` ({len(self.keypoint_names)} keypoints: "
                f"{', '.join(self.keypoint_names)}); mesh: "
                f"{self.training.get('robot_mesh', '?')}",
                f"- input: {self.input_w}x{self.input_h} RGB float32 in [0, 1], NCHW "
                "(normalised inside the graph)"]

    def markdown(self) -> str:
        t = self.training
        lines = [
            f"# {self.KIND} model card",
            "",
            f"- file: `{self.onnx}` (ONNX opset 17, one self-contained file)",
            *self._model_lines(),
            f"- parameters: {t.get('parameters', 0) / 1e6:.2f} M",
            "",
            "## Training",
            "",
            "Trained only on synthetic renders of smartedge's renderer "
            "(`smartedge train`, domain-randomized scenes plus views from the site's cameras"
            + (" and from the robot's own head camera"
               if any(s.get("mode") == "robot" for s in t.get("train_sets", [])) else "")
            + ").",
            "",
        ]
        for key in ("train_sets", "val_sets"):
            sets = ", ".join(f"{s['mode']} seed {s['seed']} x{s['count']}" for s in t.get(key, []))
            lines.append(f"- {'training' if key == 'train_sets' else 'held-out'} sets: {sets}")
        lines += self._loss_lines()
        lines += [
            f"- steps: {t.get('steps')} x batch {t.get('batch')}, AdamW lr {t.get('lr')}, "
            f"final loss {t.get('final_loss')}",
            f"- wall time: render {_render_time(t.get('render_wall_s'))}, "
            f"train {t.get('train_wall_s')} s, "
            f"total {t.get('total_wall_s')} s on {t.get('device')} ({t.get('machine')}, "
            f"torch {t.get('torch')})",
            *(f"  - {leg}" for leg in t.get("history", [])),
            "",
            "## Held-out metrics",
            "",
        ]
        for name, figures in self.metrics.items():
            lines.append(f"- {name}: " + ", ".join(f"{k} {_fmt(v)}" for k, v in figures.items()))
        lines += ["", "## Export check", "",
                  "onnxruntime vs torch, max abs difference per output: "
                  + ", ".join(f"{k} {v:.2g}" for k, v in self.onnx_check.items()), ""]
        text = "\n".join(lines) + self._sections()
        evaluations = self._evaluation_lines()
        return text + ("\n" + "\n".join(evaluations) if evaluations else "")

    def _sections(self) -> str:
        """A kind's own sections after the export check (markdown, each starting with a
        blank line)."""
        return ""

    def _evaluation_lines(self) -> list[str]:
        if not self.evaluations:
            return []
        lines = ["## Through the deployed pipeline", "",
                 "Measured with onnxruntime on fresh renders of seeds never trained on "
                 "(`smartedge evaluate keypoints ... --record`; docs/models.md, \"Evaluating\"):",
                 ""]
        for name, e in self.evaluations.items():
            lines.append(f"- {name}: `{e.get('command', '?')}`, {e.get('date', '?')}, "
                         f"{e.get('views', '?')} views, {e.get('machine', '?')}")
            for set_name, figures in e.get("figures", {}).items():
                lines.append(f"  - {set_name}: " + ", ".join(
                    f"{k} {_fmt(v)}" for k, v in figures.items()))
        return [*lines, ""]


def _render_time(seconds: float | None) -> str:
    return "n/a (an existing render cache was used)" if seconds is None else f"{seconds} s"


def _fmt(v: float) -> str:
    if isinstance(v, float) and v.is_integer():
        return str(int(v))
    return f"{v:.3f}" if isinstance(v, float) else str(v)


@dataclasses.dataclass(frozen=True)
class DetectorCard(ModelCard):
    """``flip_tta``: the detector runs with test-time flip augmentation by default
    (:class:`Detector`); ``smartedge train detector`` always mirrors half its frames, so its
    cards say so. A card written before the field existed reads as no flip."""

    KIND: ClassVar[str] = "detector"
    stride: int = 4
    flip_tta: bool = False

    def _sections(self) -> str:
        text = ""
        if self.flip_tta:
            text += ("\n## Test-time flip\n\nTrained on mirrored frames too; the edge runs each "
                     "frame mirrored as well and fuses the two passes' boxes (a box only one "
                     "pass finds keeps half its score; the held-out metrics above are without "
                     "it).\n")
        text += ("\n## Far band\n\nThe file's input height and width are free (`height`, "
                 "`width`): the edge runs the whole frame at the size above and, with "
                 "`--far-band`, the rows of a static camera's frame where far robots appear at "
                 "twice that scale (edge_agent/far_band.py; docs/models.md, \"The far "
                 "band\").\n")
        return text


@dataclasses.dataclass(frozen=True)
class KeypointCard(ModelCard):
    """``sigma_calibration``: confidence → RMS keypoint error in crop pixels, measured on the
    held-out sets (:func:`edge_agent.metrics.sigma_calibration`); empty: the edge sends no
    per-keypoint sigmas and the backend weights by confidence. ``flip_tta``: the model was
    trained on mirrored crops too and runs with test-time flip augmentation by default
    (:class:`KeypointEstimator`; a model trained without mirrors gets worse with it: the
    robot is not left/right symmetric)."""

    KIND: ClassVar[str] = "keypoints"
    crop_padding: float = CROP_PADDING
    sigma_calibration: dict[str, list[float]] = dataclasses.field(default_factory=dict)
    flip_tta: bool = False

    def __post_init__(self) -> None:
        cal = self.sigma_calibration
        if not cal:
            return
        try:
            xs = np.asarray(cal["confidence"], np.float64)
            ys = np.asarray(cal["sigma_crop_px"], np.float64)
        except (KeyError, TypeError, ValueError):
            raise ValueError("sigma_calibration needs lists 'confidence' and "
                             "'sigma_crop_px'") from None
        if (xs.ndim != 1 or xs.shape != ys.shape or not np.all(np.isfinite(xs))
                or not np.all(np.isfinite(ys)) or np.any(np.diff(xs) < 0) or np.any(ys <= 0)):
            raise ValueError("sigma_calibration: equal-length lists, confidences ascending, "
                             "sigmas > 0")

    def _sections(self) -> str:
        text = ""
        if self.flip_tta:
            text += ("\n## Test-time flip\n\nTrained on mirrored crops too (left/right keypoints "
                     "swapped); the edge runs each crop mirrored as well and averages the two "
                     "(the held-out metrics above are without it).\n")
        cal = self.sigma_calibration
        if not cal or not cal.get("confidence"):
            return text + ("\n## Keypoint uncertainty\n\nNot calibrated: the edge sends "
                           "confidences only.\n")
        rows = "\n".join(f"| {c:.3f} | {s:.2f} |" for c, s in
                         zip(cal["confidence"], cal["sigma_crop_px"], strict=True))
        return text + (
            "\n## Keypoint uncertainty\n\nPer-axis RMS keypoint error (crop pixels) by "
            "confidence through the deployed pipeline on the held-out sets; the edge sends "
            "sigma = this / crop scale (image pixels) with every keypoint and the backend "
            "weights keypoints by it (docs/pose_estimation.md).\n\n"
            "| confidence (bin median) | sigma (crop px) |\n|---|---|\n" + rows + "\n")


@dataclasses.dataclass(frozen=True)
class SegmentationCard(ModelCard):
    """The segmentation network's card: ``classes`` (the legend the output ids index; must be
    :data:`protocol.semantic_classes.SEMANTIC_CLASSES`), ``output_w`` x ``output_h`` the size of
    its class and confidence images. ``robot_model``/``keypoint_names``: the robot rendered
    in the training views (class ``robot``)."""

    KIND: ClassVar[str] = "segmentation"
    classes: list[str]
    output_w: int
    output_h: int

    def _model_lines(self) -> list[str]:
        return [f"- classes ({len(self.classes)}, ids in this order): {', '.join(self.classes)}",
                f"- input: {self.input_w}x{self.input_h} RGB float32 in [0, 1], NCHW "
                "(normalised inside the graph): the whole frame, resized",
                f"- output: {self.output_w}x{self.output_h} `class_ids` uint8 and `confidence` "
                "float32 (softmax probability of that class); output pixel (i, j) covers "
                "image pixel centre ((j + 0.5) W / w - 0.5, (i + 0.5) H / h - 0.5)",
                f"- robot in the renders: `{self.robot_model}`, mesh: "
                f"{self.training.get('robot_mesh', '?')}"]

    def _loss_lines(self) -> list[str]:
        weights = self.training.get("class_weights")
        if not weights:
            return []
        named = ", ".join(f"{name} {w:.2f}" for name, w in zip(self.classes, weights,
                                                                  strict=False) if w > 0)
        return ["- loss: cross-entropy weighted by sqrt(median frequency / class frequency) of "
                f"the training labels, clipped to [0.2, 5]: {named}"]

    def markdown(self) -> str:
        return super().markdown().replace(
            "max abs difference per output: class_ids",
            "share of pixels whose class differs: class_ids").replace(
            ", confidence", "; max abs difference: confidence")


# --------------------------------------------------------------------------------------------
# decoding (numpy; shared with the torch validation)
# --------------------------------------------------------------------------------------------


def decode_detections(peaks: np.ndarray, size: np.ndarray, offset: np.ndarray, stride: int,
                      min_score: float = 0.3, max_detections: int = 8) -> np.ndarray:
    """One image's detector outputs (peaks (1, h, w), size (2, h, w), offset (2, h, w)) →
    (n, 5) boxes ``x0, y0, x1, y1`` in input pixels (OpenCV centre convention) and score,
    best first."""
    heat = peaks[0]
    flat = heat.ravel()
    n = min(max_detections, flat.size)
    top = np.argpartition(-flat, n - 1)[:n] if n < flat.size else np.arange(flat.size)
    top = top[flat[top] >= min_score]
    top = top[np.argsort(-flat[top])]
    k, j = np.unravel_index(top, heat.shape)
    cx = (j + offset[0, k, j]) * stride - 0.5
    cy = (k + offset[1, k, j]) * stride - 0.5
    w, h = size[0, k, j], size[1, k, j]
    return np.stack([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2, flat[top]], axis=1)


# --------------------------------------------------------------------------------------------
# onnxruntime sessions
# --------------------------------------------------------------------------------------------


TENSORRT: Final = "TensorrtExecutionProvider"
CUDA: Final = "CUDAExecutionProvider"
CPU: Final = "CPUExecutionProvider"
#: the short names ``--providers`` accepts for onnxruntime's execution providers (onnxruntime's
#: own names, ``...ExecutionProvider``, are accepted as they are)
PROVIDER_ALIASES: Final = {"tensorrt": TENSORRT, "trt": TENSORRT, "cuda": CUDA, "cpu": CPU}
#: what a provider falls back to, in order, when it cannot run a node or cannot start
PROVIDER_FALLBACKS: Final = {TENSORRT: (CUDA, CPU), CUDA: (CPU,)}
#: ``auto``: the GPU providers this onnxruntime build has, else the CPU
AUTO_CHAIN: Final = (TENSORRT, CUDA, CPU)
#: where TensorRT engines are kept (default: ``$STATE_DIRECTORY/trt_engines``, which systemd sets
#: for the units' ``StateDirectory=``, else ``$XDG_CACHE_HOME/smartedge/trt_engines``)
ENGINE_CACHE_ENV: Final = "SMARTEDGE_TRT_CACHE"


def engine_cache_dir(environ: Mapping[str, str] | None = None) -> Path:
    """The TensorRT engine cache folder: ``$SMARTEDGE_TRT_CACHE``, else ``trt_engines`` in the
    service's state directory (``$STATE_DIRECTORY``, set by systemd's ``StateDirectory=``:
    ``/var/lib/smartedge`` in the shipped units), else ``$XDG_CACHE_HOME/smartedge/trt_engines``
    (``~/.cache/...`` without it). Not created here."""
    env = os.environ if environ is None else environ
    if env.get(ENGINE_CACHE_ENV):
        return Path(env[ENGINE_CACHE_ENV])
    state = env.get("STATE_DIRECTORY", "").split(":")[0]  # systemd joins several with ':'
    if state:
        return Path(state) / "trt_engines"
    base = env.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "smartedge" / "trt_engines"


def provider_names(spec: str | Sequence[str]) -> list[str]:
    """``--providers`` as onnxruntime names, in the order given: ``"tensorrt,cuda"`` or a list
    of names; short names (:data:`PROVIDER_ALIASES`, any case) or onnxruntime's
    (``...ExecutionProvider``). ``"auto"`` → ``["auto"]``. Raises ``ValueError`` naming an
    unknown name and the accepted ones."""
    items = spec.split(",") if isinstance(spec, str) else list(spec)
    names: list[str] = []
    for item in items:
        name = str(item).strip()
        if not name:
            continue
        if name.lower() == "auto":
            canonical = "auto"
        elif name.lower() in PROVIDER_ALIASES:
            canonical = PROVIDER_ALIASES[name.lower()]
        elif name.endswith("ExecutionProvider"):
            canonical = name
        else:
            raise ValueError(f"--providers: unknown execution provider {name!r} (use "
                             f"{', '.join(PROVIDER_ALIASES)}, auto, or onnxruntime's names "
                             "such as TensorrtExecutionProvider)")
        if canonical not in names:
            names.append(canonical)
    if "auto" in names and len(names) > 1:
        raise ValueError(f"--providers {spec!r}: auto stands alone")
    return names or ["auto"]


ProviderSpec = tuple[str, dict[str, str]]


@dataclasses.dataclass(frozen=True)
class ExecutionProviders:
    """The execution providers every network of an edge agent runs on (the detector, the
    keypoints and the segmentation get the same): ``asked`` the onnxruntime names asked for
    (``("auto",)`` for auto), ``chain`` what onnxruntime is handed, in order of preference, each
    with its options (only providers this onnxruntime build has; the CPU always last),
    ``missing`` the asked-for providers or fallbacks this build lacks, ``engine_cache``: the
    TensorRT engine folder (``None`` without TensorRT), ``fp16``: TensorRT builds FP16
    engines."""

    asked: tuple[str, ...]
    chain: tuple[ProviderSpec, ...]
    missing: tuple[str, ...] = ()
    engine_cache: Path | None = None
    fp16: bool = False

    @property
    def names(self) -> list[str]:
        return [name for name, _ in self.chain]

    def for_session(self) -> list[str | tuple[str, dict[str, str]]]:
        """The ``providers`` argument of ``onnxruntime.InferenceSession``."""
        return [(name, dict(opts)) if opts else name for name, opts in self.chain]

    def describe(self, got: Sequence[str]) -> str:
        """What a session ``got`` (its ``get_providers()``) against what was asked, for the
        log and the status: ``tensorrt+cuda+cpu`` or ``cpu (asked tensorrt; this onnxruntime
        lacks TensorrtExecutionProvider, CUDAExecutionProvider)``."""
        text = "+".join(short_provider_name(p) for p in got) or "none"
        if not self.fell_back(got):
            return text
        asked = ",".join(short_provider_name(p) for p in self.asked)
        why = f"; this onnxruntime lacks {', '.join(self.missing)}" if self.missing else \
            "; the provider failed to start (see the log above)"
        return f"{text} (asked {asked}{why})"

    def fell_back(self, got: Sequence[str]) -> bool:
        """Whether a session that ``got`` these providers runs on less than was asked: its
        first provider is not the first asked (``auto``: not the first this build offers)."""
        want = self.names[0] if self.asked == ("auto",) else self.asked[0]
        return not got or got[0] != want


def short_provider_name(name: str) -> str:
    """``TensorrtExecutionProvider`` → ``tensorrt``, ``CUDAExecutionProvider`` → ``cuda``."""
    for short, full in PROVIDER_ALIASES.items():
        if full == name and short != "trt":
            return short
    return name.removesuffix("ExecutionProvider").lower()


def execution_providers(spec: str | Sequence[str] = "auto", *, fp16: bool = False,
                        engine_cache: Path | str | None = None,
                        available: Sequence[str] | None = None) -> ExecutionProviders:
    """``--providers`` → the providers list onnxruntime gets, with options.

    Each asked name brings its fallbacks (:data:`PROVIDER_FALLBACKS`: TensorRT → CUDA → CPU,
    CUDA → CPU), the CPU always last; ``auto`` is :data:`AUTO_CHAIN`. Providers this build
    lacks (``available``: default ``onnxruntime.get_available_providers()``) are left out and
    listed in ``missing``. TensorRT gets its engine cache (``engine_cache``, default
    :func:`engine_cache_dir`; FP16 and FP32 engines in subfolders ``fp16`` / ``fp32``, created
    here) and timing cache enabled, and ``trt_fp16_enable`` from ``fp16``. Raises
    ``ValueError`` for an unknown name and :class:`ModelError` when the cache folder cannot
    be created."""
    asked = provider_names(spec)
    if available is None:
        import onnxruntime as ort

        available = ort.get_available_providers()
    have = set(available) | {CPU}
    wanted: list[str] = []
    for name in (AUTO_CHAIN if asked == ["auto"] else asked):
        for p in (name, *PROVIDER_FALLBACKS.get(name, ())):
            if p not in wanted:
                wanted.append(p)
    if CPU in wanted:
        wanted.remove(CPU)
    wanted.append(CPU)
    missing = tuple(p for p in wanted if p not in have and (asked != ["auto"] or p in asked))
    chain: list[ProviderSpec] = []
    cache: Path | None = None
    for name in wanted:
        if name not in have:
            continue
        opts: dict[str, str] = {}
        if name == TENSORRT:
            base = Path(engine_cache) if engine_cache is not None else engine_cache_dir()
            cache = base / ("fp16" if fp16 else "fp32")
            try:
                cache.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise ModelError(f"{cache}: cannot create the TensorRT engine cache: "
                                 f"{exc.strerror or exc}") from None
            opts = {"trt_engine_cache_enable": "True", "trt_engine_cache_path": str(cache),
                    "trt_timing_cache_enable": "True", "trt_timing_cache_path": str(base),
                    "trt_fp16_enable": "True" if fp16 else "False"}
        chain.append((name, opts))
    return ExecutionProviders(tuple(asked), tuple(chain), missing, cache, fp16)


def as_execution_providers(providers: ExecutionProviders | Sequence[Any] | None
                           ) -> ExecutionProviders:
    """``providers`` as given to the networks: an :class:`ExecutionProviders`, names (short or
    onnxruntime's, turned into one by :func:`execution_providers`), ``(name, options)`` pairs
    (taken as they are) or ``None`` (the CPU)."""
    if isinstance(providers, ExecutionProviders):
        return providers
    if not providers:
        return ExecutionProviders((CPU,), ((CPU, {}),))
    if all(isinstance(p, str) for p in providers):
        return execution_providers(list(providers))
    chain = tuple((p, {}) if isinstance(p, str) else (str(p[0]), dict(p[1])) for p in providers)
    return ExecutionProviders(tuple(n for n, _ in chain), chain)


def providers_available(prefer: Sequence[str] = AUTO_CHAIN) -> list[str]:
    """The preferred execution providers this onnxruntime build has (CPU always last)."""
    import onnxruntime as ort

    have = set(ort.get_available_providers())
    chosen = [p for p in prefer if p in have]
    return chosen or [CPU]


def _session(path: Path, threads: int, providers: ExecutionProviders | Sequence[Any] | None,
             spinning: bool = False, dims: Mapping[str, int] | None = None) -> Any:
    """An onnxruntime session of ``path``; ``dims``: sizes for the file's named (free)
    dimensions, which the session then treats as fixed (TensorRT builds one engine for them)."""
    import onnxruntime as ort

    if not path.is_file():
        raise ModelError(f"{path}: model file not found")
    chosen = as_execution_providers(providers)
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = max(1, int(threads))
    opts.inter_op_num_threads = 1
    opts.log_severity_level = 3
    if not spinning:  # idle intra-op threads sleep instead of spinning (few cores)
        opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    for name, size in (dims or {}).items():
        opts.add_free_dimension_override_by_name(name, int(size))
    t0 = time.perf_counter()
    try:
        sess = ort.InferenceSession(str(path), opts, providers=chosen.for_session())
    except Exception as exc:  # onnxruntime raises its own exception types for bad files
        raise ModelError(f"{path}: onnxruntime cannot load the model: "
                         f"{type(exc).__name__}: {str(exc).splitlines()[0][:200]}") from None
    got = list(sess.get_providers())
    if TENSORRT in got:  # the first start builds the engines: minutes on a Jetson
        log.info("%s: TensorRT session ready in %.1f s (engine cache %s)", path.name,
                 time.perf_counter() - t0, chosen.engine_cache)
    key = (chosen.asked, tuple(got))
    if key not in _REPORTED:  # once per process for each asked/got pair, not once per network
        _REPORTED.add(key)
        if chosen.fell_back(got):
            log.warning("onnxruntime runs %s on %s", path.name, chosen.describe(got))
        else:
            log.info("onnxruntime runs %s on %s", path.name, chosen.describe(got))
    return sess


_REPORTED: set[tuple[tuple[str, ...], tuple[str, ...]]] = set()


def _check_io(path: Path, sess: Any, inputs: Sequence[tuple[str, tuple[int, ...]]],
              outputs: Sequence[str]) -> None:
    got_in = [(i.name, tuple(i.shape[1:])) for i in sess.get_inputs()]
    want_in = [(n, s) for n, s in inputs]
    if got_in != want_in:
        raise ModelError(f"{path}: inputs {got_in} do not match the card ({want_in})")
    got_out = [o.name for o in sess.get_outputs()]
    if got_out != list(outputs):
        raise ModelError(f"{path}: outputs {got_out}, expected {list(outputs)}")


def card_path(onnx_path: Path) -> Path:
    """The model card beside an ONNX file (same name, ``.json``)."""
    return onnx_path.with_suffix(".json")


def reference_path(onnx_path: Path) -> Path:
    """The torch reference outputs beside an ONNX file (``<name>.reference.npz``: ``inputs``
    (N, H, W, 3) uint8, one array per output, and for the detector ``peaks_ambiguous``: cells
    at the peak test's tie threshold, which either runtime may decide either way), written by
    training for export checks."""
    return onnx_path.with_name(onnx_path.stem + ".reference.npz")


#: max abs difference between onnxruntime and torch's stored outputs, per output (export check);
#: for the segmentation's ``class_ids``: the share of pixels whose class differs (a pixel whose
#: two best classes tie within float noise may go either way)
EXPORT_TOLERANCE: Final = {"peaks": 1e-3, "size": 1e-2, "offset": 1e-3, "keypoints": 0.05,
                           "confidence": 1e-3, "class_ids": 1e-3}
#: A keypoint whose two best SimCC bins tie within float noise may have its decode window
#: centred one bin apart in two runtimes (seen: onnxruntime vs torch, 0.059 px). Such a
#: keypoint shows as a window mass (its confidence) that differs by more than float noise
#: (> 1e-4; elsewhere the two agree to < 5e-5); for it the bound is half a bin (0.25 px) and
#: 0.01 in confidence.
KEYPOINT_TIE_CONFIDENCE: Final = 1e-4
KEYPOINT_TIE_TOLERANCE: Final = {"keypoints": 0.25, "confidence": 1e-2}


def export_differences(want: dict[str, np.ndarray], got: dict[str, np.ndarray]
                       ) -> dict[str, float]:
    """Max abs difference of each output ``got`` (onnxruntime) from ``want`` (torch's stored
    reference, :func:`reference_path`), as a fraction of its tolerance: a value above 1 fails
    the export check. Cells the reference marks ambiguous (``peaks_ambiguous``: the detector's
    peak test at its tie threshold) are not compared; keypoints whose decode window may sit one
    bin apart (:data:`KEYPOINT_TIE_CONFIDENCE`) are held to :data:`KEYPOINT_TIE_TOLERANCE`.
    Segmentation ``class_ids`` are compared as the share of pixels that differ. Raises
    ``KeyError`` naming an output missing on either side."""
    got = dict(got)
    if "peaks_ambiguous" in want and "peaks" in got:
        got["peaks"] = np.where(want["peaks_ambiguous"], want["peaks"], got["peaks"])
    tie = None
    if "keypoints" in want and "confidence" in want and "confidence" in got:
        tie = np.abs(got["confidence"] - want["confidence"]) > KEYPOINT_TIE_CONFIDENCE
    ratios: dict[str, float] = {}
    for name, out in got.items():
        ref = want[name]
        if out.shape != ref.shape:
            ratios[name] = float("inf")
            continue
        if not ref.size:
            ratios[name] = 0.0
            continue
        if name == "class_ids":
            share = float(np.mean(np.asarray(out) != np.asarray(ref)))
            ratios[name] = share / EXPORT_TOLERANCE[name]
            continue
        diff = np.abs(out.astype(np.float64) - ref)
        if tie is not None and name in KEYPOINT_TIE_TOLERANCE:
            per = diff if diff.shape == tie.shape else diff.max(axis=-1)
            ratios[name] = max(
                float(np.max(per[~tie], initial=0.0)) / EXPORT_TOLERANCE[name],
                float(np.max(per[tie], initial=0.0)) / KEYPOINT_TIE_TOLERANCE[name])
        else:
            ratios[name] = float(np.max(diff)) / EXPORT_TOLERANCE.get(name, 1e-3)
    return ratios


#: a box of the frame and a box of its mirror image (mapped back) at least this IoU apart are
#: one robot (:func:`fuse_flipped_detections`)
FLIP_MATCH_IOU: Final = 0.5


def mirror_boxes(boxes: np.ndarray, width: int) -> np.ndarray:
    """(n, 5) boxes ``x0, y0, x1, y1, score`` of an image → those of its left/right mirror
    image ``width`` pixels wide (OpenCV centre convention: ``u -> width - 1 - u``)."""
    out = boxes.copy()
    out[:, 0] = width - 1 - boxes[:, 2]
    out[:, 2] = width - 1 - boxes[:, 0]
    return out


def fuse_flipped_detections(direct: np.ndarray, mirrored: np.ndarray, min_score: float,
                            max_detections: int, iou: float = FLIP_MATCH_IOU) -> np.ndarray:
    """The boxes of a frame (``direct``) and of its mirror image mapped back (``mirrored``),
    both (n, 5) ``x0, y0, x1, y1, score`` → one (m, 5) list, best first.

    Boxes are clustered greedily, highest score first, at ``iou``. A cluster's score is the
    mean of the two passes' best scores in it (0 for a pass that did not find it), its box the
    score-weighted mean of those two boxes. A box only one pass finds therefore keeps half its
    score: what the network sees in one orientation only (a wall corner that looks like a
    robot's side) falls below the floor, a robot both passes see keeps its score. The result
    does not depend on which pass is called direct, so the detections of a mirrored frame are
    the mirrored detections."""
    pool = np.concatenate([direct, mirrored]).reshape(-1, 5)
    source = np.repeat([0, 1], [len(direct), len(mirrored)])
    order = np.argsort(-pool[:, 4], kind="stable")
    pool, source = pool[order], source[order]
    near = iou_matrix(pool[:, :4]) >= iou
    used = np.zeros(len(pool), bool)
    fused: list[np.ndarray] = []
    for i in range(len(pool)):
        if used[i]:
            continue
        members = np.flatnonzero(near[i] & ~used)
        used[members] = True
        # each pass's highest-scoring box in the cluster (members are best first)
        firsts = [members[source[members] == p][0] for p in (0, 1)
                  if np.any(source[members] == p)]
        rows = pool[firsts]
        weights = rows[:, 4]
        box = (rows[:, :4] * weights[:, None]).sum(axis=0) / weights.sum()
        fused.append(np.append(box, weights.sum() / 2.0))
    out = np.array(fused).reshape(-1, 5)
    out = out[out[:, 4] >= min_score]
    return out[np.argsort(-out[:, 4], kind="stable")][:max_detections]


#: far-band sizes whose onnxruntime sessions a :class:`Detector` keeps (each holds its own
#: memory arena): a camera has one band; cameras of many poses (the randomized evaluation)
#: make a session per size, and the least recently used ones are let go
MAX_BAND_SESSIONS: Final = 4


class Detector:
    """The robot detector: full frame → boxes in frame pixels with scores.

    ``flip``: test-time flip augmentation (None: as the card's ``flip_tta`` says): each frame
    also runs mirrored (in the same batch) and the two passes' boxes are fused
    (:func:`fuse_flipped_detections`). It doubles the detector's work (1.5-3.3 ms more per
    frame on two x86 cores, ``smartedge bench edge``); on the paper lab's site cameras it raised
    the pipeline's AP@0.5 from 0.79-0.86 to 0.87-0.88, and the detector's boxes on views without
    a robot fell from 0.22-0.51 to 0.01 of them (docs/models.md).

    A frame given a :class:`~edge_agent.far_band.FarBand` also runs the band's rows at the
    band's scale (one run per band for all its frames, no flip) and those boxes join the whole
    frame's (:func:`merge_far_band_boxes`). That needs a file whose input height and width are
    free (named) dimensions, as ``smartedge train detector`` exports them; a file with a fixed
    input size runs without its far band (logged once, :attr:`runs_far_band`)."""

    def __init__(self, onnx_path: Path | str, *, threads: int = 2,
                 providers: ExecutionProviders | Sequence[Any] | None = None,
                 spinning: bool = False, flip: bool | None = None) -> None:
        self.path = Path(onnx_path)
        if not self.path.is_file():
            raise ModelError(f"{self.path}: detector model file not found")
        self.card = DetectorCard.read(card_path(self.path))
        self.flip = self.card.flip_tta if flip is None else bool(flip)
        self._session_args = (threads, providers, spinning)
        self.session = _session(self.path, threads, providers, spinning)
        shape = list(self.session.get_inputs()[0].shape)
        #: the file's names of its input's height and width, when they are free (else None)
        self.spatial_dims: tuple[str, str] | None = (
            (shape[2], shape[3]) if len(shape) == 4 and all(isinstance(d, str)
                                                            for d in shape[2:]) else None)
        if self.spatial_dims:  # the whole frame's session at the card's size, fixed
            self.session = self._session_at(self.card.input_h, self.card.input_w)
        self._band_sessions: dict[tuple[int, int], Any] = {}
        self._warned_band = False
        #: boxes the far band found that the whole frame did not, since start
        self.far_band_added = 0
        #: the execution providers the session runs on (``get_providers()``)
        self.providers_used: list[str] = list(self.session.get_providers())
        _check_io(self.path, self.session, [("image", (3, self.card.input_h, self.card.input_w))],
                  ["peaks", "size", "offset"])

    @property
    def runs_far_band(self) -> bool:
        """Whether the file's input size is free, so that a far band can run."""
        return self.spatial_dims is not None

    def _session_at(self, input_h: int, input_w: int) -> Any:
        assert self.spatial_dims is not None
        threads, providers, spinning = self._session_args
        return _session(self.path, threads, providers, spinning,
                        dims={self.spatial_dims[0]: input_h, self.spatial_dims[1]: input_w})

    def detect(self, image_rgb: np.ndarray, min_score: float = 0.3,
               max_detections: int = 8, far_band: FarBand | None = None) -> np.ndarray:
        """(n, 5) ``x0, y0, x1, y1, score`` in the frame's pixels, best first."""
        return self.detect_many([image_rgb], min_score, max_detections, [far_band])[0]

    def detect_many(self, images_rgb: Sequence[np.ndarray], min_score: float = 0.3,
                    max_detections: int = 8,
                    far_bands: Sequence[FarBand | None] | None = None) -> list[np.ndarray]:
        """:meth:`detect` of several frames (any sizes) in one network run (a batch);
        ``far_bands``: each frame's far band (None: none), a band applying only to frames of
        the size it was computed for."""
        c = self.card
        if not images_rgb:
            return []
        x = to_nchw(np.stack([resize_for_detector(im, c.input_w, c.input_h)
                              for im in images_rgb]))
        n = len(images_rgb)
        if self.flip:
            x = np.concatenate([x, x[..., ::-1]])  # the mirror images, as a batch after
        peaks, size, offset = self.session.run(None, {"image": x})
        out = []
        for i, image_rgb in enumerate(images_rgb):
            h, w = image_rgb.shape[:2]
            if self.flip:
                # each pass down to half the floor: a robot the other pass scores low is one
                # cluster, not a lone half-score box
                floor = min_score / 2.0
                direct = decode_detections(peaks[i], size[i], offset[i], c.stride, floor,
                                           2 * max_detections)
                mirrored = mirror_boxes(decode_detections(
                    peaks[n + i], size[n + i], offset[n + i], c.stride, floor,
                    2 * max_detections), c.input_w)
                boxes = fuse_flipped_detections(direct, mirrored, min_score, max_detections)
            else:
                boxes = decode_detections(peaks[i], size[i], offset[i], c.stride, min_score,
                                          max_detections)
            s = np.array([w / c.input_w, h / c.input_h] * 2)
            boxes[:, :4] = (boxes[:, :4] + 0.5) * s - 0.5
            out.append(boxes)
        if far_bands is not None and any(b is not None for b in far_bands):
            if len(far_bands) != n:
                raise ValueError(f"{len(far_bands)} far bands for {n} frames")
            self._add_far_bands(images_rgb, far_bands, out, min_score, max_detections)
        return out

    def _add_far_bands(self, images_rgb: Sequence[np.ndarray],
                       far_bands: Sequence[FarBand | None], out: list[np.ndarray],
                       min_score: float, max_detections: int) -> None:
        """Each far band's frames through the detector at the band's size (one batch per
        band), their boxes merged into ``out``."""
        if not self.runs_far_band:
            if not self._warned_band:
                log.warning("%s has a fixed input size: the far band does not run (export the "
                            "detector again with `smartedge train detector`, whose files have "
                            "a free input size)", self.path)
                self._warned_band = True
            return
        groups: dict[FarBand, list[int]] = {}
        for i, (image_rgb, band) in enumerate(zip(images_rgb, far_bands, strict=True)):
            h, w = image_rgb.shape[:2]
            if band is not None and band.applies_to(w, h):
                groups.setdefault(band, []).append(i)
        for band, index in groups.items():
            key = (band.input_h, band.input_w)
            session = self._band_sessions.pop(key, None) or self._session_at(*key)
            self._band_sessions[key] = session  # the most recently used last
            while len(self._band_sessions) > MAX_BAND_SESSIONS:
                self._band_sessions.pop(next(iter(self._band_sessions)))
            x = to_nchw(np.stack([resize_for_detector(images_rgb[i][band.v0:band.v1],
                                                      band.input_w, band.input_h)
                                  for i in index]))
            peaks, size, offset = session.run(None, {"image": x})
            for j, i in enumerate(index):
                boxes = decode_detections(peaks[j], size[j], offset[j], self.card.stride,
                                          min_score, max_detections)
                found = far_band_to_frame(boxes, band)
                out[i], added = merge_far_band_boxes(out[i], found, max_detections)
                self.far_band_added += added


#: a far-band box whose top lies this close to the band's upper edge (frame pixels), or whose
#: bottom lies this far below the lowest row of a far robot's feet, is a robot the band cuts:
#: the whole frame's
FAR_BAND_EDGE_PX: Final = 4.0


def far_band_to_frame(boxes: np.ndarray, band: FarBand) -> np.ndarray:
    """(n, 5) boxes in the far band's input pixels → those in frame pixels, less the boxes the
    band cuts: reaching up to its upper edge (where that is not the frame's), or down below the
    rows of a far robot's feet (``FarBand.feet_max_v``: a nearer robot, cut by the band's lower
    edge)."""
    out = boxes.copy()
    sx = band.frame_w / band.input_w
    sy = (band.v1 - band.v0) / band.input_h
    out[:, [0, 2]] = (boxes[:, [0, 2]] + 0.5) * sx - 0.5
    out[:, [1, 3]] = (boxes[:, [1, 3]] + 0.5) * sy - 0.5 + band.v0
    keep = out[:, 3] <= float(band.feet_max_v or band.v1) + FAR_BAND_EDGE_PX
    if band.v0 > 0:
        keep &= out[:, 1] > band.v0 - 0.5 + FAR_BAND_EDGE_PX
    return out[keep]


def merge_far_band_boxes(whole: np.ndarray, band: np.ndarray, max_detections: int,
                         iou: float = FLIP_MATCH_IOU) -> tuple[np.ndarray, int]:
    """The whole frame's boxes and the far band's (both (n, 5) in frame pixels, best first) →
    one list, best first, and how many boxes the band added. A band box on a robot the whole
    frame found (IoU >= ``iou`` with its box) makes one box with it: the score-weighted mean
    of the two boxes, scored as the higher of the two (the band sees the robot at twice the
    resolution; neither box is consistently the better one). A band box on no whole-frame
    box is added."""
    out = [row.copy() for row in whole.reshape(-1, 5)]
    matched = np.zeros(len(out), bool)
    added = 0
    for row in band.reshape(-1, 5):
        ious = [box_iou(row[:4], w[:4]) for w in out]
        j = int(np.argmax(ious)) if ious else -1
        if j >= 0 and ious[j] >= iou:
            if j < len(matched) and not matched[j]:  # one band box per whole-frame box
                w = out[j]
                weights = np.array([w[4], row[4]])
                box = (w[:4] * weights[0] + row[:4] * weights[1]) / weights.sum()
                out[j] = np.append(box, weights.max())
                matched[j] = True
            continue
        out.append(row.copy())
        added += 1
    merged = np.array(out).reshape(-1, 5)
    order = np.argsort(-merged[:, 4], kind="stable")[:max_detections]
    return merged[order], added


def mirror_permutation(keypoint_names: Sequence[str]) -> np.ndarray:
    """(K,) index of each keypoint's mirror partner under a left/right flip of the image:
    ``left`` and ``right`` swapped in the name (``front_left_top`` ↔ ``front_right_top``), a
    name with neither is its own partner. Raises :class:`ModelError` when a partner is
    missing (the robot's keypoints are not left/right paired)."""
    names = list(keypoint_names)
    index = {n: i for i, n in enumerate(names)}
    perm = np.arange(len(names))
    for i, name in enumerate(names):
        parts = name.split("_")
        if "left" not in parts and "right" not in parts:
            continue
        mirrored = "_".join({"left": "right", "right": "left"}.get(w, w) for w in parts)
        if mirrored not in index:
            raise ModelError(f"keypoint {name!r} has no mirror partner {mirrored!r} in "
                             f"{names}: flipping needs left/right pairs")
        perm[i] = index[mirrored]
    return perm


class KeypointEstimator:
    """The keypoint network: crops around boxes → keypoints in frame pixels + confidences.

    ``flip``: test-time flip augmentation (None: as the card's ``flip_tta`` says): each crop
    also runs mirrored (one batch of two), the mirrored result is mapped back
    (``u -> w - 1 - u``, each keypoint to its left/right partner, :func:`mirror_permutation`)
    and averaged with the direct one. It doubles the network's work; the result is exactly
    mirror-consistent (the estimate on a mirrored frame is the mirrored estimate)."""

    def __init__(self, onnx_path: Path | str, *, threads: int = 2,
                 providers: ExecutionProviders | Sequence[Any] | None = None,
                 spinning: bool = False, flip: bool | None = None) -> None:
        self.path = Path(onnx_path)
        if not self.path.is_file():
            raise ModelError(f"{self.path}: keypoint model file not found")
        self.card = KeypointCard.read(card_path(self.path))
        flip = self.card.flip_tta if flip is None else flip
        self.flip = flip
        self._mirror = mirror_permutation(self.card.keypoint_names) if flip else None
        self.session = _session(self.path, threads, providers, spinning)
        self.providers_used: list[str] = list(self.session.get_providers())
        _check_io(self.path, self.session, [("crop", (3, self.card.input_h, self.card.input_w))],
                  ["keypoints", "confidence"])

    @property
    def num_keypoints(self) -> int:
        return len(self.card.keypoint_names)

    @property
    def calibrated(self) -> bool:
        """Whether the card maps confidences to pixel sigmas."""
        return bool(self.card.sigma_calibration.get("confidence"))

    def estimate(self, image_rgb: np.ndarray, boxes_xyxy: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
        """(n, K, 2) keypoints in frame pixels and (n, K) confidences for (n, 4) boxes."""
        kp, conf, _ = self.estimate_with_sigma(image_rgb, boxes_xyxy)
        return kp, conf

    def estimate_with_sigma(self, image_rgb: np.ndarray, boxes_xyxy: np.ndarray
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """As :meth:`estimate`, plus (n, K) 1-sigma keypoint errors in frame pixels from the
        card's calibration (``None`` when the card has none)."""
        return self.estimate_many([image_rgb], [boxes_xyxy])[0]

    def estimate_many(self, images_rgb: Sequence[np.ndarray], boxes_xyxy: Sequence[np.ndarray]
                      ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray | None]]:
        """:meth:`estimate_with_sigma` of several frames, each with its (n_i, 4) boxes: the
        crops of all frames in one network run (a batch)."""
        c = self.card
        k = self.num_keypoints
        tfs = [[crop_transform(b[:4], c.input_w, c.input_h, padding=c.crop_padding)
                for b in boxes] for boxes in boxes_xyxy]
        crops = [extract_crop(image_rgb, tf, c.input_w, c.input_h)
                 for image_rgb, frame_tfs in zip(images_rgb, tfs, strict=True)
                 for tf in frame_tfs]
        if crops:
            kp_all, conf_all = self._run(np.stack(crops))
        out: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]] = []
        start = 0
        for frame_tfs in tfs:
            n = len(frame_tfs)
            if n == 0:
                out.append((np.zeros((0, k, 2)), np.zeros((0, k)),
                            np.zeros((0, k)) if self.calibrated else None))
                continue
            kp, conf = kp_all[start:start + n], conf_all[start:start + n]
            start += n
            kp_img = np.stack([tf.to_image(p) for tf, p in zip(frame_tfs, kp, strict=True)])
            conf = conf.astype(np.float64)
            sigma_crop = sigma_from_confidence(conf, c.sigma_calibration)
            if sigma_crop is None:
                out.append((kp_img, conf, None))
                continue
            scales = np.array([tf.scale for tf in frame_tfs])[:, None]  # crop px per image px
            out.append((kp_img, conf, sigma_crop / scales))
        return out

    def _run(self, crops: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(n, K, 2) crop-pixel keypoints and (n, K) confidences of (n, h, w, 3) crops."""
        if self._mirror is None:
            kp, conf = self.session.run(None, {"crop": to_nchw(crops)})
            return kp, conf
        n = len(crops)
        kp, conf = self.session.run(None, {"crop": to_nchw(np.concatenate(
            [crops, crops[:, :, ::-1]]))})
        kp_m = kp[n:][:, self._mirror].astype(np.float64)
        kp_m[..., 0] = self.card.input_w - 1 - kp_m[..., 0]
        conf_m = conf[n:][:, self._mirror]
        return (kp[:n] + kp_m) / 2.0, (conf[:n] + conf_m) / 2.0


@dataclasses.dataclass(frozen=True)
class RobotObservation:
    """One detected robot: ``bbox_xyxy`` and ``score`` from the detector, ``keypoints_px``
    (K, 2) raw frame pixels, ``confidence`` (K,), ``sigma_px`` (K,) calibrated 1-sigma errors
    in frame pixels (``None``: the keypoint model's card has no calibration); ``robot_model``:
    the site's robot model whose networks saw it (``""``: not known)."""

    bbox_xyxy: np.ndarray
    score: float
    keypoints_px: np.ndarray
    confidence: np.ndarray
    sigma_px: np.ndarray | None = None
    robot_model: str = ""


@dataclasses.dataclass
class StageTimes:
    detector_ms: float = 0.0
    keypoints_ms: float = 0.0


def model_files(folder: Path | str | None = None) -> tuple[Path, Path]:
    """(detector, keypoints) ONNX files of a model folder (default: the shipped models)."""
    base = Path(folder) if folder is not None else default_model_dir()
    if not base.is_dir():
        raise ModelError(f"{base}: model folder not found")
    return base / "detector.onnx", base / "keypoints.onnx"


#: a box whose keypoints the keypoint network finds with a mean confidence below this holds no
#: robot: the detector's false boxes (a wall corner of one site camera scored 0.3-0.57 in most
#: of its views) get 0.20-0.24, true boxes 0.29-0.96 (below 0.3: 5 of 650 true boxes on four
#: held-out sets, robots mostly hidden, whose keypoints carry sigmas of 30 px and more; above
#: it: 80 % of the false boxes removed; docs/models.md)
MIN_KEYPOINT_CONFIDENCE: Final = 0.3


class RobotKeypointPipeline:
    """Detector → crop → keypoints for one robot model.

    ``detector`` / ``keypoints``: ONNX files (each with its card beside it); default: the
    shipped models. ``keypoint_names``: the site's robot model's, checked against the keypoint
    model's card. ``providers``: onnxruntime execution providers in order of preference
    (default CPU). ``spinning``: let onnxruntime's idle threads spin (its default); off here,
    because on a 2-core board spinning threads starve the frame pre-processing (measured
    ~2x slower per frame, ``smartedge bench edge``). ``flip``: the keypoint network's
    test-time flip augmentation (:class:`KeypointEstimator`; None: as its card says).
    ``detector_flip``: the detector's (:class:`Detector`; None: as its card says).
    ``robot_model``: the site's model name put on every observation (``""``: none).
    ``min_keypoint_confidence``: a box whose keypoints' mean confidence is below this is not
    reported (:data:`MIN_KEYPOINT_CONFIDENCE`; counted in :attr:`unconfirmed`); only with a
    keypoint model whose card calibrates its confidence (``sigma_calibration``), else 0."""

    def __init__(self, detector: Path | str | None = None, keypoints: Path | str | None = None,
                 *, threads: int = 2,
                 providers: ExecutionProviders | Sequence[Any] | None = None,
                 keypoint_names: Sequence[str] | None = None, spinning: bool = False,
                 flip: bool | None = None, detector_flip: bool | None = None,
                 robot_model: str = "",
                 min_keypoint_confidence: float = MIN_KEYPOINT_CONFIDENCE) -> None:
        shipped = default_model_dir()
        self.robot_model = robot_model
        if not 0.0 <= min_keypoint_confidence < 1.0:
            raise ValueError(f"min_keypoint_confidence must lie in [0, 1), got "
                             f"{min_keypoint_confidence}")
        #: boxes dropped because the keypoint network found no robot in them, since start
        self.unconfirmed = 0
        #: what both networks were asked to run on (:func:`execution_providers`)
        self.execution = as_execution_providers(providers)
        self.providers = self.execution.names
        self.detector = Detector(shipped / "detector.onnx" if detector is None else detector,
                                 threads=threads, providers=self.execution, spinning=spinning,
                                 flip=detector_flip)
        self.keypoints = KeypointEstimator(
            shipped / "keypoints.onnx" if keypoints is None else keypoints, threads=threads,
            providers=self.execution, spinning=spinning, flip=flip)
        self.folder = self.keypoints.path.parent
        # a floor on a confidence means something only where the card calibrates it
        self.min_keypoint_confidence = (float(min_keypoint_confidence)
                                        if self.keypoints.calibrated else 0.0)
        kp_names = list(self.keypoints.card.keypoint_names)
        if keypoint_names is not None and list(keypoint_names) != kp_names:
            raise ModelError(
                f"{self.keypoints.path}: the model has {len(kp_names)} keypoints {kp_names}; "
                f"the site's robot model has {len(keypoint_names)} {list(keypoint_names)}")
        self.times = StageTimes()

    @classmethod
    def for_robot(cls, robot_model: Any, model_dir: Path | str | None = None,
                  **kwargs: Any) -> RobotKeypointPipeline:
        """The models of ``model_dir`` when given (a ``--model`` override), else those a
        site's :class:`core.site.RobotModel` names (default: shipped); checked against the
        robot model's keypoint names."""
        det, kp = (model_files(model_dir) if model_dir else
                   (robot_model.detector_onnx, robot_model.keypoints_onnx))
        kwargs.setdefault("robot_model", robot_model.name)
        return cls(det, kp, keypoint_names=robot_model.keypoint_names, **kwargs)

    @classmethod
    def from_folder(cls, folder: Path | str | None, **kwargs: Any) -> RobotKeypointPipeline:
        """The ``detector.onnx`` + ``keypoints.onnx`` of ``folder`` (default: shipped)."""
        det, kp = model_files(folder)
        return cls(det, kp, **kwargs)

    @property
    def model_id(self) -> str:
        return f"{self.keypoints.card.robot_model}/{self.folder.name}"

    @property
    def far_band_added(self) -> int:
        """Boxes the far band found that the whole frame did not, since start."""
        return self.detector.far_band_added

    @property
    def providers_used(self) -> list[str]:
        """The execution providers the detector's session runs on."""
        return self.detector.providers_used

    def providers_note(self) -> str:
        """What the networks run on against what was asked (:meth:`ExecutionProviders.describe`),
        for the status."""
        return self.execution.describe(self.providers_used)

    def __call__(self, image_rgb: np.ndarray, *, min_score: float = 0.3,
                 max_robots: int = 4, far_band: FarBand | None = None
                 ) -> list[RobotObservation]:
        return self.run_many([image_rgb], min_score=min_score, max_robots=max_robots,
                             far_bands=[far_band])[0]

    def run_many(self, images_rgb: Sequence[np.ndarray], *, min_score: float = 0.3,
                 max_robots: int = 4, far_bands: Sequence[FarBand | None] | None = None
                 ) -> list[list[RobotObservation]]:
        """The robots of several frames (e.g. the cameras of one capture), each network run
        once for all of them (a batch); what each frame gets is what it gets alone.
        ``far_bands``: each frame's camera's far band (:meth:`Detector.detect_many`).
        :attr:`times` holds the whole call's stage times."""
        for image_rgb in images_rgb:
            if image_rgb.ndim != 3 or image_rgb.shape[2] != 3 or image_rgb.dtype != np.uint8:
                raise ValueError(f"expected an (H, W, 3) uint8 RGB image, got "
                                 f"{image_rgb.shape} {image_rgb.dtype}")
        t0 = time.perf_counter()
        boxes = self.detector.detect_many(images_rgb, min_score, max_robots, far_bands)
        t1 = time.perf_counter()
        keypoints = self.keypoints.estimate_many(images_rgb, boxes)
        t2 = time.perf_counter()
        self.times = StageTimes((t1 - t0) * 1e3, (t2 - t1) * 1e3)
        out = []
        for frame_boxes, (kp, conf, sigma) in zip(boxes, keypoints, strict=True):
            found = []
            for i, b in enumerate(frame_boxes):
                obs = RobotObservation(b[:4].copy(), float(b[4]), kp[i], conf[i],
                                       None if sigma is None else sigma[i], self.robot_model)
                if type_evidence(obs)[0] < self.min_keypoint_confidence:
                    self.unconfirmed += 1
                    continue
                found.append(obs)
            out.append(found)
        return out


def type_evidence(obs: RobotObservation) -> tuple[float, float]:
    """How well one model's networks explain a box, for choosing between two types' boxes on
    one robot: the mean confidence of that model's keypoints in it, then the detector's score.
    A keypoint network shown another type's robot finds its keypoints with low confidence,
    while a detector trained without the other types may still score that robot high
    (measured on the two-type lab: ranking by confidence keeps the right type on 97 % of the
    HSR's views against 78 % by detector score; docs/models.md, "Several robot types")."""
    conf = np.nan_to_num(np.asarray(obs.confidence, np.float64), nan=0.0)
    mean = float(np.clip(conf, 0.0, 1.0).mean()) if conf.size else 0.0
    return mean, float(obs.score)


def suppress_across_models(found: Sequence[RobotObservation], iou: float, max_robots: int,
                           inside: float = 1.0) -> tuple[list[RobotObservation], int]:
    """The robots of one frame from several models' networks without the duplicates: boxes of
    two **different** models on one robot (:func:`same_robot` with ``iou`` and ``inside``)
    keep the one with the higher :func:`type_evidence` (boxes of one model were already
    suppressed by its own detector's decoding). Returns (kept, best evidence first, at most
    ``max_robots``; how many duplicates were dropped)."""
    kept: list[RobotObservation] = []  # sorted() is stable: equal evidence keeps input order
    dropped = 0
    for obs in sorted(found, key=type_evidence, reverse=True):
        if any(k.robot_model != obs.robot_model
               and same_robot(k.bbox_xyxy, obs.bbox_xyxy, iou, inside) for k in kept):
            dropped += 1
            continue
        kept.append(obs)
    return kept[:max_robots], dropped


#: on a site with several robot types, a box whose own keypoint network's mean confidence is
#: below this is not that type's robot: a single-class detector trained without the other
#: types may box them (the shipped HSR detector scored the box base 0.49-0.89 in 10 of 12
#: views, its keypoint network 0.27-0.46 there; true HSR boxes 0.89-0.95, and 5 % of them,
#: robots mostly hidden, below 0.5, whose keypoints carry sigmas of 24 px or more)
MIN_TYPE_CONFIDENCE: Final = 0.5


class RobotTypesPipeline:
    """Detector → crop → keypoints for every robot model (type) of a site: one
    :class:`RobotKeypointPipeline` per model (``pipelines``: model name → its pipeline, each
    with its own detector; the shipped detector is single-class), each model's keypoint network
    on that model's boxes, every observation tagged with its model. Boxes of two models on one
    robot (IoU >= ``nms_iou``, or the smaller at least ``nms_inside`` within the other) keep the
    one its own keypoint network is more confident of, then the higher detector score
    (:func:`suppress_across_models`, :func:`type_evidence`), the other counted in
    :attr:`duplicates_dropped`; a box whose own model's keypoints have a mean confidence
    below ``min_type_confidence`` (:data:`MIN_TYPE_CONFIDENCE`; models whose card calibrates
    the confidence) is not that model's robot (dropped, counted in :attr:`type_rejected`).
    The cost is the sum of the models' (measured in docs/models.md, "Several robot types").
    Same interface as :class:`RobotKeypointPipeline` where the edge pipeline uses it."""

    def __init__(self, pipelines: Mapping[str, RobotKeypointPipeline], *,
                 nms_iou: float = 0.5, nms_inside: float = 0.6,
                 min_type_confidence: float = MIN_TYPE_CONFIDENCE) -> None:
        if not pipelines:
            raise ModelError("RobotTypesPipeline: no robot models")
        if not 0.0 < nms_iou <= 1.0:
            raise ValueError(f"nms_iou must lie in (0, 1], got {nms_iou}")
        self.pipelines: dict[str, RobotKeypointPipeline] = dict(pipelines)
        for name, pipe in self.pipelines.items():
            pipe.robot_model = name
        if not 0.0 < nms_inside <= 1.0:
            raise ValueError(f"nms_inside must lie in (0, 1], got {nms_inside}")
        if not 0.0 <= min_type_confidence < 1.0:
            raise ValueError(f"min_type_confidence must lie in [0, 1), got "
                             f"{min_type_confidence}")
        self.nms_iou = float(nms_iou)
        self.nms_inside = float(nms_inside)
        self.min_type_confidence = float(min_type_confidence)
        #: boxes dropped because their own model's keypoints were not found (another type's
        #: robot, or a detector's false box), since start
        self.type_rejected = 0
        first = next(iter(self.pipelines.values()))
        self.execution = first.execution
        self.providers = first.providers
        self.times = StageTimes()
        #: boxes dropped as another model's duplicate, since start
        self.duplicates_dropped = 0

    @property
    def model_id(self) -> str:
        return "+".join(p.model_id for p in self.pipelines.values())

    @property
    def unconfirmed(self) -> int:
        """Boxes the models' own keypoint floors dropped (:attr:`RobotKeypointPipeline.
        unconfirmed`), since start."""
        return sum(p.unconfirmed for p in self.pipelines.values())

    @property
    def far_band_added(self) -> int:
        """Boxes the models' far bands found that their whole frames did not, since start."""
        return sum(p.far_band_added for p in self.pipelines.values())

    @property
    def providers_used(self) -> list[str]:
        return next(iter(self.pipelines.values())).providers_used

    def providers_note(self) -> str:
        return next(iter(self.pipelines.values())).providers_note()

    def describe(self) -> str:
        """One line per model: its name and model files (for the log)."""
        return "; ".join(f"{name}: {p.detector.path} + {p.keypoints.path}"
                         for name, p in self.pipelines.items())

    def __call__(self, image_rgb: np.ndarray, *, min_score: float = 0.3,
                 max_robots: int = 4, far_band: FarBand | None = None
                 ) -> list[RobotObservation]:
        return self.run_many([image_rgb], min_score=min_score, max_robots=max_robots,
                             far_bands=[far_band])[0]

    def run_many(self, images_rgb: Sequence[np.ndarray], *, min_score: float = 0.3,
                 max_robots: int = 4, far_bands: Sequence[FarBand | None] | None = None
                 ) -> list[list[RobotObservation]]:
        """The robots of several frames through every model's networks (each a batch), the
        duplicates across models removed; :attr:`times` sums the models' stage times."""
        merged: list[list[RobotObservation]] = [[] for _ in images_rgb]
        det_ms = kp_ms = 0.0
        for pipe in self.pipelines.values():
            per_frame = pipe.run_many(images_rgb, min_score=min_score, max_robots=max_robots,
                                      far_bands=far_bands)
            det_ms += pipe.times.detector_ms
            kp_ms += pipe.times.keypoints_ms
            # as the pipeline's own floor: only a calibrated confidence is a measure
            floor = self.min_type_confidence if pipe.keypoints.calibrated else 0.0
            for out, found in zip(merged, per_frame, strict=True):
                for obs in found:
                    if type_evidence(obs)[0] < floor:
                        self.type_rejected += 1
                        continue
                    out.append(obs)
        self.times = StageTimes(det_ms, kp_ms)
        result = []
        for found in merged:
            kept, dropped = suppress_across_models(found, self.nms_iou, max_robots,
                                                   self.nms_inside)
            if dropped:
                self.duplicates_dropped += dropped
                log.debug("dropped %d duplicate box(es) of another robot model", dropped)
            result.append(kept)
        return result


def models_for_site(site: Any, model_dir: Path | str | None = None, *,
                    robot_ids: Sequence[str] | None = None, nms_iou: float = 0.5,
                    **kwargs: Any) -> RobotKeypointPipeline | RobotTypesPipeline:
    """The edge's networks for the robots of ``site`` (a :class:`core.site.Site`;
    ``robot_ids``: only these robots' models, default all): the models of a site with one robot
    model (``model_dir`` overrides its files, the ``--model`` option), a
    :class:`RobotTypesPipeline` over each model's files (``robot_models.<name>.models``; none:
    the shipped models, which fit only the built-in HSR's keypoints) when there are several.
    ``kwargs`` go to every :class:`RobotKeypointPipeline`. Raises :class:`ModelError` naming the
    robot model whose files are missing or do not fit."""
    ids = list(site.robots) if robot_ids is None else list(robot_ids)
    names: list[str] = []
    for rid in ids:
        name = site.robots[rid]
        if name not in names:
            names.append(name)
    if not names:
        raise ModelError(f"site {site.name!r}: no robots, so no robot models to run")
    if len(names) == 1:
        return RobotKeypointPipeline.for_robot(site.robot_models[names[0]], model_dir, **kwargs)
    if model_dir:
        raise ModelError(f"site {site.name!r} has {len(names)} robot models {names}: one model "
                         "folder (--model) cannot serve them; name each model's files under "
                         "robot_models.<name>.models in the site file")
    pipelines: dict[str, RobotKeypointPipeline] = {}
    for name in names:
        model = site.robot_models[name]
        try:
            pipelines[name] = RobotKeypointPipeline.for_robot(model, None, **kwargs)
        except ModelError as exc:
            hint = ("" if model.keypoints_onnx is not None else
                    f" (no robot_models.{name}.models in the site file: the shipped models "
                    "are the built-in HSR's)")
            raise ModelError(f"robot model {name!r} of site {site.name!r}: {exc}{hint}"
                             ) from None
    return RobotTypesPipeline(pipelines, nms_iou=nms_iou)


# --------------------------------------------------------------------------------------------
# semantic segmentation
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Segmentation:
    """One segmented image. ``class_ids`` (h, w) uint8 ids of
    :data:`protocol.semantic_classes.SEMANTIC_CLASSES`; ``confidence`` (h, w) float32 in
    [0, 1], the softmax probability of that class; ``image_width`` x ``image_height`` (W, H):
    the image that was segmented. Output pixel ``(i, j)`` covers the image pixel centre
    ``((j + 0.5) * W / w - 0.5, (i + 0.5) * H / h - 0.5)`` (OpenCV convention: pixel centres
    at integer coordinates); ``infer_ms``: resize + network, milliseconds."""

    class_ids: np.ndarray
    confidence: np.ndarray
    image_width: int
    image_height: int
    infer_ms: float

    def image_pixels(self) -> tuple[np.ndarray, np.ndarray]:
        """(h, w) image x and y (pixels, OpenCV convention) of every output pixel's centre."""
        h, w = self.class_ids.shape
        x = (np.arange(w) + 0.5) * (self.image_width / w) - 0.5
        y = (np.arange(h) + 0.5) * (self.image_height / h) - 0.5
        return np.broadcast_to(x[None], (h, w)), np.broadcast_to(y[:, None], (h, w))


class SemanticSegmenter:
    """The segmentation network: a whole frame → per-pixel classes and confidences.

    ``onnx_path``: the model (its :class:`SegmentationCard` beside it); ``None``: the shipped
    ``edge_agent/models/segmentation.onnx``. ``threads``: onnxruntime intra-op threads;
    ``providers``: execution providers in order of preference (default CPU; names or an
    :class:`ExecutionProviders`, the same the detector gets). A missing, corrupt
    or truncated model, a missing or wrong card, a card whose classes are not
    :data:`protocol.semantic_classes.SEMANTIC_CLASSES` and a graph whose input or output size is
    not the card's raise :class:`ModelError` naming the file."""

    def __init__(self, onnx_path: Path | str | None = None, *, threads: int = 2,
                 providers: ExecutionProviders | Sequence[Any] | None = None) -> None:
        self.path = Path(onnx_path) if onnx_path is not None else (
            default_model_dir() / "segmentation.onnx")
        if not self.path.is_file():
            raise ModelError(f"{self.path}: segmentation model file not found")
        card = SegmentationCard.read(card_path(self.path))
        if list(card.classes) != list(SEMANTIC_CLASSES):
            raise ModelError(f"{card_path(self.path)}: the model's classes {card.classes} are not "
                             f"smartedge's legend {list(SEMANTIC_CLASSES)} "
                             "(protocol.semantic_classes); retrain it")
        self.card = card
        self.execution = as_execution_providers(providers)
        self.session = _session(self.path, threads, self.execution)
        self.providers_used: list[str] = list(self.session.get_providers())
        _check_io(self.path, self.session, [("image", (3, card.input_h, card.input_w))],
                  ["class_ids", "confidence"])
        for out in self.session.get_outputs():
            if tuple(out.shape[1:]) != (card.output_h, card.output_w):
                raise ModelError(f"{self.path}: output {out.name} of shape {out.shape[1:]}, the "
                                 f"card says {card.output_h}x{card.output_w} (h x w)")

    @property
    def model_id(self) -> str:
        """Which model this is (provenance): ``segmentation/<its folder's name>``."""
        return f"{self.card.KIND}/{self.path.parent.name}"

    def __call__(self, image_rgb: np.ndarray) -> Segmentation:
        """Segment an (H, W, 3) uint8 RGB image of any size (resized to the network's input
        inside); raises ``ValueError`` for anything else."""
        if (not isinstance(image_rgb, np.ndarray) or image_rgb.ndim != 3
                or image_rgb.shape[2] != 3 or image_rgb.dtype != np.uint8
                or min(image_rgb.shape[:2]) < 1):
            got = (f"{image_rgb.shape} {image_rgb.dtype}" if isinstance(image_rgb, np.ndarray)
                   else type(image_rgb).__name__)
            raise ValueError(f"expected an (H, W, 3) uint8 RGB image, got {got}")
        c = self.card
        h, w = image_rgb.shape[:2]
        t0 = time.perf_counter()
        x = to_nchw(resize_for_detector(image_rgb, c.input_w, c.input_h))
        class_ids, confidence = self.session.run(None, {"image": x})
        infer_ms = (time.perf_counter() - t0) * 1e3
        return Segmentation(class_ids[0].astype(np.uint8, copy=False),
                            np.clip(confidence[0], 0.0, 1.0).astype(np.float32, copy=False),
                            int(w), int(h), infer_ms)
