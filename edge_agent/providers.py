"""Where the edge's networks run: onnxruntime execution providers (TensorRT, CUDA, the CPU),
their fallbacks and engine cache, and the sessions opened on them (:func:`open_session`, the
graph's inputs and outputs checked against the model card).
"""

from __future__ import annotations

import dataclasses
import logging
import os
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Final

from edge_agent.model_cards import ModelError

log = logging.getLogger(__name__)

#: an execution provider with its options, as onnxruntime takes it
ProviderSpec = tuple[str, dict[str, str]]

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


def open_session(path: Path, threads: int, providers: ExecutionProviders | Sequence[Any] | None,
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
    if key not in REPORTED_FALLBACKS:  # once per process per asked/got pair, not per network
        REPORTED_FALLBACKS.add(key)
        if chosen.fell_back(got):
            log.warning("onnxruntime runs %s on %s", path.name, chosen.describe(got))
        else:
            log.info("onnxruntime runs %s on %s", path.name, chosen.describe(got))
    return sess


REPORTED_FALLBACKS: set[tuple[tuple[str, ...], tuple[str, ...]]] = set()


def check_io(path: Path, sess: Any, inputs: Sequence[tuple[str, tuple[int, ...]]],
              outputs: Sequence[str]) -> None:
    got_in = [(i.name, tuple(i.shape[1:])) for i in sess.get_inputs()]
    want_in = [(n, s) for n, s in inputs]
    if got_in != want_in:
        raise ModelError(f"{path}: inputs {got_in} do not match the card ({want_in})")
    got_out = [o.name for o in sess.get_outputs()]
    if got_out != list(outputs):
        raise ModelError(f"{path}: outputs {got_out}, expected {list(outputs)}")
