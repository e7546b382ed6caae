"""``smartedge evaluate fleet``: three identical robots crossing paths through the real
pipeline (CasADi solves, GTSAM pose graphs, one real robot bridge per robot), scored against
the truth the simulation keeps aside; two robot types (``--types``), typed and untyped; and
the scores themselves, shown to fail when the assignment is wrong."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("gtsam")

from lab.evaluate import main
from lab.experiments.fleet import (
    count_wrong_corrections,
    drive,
    identity_score,
)
from protocol.messages import PoseCorrection
from simulation.fleet import CROSSING_ROUTES, FleetRun, fleet_routes, fleet_run, fleet_site


def test_evaluate_fleet_quick_end_to_end(tmp_path: Path, capsys: pytest.CaptureFixture[str]
                                         ) -> None:
    assert main(["fleet", "--quick", "--out", str(tmp_path)]) == 0
    printed = capsys.readouterr().out
    assert "closest approach 0.47 m" in printed and "target met" in printed
    report = (tmp_path / "report.md").read_text()
    assert "| hsr_a |" in report and "| hsr_c |" in report and "fleet_routes.png" in report
    assert (tmp_path / "fleet_routes.png").stat().st_size > 10_000
    data = json.loads((tmp_path / "fleet_results.json").read_text())
    numbers = data["numbers"]
    assert numbers["identity_switches"] == 0
    assert numbers["wrong_detections"] == 0 and numbers["wrong_corrections"] == 0
    assert numbers["closest_m"] <= 0.5
    assert numbers["assigned"] > 1500  # three robots, four cameras, 12 s
    # the few detections before the robots' first localization: counted, not guessed
    assert 0 < numbers["no_prediction"] < 50
    run = data["runs"][0]
    for rid in CROSSING_ROUTES:
        r = run["robots"][rid]
        assert r["camera_estimates"] > 100
        assert 0.0 < r["camera_rms_m"] < 0.05 and 0.0 < r["fused_rms_m"] < 0.1
        assert r["camera_ratio"] <= 1.10 and r["fused_ratio"] <= 1.10
        # the same robot alone: its own estimates, not a copy of the fleet's numbers
        assert r["alone_camera_estimates"] >= r["camera_estimates"]


def test_the_scores_count_detections_given_to_the_wrong_robot() -> None:
    # the truth says hsr_a's detections are hsr_b's and back: every assignment the router
    # gets right must now count as wrong, and the robots' data as holding the other's
    fleet = fleet_run({k: CROSSING_ROUTES[k] for k in ("hsr_a", "hsr_b")}, until_s=6.0)
    swap = {"hsr_a": "hsr_b", "hsr_b": "hsr_a"}
    real_merge = FleetRun._merge

    def lying_merge(self, parts, rng):  # type: ignore[no-untyped-def]
        tm = real_merge(self, parts, rng)
        self.truth[id(tm.message)] = tuple(swap[r] for r in self.truth[id(tm.message)])
        return tm

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(FleetRun, "_merge", lying_merge)
        dr = drive(fleet, feedback=False)
    assert dr.wrong_detections["hsr_a"] > 100 and dr.wrong_detections["hsr_b"] > 100
    assert set(dr.contaminated_from_ns) == {"hsr_a", "hsr_b"}
    correction = PoseCorrection("hsr_a", dr.contaminated_from_ns["hsr_a"] + 1, 0, 8.5, 5.76,
                                0.0, np.eye(3) * 1e-4, "correction")
    dr.corrections["hsr_a"] = [(correction, True)]
    assert count_wrong_corrections(fleet, "hsr_a", dr) == 1


def test_identity_switches_and_corrections_placed_on_another_robot() -> None:
    fleet = fleet_run({k: CROSSING_ROUTES[k] for k in ("hsr_a", "hsr_b")}, until_s=6.0)
    stamps = np.array([fleet.runs["hsr_a"].stamp_ns(t) for t in np.arange(0.5, 5.0, 0.5)])
    own = fleet.runs["hsr_a"].ground_truth_at(stamps)
    other = fleet.runs["hsr_b"].ground_truth_at(stamps)
    est = np.column_stack([stamps, own])
    assert identity_score(fleet, "hsr_a", est) == (0, 0)
    est[3:5, 1:3] = other[3:5, :2]  # two estimates on the other robot, then back
    assert identity_score(fleet, "hsr_a", est) == (2, 2)
    est[6:, 1:3] = other[6:, :2]  # and over to it for good
    assert identity_score(fleet, "hsr_a", est) == (3, 5)
    dr = drive(fleet, feedback=False)
    assert dr.contaminated_from_ns == {}
    on_b = PoseCorrection("hsr_a", int(stamps[2]), 0, *other[2], np.eye(3) * 1e-4,
                          "correction")
    on_a = dataclasses.replace(on_b, x=float(own[2, 0]), y=float(own[2, 1]))
    dr.corrections["hsr_a"] = [(on_a, True), (on_b, True)]
    assert count_wrong_corrections(fleet, "hsr_a", dr) == 1


def test_evaluate_fleet_two_types_quick_typed_and_untyped(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["fleet", "--quick", "--types", "--out", str(tmp_path)]) == 0
    printed = capsys.readouterr().out
    assert "box_c (box_base)" in printed and "target met" in printed
    report = (tmp_path / "report.md").read_text()
    assert "| box_c | box_base |" in report and "| hsr_a | hsr |" in report
    assert "| untyped |" in report and "| typed |" in report
    data = json.loads((tmp_path / "fleet_results.json").read_text())
    numbers = data["numbers"]
    # typed: every detection goes to a robot of its type, and to the right one
    assert numbers["wrong_type_detections"] == 0 and numbers["wrong_detections"] == 0
    assert numbers["identity_switches"] == 0 and numbers["wrong_corrections"] == 0
    assert numbers["unknown_model"] == 0 and numbers["assigned"] > 1500
    untyped = numbers["untyped"]
    assert untyped["assigned"] > 1500 and untyped["unknown_model"] == 0
    # without the type, the box base is one more candidate for the HSRs' detections
    assert untyped["ambiguous"] >= numbers["ambiguous"]
    assert untyped["wrong_corrections"] == 0 and untyped["identity_switches"] == 0
    run = data["runs"][0]
    assert run["typed"] is True and run["untyped"]["typed"] is False
    for rid, model in (("hsr_a", "hsr"), ("hsr_b", "hsr"), ("box_c", "box_base")):
        r = run["robots"][rid]
        assert r["model"] == model
        assert r["camera_estimates"] > 100, rid
        assert 0.0 < r["camera_rms_m"] < 0.05 and 0.0 < r["fused_rms_m"] < 0.1, rid
        assert r["camera_ratio"] <= 1.10 and r["fused_ratio"] <= 1.10, rid


def test_detections_given_to_a_robot_of_another_type_are_counted() -> None:
    # the truth says the HSR's detections are the box base's and back; typed detections would
    # keep the router from making that mistake, so the fleet is untyped: the router assigns
    # by position (rightly), and every assignment now counts as wrong and of another type
    models = {"hsr_a": "hsr", "box_c": "box_base"}
    fleet = fleet_run(fleet_routes(list(models)), until_s=5.0, site=fleet_site(models),
                      typed=False)
    swap = {"hsr_a": "box_c", "box_c": "hsr_a"}
    real_merge = FleetRun._merge

    def lying_merge(self, parts, rng):  # type: ignore[no-untyped-def]
        tm = real_merge(self, parts, rng)
        self.truth[id(tm.message)] = tuple(swap[r] for r in self.truth[id(tm.message)])
        return tm

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(FleetRun, "_merge", lying_merge)
        dr = drive(fleet, feedback=False)
    for rid in models:
        assert dr.wrong_type[rid] == dr.wrong_detections[rid] > 100, rid
