"""The one Levenberg-Marquardt loop of the calibration's least-squares problems.

Both joint adjustments (every camera's pose from board sightings, :mod:`calibration.
board_extrinsics`; cameras and the robot's trajectory with the robot as the target,
:mod:`calibration.robot_problem`) hand it their own pieces: the normal equations at a state
(with their robust weights refreshed there), the cost, and a step from the damped system.
The loop itself is the textbook one (Marquardt's scaling of the diagonal): try a step, keep it
when the cost falls and relax the damping, else raise the damping and try again.

Why not GTSAM or CasADi here: both problems are solved from vectorized numpy Jacobians of the
one projection (:mod:`core.projection`, OpenCV's distortion with up to 8 coefficients, which
GTSAM's ``Cal3DS2`` lacks) and a Schur complement over the boards. The same board adjustment as
a GTSAM factor graph (one Python ``CustomFactor`` per corner) reaches the same minimum in 37x
the time (``smartedge bench calibration-solver``, docs/calibration.md).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Generic, TypeVar

import numpy as np

State = TypeVar("State")


@dataclasses.dataclass(frozen=True)
class Damping:
    """The damping schedule and the stopping rules: start at ``initial``; after a kept step
    divide by ``down`` (not below ``floor``), after a refused one multiply by ``up``, at most
    ``tries`` times per iteration; stop when a step's largest component is below ``step_tol``
    or the cost's relative fall below ``rel_tol``."""

    initial: float = 1e-3
    down: float = 10.0
    up: float = 10.0
    floor: float = 1e-9
    tries: int = 10
    step_tol: float = 1e-9
    rel_tol: float = 1e-10


@dataclasses.dataclass(frozen=True)
class Problem(Generic[State]):
    """A least-squares problem as the loop sees it.

    ``linearize(state) -> (H, g)``: the normal equations at ``state`` (refresh any robust
    weights there first); ``cost(state)``: the cost under the same weights (``inf`` for a
    state that cannot be evaluated); ``step(state, A, g) -> (state', delta)``: solve
    ``A delta = -g`` (``numpy.linalg.LinAlgError`` when it cannot) and apply ``delta``."""

    linearize: Callable[[State], tuple[np.ndarray, np.ndarray]]
    cost: Callable[[State], float]
    step: Callable[[State, np.ndarray, np.ndarray], tuple[State, np.ndarray]]


def levenberg_marquardt(problem: Problem[State], state: State, max_iterations: int,
                        damping: Damping = Damping()
                        ) -> tuple[State, int]:
    """Minimise ``problem``'s cost from ``state``; the final state and the iterations run."""
    lam = damping.initial
    iterations = 0
    for iterations in range(1, max_iterations + 1):  # noqa: B007 (returned)
        H, g = problem.linearize(state)
        current = problem.cost(state)
        diag = np.diag(np.maximum(np.diag(H), 1e-9))
        accepted = None
        for _ in range(damping.tries):
            try:
                candidate, delta = problem.step(state, H + lam * diag, g)
            except np.linalg.LinAlgError:
                lam *= damping.up
                continue
            new = problem.cost(candidate)
            if new < current:
                accepted = candidate, delta, new
                lam = max(lam / damping.down, damping.floor)
                break
            lam *= damping.up
        if accepted is None:
            break
        state, delta, new = accepted
        rel = (current - new) / max(current, 1e-12)
        if float(np.abs(delta).max()) < damping.step_tol or rel < damping.rel_tol:
            break
    return state, iterations


def huber_weights(errors: np.ndarray, k: float) -> np.ndarray:
    """IRLS weights of the Huber loss with threshold ``k`` for error norms ``errors``."""
    return np.where(errors <= k, 1.0, k / np.maximum(errors, 1e-12))


__all__ = ["Damping", "Problem", "huber_weights", "levenberg_marquardt"]
