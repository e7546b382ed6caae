"""The one Levenberg-Marquardt loop: it finds a known minimum, keeps only steps that lower the
cost, and stops where a step cannot be taken."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from calibration.least_squares import Damping, Problem, huber_weights, levenberg_marquardt


def _rosenbrock() -> Problem[np.ndarray]:
    """r(x) = (10 (x1 - x0^2), 1 - x0): minimum 0 at (1, 1), a curved valley."""

    def residual(x: np.ndarray) -> np.ndarray:
        return np.array([10.0 * (x[1] - x[0] ** 2), 1.0 - x[0]])

    def jacobian(x: np.ndarray) -> np.ndarray:
        return np.array([[-20.0 * x[0], 10.0], [-1.0, 0.0]])

    def linearize(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        J = jacobian(x)
        return J.T @ J, J.T @ residual(x)

    def step(x: np.ndarray, A: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        delta = -np.linalg.solve(A, g)
        return x + delta, delta

    return Problem(linearize, lambda x: 0.5 * float(residual(x) @ residual(x)), step)


def test_finds_the_minimum_of_a_curved_valley() -> None:
    x, iterations = levenberg_marquardt(_rosenbrock(), np.array([-1.2, 1.0]), 200)
    np.testing.assert_allclose(x, [1.0, 1.0], atol=1e-6)
    assert 1 < iterations < 200


def test_every_kept_step_lowers_the_cost() -> None:
    problem = _rosenbrock()
    seen: list[float] = []

    def cost(x: np.ndarray) -> float:
        return problem.cost(x)

    def linearize(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        seen.append(cost(x))  # the state each iteration starts from: the last kept one
        return problem.linearize(x)

    levenberg_marquardt(Problem(linearize, cost, problem.step), np.array([-1.2, 1.0]), 50)
    assert len(seen) > 3 and all(b < a for a, b in itertools.pairwise(seen))


def test_stops_when_no_step_can_be_solved() -> None:
    def singular(x: np.ndarray, A: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        raise np.linalg.LinAlgError("singular")

    start = np.array([3.0, -2.0])
    p = _rosenbrock()
    x, iterations = levenberg_marquardt(Problem(p.linearize, p.cost, singular), start, 10,
                                        Damping(tries=3))
    assert iterations == 1 and x is start


def test_huber_weights() -> None:
    np.testing.assert_allclose(huber_weights(np.array([0.0, 1.0, 2.0, 4.0]), 2.0),
                               [1.0, 1.0, 1.0, 0.5])
    assert huber_weights(np.array([0.0]), 0.0)[0] == pytest.approx(1.0)
