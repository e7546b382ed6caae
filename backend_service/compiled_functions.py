"""CasADi functions compiled to C once per machine, kept on disk, built in the background.

:func:`compiled` turns a :class:`casadi.Function` (built by ``build`` on first use) into a
loaded shared library: the C source is generated at once (milliseconds), the compiler runs in a
background thread at low priority (a second or two), and the library is kept in a cache
directory named by the hash of its source, compiler flags and CasADi version
(:data:`KERNEL_CACHE_ENV`, default ``$XDG_CACHE_HOME/smartedge/pose_kernels``), so the next
process only loads it. A library is used only after it gave CasADi's virtual machine's numbers
at a test point. Until it is ready, and for good with no compiler, a failed build, an
unwritable cache or :data:`JIT_ENV` = ``"0"``, callers get ``None`` and evaluate the virtual
machine: a build never stalls a caller. :mod:`backend_service.pose_solver` uses it for its
per-camera kernels.

Deployment: the backend's systemd unit points :data:`KERNEL_CACHE_ENV` at its state directory
(deploy/); without a C compiler on the host the backend runs exactly as before, only slower at
many cameras.
"""

from __future__ import annotations

import hashlib
import logging
import os
import shutil
import subprocess
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Final

import casadi as ca
import numpy as np

log = logging.getLogger(__name__)

#: ``"0"`` turns the compiled kernel off (CasADi's virtual machine only, as before).
JIT_ENV: Final = "SMARTEDGE_POSE_JIT"
#: Where compiled kernels are kept (default: ``$XDG_CACHE_HOME/smartedge/pose_kernels``,
#: ``~/.cache/...`` without it).
KERNEL_CACHE_ENV: Final = "SMARTEDGE_KERNEL_CACHE"
_CC_FLAGS: Final = ("-O2", "-shared", "-fPIC")
_COMPILE_TIMEOUT_S: Final = 120.0
_KERNEL_LOCK: Final = threading.Lock()


def _kernel_cache_dir() -> Path:
    configured = os.environ.get(KERNEL_CACHE_ENV)
    if configured:
        return Path(configured)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "smartedge" / "pose_kernels"


class _KernelBuild:
    """One kernel's way to a loaded library: the C source is generated at once (milliseconds),
    the compiler runs in a background thread (a second or two; it touches no CasADi object),
    and the library is loaded and checked against the virtual machine by the next caller
    that finds it built. Until then, and for good after a failure, the kernel is ``None``
    and the virtual machine evaluates the problem: a build never stalls a solve."""

    def __init__(self, reference: ca.Function) -> None:
        self.reference = reference
        self.function: ca.Function | None = None
        self.done = False  # loaded, or given up
        self._library: Path | None = None
        self._thread: threading.Thread | None = None
        self._failed = False
        self._start()

    def _start(self) -> None:
        name = self.reference.name()
        compiler = shutil.which(os.environ.get("CC", "cc")) or shutil.which("gcc")
        if compiler is None:
            log.info("pose solver: no C compiler found; CasADi's virtual machine evaluates "
                     "the pose problem")
            self.done = True
            return
        try:
            cache = _kernel_cache_dir()
            cache.mkdir(parents=True, exist_ok=True)
            tmp = Path(tempfile.mkdtemp(dir=cache, prefix=".build-"))
            gen = ca.CodeGenerator(f"{name}.c", {"with_header": False})
            gen.add(self.reference)
            source = Path(gen.generate(str(tmp) + os.sep))
        except (OSError, RuntimeError) as exc:
            self._give_up(exc)
            return
        digest = hashlib.blake2b(
            source.read_bytes() + " ".join(_CC_FLAGS).encode() + ca.__version__.encode(),
            digest_size=10).hexdigest()
        self._library = cache / f"{name}_{digest}.so"
        if self._library.exists():
            shutil.rmtree(tmp, ignore_errors=True)
            return
        self._thread = threading.Thread(target=self._build, args=(compiler, source, tmp),
                                        name=f"compile-{name}", daemon=True)
        self._thread.start()

    def _build(self, compiler: str, source: Path, tmp: Path) -> None:
        """The background thread: the compiler and the file system only, no CasADi call."""
        assert self._library is not None
        started = time.perf_counter()
        try:
            built = tmp / self._library.name
            # at low priority: the solves it is meant to speed up come first
            nice = shutil.which("nice")
            subprocess.run([*([nice, "-n", "15"] if nice else []), compiler, *_CC_FLAGS,
                            str(source), "-o", str(built), "-lm"],
                           check=True, capture_output=True, timeout=_COMPILE_TIMEOUT_S)
            os.replace(built, self._library)  # atomic: another process sees all or nothing
            log.info("pose solver: compiled %s in %.1f s", self._library,
                     time.perf_counter() - started)
        except (OSError, subprocess.SubprocessError) as exc:
            self._failed = True
            self._give_up(exc, self._library.name)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)

    def _give_up(self, exc: BaseException, what: str | None = None) -> None:
        detail = getattr(exc, "stderr", b"") or b""
        log.warning("pose solver: compiling %s failed (%s%s); CasADi's virtual machine "
                    "evaluates the pose problem", what or self.reference.name(), exc,
                    f": {detail.decode(errors='replace')[:300]}" if detail else "")
        self.done = True

    def poll(self, wait: bool) -> ca.Function | None:
        """The kernel if its library is loaded (loading and checking it now if it has just
        been built; ``wait``: block until the build ends), else ``None``."""
        if self.done:
            return self.function
        if self._thread is not None:
            if wait:
                self._thread.join()
            if self._thread.is_alive():
                return None
        if self._failed or self._library is None:
            self.done = True
            return None
        self.done = True
        try:
            compiled = ca.external(self.reference.name(), str(self._library))
        except RuntimeError as exc:
            self._give_up(exc)
            return None
        if _same_numbers(self.reference, compiled):
            self.function = compiled
        else:
            log.warning("pose solver: the compiled %s disagrees with CasADi's virtual "
                        "machine; not used", self.reference.name())
        return self.function


def _same_numbers(reference: ca.Function, compiled: ca.Function) -> bool:
    """Both functions agree (1e-9 relative) at a fixed test point: a plausible camera in
    front of random keypoints, random pose, pixels and weights."""
    rng = np.random.default_rng(0)
    camera = np.concatenate([[400.0, 0.5, 320.0, 410.0, 240.0],
                             [-0.05, 0.06, 1e-3, -1e-3, -0.02, 0.01, -0.02, 0.005],
                             np.eye(3).reshape(-1), [0.1, -0.2, 4.0]])
    args = []
    for name in reference.name_in():
        size = reference.size1_in(name)
        args.append(camera if name == "camera" else
                    rng.uniform(100.0, 400.0, size) if name == "uv" else
                    rng.uniform(0.2, 1.0, size) if name == "w" else
                    np.array([5.0]) if name == "c" else rng.normal(0.0, 0.3, size))
    for want, got in zip(reference.call(args), compiled.call(args), strict=True):
        want, got = np.asarray(want), np.asarray(got)
        if not (np.all(np.isfinite(want)) and
                np.allclose(got, want, rtol=1e-9, atol=1e-9 * float(np.abs(want).max()))):
            return False
    return True


_KERNELS: dict[tuple, _KernelBuild | None] = {}


def _kernel(key: tuple, build: Callable[[], ca.Function], wait: bool
            ) -> tuple[ca.Function | None, bool]:
    """(the kernel or ``None``, whether that is final: loaded, or never going to be)."""
    with _KERNEL_LOCK:
        if key not in _KERNELS:
            off = os.environ.get(JIT_ENV, "1").strip() == "0"
            _KERNELS[key] = None if off else _KernelBuild(build())
        entry = _KERNELS[key]
        if entry is None:
            return None, True
        return entry.poll(wait), entry.done


def compiled(key: tuple, build: Callable[[], ca.Function], wait: bool = False
             ) -> tuple[ca.Function | None, bool]:
    """The compiled library of the function ``build()`` returns, under ``key`` (one build per
    key and process), and whether that answer is final (loaded, or never going to be);
    ``wait``: block until a build in progress ends."""
    return _kernel(key, build, wait)


def forget_compiled_kernels() -> None:
    """Forget the loaded kernels (as in a new process; their libraries stay on disk)."""
    with _KERNEL_LOCK:
        _KERNELS.clear()
