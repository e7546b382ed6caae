"""``smartedge bench calibration-solver``: the GTSAM factor graph and the numpy
Levenberg-Marquardt solve the same board adjustment to the same minimum, and the bench prints
both with their ratio."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.board_extrinsics import HUBER_PX, prepare_board_adjustment, solve_board_extrinsics
from lab.bench import calibration_solver as bench
from simulation.detections import true_cameras
from simulation.scenario import PAPER_SCENARIO, load_scenario


@pytest.fixture(scope="module")
def walk() -> bench.SyntheticSightings:
    truth = true_cameras(load_scenario(PAPER_SCENARIO))
    return bench.synthetic_sightings(truth, rounds=2, noise_px=0.3, outlier_share=0.03, seed=1)


def test_both_solvers_reach_the_same_minimum_and_the_truth(walk) -> None:
    adjustment = prepare_board_adjustment(walk.cameras, walk.sightings, bench.BOARD,
                                          {"000": walk.board_poses["000"]})
    start_cost = adjustment.problem.huber_cost(*adjustment.initial, HUBER_PX)
    ours, peer = bench.compare_solvers(walk, adjustment, repeats=1)
    assert walk.outliers > 0
    assert ours.cost < 0.5 * start_cost
    # the same objective, minimised by both: equal to rounding, the same cameras
    assert peer.cost == pytest.approx(ours.cost, rel=1e-4)
    gap_mm, gap_deg = bench.solution_gap(ours.state, peer.state)
    assert gap_mm < 0.05 and gap_deg < 1e-3
    # two rounds chained from one fixed board pose: cm-level, as the full evaluation shows
    for f in (ours, peer):
        assert f.worst_position_cm < 3.0 and f.worst_rotation_deg < 0.5
    assert peer.callback_s > 0 and peer.iterations >= 1


def test_the_split_solve_is_the_one_solve(walk) -> None:
    """prepare + adjust + result (the pieces the bench uses) is solve_board_extrinsics."""
    fixed = {"000": walk.board_poses["000"]}
    whole = solve_board_extrinsics(walk.cameras, walk.sightings, bench.BOARD, fixed)
    adjustment = prepare_board_adjustment(walk.cameras, walk.sightings, bench.BOARD, fixed)
    ours, _ = bench.compare_solvers(walk, adjustment, repeats=1)
    for i, cid in enumerate(adjustment.problem.cam_ids):
        np.testing.assert_allclose(whole.cameras[cid].T_world_cam[:3, 3], ours.state[1][i],
                                   atol=1e-9)


def test_bench_prints_both_solvers_and_the_ratio(capsys) -> None:
    assert bench.main(["--rounds", "1", "--repeats", "1"]) == 0
    out = capsys.readouterr().out
    assert "numpy LM" in out and "GTSAM LM" in out and "GTSAM / numpy:" in out


def test_bench_refuses_bad_options(capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        bench.main(["--outliers", "1.5"])
    assert exc.value.code == 2
    assert "--outliers" in capsys.readouterr().err
