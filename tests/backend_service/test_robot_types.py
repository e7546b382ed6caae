"""Several robot types on one site (issue #30 item 2), on the backend: a detection that names
its robot model goes only to robots of that model, even when a robot of another type is
predicted closer; a model the site has no robot of is counted and dropped; detections from
senders that do not know the field still decode. The site is simulation/sites/two_types_lab.yaml
(the built-in HSR and the box base, both with 12 keypoints, so the keypoint count cannot tell
them apart: only the type does)."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import msgpack
import numpy as np
import pytest

from backend_service.association import (
    AssociationConfig,
    RobotPrediction,
    associate,
    association_costs,
)
from backend_service.detection_router import DetectionRouter
from backend_service.projection import project_planar, stacked_cameras
from core.pose import PlanarPose
from core.site import load_site
from protocol import codec
from protocol.errors import DecodeError
from protocol.messages import Detection, RobotDetections
from tests.conftest import REPO_ROOT

SITE = load_site(REPO_ROOT / "simulation" / "sites" / "two_types_lab.yaml")
CAMERA = SITE.cameras["cam1"]
KEYPOINTS = {rid: SITE.robot_model(rid).keypoints_base_m for rid in SITE.robots}
MODELS = dict(SITE.robots)  # robot id -> model name
CONFIG = AssociationConfig()


def _detection(robot_id: str, pose: tuple[float, float, float], robot_model: str = "",
               noise_px: float = 1.0, seed: int = 0) -> Detection:
    """What cam1 reports for robot ``robot_id`` (its model's keypoints) at ``pose``: exact
    projections plus pixel noise, unnamed, typed ``robot_model``."""
    uv, depth = project_planar(stacked_cameras((CAMERA,)), KEYPOINTS[robot_id],
                               np.array([pose]))
    assert np.all(depth > 0)
    uv = uv[0, 0] + np.random.default_rng(seed).normal(0.0, noise_px, uv[0, 0].shape)
    lo, hi = uv.min(axis=0) - 4.0, uv.max(axis=0) + 4.0
    return Detection(np.array([lo[0], lo[1], hi[0], hi[1]]), 0.9, uv, np.full(len(uv), 0.9),
                     "", None, robot_model)


def _prediction(robot_id: str, pose: tuple[float, float, float],
                sigma_xy_m: float) -> RobotPrediction:
    cov = np.diag([sigma_xy_m ** 2, sigma_xy_m ** 2, 0.02 ** 2])
    return RobotPrediction(robot_id, PlanarPose(*pose), cov, "fused")


def test_the_two_types_have_the_same_keypoint_count() -> None:
    """The premise of the tests below: the count filter alone cannot separate the types."""
    assert SITE.robots == {"hsr": "hsr", "box1": "box_base"}
    assert KEYPOINTS["hsr"].shape == KEYPOINTS["box1"].shape == (12, 3)


HSR_TRUE = (9.6, 6.0, 0.3)


def test_a_typed_detection_never_goes_to_a_closer_robot_of_another_type() -> None:
    """The HSR is seen exactly where the box base is predicted (the box's prediction, 20 cm
    sigma, fits the HSR's detection better than the HSR's own, 0.35 m off with 12 cm sigma):
    untyped, the detection is not the HSR's (ambiguous or the box's); typed ``hsr`` it goes to
    the HSR."""
    det = _detection("hsr", HSR_TRUE, seed=3)
    preds = [_prediction("hsr", (9.6, 6.35, 0.3), 0.12), _prediction("box1", HSR_TRUE, 0.2)]
    costs = association_costs(CAMERA, [det], preds, KEYPOINTS, CONFIG)
    assert math.isfinite(costs[0, 0]) and costs[0, 0] <= CONFIG.gate
    assert costs[0, 1] < costs[0, 0], "precondition: the box base's prediction is closer"
    untyped = associate(CAMERA, [det], preds, KEYPOINTS, CONFIG, tuple(SITE.robots),
                        robot_models=MODELS)
    assert untyped.outcomes[0].robot_id != "hsr"
    typed_det = _detection("hsr", HSR_TRUE, robot_model="hsr", seed=3)
    typed = associate(CAMERA, [typed_det], preds, KEYPOINTS, CONFIG, tuple(SITE.robots),
                      robot_models=MODELS)
    assert typed.outcomes[0].robot_id == "hsr"
    assert typed.outcomes[0].reason == "assigned"
    assert typed.costs[0, 1] == math.inf  # the box base is no candidate at all


def test_each_type_goes_to_its_robot_when_the_two_are_side_by_side() -> None:
    """Random nearby poses (0.45-0.7 m apart) and offset predictions: a typed detection goes to
    its type's robot or to none, never to the other type's; most go to their own robot."""
    rng = np.random.default_rng(7)
    own = 0
    trials = 60
    for k in range(trials):
        hsr = (9.0 + rng.uniform(0, 1.5), 5.5 + rng.uniform(0, 1.0), rng.uniform(-3, 3))
        ang = rng.uniform(0, 2 * math.pi)
        dist = rng.uniform(0.45, 0.7)
        box = (hsr[0] + dist * math.cos(ang), hsr[1] + dist * math.sin(ang), rng.uniform(-3, 3))
        dets = [_detection("box1", box, "box_base", seed=2 * k),
                _detection("hsr", hsr, "hsr", seed=2 * k + 1)]
        off = rng.normal(0.0, 0.05, (2, 2))
        preds = [_prediction("hsr", (hsr[0] + off[0, 0], hsr[1] + off[0, 1], hsr[2]), 0.08),
                 _prediction("box1", (box[0] + off[1, 0], box[1] + off[1, 1], box[2]), 0.08)]
        result = associate(CAMERA, dets, preds, KEYPOINTS, CONFIG, tuple(SITE.robots),
                           robot_models=MODELS)
        got = [o.robot_id for o in result.outcomes]
        assert got[0] in ("box1", ""), (k, got)
        assert got[1] in ("hsr", ""), (k, got)
        own += (got[0] == "box1") + (got[1] == "hsr")
    assert own >= 0.9 * 2 * trials


def _half_size(det: Detection) -> Detection:
    """``det`` as a camera streaming at half the calibrated resolution reports it."""
    def half(a: np.ndarray) -> np.ndarray:
        return (np.asarray(a) + 0.5) / 2.0 - 0.5

    return Detection(half(det.bbox_xyxy), det.score, half(det.keypoints_px),
                     det.keypoint_scores, det.robot_id, None, det.robot_model)


@pytest.mark.parametrize("half", [False, True], ids=["calibrated_size", "half_size"])
def test_the_router_counts_a_model_the_site_has_no_robot_of(half: bool) -> None:
    """Through :class:`DetectionRouter` (also from a camera streaming at half its calibrated
    size: the type survives the rescaling): typed detections routed to their robots (named
    after them), one of a type the site has no robot of removed and counted."""
    router = DetectionRouter(SITE)
    box_true = (10.3, 6.2, 1.0)
    dets = (_detection("hsr", HSR_TRUE, "hsr", seed=1),
            _detection("box1", box_true, "box_base", seed=2),
            _detection("box1", (8.6, 5.6, 0.0), "forklift", seed=3))
    size = (CAMERA.width, CAMERA.height)
    if half:
        dets = tuple(_half_size(d) for d in dets)
        size = (CAMERA.width // 2, CAMERA.height // 2)
    msg = RobotDetections("cam1", 1_700_000_000_000_000_000, 0, *size,
                          "hsr/models+box_base/models", dets)
    preds = {"hsr": _prediction("hsr", (9.62, 6.02, 0.3), 0.05),
             "box1": _prediction("box1", (10.28, 6.21, 1.0), 0.05)}
    out = router.route(msg, preds)
    assert [(d.robot_id, d.robot_model) for d in out.detections] == [("hsr", "hsr"),
                                                                     ("box1", "box_base")]
    assert router.counters["detections_unknown_model"] == 1
    assert router.counters["detections_assigned"] == 2
    assert router.counters["detections_routed.hsr"] == 1
    assert router.counters["detections_routed.box1"] == 1


# -- on the wire ------------------------------------------------------------------------------


def _message(robot_model: str) -> RobotDetections:
    return RobotDetections("cam1", 5, 1, 848, 480, "m",
                           (_detection("box1", (10.3, 6.2, 1.0), robot_model),))


def test_the_robot_model_round_trips() -> None:
    msg = _message("box_base")
    back = codec.decode(codec.encode(msg), RobotDetections)
    assert back == msg and back.detections[0].robot_model == "box_base"
    assert codec.decode_checked(codec.encode(msg), RobotDetections) == msg


def test_a_message_of_an_older_sender_without_the_field_decodes() -> None:
    """An older sender's detection has no ``robot_model`` key: it decodes (both paths) with
    the model unknown, which the association treats as before."""
    wire = msgpack.unpackb(codec.encode(_message("box_base")), raw=False)
    for det in wire["detections"]:
        del det["robot_model"]
    payload = msgpack.packb(wire, use_bin_type=True)
    for decode in (codec.decode, codec.decode_checked):
        back = decode(payload, RobotDetections)
        assert back.detections[0].robot_model == ""
        assert back == _message("")


@pytest.mark.parametrize("bad", ["box base", "x" * 65, "box/base", "ü", 7])
def test_a_bad_robot_model_is_refused_naming_the_field(bad: object) -> None:
    wire = msgpack.unpackb(codec.encode(_message("box_base")), raw=False)
    wire["detections"][0]["robot_model"] = bad
    with pytest.raises(DecodeError, match=r"detections\[0\]\.robot_model"):
        codec.decode(msgpack.packb(wire, use_bin_type=True), RobotDetections)


# -- two types crossing, through the pipeline -------------------------------------------------

#: the HSR and the box base on lanes 0.48 m apart (centres), driving past each other
CROSSING = {"hsr": [(8.5, 5.76, 0.0), (11.5, 5.76, 0.0)],
            "box1": [(11.5, 6.24, 180.0), (8.5, 6.24, 180.0)]}


def _typed_run(typed: bool) -> tuple[list[tuple[int, object]], dict[int, tuple[str, ...]], Any]:
    """The crossing simulated (:mod:`simulation.fleet`: each robot's own motion, odometry,
    localization and the detection noise model with its model's keypoints), each camera
    image's detections of both robots merged unnamed; ``typed``: each detection carries its
    robot's model, as a two-type edge sends it. Returns (arrival_ns, message) pairs, the true
    robot of each merged message's detections (by ``id``), the fleet run."""
    from robot_bridge.service import LOCALIZATION_PERIOD_NS
    from simulation.fleet import fleet_run, merged_messages

    fleet = fleet_run(CROSSING, until_s=12.0, seed=5, site=SITE, typed=False)  # typed below
    messages = merged_messages(fleet, 1e9 / LOCALIZATION_PERIOD_NS)
    out: list[tuple[int, object]] = []
    truth: dict[int, tuple[str, ...]] = {}
    for arrival_ns, msg in messages:
        if isinstance(msg, RobotDetections) and msg.detections:
            true_ids = fleet.truth[id(msg)]
            if typed:
                dets = tuple(dataclasses.replace(d, robot_model=SITE.robots[rid])
                             for d, rid in zip(msg.detections, true_ids, strict=True))
                msg = dataclasses.replace(msg, detections=dets)
            truth[id(msg)] = true_ids
        out.append((arrival_ns, msg))
    return out, truth, fleet


@pytest.mark.parametrize("typed", [True, False], ids=["typed", "untyped"])
def test_two_types_crossing_each_types_detections_go_to_its_robot(typed: bool) -> None:
    """The HSR and the box base pass within half a metre while their predictions are vague
    (no sharper than 0.35 m, so each robot's gate holds both): typed, every detection goes to
    the robot of its type (none ambiguous, none to the other robot) and both are tracked to a
    few cm; untyped (identical keypoint counts) the same crossing leaves detections ambiguous,
    so the type is what decides."""
    pytest.importorskip("gtsam")
    from backend_service.pipeline import BackendPipeline
    from backend_service.pipeline_config import PipelineConfig

    messages, truth, fleet = _typed_run(typed)
    config = PipelineConfig.from_site(SITE, association=AssociationConfig(min_sigma_xy_m=0.35))
    pipeline = BackendPipeline(SITE, config)
    wrong = 0
    reasons: dict[str, int] = {}
    min_gap = math.inf
    errors: dict[str, list[float]] = {"hsr": [], "box1": []}
    for arrival_ns, msg in messages:
        out = pipeline.step(msg, arrival_ns)
        if isinstance(msg, RobotDetections) and msg.detections:
            assert pipeline.router is not None and pipeline.router.last is not None
            a, b = (fleet.true_pose(r, msg.stamp_ns)[:2] for r in ("hsr", "box1"))
            min_gap = min(min_gap, float(np.hypot(*(a - b))))
            for outcome, true_id in zip(pipeline.router.last.outcomes, truth[id(msg)],
                                        strict=True):
                reasons[outcome.reason] = reasons.get(outcome.reason, 0) + 1
                wrong += int(outcome.used and outcome.robot_id != true_id)
        for est in out.fused:
            own = fleet.true_pose(est.robot_id, est.stamp_ns)[:2]
            errors[est.robot_id].append(float(np.hypot(est.x - own[0], est.y - own[1])))
    assert min_gap <= 0.5
    assert wrong == 0
    if typed:
        assert reasons.get("ambiguous", 0) == 0, reasons
        assert reasons["assigned"] > 500, reasons
        for rid, errs in errors.items():
            assert len(errs) > 50 and max(errs) < 0.1, (rid, len(errs), max(errs, default=0))
    else:
        assert reasons.get("ambiguous", 0) > 20, reasons
