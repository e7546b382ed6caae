"""Hypothesis strategies producing valid protocol messages (including empty and large arrays)."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from protocol.messages import (
    CameraImage,
    Detection,
    Odometry,
    PoseCorrection,
    PoseEstimate,
    RobotDetections,
    SemanticCloud,
    ServiceStatus,
)

ids = st.from_regex(r"[A-Za-z0-9_.\-]{1,64}", fullmatch=True)
stamps = st.integers(min_value=0, max_value=2**63 - 1)
seqs = st.integers(min_value=0, max_value=2**40)
finite = st.floats(allow_nan=False, allow_infinity=False, width=64, min_value=-1e9, max_value=1e9)
unit = st.floats(min_value=0.0, max_value=1.0, allow_nan=False)
angles = st.floats(min_value=-math.pi, max_value=math.pi, allow_nan=False)


def _float_arrays(dtype: str, shape, lo: float = -1e4, hi: float = 1e4):
    return hnp.arrays(
        dtype=dtype,
        shape=shape,
        elements=st.floats(lo, hi, allow_nan=False, allow_infinity=False, width=32),
    )


@st.composite
def covariances(draw) -> np.ndarray:
    a = draw(_float_arrays("float64", (3, 3), -10.0, 10.0))
    return a @ a.T


@st.composite
def detections(draw) -> Detection:
    m = draw(st.integers(0, 40))
    lo = draw(st.floats(0, 800))
    hi = lo + draw(st.floats(0, 400))
    return Detection(
        bbox_xyxy=np.array([lo, lo / 2, hi, hi / 2 + 1]),
        score=draw(unit),
        keypoints_px=draw(_float_arrays(draw(st.sampled_from(["float32", "float64"])), (m, 2))),
        keypoint_scores=draw(_float_arrays("float32", (m,), 0.0, 1.0)),
        robot_id=draw(st.one_of(st.just(""), ids)),
        keypoint_sigmas_px=draw(st.one_of(
            st.none(), _float_arrays("float64", (m,), 0.5, 500.0))),
        robot_model=draw(st.one_of(st.just(""), ids)),
    )


@st.composite
def robot_detections(draw) -> RobotDetections:
    return RobotDetections(
        camera_id=draw(ids),
        stamp_ns=draw(stamps),
        seq=draw(seqs),
        image_width=draw(st.integers(1, 65535)),
        image_height=draw(st.integers(1, 65535)),
        model_id=draw(st.text(max_size=40)),
        detections=tuple(draw(st.lists(detections(), max_size=4))),
    )


@st.composite
def camera_images(draw) -> CameraImage:
    return CameraImage(
        camera_id=draw(ids),
        stamp_ns=draw(stamps),
        seq=draw(seqs),
        image_width=draw(st.integers(1, 65535)),
        image_height=draw(st.integers(1, 65535)),
        encoding="jpeg",
        data=draw(hnp.arrays("uint8", st.integers(1, 4096))),
    )


@st.composite
def semantic_clouds(draw, max_points: int = 2000) -> SemanticCloud:
    n = draw(st.integers(0, max_points))
    pose = draw(st.one_of(st.none(), _float_arrays("float64", (4, 4))))
    return SemanticCloud(
        sensor_id=draw(ids),
        stamp_ns=draw(stamps),
        seq=draw(seqs),
        frame_id=draw(ids),
        points_xyz=draw(_float_arrays("float32", (n, 3))),
        class_ids=draw(hnp.arrays(draw(st.sampled_from(["uint8", "uint16"])), (n,))),
        confidences=draw(_float_arrays("float32", (n,), 0.0, 1.0)),
        T_frame_sensor=pose,
    )


@st.composite
def odometries(draw) -> Odometry:
    return Odometry(
        robot_id=draw(ids),
        stamp_ns=draw(stamps),
        seq=draw(seqs),
        x=draw(finite),
        y=draw(finite),
        theta=draw(angles),
        vx=draw(finite),
        vy=draw(finite),
        wz=draw(finite),
        covariance=draw(covariances()),
        frame_id=draw(ids),
    )


@st.composite
def pose_estimates(draw) -> PoseEstimate:
    return PoseEstimate(
        robot_id=draw(ids),
        stamp_ns=draw(stamps),
        seq=draw(seqs),
        x=draw(finite),
        y=draw(finite),
        theta=draw(angles),
        covariance=draw(covariances()),
        source=draw(st.sampled_from(["cameras", "fused", "robot", "ground_truth"])),
        camera_ids=tuple(draw(st.lists(ids, max_size=8))),
        reprojection_rmse_px=draw(st.one_of(st.just(math.nan), st.floats(0, 1e3))),
        flags=tuple(draw(st.lists(ids, max_size=5))),
    )


@st.composite
def pose_corrections(draw) -> PoseCorrection:
    return PoseCorrection(
        robot_id=draw(ids),
        stamp_ns=draw(stamps),
        seq=draw(seqs),
        x=draw(finite),
        y=draw(finite),
        theta=draw(angles),
        covariance=draw(covariances()),
        kind=draw(st.sampled_from(["initialization", "correction"])),
        offset_m=draw(st.floats(0, 100)),
        offset_rad=draw(st.floats(0, 7)),
    )


@st.composite
def service_statuses(draw) -> ServiceStatus:
    names = st.text(min_size=1, max_size=20)
    return ServiceStatus(
        service=draw(st.sampled_from(["edge-agent", "backend", "robot-bridge"])),
        instance_id=draw(ids),
        stamp_ns=draw(stamps),
        seq=draw(seqs),
        state=draw(st.sampled_from(["starting", "ok", "degraded", "error", "stopping"])),
        uptime_s=draw(st.floats(0, 1e7)),
        rates_hz=draw(st.dictionaries(names, st.floats(0, 1e4), max_size=5)),
        latency_p50_ms=draw(st.dictionaries(names, st.floats(0, 1e4), max_size=5)),
        latency_p99_ms=draw(st.dictionaries(names, st.floats(0, 1e4), max_size=5)),
        counters=draw(st.dictionaries(names, st.integers(0, 2**62), max_size=8)),
        peers_alive=tuple(draw(st.lists(ids, max_size=8))),
        detail=draw(st.text(max_size=100)),
    )


any_message = st.one_of(
    robot_detections(),
    semantic_clouds(200),
    odometries(),
    pose_estimates(),
    pose_corrections(),
    service_statuses(),
)


def sample_odometry() -> Odometry:
    """A fixed valid odometry message (for tests that mutate a known payload)."""
    return Odometry(
        "hsr",
        1_700_000_000_000_000_000,
        3,
        1.0,
        -2.0,
        0.5,
        0.1,
        0.0,
        0.02,
        np.diag([0.01, 0.01, 0.001]),
    )


def sample_cloud(n: int, seed: int = 0) -> SemanticCloud:
    """A fixed valid cloud of ``n`` points."""
    rng = np.random.default_rng(seed)
    return SemanticCloud(
        "cam0",
        5,
        0,
        "map",
        rng.normal(size=(n, 3)).astype(np.float32),
        rng.integers(0, 20, n).astype(np.uint8),
        rng.random(n).astype(np.float32),
    )
