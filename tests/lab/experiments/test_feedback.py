"""Experiments 2 and 3 of the paper: correction feedback through the real robot bridge and the
robustness failure model (docs/simulation.md, "Robustness")."""

from __future__ import annotations

import dataclasses

import pytest

from lab.experiments import (
    EMERGENCY_STOP,
    SUCCESS,
    WP_NOT_REACHED,
    FailureModel,
    robustness_table,
    run_feedback,
)
from simulation.runner import run_seed
from simulation.scenario import load_scenario


@pytest.fixture(scope="module")
def scenario():
    sc = load_scenario()
    return sc.with_overrides(motion=dataclasses.replace(sc.motion, stop_s=3.0))


@pytest.fixture(scope="module")
def exp2(scenario):
    seed = run_seed(scenario, "traj3x3", False, 0, 0)
    return [run_feedback(scenario, "traj3x3", fb, seed) for fb in (False, True)]


def test_feedback_halves_internal_localization_error(exp2) -> None:
    without, with_fb = exp2
    assert without.travelled_m > 45.0  # 3x Traj. 3
    assert with_fb.robot_rms_m() < 0.5 * without.robot_rms_m(), (
        with_fb.robot_rms_m(), without.robot_rms_m())
    assert not without.corrections


def test_corrections_only_while_static(exp2) -> None:
    with_fb = exp2[1]
    accepted = [c for c in with_fb.corrections if c.accepted]
    assert len(accepted) >= 5  # one per stop where the offset exceeded the threshold
    assert all(c.static_now and c.static_at_stamp for c in accepted)
    assert with_fb.bridge_counters.get("corrections_refused", 0) == 0


def _mislocalized(scenario, init_sigma_m: float):
    # a localization that starts off by ~init_sigma_m and then barely changes: only a
    # correction can fix it, so the outcome does not hinge on how the noise falls
    loc = dataclasses.replace(scenario.localization, stationary_sigma_m=0.002,
                              init_sigma_m=init_sigma_m)
    motion = dataclasses.replace(scenario.motion, start_s=4.0)
    return scenario.with_overrides(localization=loc, motion=motion, clutter=())


@pytest.mark.slow
def test_robustness_failure_model(scenario) -> None:
    fm = FailureModel(waypoint_tolerance_m=0.15, footprint_m=0.215)
    route = "traj3"
    seed = run_seed(scenario, route, False, 3, 0)
    bad = _mislocalized(scenario, 0.5)
    runs = [run_feedback(bad, route, fb, seed, failure=fm) for fb in (False, True)]
    without, with_fb = runs
    assert without.outcome in (WP_NOT_REACHED, EMERGENCY_STOP)
    assert without.failure_distance_m < without.travelled_m + 1e-9
    assert with_fb.outcome == SUCCESS, (with_fb.outcome, with_fb.failure_distance_m)
    # control: the detector lets a run through when the localization is good
    calm = run_feedback(_mislocalized(scenario, 0.02), route, False, seed, failure=fm)
    assert calm.outcome == SUCCESS
    md, numbers = robustness_table(runs)
    assert "| w/o correction fb |" in md and numbers["with_feedback"]["success"] == 1
