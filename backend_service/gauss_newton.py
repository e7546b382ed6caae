"""The damped Gauss-Newton (Levenberg-Marquardt) loop of the pose solver's default method:
Marquardt's diagonal scaling and Nielsen's gain-ratio damping, run from Python on ONE CasADi
function that returns the cost, the gradient and the normal matrix (bound to preallocated numpy
buffers), with closed-form Cholesky solves of the 3x3 / 6x6 systems.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Final

import casadi as ca
import numpy as np

#: Stopping rules of the ``gauss_newton`` method. ``GN_XTOL``: the estimated remaining error
#: of q (metres / radians), relative to |q|, from the step norm and the observed contraction
#: of successive steps (exact for linear convergence, conservative for Gauss-Newton's faster
#: convergence on small residuals; robust losses and gross outliers converge only linearly).
#: ``GN_FTOL``: relative cost decrease of an accepted step at rounding-noise level (nothing
#: left to gain). ``GN_GTOL``: gradient max-norm in px^2 per metre/radian.
GN_XTOL: Final = 1e-10
GN_FTOL: Final = 1e-15
GN_GTOL: Final = 1e-9


@dataclasses.dataclass(frozen=True)
class SolveOutput:
    """Result of one solve: ``q`` the parameters ((3,) or (6,)), ``success`` as reported by the
    solver, ``iterations``, ``cost`` the final objective value (px^2)."""

    q: np.ndarray
    success: bool
    iterations: int
    cost: float


def _cholesky_solve(a_upper: list[float], diag_idx: tuple[int, ...], lam: float,
                    rhs: list[float]) -> list[float] | None:
    """Solve ``(A + lam diag(A)) x = rhs`` for symmetric ``A`` given as its upper triangle
    (row-major). Plain Python floats: for n <= 6 this is several times cheaper than a numpy
    call. ``None`` if the damped matrix is not positive definite."""
    n = len(rhs)
    if n == 3:
        return _cholesky_solve3(a_upper, lam, rhs)
    A = [[0.0] * n for _ in range(n)]
    k = 0
    for i in range(n):
        for j in range(i, n):
            A[i][j] = A[j][i] = a_upper[k]
            k += 1
    for i in range(n):
        A[i][i] += lam * max(a_upper[diag_idx[i]], 1e-300)
    L = [[0.0] * n for _ in range(n)]
    for j in range(n):
        d = A[j][j] - sum(L[j][m] * L[j][m] for m in range(j))
        if not d > 0.0 or not math.isfinite(d):
            return None
        L[j][j] = math.sqrt(d)
        for i in range(j + 1, n):
            L[i][j] = (A[i][j] - sum(L[i][m] * L[j][m] for m in range(j))) / L[j][j]
    y = [0.0] * n
    for i in range(n):
        y[i] = (rhs[i] - sum(L[i][m] * y[m] for m in range(i))) / L[i][i]
    x = [0.0] * n
    for i in reversed(range(n)):
        x[i] = (y[i] - sum(L[m][i] * x[m] for m in range(i + 1, n))) / L[i][i]
    return x


def _cholesky_solve3(a: list[float], lam: float, b: list[float]) -> list[float] | None:
    """:func:`_cholesky_solve` unrolled for the planar problem (the hot path)."""
    a00, a01, a02, a11, a12, a22 = a
    a00 += lam * max(a00, 1e-300)
    a11 += lam * max(a11, 1e-300)
    a22 += lam * max(a22, 1e-300)
    if not a00 > 0.0:
        return None
    l00 = math.sqrt(a00)
    l10 = a01 / l00
    l20 = a02 / l00
    d1 = a11 - l10 * l10
    if not d1 > 0.0:
        return None
    l11 = math.sqrt(d1)
    l21 = (a12 - l20 * l10) / l11
    d2 = a22 - l20 * l20 - l21 * l21
    if not d2 > 0.0 or not math.isfinite(d2):
        return None
    l22 = math.sqrt(d2)
    y0 = b[0] / l00
    y1 = (b[1] - l10 * y0) / l11
    y2 = (b[2] - l20 * y0 - l21 * y1) / l22
    x2 = y2 / l22
    x1 = (y1 - l21 * x2) / l11
    return [(y0 - l10 * x1 - l20 * x2) / l00, x1, x2]


class GaussNewtonKernel:
    """The normal-equations :class:`casadi.Function` bound to preallocated numpy buffers.

    :meth:`casadi.Function.buffer` evaluates straight from/into numpy memory: no DM
    conversion, no argument checking, which is most of the cost of ``f(q, p)`` on this small
    function. Not thread-safe (shared buffers), like the rest of a :class:`PoseProblem`.
    """

    def __init__(self, function: ca.Function) -> None:
        self.function = function
        self.dof = int(function.size1_in(0))
        self.num_params = int(function.size1_in(1))
        self._q = np.zeros(self.dof)
        self._p = np.zeros(self.num_params)
        self._out = np.zeros(int(function.size1_out(0)))
        self._buffer, self._eval = function.buffer()
        self._buffer.set_arg(0, memoryview(self._q))
        self._buffer.set_arg(1, memoryview(self._p))
        self._buffer.set_res(0, memoryview(self._out))
        n = self.dof
        # index of H[i, i] in the row-major upper triangle, offset by cost and gradient
        self._diag = tuple(i * n - i * (i - 1) // 2 for i in range(n))

    def evaluate(self, q: Sequence[float]) -> tuple[float, list[float], list[float]]:
        """(cost, gradient, normal-matrix upper triangle) at ``q`` for the bound parameters."""
        self._q[:] = q
        self._eval()
        out = self._out.tolist()
        n = self.dof
        return out[0], out[1:1 + n], out[1 + n:]

    def solve(self, q0: np.ndarray, p: np.ndarray, max_iterations: int) -> SolveOutput:
        """Levenberg-Marquardt (Marquardt's diagonal scaling, Nielsen's gain-ratio update of
        the damping) from ``q0``; stops on :data:`GN_GTOL`, :data:`GN_XTOL`, :data:`GN_FTOL`
        or ``max_iterations`` evaluations."""
        self._p[:] = p
        q = [float(v) for v in q0]
        cost, g, h = self.evaluate(q)
        if not math.isfinite(cost):
            return SolveOutput(np.asarray(q), False, 0, cost)
        lam = 1e-8  # with Marquardt scaling: (almost) a pure Gauss-Newton first step
        prev_step = 0.0
        success = False
        it = 0
        while it < max_iterations:
            if max(abs(v) for v in g) <= GN_GTOL:
                success = True
                break
            dq = _cholesky_solve(h, self._diag, lam, [-v for v in g])
            if dq is None:
                prev_step = 0.0
                lam = max(10.0 * lam, 1e-3)
                if lam > 1e16:
                    break
                continue
            step = math.sqrt(sum(v * v for v in dq))
            # error left after taking dq: step * theta / (1 - theta) for a contraction theta
            # per iteration, estimated from the previous accepted step (only if no rejection
            # since: a step shortened by extra damping says nothing about convergence)
            if prev_step > 0.0:
                theta = step / prev_step
                remaining = step * theta / (1.0 - theta) if theta < 1.0 else math.inf
            else:
                remaining = step
            if remaining <= GN_XTOL * (math.sqrt(sum(v * v for v in q)) + GN_XTOL):
                # Converged. The step is still applied without re-evaluating: it only
                # removes error, and its cost change is second order in a tiny step.
                q = [a + b for a, b in zip(q, dq, strict=True)]
                success = True
                break
            it += 1
            q_new = [a + b for a, b in zip(q, dq, strict=True)]
            cost_new, g_new, h_new = self.evaluate(q_new)
            if math.isfinite(cost_new) and cost_new <= cost:
                # gain ratio: actual over the damped model's predicted decrease, which for
                # (H + lam D) dq = -g is (lam dq^T D dq - g^T dq) / 2
                pred = 0.5 * (lam * sum(max(h[i], 1e-300) * d * d
                                        for i, d in zip(self._diag, dq, strict=True))
                              - sum(a * b for a, b in zip(g, dq, strict=True)))
                decrease = cost - cost_new
                gain = decrease / pred if pred > 0 else 0.0
                q, cost, g, h = q_new, cost_new, g_new, h_new
                prev_step = step
                lam = max(lam * max(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3), 1e-15)
                if decrease <= GN_FTOL * cost:
                    success = True
                    break
            else:
                prev_step = 0.0
                lam = max(10.0 * lam, 1e-3)
                if lam > 1e16:
                    success = True  # no decreasing step at any damping: a (local) minimum
                    break
        return SolveOutput(np.asarray(q), success, it, cost)
