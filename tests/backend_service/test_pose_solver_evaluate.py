"""``PoseProblem.evaluate`` keeps its last outputs: the same ``q`` and ``p`` again (the
solution's checks, then its covariance) cost no second CasADi evaluation, anything else
evaluates afresh, and the caller always gets arrays of its own."""

from __future__ import annotations

import numpy as np

from backend_service.pose_solver import get_problem
from tests.backend_service.pose_synth import (
    ROBOT,
    example_site,
    make_frame_set,
    random_pose,
)

SITE = example_site()


def _problem_and_params(seed: int):
    rng = np.random.default_rng(seed)
    truth = random_pose(rng)
    ids = sorted(SITE.cameras)[:3]
    fs = make_frame_set(SITE, truth, ids, sigma_px=2.0, rng=rng)
    by_id = {o.camera_id: o for o in fs.observations}
    problem = get_problem([SITE.camera(c) for c in ids],
                          SITE.robot_model(ROBOT).keypoints_base_m, 3, "cauchy")
    uv = np.stack([by_id[c].keypoints_px for c in ids])
    w = np.stack([by_id[c].keypoint_scores for c in ids])
    return problem, problem.pack(uv, w, 5.0), truth.as_array()


def _count_evaluations(problem) -> list[int]:
    problem.evaluate(np.zeros(3), np.zeros(problem.residual_fn.size1_in(1)))  # bind buffers
    io, buf, run = problem._residual_buffer
    calls = [0]

    def counted() -> None:
        calls[0] += 1
        run()

    problem._residual_buffer = (io, buf, counted)
    return calls


def test_repeated_evaluation_reuses_the_outputs_and_changes_evaluate_again() -> None:
    problem, p, q = _problem_and_params(1)
    calls = _count_evaluations(problem)
    r1, J1, z1 = problem.evaluate(q, p)
    r2, J2, z2 = problem.evaluate(q.copy(), p.copy())
    assert calls[0] == 1
    np.testing.assert_array_equal(r1, r2)
    np.testing.assert_array_equal(J1, J2)
    np.testing.assert_array_equal(z1, z2)
    # the outputs are the caller's: writing into them changes nothing kept
    r1[:] = 0.0
    J1[:] = 0.0
    r3, J3, _ = problem.evaluate(q, p)
    assert calls[0] == 1
    np.testing.assert_array_equal(r3, r2)
    np.testing.assert_array_equal(J3, J2)
    # another pose, other observations: evaluated again, and equal to a fresh evaluation
    q_moved = q + np.array([1e-12, 0.0, 0.0])
    r4, _, _ = problem.evaluate(q_moved, p)
    assert calls[0] == 2
    p_moved = p.copy()
    p_moved[0] += 0.5  # the first keypoint's u by half a pixel
    r5, _, _ = problem.evaluate(q_moved, p_moved)
    assert calls[0] == 3
    assert r5[0] != r4[0]
    ref = np.asarray(problem.residual_fn(q_moved, p_moved)[0]).reshape(-1)
    np.testing.assert_allclose(r5, ref, rtol=1e-12, atol=1e-9)
    # NaN never compares equal: evaluated, not served from the kept outputs
    q_nan = np.array([np.nan, q[1], q[2]])
    problem.evaluate(q_nan, p)
    problem.evaluate(q_nan, p)
    assert calls[0] == 5
