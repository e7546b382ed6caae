"""Detections to robots (issue #30 item 1): the gated optimal assignment by predicted pose, the
ambiguity rule, named detections, and the rule in the pipeline with two identical robots of the
paper lab driven by the simulation (real CasADi solves, real GTSAM pose graphs)."""

from __future__ import annotations

import collections
import dataclasses
import itertools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from backend_service import association
from backend_service.assignment import hungarian
from backend_service.association import (
    AssociationConfig,
    RobotPrediction,
    associate,
    association_costs,
    predicted_covariance,
    predicted_views,
)
from backend_service.detection_router import DetectionRouter
from backend_service.projection import project_planar, stacked_cameras
from core.camera import CameraModel
from core.pose import PlanarPose
from protocol.messages import Detection, PoseEstimate, RobotDetections

from .two_robots import ROBOTS, TwoRobotRun, two_robot_run, two_robot_site

# -- the assignment ---------------------------------------------------------------------------


def _brute_force(cost: np.ndarray) -> float:
    n, m = cost.shape
    if n <= m:
        return min(sum(cost[i, p[i]] for i in range(n))
                   for p in itertools.permutations(range(m), n))
    return min(sum(cost[p[j], j] for j in range(m)) for p in itertools.permutations(range(n), m))


def test_hungarian_is_the_optimal_assignment() -> None:
    rng = np.random.default_rng(4)
    for _ in range(200):
        n, m = (int(v) for v in rng.integers(1, 6, 2))
        cost = rng.uniform(0.0, 10.0, (n, m))
        pairs = hungarian(cost)
        assert len(pairs) == min(n, m)
        assert len({i for i, _ in pairs}) == len(pairs) == len({j for _, j in pairs})
        assert sum(cost[i, j] for i, j in pairs) == pytest.approx(_brute_force(cost), abs=1e-9)
    assert hungarian(np.zeros((0, 3))) == []
    with pytest.raises(ValueError, match="finite"):
        hungarian(np.array([[1.0, np.inf]]))


# -- one image, built from exact projections ---------------------------------------------------

SITE = two_robot_site()
CAMERA = SITE.cameras["cam1"]
KEYPOINTS = {rid: SITE.robot_model(rid).keypoints_base_m for rid in ROBOTS}


def _detection(pose: tuple[float, float, float], robot_id: str = "", noise_px: float = 0.0,
               seed: int = 0, camera: CameraModel = CAMERA) -> Detection:
    """What ``camera`` would report for a robot at ``pose``: exact projections plus noise."""
    uv, depth = project_planar(stacked_cameras((camera,)), KEYPOINTS["hsr_a"],
                               np.array([pose]))
    uv = uv[0, 0] + np.random.default_rng(seed).normal(0.0, noise_px, uv[0, 0].shape)
    assert np.all(depth > 0)
    lo, hi = uv.min(axis=0) - 4.0, uv.max(axis=0) + 4.0
    return Detection(np.array([lo[0], lo[1], hi[0], hi[1]]), 0.9, uv, np.full(len(uv), 0.9),
                     robot_id)


def _prediction(robot_id: str, pose: tuple[float, float, float], sigma_xy_m: float,
                source: str = "fused") -> RobotPrediction:
    cov = np.diag([sigma_xy_m ** 2, sigma_xy_m ** 2, 0.01 ** 2])
    return RobotPrediction(robot_id, PlanarPose(*pose), cov, source)


A_TRUE = (9.5, 5.75, 0.3)
B_TRUE = (9.5, 6.25, 0.3)  # 0.5 m beside A


def test_each_detection_goes_to_the_robot_predicted_there() -> None:
    dets = [_detection(B_TRUE, noise_px=1.0, seed=1), _detection(A_TRUE, noise_px=1.0, seed=2)]
    preds = [_prediction("hsr_a", (9.52, 5.74, 0.3), 0.03),
             _prediction("hsr_b", (9.49, 6.27, 0.31), 0.03)]
    result = associate(CAMERA, dets, preds, KEYPOINTS)
    assert [o.robot_id for o in result.outcomes] == ["hsr_b", "hsr_a"]
    assert [o.reason for o in result.outcomes] == ["assigned", "assigned"]
    assert result.by_robot == {"hsr_a": 1, "hsr_b": 0}
    # the wrong pairs are far outside the gate, the right ones well inside
    assert result.costs[0, 1] < 2.0 and result.costs[1, 0] < 2.0
    assert result.costs[0, 0] > 4.0 and result.costs[1, 1] > 4.0


def test_vague_predictions_of_two_close_robots_leave_their_detections_ambiguous() -> None:
    dets = [_detection(A_TRUE, noise_px=1.0, seed=3), _detection(B_TRUE, noise_px=1.0, seed=4)]
    # both predictions right, but 0.5 m apart with a 0.5 m sigma: a guess either way
    preds = [_prediction("hsr_a", A_TRUE, 0.5, "localization"),
             _prediction("hsr_b", B_TRUE, 0.5, "localization")]
    result = associate(CAMERA, dets, preds, KEYPOINTS)
    assert [o.reason for o in result.outcomes] == ["ambiguous", "ambiguous"]
    assert not result.by_robot and not any(o.used for o in result.outcomes)
    # the same robots 2 m apart are told apart with the same vague predictions
    far = (9.5, 7.75, 0.3)
    dets = [_detection(A_TRUE, noise_px=1.0, seed=3), _detection(far, noise_px=1.0, seed=4)]
    preds = [_prediction("hsr_a", A_TRUE, 0.5, "localization"),
             _prediction("hsr_b", far, 0.5, "localization")]
    result = associate(CAMERA, dets, preds, KEYPOINTS)
    assert [o.robot_id for o in result.outcomes] == ["hsr_a", "hsr_b"]


def test_one_prediction_that_fits_two_detections_takes_neither() -> None:
    # hsr_b has no prediction (not localized): its detection beside hsr_a must not be taken by
    # hsr_a just because it fits a vague prediction about as well
    dets = [_detection(A_TRUE, seed=5), _detection(B_TRUE, seed=6)]
    preds = [_prediction("hsr_a", (9.5, 6.0, 0.3), 0.5, "localization")]
    result = associate(CAMERA, dets, preds, KEYPOINTS, site_robots=ROBOTS)
    assert result.count("ambiguous") == 1 and result.count("unassigned") == 1
    assert not result.by_robot
    # even alone in the image, hsr_a's detection may be hsr_b's while hsr_b is unknown
    result = associate(CAMERA, dets[:1], preds, KEYPOINTS, site_robots=ROBOTS)
    assert [o.reason for o in result.outcomes] == ["ambiguous"]
    # a site without an unknown twin: the vague prediction takes it
    result = associate(CAMERA, dets[:1], preds, KEYPOINTS, site_robots=("hsr_a",))
    assert [o.reason for o in result.outcomes] == ["assigned"]
    # with a sharp prediction the other detection is out of its gate
    preds = [_prediction("hsr_a", A_TRUE, 0.03)]
    result = associate(CAMERA, dets, preds, KEYPOINTS, site_robots=ROBOTS)
    assert [o.reason for o in result.outcomes] == ["assigned", "unassigned"]
    assert result.outcomes[1].cost > AssociationConfig().gate


def test_no_prediction_no_identity() -> None:
    dets = [_detection(A_TRUE), _detection(B_TRUE)]
    result = associate(CAMERA, dets, [], KEYPOINTS, site_robots=ROBOTS)
    assert [o.reason for o in result.outcomes] == ["no_prediction", "no_prediction"]


def test_named_detections_keep_their_id_and_a_contradicting_one_is_counted() -> None:
    preds = [_prediction("hsr_a", A_TRUE, 0.03), _prediction("hsr_b", B_TRUE, 0.03)]
    dets = [_detection(A_TRUE, "hsr_a"), _detection(B_TRUE, "hsr_a"), _detection(B_TRUE, "ghost")]
    # the second one claims hsr_a too: a robot is seen once per image (the first keeps it)
    result = associate(CAMERA, dets, preds, KEYPOINTS, site_robots=ROBOTS)
    assert [o.reason for o in result.outcomes] == ["named", "unassigned", "unknown_robot"]
    # hsr_b's detection named hsr_a: the id is kept but the geometry contradicts it
    dets = [_detection(B_TRUE, "hsr_a"), _detection(A_TRUE)]
    result = associate(CAMERA, dets, preds, KEYPOINTS, site_robots=ROBOTS)
    assert result.outcomes[0].reason == "id_contradicted"
    assert result.outcomes[0].robot_id == "hsr_a" and result.outcomes[0].cost > 4.0
    # the named robot is not a candidate for the unnamed detection: hsr_b's prediction does
    # not fit it either, so it stays unassigned
    assert result.outcomes[1].reason == "unassigned"


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.floats(8.5, 11.5), st.floats(4.5, 7.5), st.floats(-3.1, 3.1),
                          st.sampled_from([0.03, 0.15, 0.5]), st.booleans()),
                min_size=1, max_size=4),
       st.integers(0, 2**31 - 1))
def test_assignment_invariants(robots, seed) -> None:
    """Random robots (pose, prediction sigma, seen or not) around cam1's view: each robot gets at
    most one detection and each detection at most one robot, only within the gate, and the
    outcome does not depend on the order of the detections."""
    rng = np.random.default_rng(seed)
    ids = tuple(f"r{i}" for i in range(len(robots)))
    keypoints = dict.fromkeys(ids, KEYPOINTS["hsr_a"])
    preds, dets, truth = [], [], []
    for rid, (x, y, theta, sigma, seen) in zip(ids, robots, strict=True):
        err = rng.normal(0.0, sigma / 2, 2)
        preds.append(_prediction(rid, (x + err[0], y + err[1], theta), sigma))
        if seen:
            dets.append(_detection((x, y, theta), noise_px=1.0, seed=int(rng.integers(1 << 30))))
            truth.append(rid)
    result = associate(CAMERA, dets, preds, keypoints, site_robots=ids)
    used = [o.robot_id for o in result.outcomes if o.used]
    assert len(used) == len(set(used)) == len(result.by_robot)
    for o in result.outcomes:
        assert o.reason in ("assigned", "ambiguous", "unassigned")
        if o.used:
            assert o.cost <= AssociationConfig().gate
    order = rng.permutation(len(dets))
    shuffled = associate(CAMERA, [dets[i] for i in order], preds, keypoints, site_robots=ids)
    assert [shuffled.outcomes[k] for k in np.argsort(order)] == list(result.outcomes)


def test_costs_need_shared_keypoints_and_overlapping_boxes() -> None:
    det = _detection(A_TRUE)
    pred = _prediction("hsr_a", A_TRUE, 0.03)
    assert association_costs(CAMERA, [det], [pred], KEYPOINTS, AssociationConfig())[0, 0] < 0.1
    few = dataclasses.replace(det, keypoint_scores=np.where(np.arange(12) < 3, 0.9, 0.0))
    assert np.isinf(association_costs(CAMERA, [few], [pred], KEYPOINTS, AssociationConfig()))
    box_elsewhere = dataclasses.replace(det, bbox_xyxy=np.array([0.0, 0.0, 5.0, 5.0]))
    assert np.isinf(association_costs(CAMERA, [box_elsewhere], [pred], KEYPOINTS,
                                      AssociationConfig()))
    # the detector's own sigmas: at or below the floor they change nothing, wider ones
    # forgive a detection that sits 10 cm off the prediction
    off = _detection((A_TRUE[0] + 0.1, A_TRUE[1], A_TRUE[2]))
    cfg = AssociationConfig()
    plain = association_costs(CAMERA, [off], [pred], KEYPOINTS, cfg)[0, 0]
    sharp = dataclasses.replace(off, keypoint_sigmas_px=np.full(12, 1.0))
    wide = dataclasses.replace(off, keypoint_sigmas_px=np.full(12, 30.0))
    costs = association_costs(CAMERA, [sharp, wide, off], [pred], KEYPOINTS, cfg)[:, 0]
    assert costs[0] == pytest.approx(plain) and costs[2] == pytest.approx(plain)
    assert costs[1] < 0.5 * plain
    other_model = Detection(det.bbox_xyxy, 0.9, det.keypoints_px[:8], det.keypoint_scores[:8])
    assert np.isinf(association_costs(CAMERA, [other_model], [pred], KEYPOINTS,
                                      AssociationConfig()))


def test_predicted_pixel_covariance_is_the_pose_covariance_through_the_projection() -> None:
    # against central differences of the solver's own projection (with distortion)
    cov = np.array([[0.04, 0.01, 0.002], [0.01, 0.09, -0.003], [0.002, -0.003, 0.01]])
    pred = RobotPrediction("hsr_a", PlanarPose(9.6, 5.9, 0.4), cov, "fused")
    cameras = list(SITE.cameras.values())
    views = predicted_views(cameras, KEYPOINTS["hsr_a"], [pred], AssociationConfig())
    cams = stacked_cameras(tuple(cameras))
    q0, h = np.array([9.6, 5.9, 0.4]), 1e-5
    J = np.stack([(project_planar(cams, KEYPOINTS["hsr_a"], (q0 + dq)[None])[0][0]
                   - project_planar(cams, KEYPOINTS["hsr_a"], (q0 - dq)[None])[0][0]) / (2 * h)
                  for dq in np.eye(3) * h], axis=-1)  # (N, M, 2, 3)
    expected = J @ cov @ np.swapaxes(J, -1, -2)
    uv, _ = project_planar(cams, KEYPOINTS["hsr_a"], q0[None])
    for i, view in enumerate(views):
        assert view.visible.all()
        np.testing.assert_allclose(view.uv[0], uv[0, i])
        # the lens distortion is left out of the uncertainty: within a few per cent
        assert np.abs(view.sigma_uv[0] - expected[i]).max() < 0.03 * np.abs(expected[i]).max()


def test_prediction_covariance_floors_and_growth() -> None:
    cfg = AssociationConfig()
    tight = predicted_covariance(np.diag([1e-6, 1e-6, 1e-8]), 0.0, "fused", cfg)
    assert np.sqrt(tight[0, 0]) == pytest.approx(cfg.min_sigma_xy_m)
    wide = predicted_covariance(np.diag([1e-4, 1e-4, 1e-6]), 0.0, "localization", cfg)
    assert np.sqrt(wide[0, 0]) == pytest.approx(cfg.unlocalized_sigma_xy_m)
    grown = predicted_covariance(np.diag([0.05 ** 2] * 3), 0.2, "fused", cfg)
    assert grown[0, 0] == pytest.approx(0.05 ** 2 + (cfg.max_speed_mps * 0.2) ** 2)
    # a faulty sender's covariance: negative variance, NaN, wrong shape
    for bad in (np.diag([-1.0, 0.01, 0.01]), np.full((3, 3), np.nan), np.eye(2)):
        cov = predicted_covariance(bad, 0.0, "localization", cfg)
        assert np.all(np.isfinite(cov)) and np.linalg.eigvalsh(cov).min() > 0
    with pytest.raises(ValueError, match="ambiguity_ratio"):
        AssociationConfig(ambiguity_ratio=1.5)


def test_router_names_the_detections_of_a_scaled_image_and_counts() -> None:
    router = DetectionRouter(SITE)
    preds = {"hsr_a": _prediction("hsr_a", A_TRUE, 0.03),
             "hsr_b": _prediction("hsr_b", B_TRUE, 0.03)}
    half = [_detection(B_TRUE), _detection(A_TRUE)]
    # a 424x240 stream of the 848x480 calibration: keypoints in half-size pixels
    half = [dataclasses.replace(d, keypoints_px=(d.keypoints_px + 0.5) / 2 - 0.5,
                                bbox_xyxy=(d.bbox_xyxy + 0.5) / 2 - 0.5) for d in half]
    msg = RobotDetections("cam1", 1, 0, 424, 240, "test", tuple(half))
    out = router.route(msg, preds)
    assert [d.robot_id for d in out.detections] == ["hsr_b", "hsr_a"]
    assert np.array_equal(out.detections[0].keypoints_px, half[0].keypoints_px)  # as sent
    out = router.route(msg, {"hsr_a": preds["hsr_a"], "hsr_b": None})
    assert [d.robot_id for d in out.detections] == ["hsr_a"]
    assert router.counters["detections_assigned"] == 3
    assert router.counters["detections_unassigned"] == 1
    assert router.counters["detections_routed.hsr_a"] == 2


# -- two identical robots on the paper lab, through the pipeline --------------------------------

pytest.importorskip("gtsam")

from backend_service.pipeline import BackendPipeline  # noqa: E402
from backend_service.pipeline_config import PipelineConfig  # noqa: E402

#: the crossing: two HSRs on lanes 0.48 m apart (centres), driving past each other
CROSSING = {"hsr_a": [(8.5, 5.76, 0.0), (11.5, 5.76, 0.0)],
            "hsr_b": [(11.5, 6.24, 180.0), (8.5, 6.24, 180.0)]}


@dataclasses.dataclass
class Replay:
    """What a two-robot run did in the pipeline, scored against the simulation's truth."""

    wrong: int  # detections routed to the robot they are not
    reasons: collections.Counter[str]
    ambiguous_at_m: list[float]  # true distance between the robots at each ambiguous one
    camera_error_m: dict[str, list[float]]
    fused_error_m: dict[str, list[float]]
    switches: int  # estimates nearer the other robot's true pose than their own
    min_distance_m: float
    pipeline: BackendPipeline
    first_prior: dict[str, str]  # robot -> prior source of its first solved frame-set
    camera_stamps_errors: dict[str, list[tuple[int, float]]] = dataclasses.field(
        default_factory=lambda: collections.defaultdict(list))


def replay(run: TwoRobotRun, config: PipelineConfig | None = None) -> Replay:
    pipeline = BackendPipeline(run.site, config)
    rep = Replay(0, collections.Counter(), [], collections.defaultdict(list),
                 collections.defaultdict(list), 0, math.inf, pipeline, {})

    def score(est, errors: dict[str, list[float]]) -> None:
        own = run.true_pose(est.robot_id, est.stamp_ns)[:2]
        if errors is rep.camera_error_m:
            rep.camera_stamps_errors[est.robot_id].append(
                (est.stamp_ns, float(np.hypot(est.x - own[0], est.y - own[1]))))
        other = run.true_pose(next(r for r in ROBOTS if r != est.robot_id), est.stamp_ns)[:2]
        xy = np.array([est.x, est.y])
        errors[est.robot_id].append(float(np.hypot(*(xy - own))))
        rep.switches += int(np.hypot(*(xy - other)) < np.hypot(*(xy - own)))

    for arrival_ns, msg in run.messages:
        out = pipeline.step(msg, arrival_ns)
        if isinstance(msg, RobotDetections) and msg.detections:
            assert pipeline.router is not None and pipeline.router.last is not None
            a, b = (run.true_pose(r, msg.stamp_ns)[:2] for r in ROBOTS)
            gap = float(np.hypot(*(a - b)))
            rep.min_distance_m = min(rep.min_distance_m, gap)
            for outcome, true_id in zip(pipeline.router.last.outcomes, run.truth[id(msg)],
                                        strict=True):
                rep.reasons[outcome.reason] += 1
                rep.wrong += int(outcome.used and outcome.robot_id != true_id)
                if outcome.reason == "ambiguous":
                    rep.ambiguous_at_m.append(gap)
        for solve in out.solves:
            if solve.result.ok:
                rep.first_prior.setdefault(solve.robot_id, solve.prior_source)
        for est in out.camera:
            score(est, rep.camera_error_m)
        for est in out.fused:
            score(est, rep.fused_error_m)
    return rep


@pytest.fixture(scope="module")
def crossing() -> TwoRobotRun:
    return two_robot_run(CROSSING, until_s=16.0)


def _check_no_switch(rep: Replay, max_error_m: float) -> None:
    assert rep.wrong == 0  # no detection (and so no correction) went to the wrong robot
    assert rep.switches == 0
    for rid in ROBOTS:
        assert len(rep.camera_error_m[rid]) > 100 and len(rep.fused_error_m[rid]) > 100
        assert max(rep.camera_error_m[rid]) < max_error_m, rid
        assert max(rep.fused_error_m[rid]) < max_error_m, rid


def test_two_identical_robots_passing_within_half_a_metre(crossing: TwoRobotRun) -> None:
    rep = replay(crossing)
    assert rep.min_distance_m <= 0.5
    _check_no_switch(rep, 0.1)
    # tracked (fused poses, a few cm), the other robot is never inside a robot's gate
    assert rep.reasons["ambiguous"] == 0
    counters = rep.pipeline.counter_snapshot()
    # one prediction per robot and one projection of both into all cameras per frame time
    # (the images of one frame-set share them)
    assert rep.pipeline.router is not None
    assert rep.pipeline.router.views.computed <= counters["sync.emitted"] // 2 + 5
    # unnamed detections before the robots' first localization arrived: counted, not guessed
    assert counters.get("association.detections_no_prediction", 0) == rep.reasons[
        "no_prediction"]
    assert counters["association.detections_assigned"] == rep.reasons["assigned"] > 1500
    # every assigned detection reached its robot's frame-sets: nothing else did
    assert (counters["association.detections_routed.hsr_a"]
            + counters["association.detections_routed.hsr_b"]) == rep.reasons["assigned"]


def test_vaguer_predictions_while_passing_leave_detections_ambiguous_not_guessed(
        crossing: TwoRobotRun) -> None:
    # predictions no sharper than 0.35 m: while the robots pass, their detections fit both
    config = PipelineConfig.from_site(crossing.site,
                                      association=AssociationConfig(min_sigma_xy_m=0.35))
    rep = replay(crossing, config)
    _check_no_switch(rep, 0.1)
    counters = rep.pipeline.counter_snapshot()
    assert rep.reasons["ambiguous"] > 20
    assert counters["association.detections_ambiguous"] == rep.reasons["ambiguous"]
    assert max(rep.ambiguous_at_m) < 1.2  # only while they are close
    assert (counters["association.detections_routed.hsr_a"]
            + counters["association.detections_routed.hsr_b"]) == rep.reasons["assigned"]


def test_robots_not_yet_localized_start_side_by_side_and_are_told_apart_once_apart() -> None:
    # both start 0.48 m apart, known only by their own localization (wide): no detection is
    # used until they have driven apart; then each is initialized from its localization
    run = two_robot_run({"hsr_a": [(9.5, 5.76, 0.0), (9.5, 3.6, -90.0)],
                         "hsr_b": [(9.5, 6.24, 0.0), (9.5, 8.4, 90.0)]}, until_s=12.0)
    rep = replay(run)
    assert rep.wrong == 0 and rep.switches == 0
    assert rep.reasons["ambiguous"] > 200
    assert min(rep.ambiguous_at_m) < 0.5 and max(rep.ambiguous_at_m) < 1.5
    for rid in ROBOTS:
        assert len(rep.camera_error_m[rid]) > 30
        assert max(rep.camera_error_m[rid]) < 0.1
    assert rep.first_prior == {"hsr_a": "localization", "hsr_b": "localization"}


def test_while_a_robot_has_no_prediction_its_twin_is_not_initialized_from_a_guess() -> None:
    # hsr_b's bridge publishes nothing for the first 3 s and the cameras never had it: hsr_b
    # could be anywhere, so hsr_a, known only by its own localization (0.5 m), takes no
    # detection either (the one near it may be hsr_b's); counted, not guessed. Once hsr_b's
    # localization arrives both are initialized, 3 m apart.
    run = two_robot_run({"hsr_a": [(8.6, 5.0, 0.0), (9.6, 5.0, 0.0)],
                         "hsr_b": [(11.6, 7.0, 180.0), (10.6, 7.0, 180.0)]}, until_s=7.0)
    start_ns = run.messages[0][0]
    bridge_up_ns = start_ns + 3 * 10**9
    messages = [(a, m) for a, m in run.messages if not (
        isinstance(m, PoseEstimate) and m.robot_id == "hsr_b" and a < bridge_up_ns)]
    rep = replay(dataclasses.replace(run, messages=messages))
    assert rep.wrong == 0 and rep.switches == 0
    first = {rid: min(stamp for stamp, _ in rep.camera_stamps_errors[rid]) for rid in ROBOTS}
    assert all(t > bridge_up_ns - 100_000_000 for t in first.values()), first
    assert rep.reasons["ambiguous"] > 50  # hsr_a's detections while hsr_b was unknown
    for rid in ROBOTS:
        assert len(rep.camera_error_m[rid]) > 20 and max(rep.camera_error_m[rid]) < 0.1


def test_the_backend_node_publishes_each_robots_pose_from_unnamed_detections(
        crossing: TwoRobotRun) -> None:
    from backend_service.service import BackendNode
    from core.runtime import ScriptedRunner
    from protocol import encode, keys
    from protocol.messages import Odometry

    site = crossing.site.name
    node = BackendNode(crossing.site)
    runner = ScriptedRunner(node)
    for arrival_ns, msg in crossing.messages:
        if isinstance(msg, RobotDetections):
            key = keys.detections_key(site, msg.camera_id)
        elif isinstance(msg, Odometry):
            key = keys.odom_key(site, msg.robot_id)
        else:
            assert isinstance(msg, PoseEstimate)
            key = keys.localization_key(site, msg.robot_id)
        runner.tick(arrival_ns)
        runner.feed(key, encode(msg), arrival_ns)
    poses: dict[str, list[float]] = collections.defaultdict(list)
    for out in runner.published:
        for rid in ROBOTS:
            if out.key == keys.pose_key(site, rid):
                est = out.message
                assert isinstance(est, PoseEstimate) and est.robot_id == rid
                true_xy = crossing.true_pose(rid, est.stamp_ns)[:2]
                poses[rid].append(float(np.hypot(est.x - true_xy[0], est.y - true_xy[1])))
    for rid in ROBOTS:
        assert len(poses[rid]) > 100 and max(poses[rid]) < 0.1, rid
    counters = node.counters()
    assert counters["association.detections_assigned"] > 1500
    assert counters.get("association.detections_ambiguous", 0) == 0
    _state, detail = node.state()
    assert "detections assigned" in detail and "robots localized: hsr_a,hsr_b" in detail


def test_the_backend_status_names_robots_without_prediction_and_contradicted_ids() -> None:
    from backend_service.service import BackendNode

    node = BackendNode(SITE)
    t0 = 1_700_000_000 * 10**9
    cov = np.diag([0.01, 0.01, 0.001])
    node.handle("loc", PoseEstimate("hsr_a", t0, 0, *A_TRUE, cov, "robot"), t0)
    # 2.5 m from hsr_a's localization (sigma >= 0.5 m), across cam3's line of sight
    far = (11.0, 3.75, 0.3)
    cam3 = SITE.cameras["cam3"]
    msg = RobotDetections("cam3", t0 - cam3.clock_offset_ns, 0, cam3.width, cam3.height,
                          "test", (_detection(far, "hsr_a", camera=cam3),))
    node.handle("det", msg, t0 + 1)
    state, detail = node.state()
    assert state == "degraded" and "contradict" in detail
    assert "no prediction: hsr_b" in detail
    assert node.counters()["association.detections_id_contradicted"] == 1
    state, _ = node.state()  # reported once, not forever
    assert state == "ok"


def test_a_robot_in_no_image_is_not_projected_further_and_changes_no_cost() -> None:
    # a site's predicted views compute the pixel covariance only for the (camera, robot) pairs
    # with a keypoint in the image; a robot a camera cannot see costs inf there, as before
    near = _prediction("hsr_a", (9.6, 5.9, 0.4), 0.05)
    far = _prediction("hsr_b", (400.0, -300.0, 0.0), 0.05)  # outside most cameras' views
    cameras = list(SITE.cameras.values())
    both = predicted_views(cameras, KEYPOINTS["hsr_a"], [near, far], AssociationConfig())
    alone = {r: predicted_views(cameras, KEYPOINTS["hsr_a"], [p], AssociationConfig())
             for r, p in (("near", near), ("far", far))}
    unseen = 0
    for i, v2 in enumerate(both):
        for row, who in ((0, "near"), (1, "far")):
            v1 = alone[who][i]
            np.testing.assert_array_equal(v2.visible[row], v1.visible[0])
            if v1.visible[0].any():
                np.testing.assert_allclose(v2.sigma_uv[row], v1.sigma_uv[0], rtol=1e-12)
                np.testing.assert_allclose(v2.box_lo[row], v1.box_lo[0], rtol=1e-12)
                np.testing.assert_allclose(v2.info[:, row], v1.info[:, 0], rtol=1e-12)
            else:
                unseen += 1
                assert not np.any(v2.sigma_uv[row]) and np.all(np.isinf(v2.box_lo[row]))
    assert unseen >= 3
    assert not alone["far"][cameras.index(CAMERA)].visible.any()
    det = _detection((9.6, 5.9, 0.4), noise_px=0.5)
    costs = association_costs(CAMERA, [det], [near, far], KEYPOINTS, AssociationConfig())
    single = association_costs(CAMERA, [det], [near], KEYPOINTS, AssociationConfig())
    assert costs[0, 0] == pytest.approx(single[0, 0]) and np.isinf(costs[0, 1])


def test_the_one_pair_shortcut_gives_the_costs_of_the_general_path() -> None:
    # one detection takes a shortcut without the (D, R) arrays; its costs must be the general
    # path's (here with a second detection beside it), box gate, keypoint count, detector
    # sigmas and clipping included
    rng = np.random.default_rng(7)
    cfg = AssociationConfig()
    checked = finite = 0
    for k in range(60):
        true = (9.5 + rng.uniform(-1, 1), 5.9 + rng.uniform(-1, 1), rng.uniform(-3, 3))
        pred = _prediction("hsr_a", (true[0] + rng.normal(0, 0.1), true[1] + rng.normal(0, 0.1),
                                     true[2] + rng.normal(0, 0.05)), rng.uniform(0.02, 0.3))
        det = _detection(true, noise_px=rng.uniform(0.3, 8.0), seed=k)
        scores = det.keypoint_scores.copy()
        scores[rng.uniform(size=scores.shape) < 0.3] = 0.0  # some dropped keypoints
        det = dataclasses.replace(det, keypoint_scores=scores)
        if k % 3 == 0:
            det = dataclasses.replace(det, keypoint_sigmas_px=rng.uniform(0.2, 5.0, 12))
        if k % 7 == 0:  # a box beside the prediction: the gate
            det = dataclasses.replace(det, bbox_xyxy=det.bbox_xyxy + 300.0)
        other = _detection((true[0] + 0.8, true[1], true[2]), seed=100 + k)
        twin = _prediction("hsr_b", (true[0] + rng.uniform(-0.6, 0.6), true[1] + 0.5,
                                     true[2]), 0.1)
        one = association_costs(CAMERA, [det], [pred, twin], KEYPOINTS, cfg)[0]
        general = association_costs(CAMERA, [det, other], [pred, twin], KEYPOINTS, cfg)[0]
        np.testing.assert_array_equal(np.isinf(one), np.isinf(general))
        np.testing.assert_allclose(one[np.isfinite(one)], general[np.isfinite(general)],
                                   rtol=1e-12)
        checked += 1
        finite += int(np.isfinite(one).sum())
    assert checked == 60 and 10 < finite < 120



def test_one_detections_decision_is_the_assignments() -> None:
    # a lone unnamed detection is decided in closed form; on random cost rows (ties, values
    # within and beyond the gate and the ambiguity margin, vague predictions, robots of the
    # site without a prediction) it must decide exactly as the gated assignment of one row
    rng = np.random.default_rng(11)
    cfg = AssociationConfig()
    kp_b = KEYPOINTS["hsr_a"].copy()  # another model's keypoints (another object)
    models = {"hsr_a": KEYPOINTS["hsr_a"], "hsr_b": KEYPOINTS["hsr_a"], "hsr_c": kp_b}
    margin = -math.log(cfg.ambiguity_ratio)
    reasons: collections.Counter[str] = collections.Counter()
    for _ in range(600):
        n = int(rng.integers(1, 4))
        ids = list(models)[:n]
        preds = [_prediction(rid, (9.5, 5.9, 0.0), float(rng.choice([0.03, 0.3])))
                 for rid in ids]
        base = rng.uniform(0.0, cfg.gate * 1.2)
        row = base + rng.choice([0.0, 0.5 * margin / max(base, 0.1), 3.0, np.inf], size=n)
        if rng.uniform() < 0.2:
            row[rng.integers(n)] = row[0]  # an exact tie
        unpredicted = [set(), {None}, {id(KEYPOINTS["hsr_a"])}, {id(kp_b)}][rng.integers(4)]
        fast = association._one_detection(row, preds, models, unpredicted, cfg)
        general = association._assign_rows(row[None, :], preds, models, unpredicted, cfg)[0]
        assert (fast.robot_id, fast.reason) == (general.robot_id, general.reason)
        assert fast.cost == general.cost or (math.isinf(fast.cost) and math.isinf(general.cost))
        reasons[fast.reason] += 1
    assert min(reasons[r] for r in ("assigned", "ambiguous", "unassigned")) > 50, reasons


def test_the_cameras_seeing_a_robot_are_the_only_ones_that_can_give_it_a_detection() -> None:
    # what a robot's frame-set waits for on a site with several robots: the cameras where its
    # prediction has a keypoint in the image (and any camera outside the view cache)
    pose = (12.0, 8.0, 0.4)  # seen by cam1, cam2, cam4
    near = _prediction("hsr_a", pose, 0.05)
    far = _prediction("hsr_b", (400.0, -300.0, 0.0), 0.05)
    router = DetectionRouter(SITE)
    preds = {"hsr_a": near, "hsr_b": far}
    cameras = list(SITE.cameras.values())
    views = predicted_views(cameras, KEYPOINTS["hsr_a"], [near, far], AssociationConfig())
    seeing = {c.camera_id for c, v in zip(cameras, views, strict=True) if v.visible[0].any()}
    assert CAMERA.camera_id in seeing and len(seeing) < len(cameras)
    assert router.cameras_seeing("hsr_a", preds) == seeing
    assert router.cameras_seeing("hsr_b", preds) == {
        c.camera_id for c, v in zip(cameras, views, strict=True) if v.visible[1].any()}
    assert router.cameras_seeing("hsr_b", {"hsr_a": near, "hsr_b": None}) is None
    assert router.cameras_seeing("nobody", preds) is None
    # the robot as cam1 sees it, reported by every camera: only those seeing it assign it
    det = _detection(pose)
    for cam in cameras:
        out = associate(cam, [det], [near, far], KEYPOINTS)
        assert (out.outcomes[0].robot_id == "hsr_a") <= (cam.camera_id in seeing)
    assert associate(CAMERA, [det], [near, far], KEYPOINTS).outcomes[0].robot_id == "hsr_a"
    # a backend of some cameras: the others are projected on their own, so they count
    some = sorted(seeing)[:1]
    router.serve_cameras(some)
    assert router.cameras_seeing("hsr_a", preds) == (
        set(some) | (set(SITE.cameras) - set(some)))
