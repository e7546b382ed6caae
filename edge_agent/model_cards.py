"""Model cards: what an ONNX model of the edge is (no torch, no onnxruntime).

A model is an ONNX file with its card beside it (same name, ``.json``: :class:`DetectorCard` /
:class:`KeypointCard` / :class:`SegmentationCard`: input size, robot model and keypoint names,
the segmentation's classes and output size, training record, held-out metrics, the figures
measured through the deployed pipeline); ``.md`` is the same card for people and
``.reference.npz`` holds torch's outputs on fixed inputs (:func:`export_differences`, the export
check). The shipped models for the built-in robot live in ``edge_agent/models/``
(:func:`default_model_dir`); a site file's robot model may name others.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
from typing import Any, ClassVar, Final

import numpy as np

from edge_agent.crop import CROP_PADDING
from protocol.errors import SmartedgeError

CARD_VERSION: Final = 1
KINDS: Final = ("detector", "keypoints", "segmentation")


class ModelError(SmartedgeError):
    """A model file or card is missing, corrupt or does not fit the site's robot model."""


def usable_cores() -> int:
    """The CPU cores this process may run on (its affinity where the OS says, else all)."""

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


def model_files(folder: Path | str | None = None) -> tuple[Path, Path]:
    """(detector, keypoints) ONNX files of a model folder (default: the shipped models)."""
    base = Path(folder) if folder is not None else default_model_dir()
    if not base.is_dir():
        raise ModelError(f"{base}: model folder not found")
    return base / "detector.onnx", base / "keypoints.onnx"
