"""Pose-graph fusion (real GTSAM ISAM2) on synthetic runs with drifting odometry."""

from __future__ import annotations

import math
import tracemalloc

import numpy as np
import pytest

from backend_service.fusion import FusionConfig, PoseGraphFusion
from protocol.messages import Odometry, PoseEstimate
from simulation.synthetic_run import CameraNoise, SyntheticRoute, make_synthetic_run, replay

ROBOT = "hsr1"
T0 = 1_700_000_000_000_000_000
MS = 1_000_000


def _rms(errors: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(errors))))


def _odom(stamp_ns: int, x: float, y: float = 0.0, theta: float = 0.0, seq: int = 0) -> Odometry:
    return Odometry(robot_id=ROBOT, stamp_ns=stamp_ns, seq=seq, x=x, y=y, theta=theta)


def _camera(stamp_ns: int, x: float, y: float = 0.0, theta: float = 0.0,
            sigma_m: float = 0.03, sigma_rad: float = 0.02, robot_id: str = ROBOT) -> PoseEstimate:
    return PoseEstimate(
        robot_id=robot_id, stamp_ns=stamp_ns, seq=0, x=x, y=y, theta=theta,
        covariance=np.diag([sigma_m**2, sigma_m**2, sigma_rad**2]), source="cameras",
    )


def _straight_line(fusion: PoseGraphFusion, seconds: float, speed_m_s: float = 0.5,
                   hz: float = 30.0, start_ns: int = T0) -> list[PoseEstimate | None]:
    """Odometry of a robot driving along +x (odom == world here)."""
    out = []
    for i in range(int(seconds * hz) + 1):
        t = i / hz
        out.append(fusion.add_odometry(
            _odom(start_ns + int(t * 1e9), speed_m_s * t, seq=i)))
    return out


@pytest.fixture(scope="module")
def stops_run():
    """4 min of driving between static waypoints; one camera estimate per stop (sparse)."""
    run = make_synthetic_run(240.0, seed=1)
    fusion = PoseGraphFusion(run.robot_id)
    fused = replay(run, fusion)
    return run, fusion, fused


def test_fused_ate_at_least_3x_lower_than_odometry(stops_run):
    run, fusion, fused = stops_run
    valid = ~np.isnan(fused[:, 0])
    # fused poses exist from the first camera estimate on (the first stop) to the end
    assert valid.sum() > 0.95 * len(valid)
    fused_ate = _rms(np.hypot(*(fused[valid, :2] - run.truth[valid, :2]).T))
    odom_ate = _rms(np.hypot(*(run.odometry_in_world()[valid, :2] - run.truth[valid, :2]).T))
    assert odom_ate > 0.5  # the odometry really drifts
    assert fused_ate * 3.0 <= odom_ate, (fused_ate, odom_ate)
    assert fusion.counters["camera_fused"] == len(run.shots)


def test_fused_beats_camera_only_at_poorly_observed_stops(stops_run):
    run, fusion, fused = stops_run
    cam_err, online_err, smoothed_err = [], [], []
    # the first stop anchors the graph: with nothing to fuse it with, fused == camera there
    for shot in run.shots[1:]:
        if not shot.poorly_observed:
            continue
        cam_err.append(math.hypot(*(shot.pose[:2] - shot.truth[:2])))
        # online output while still at the stop, after the (late) estimate was fused
        deliver = shot.stamp_ns + shot.latency_ns
        window = (run.stamps_ns > deliver) & (run.stamps_ns < deliver + 1_000 * MS)
        online_err.append(np.mean(np.hypot(*(fused[window, :2] - shot.truth[:2]).T)))
        pose = fusion.pose_at(shot.stamp_ns)
        assert pose is not None
        smoothed_err.append(math.hypot(pose.x - shot.truth[0], pose.y - shot.truth[1]))
    assert len(cam_err) >= 4
    assert np.mean(online_err) < 0.6 * np.mean(cam_err), (online_err, cam_err)
    assert np.mean(smoothed_err) < 0.6 * np.mean(cam_err), (smoothed_err, cam_err)


def test_marginal_covariance_on_every_fused_pose():
    fusion = PoseGraphFusion(ROBOT)
    assert _straight_line(fusion, 1.0, speed_m_s=0.0)[-1] is None  # not anchored yet
    fusion.add_camera_estimate(_camera(T0 + 500 * MS, 2.0, 1.0, 0.0, sigma_m=0.03))
    outs = _straight_line(fusion, 10.0, start_ns=T0 + 1_100 * MS)
    # odometry restarted at x=0 but the anchor holds: fused x = 2 + (odom since the anchor)
    assert all(o is not None for o in outs)
    sig = [math.sqrt(o.covariance[0, 0] + o.covariance[1, 1]) for o in outs]
    for o in outs:
        assert o.source == "fused" and o.covariance.shape == (3, 3)
        assert np.all(np.linalg.eigvalsh(o.covariance) > 0)
    assert sig[0] == pytest.approx(0.03 * math.sqrt(2), rel=0.2)
    assert sig[-1] > 2 * sig[0]  # grows with the distance driven since the camera estimate
    stamp = outs[-1].stamp_ns
    after = fusion.add_camera_estimate(_camera(stamp - 100 * MS, 6.95, 1.0, 0.0, sigma_m=0.02))
    assert after is not None
    assert math.sqrt(after.covariance[0, 0] + after.covariance[1, 1]) < 0.5 * sig[-1]


def test_late_estimate_lands_at_its_own_stamp():
    run = make_synthetic_run(120.0, seed=2, cameras=CameraNoise(moving_camera_hz=2.0))
    grid = run.stamps_ns[::5]

    def smoothed(latency_ns: int, stamp_shift_ns: int = 0) -> tuple[np.ndarray, PoseGraphFusion]:
        fusion = PoseGraphFusion(run.robot_id)
        replay(run, fusion, latency_ns=latency_ns, stamp_shift_ns=stamp_shift_ns)
        poses = [fusion.pose_at(int(s)) for s in grid]
        return np.array([[p.x, p.y] if p else [np.nan, np.nan] for p in poses]), fusion

    on_time, _ = smoothed(0)
    late, late_fusion = smoothed(200 * MS)
    # most late estimates fell between two keyframes that already existed: factors were split
    assert late_fusion.counters["keyframes_inserted"] >= 5
    assert late_fusion.counters["camera_fused"] == len(run.shots)
    both = ~np.isnan(on_time[:, 0]) & ~np.isnan(late[:, 0])
    assert both.sum() > 0.9 * len(grid)
    diff_late = np.hypot(*(late[both] - on_time[both]).T)
    assert diff_late.max() < 0.005, diff_late.max()
    # control: the same estimates attached at their arrival time ("now") are visibly wrong
    now, _ = smoothed(200 * MS, stamp_shift_ns=200 * MS)
    both = both & ~np.isnan(now[:, 0])
    diff_now = np.hypot(*(now[both] - on_time[both]).T)
    assert np.mean(diff_now) > 20 * max(np.mean(diff_late), 1e-4)


def test_estimate_newer_than_odometry_waits_for_it():
    fusion = PoseGraphFusion(ROBOT)
    _straight_line(fusion, 1.0)  # odometry up to T0 + 1 s, x = 0.5
    assert fusion.add_camera_estimate(_camera(T0 + 1_200 * MS, 10.6, 0.0)) is None
    assert fusion.counters["camera_deferred"] == 1 and not fusion.anchored
    out = fusion.add_odometry(_odom(T0 + 1_300 * MS, 0.65, seq=99))
    assert fusion.anchored and out is not None
    # anchored at the estimate's stamp (odom x = 0.6 there), then 5 cm more of odometry
    assert out.x == pytest.approx(10.65, abs=1e-3)
    # too far in the future: rejected, not queued
    assert fusion.add_camera_estimate(_camera(T0 + 5_000 * MS, 10.0)) is None
    assert fusion.counters["camera_future"] == 1


def test_robust_prior_limits_an_outlier():
    def run(kernel: str) -> float:
        fusion = PoseGraphFusion(ROBOT, FusionConfig(robust_kernel=kernel))
        _straight_line(fusion, 0.2, speed_m_s=0.0)
        fusion.add_camera_estimate(_camera(T0 + 100 * MS, 0.0, sigma_m=0.03))
        _straight_line(fusion, 2.0, start_ns=T0 + 300 * MS)
        # an outlier 1.5 m off with a confident covariance, 1 m travelled after the anchor
        out = fusion.add_camera_estimate(_camera(T0 + 2_300 * MS, 2.5, sigma_m=0.03))
        assert out is not None
        return abs(out.x - 1.0)

    assert run("none") > 0.5
    assert run("huber") < 0.5 * run("none")
    assert run("cauchy") < 0.5 * run("none")


def test_bounded_memory_over_a_long_run():
    config = FusionConfig(window_s=30.0, max_keyframes=80, marginalize_batch=20)
    run = make_synthetic_run(900.0, seed=3, route=SyntheticRoute(odom_hz=15.0),
                             cameras=CameraNoise(moving_camera_hz=1.0))
    fusion = PoseGraphFusion(run.robot_id, config)
    n = len(run.stamps_ns)
    checkpoints = {n * k // 6 for k in range(2, 7)} | {n - 1}
    deliveries = sorted((s.stamp_ns + s.latency_ns, k) for k, s in enumerate(run.shots))
    sizes, traced, keyframes = [], [], []
    d = 0
    tracemalloc.start()
    try:
        for i in range(n):
            fusion.add_odometry(run.odometry(i))
            while d < len(deliveries) and deliveries[d][0] <= run.stamps_ns[i]:
                fusion.add_camera_estimate(run.shots[deliveries[d][1]].estimate(ROBOT, d))
                d += 1
            if i in checkpoints:
                sizes.append((fusion.graph_size(), fusion.buffer_sizes()))
                traced.append(tracemalloc.get_traced_memory()[0])
                keyframes.append(
                    fusion.counters["keyframes_created"] + fusion.counters["camera_fused"]
                )
    finally:
        tracemalloc.stop()
    bound = config.max_keyframes + config.marginalize_batch
    for (variables, factors), buffers in sizes:
        assert variables <= bound and buffers["keyframes"] <= bound
        # one between factor per keyframe and at most a few camera priors per keyframe
        assert factors <= 3 * bound
        assert buffers["odometry_samples"] <= 15 * (config.window_s + 30)
    assert fusion.counters["marginalizations"] >= 20
    # Python-side memory is flat from 5 to 15 min although hundreds of keyframes and priors
    # were added in between (a leaked record per keyframe would be several hundred kB)
    assert keyframes[-1] - keyframes[0] > 500
    assert traced[-1] - traced[0] < 100_000, traced
    # and the fusion still tracks the robot after many marginalizations
    last = fusion.latest()
    assert last is not None
    assert math.hypot(last.x - run.truth[-1, 0], last.y - run.truth[-1, 1]) < 0.3


def test_marginalization_matches_the_full_graph():
    """A small window gives the same fused poses and covariances as keeping everything: the
    marginal prior carries exactly what the dropped factors said (no double counting)."""

    def run(config: FusionConfig) -> tuple[np.ndarray, PoseGraphFusion]:
        rng = np.random.default_rng(0)
        fusion = PoseGraphFusion(ROBOT, config)
        out = []
        for i in range(30 * 60):
            t = i / 30
            o = fusion.add_odometry(_odom(T0 + int(t * 1e9), 0.2 * t, seq=i))
            if i % 15 == 5:  # noisy estimates 100 ms late, 2 Hz
                dx, dy, th = rng.normal(0, 0.2), rng.normal(0, 0.2), rng.normal(0, 0.1)
                x, y = 0.2 * (t - 0.1) + dx, dy
                r = fusion.add_camera_estimate(
                    _camera(T0 + int(t * 1e9) - 100 * MS, x, y, th, sigma_m=0.2, sigma_rad=0.1))
                o = r or o
            if o is not None:
                out.append((o.x, o.y, math.sqrt(o.covariance[0, 0]), math.sqrt(o.covariance[1, 1])))
        return np.array(out), fusion

    full, full_fusion = run(FusionConfig(robust_kernel="none"))
    windowed, fusion = run(FusionConfig(robust_kernel="none", window_s=5.0, max_keyframes=20,
                                        marginalize_batch=5))
    assert full_fusion.counters["marginalizations"] == 0
    assert fusion.counters["marginalizations"] >= 10
    assert full.shape == windowed.shape
    assert np.abs(windowed[:, :2] - full[:, :2]).max() < 0.002
    ratio = windowed[:, 2:] / full[:, 2:]
    assert ratio.min() > 0.99 and ratio.max() < 1.01, (ratio.min(), ratio.max())


def test_deferred_marginalization_waits_for_maintain_and_matches_inline():
    """A service's pose graph marginalizes in maintain() (its worker's idle time), never inside
    the call that filled the window until the backlog reaches twice the batch; the poses are
    those of the inline marginalization."""
    config = FusionConfig(robust_kernel="none", window_s=5.0, max_keyframes=20,
                          marginalize_batch=5)

    def run(deferred: bool, maintain_every: int | None) -> tuple[np.ndarray, PoseGraphFusion,
                                                                  list[int]]:
        rng = np.random.default_rng(1)
        fusion = PoseGraphFusion(ROBOT, config, deferred_marginalization=deferred)
        out, sizes = [], []
        for i in range(30 * 40):
            t = i / 30
            o = fusion.add_odometry(_odom(T0 + int(t * 1e9), 0.2 * t, seq=i))
            if i % 15 == 5:
                x = 0.2 * (t - 0.1) + rng.normal(0, 0.2)
                r = fusion.add_camera_estimate(_camera(T0 + int(t * 1e9) - 100 * MS, x,
                                                       rng.normal(0, 0.2), sigma_m=0.2))
                o = r or o
            sizes.append(fusion.num_keyframes)
            if maintain_every and i % maintain_every == 0:
                while fusion.maintain():
                    pass
            if o is not None:
                out.append((o.x, o.y, math.sqrt(o.covariance[0, 0])))
        return np.array(out), fusion, sizes

    inline, _, inline_sizes = run(False, None)
    # no maintain(): only the overdue backlog marginalizes, inside the calls, and is counted
    never, never_fusion, never_sizes = run(True, None)
    assert never_fusion.counters["marginalizations_overdue"] >= 5
    assert never_fusion.counters["marginalizations"] == never_fusion.counters[
        "marginalizations_overdue"]
    assert max(never_sizes) <= config.max_keyframes + 2 * config.marginalize_batch - 1
    assert max(never_sizes) > max(inline_sizes)
    # maintain() every 10 odometry messages: nothing overdue, the window is kept
    kept, fusion, sizes = run(True, 10)
    assert fusion.counters["marginalizations_overdue"] == 0
    assert fusion.counters["marginalizations"] >= 10
    assert fusion.marginalization_due == 0
    assert max(sizes) <= config.max_keyframes + 2 * config.marginalize_batch - 1
    assert kept.shape == inline.shape == never.shape
    assert np.abs(kept[:, :2] - inline[:, :2]).max() < 0.002
    ratio = kept[:, 2] / inline[:, 2]
    assert ratio.min() > 0.99 and ratio.max() < 1.01, (ratio.min(), ratio.max())
    assert not PoseGraphFusion(ROBOT).maintain()  # nothing to do on an empty graph


def test_garbage_is_counted_never_raised():
    fusion = PoseGraphFusion(ROBOT)
    _straight_line(fusion, 0.5, speed_m_s=0.0)
    assert fusion.add_camera_estimate(_camera(T0 + 400 * MS, 1.0)) is not None
    outs = _straight_line(fusion, 20.0, start_ns=T0 + 600 * MS)
    assert outs[-1] is not None
    now = outs[-1].stamp_ns

    nan_est = _camera(now - 100 * MS, 1.0)
    object.__setattr__(nan_est, "x", float("nan"))  # a corrupted object bypassing validation
    nan_cov = _camera(now - 100 * MS, 1.0)
    object.__setattr__(nan_cov, "covariance", np.full((3, 3), np.nan))
    bad_shape = _camera(now - 100 * MS, 1.0)
    object.__setattr__(bad_shape, "covariance", np.eye(2))
    indefinite = _camera(now - 100 * MS, 1.0)
    object.__setattr__(indefinite, "covariance", np.array([[1.0, 2, 0], [2, 1, 0], [0, 0, 1]]))
    zero_cov = PoseEstimate(robot_id=ROBOT, stamp_ns=now - 100 * MS, seq=0, x=1.0, y=0.0,
                            theta=0.0, covariance=np.zeros((3, 3)), source="cameras")
    fused_src = PoseEstimate(robot_id=ROBOT, stamp_ns=now - 100 * MS, seq=0, x=1.0, y=0.0,
                             theta=0.0, covariance=np.eye(3) * 1e-3, source="fused")
    cases = {
        "camera_invalid": [None, "garbage", {"x": 1.0}, _odom(now, 1.0), nan_est],
        "camera_bad_covariance": [nan_cov, bad_shape, indefinite, zero_cov],
        "camera_wrong_robot": [_camera(now - 100 * MS, 1.0, robot_id="other")],
        "camera_fused_source": [fused_src],
        "camera_uninformative": [_camera(now - 100 * MS, 1.0, sigma_m=50.0)],
        "camera_too_old": [_camera(T0, 1.0), _camera(T0 + 100 * MS, 1.0)],
        "camera_future": [_camera(now + 10_000 * MS, 1.0)],
    }
    for reason, inputs in cases.items():
        for bad in inputs:
            assert fusion.add_camera_estimate(bad) is None  # type: ignore[arg-type]
        assert fusion.counters[reason] == len(inputs), (reason, dict(fusion.counters))

    nan_odom = _odom(now + 33 * MS, 1.0)
    object.__setattr__(nan_odom, "theta", float("inf"))
    odo_cases = {
        "odometry_invalid": [None, 3.5, nan_odom, _camera(now, 1.0)],
        "odometry_wrong_robot": [Odometry(robot_id="other", stamp_ns=now + 33 * MS, seq=0,
                                          x=0.0, y=0.0, theta=0.0)],
        "odometry_out_of_order": [_odom(now, 0.0), _odom(now - 500 * MS, 0.0)],
    }
    for reason, inputs in odo_cases.items():
        for bad in inputs:
            assert fusion.add_odometry(bad) is None  # type: ignore[arg-type]
        assert fusion.counters[reason] == len(inputs), reason
    assert fusion.last_reject_reason == "odometry_out_of_order"
    # the fusion is unharmed: the next good odometry gives the same pose as before
    good = fusion.add_odometry(_odom(now + 33 * MS, 10.0))
    assert good is not None and good.x == pytest.approx(outs[-1].x, abs=1e-6)


def test_odometry_jump_keeps_the_map_anchor():
    fusion = PoseGraphFusion(ROBOT)
    _straight_line(fusion, 0.5, speed_m_s=0.0)
    fusion.add_camera_estimate(_camera(T0 + 400 * MS, 3.0, 2.0))
    before = fusion.add_odometry(_odom(T0 + 600 * MS, 0.0, seq=50))
    # the robot's odometry restarts elsewhere (driver restart): 40 m jump in 33 ms
    after = fusion.add_odometry(_odom(T0 + 633 * MS, 40.0, 7.0, 1.0, seq=51))
    assert fusion.counters["odometry_jump"] == 1
    assert after is not None and before is not None
    assert math.hypot(after.x - before.x, after.y - before.y) < 1e-6
    assert after.covariance[0, 0] > before.covariance[0, 0]


def test_initial_pose_anchors_without_cameras():
    fusion = PoseGraphFusion(ROBOT)
    assert _straight_line(fusion, 0.5, speed_m_s=0.0)[-1] is None
    assert fusion.counters["uninitialized"] > 0
    init = _camera(T0 + 500 * MS, 1.0, 2.0, 0.5, sigma_m=0.1)
    out = fusion.set_initial_pose(init)
    assert out is not None and out.x == pytest.approx(1.0) and out.theta == pytest.approx(0.5)
    assert fusion.counters["initial_fused"] == 1


def test_config_is_validated():
    with pytest.raises(ValueError, match="robust_kernel"):
        FusionConfig(robust_kernel="tukey-ish")
    with pytest.raises(ValueError, match="keyframe_distance_m"):
        FusionConfig(keyframe_distance_m=-1.0)
    with pytest.raises(ValueError, match="window_s"):
        FusionConfig(window_s=float("nan"))


def test_a_poisoned_stamp_is_recovered_from():
    """One odometry message stamped 2**63 - 1 (issue #17) used to make every later message
    "out of order" forever. After out_of_order_reset_count consistent messages the fusion
    restarts from them, keeps the map anchor, and follows the robot again."""
    fusion = PoseGraphFusion(ROBOT, FusionConfig(out_of_order_reset_count=25))
    _straight_line(fusion, 1.0, speed_m_s=0.0)
    fusion.add_camera_estimate(_camera(T0 + 500 * MS, 3.0, 2.0))
    anchored = fusion.add_odometry(_odom(T0 + 1100 * MS, 0.0, seq=40))
    assert anchored is not None and anchored.x == pytest.approx(3.0, abs=0.05)
    assert fusion.add_odometry(_odom(2**63 - 1, 0.0, seq=41)) is not None  # accepted, alas
    out = []
    for i in range(60):  # 2 s at 30 Hz, driving +x at 0.5 m/s
        out.append(fusion.add_odometry(_odom(T0 + 1133 * MS + i * 33 * MS, 0.5 * i * 0.033,
                                             seq=42 + i)))
    assert fusion.counters["odometry_out_of_order"] == 24
    assert fusion.counters["odometry_stamp_reset"] == 1
    assert all(o is None for o in out[:24]) and all(o is not None for o in out[25:])
    # the anchor survived: the fused pose moves with the odometry from x = 3 again (the 0.4 m
    # driven while the messages were refused is lost until the next camera estimate)
    assert out[-1].x == pytest.approx(3.0 + 0.5 * (59 - 24) * 0.033, abs=0.01)
    assert out[-1].stamp_ns < 2**62
    # duplicates (not in order among themselves) and a replay of the last second (a bridge
    # after a link loss: in order, but close to the newest stamp) never trigger a reset
    fusion2 = PoseGraphFusion(ROBOT, FusionConfig(out_of_order_reset_count=5))
    _straight_line(fusion2, 1.0, speed_m_s=0.0)
    for _ in range(20):
        fusion2.add_odometry(_odom(T0 + 500 * MS, 0.0))
    _straight_line(fusion2, 1.0, speed_m_s=0.0, start_ns=T0 + 10 * MS)
    assert fusion2.counters["odometry_out_of_order"] == 20 + 30
    assert fusion2.counters["odometry_stamp_reset"] == 0
