"""The per-robot pipeline's parameters (:class:`PipelineConfig`: solver, multi-frame averaging,
prior rule, static detection, input delay, camera health, association) read from the site file,
and what a pose graph must offer the pipeline (:class:`Fusion`).
"""

from __future__ import annotations

import dataclasses
from typing import Final, Protocol

from backend_service.association import AssociationConfig
from backend_service.camera_health import CameraHealthConfig
from backend_service.estimate import SolverConfig
from backend_service.multi_frame import MultiFrameConfig
from core.site import Site
from protocol.messages import Odometry, PoseEstimate

#: Where a solve's prior comes from first (the other sources are the fallbacks, in order).
PRIOR_SOURCES: Final = ("fused", "localization")


class Fusion(Protocol):
    """What the pipeline needs from a pose graph (:class:`~backend_service.fusion.
    PoseGraphFusion`)."""

    @property
    def anchored(self) -> bool: ...

    def add_odometry(self, msg: Odometry) -> PoseEstimate | None: ...

    def add_camera_estimate(self, est: PoseEstimate) -> PoseEstimate | None: ...

    def pose_at(self, stamp_ns: int) -> PoseEstimate | None: ...

    def latest(self) -> PoseEstimate | None: ...


@dataclasses.dataclass(frozen=True)
class PipelineConfig:
    """How the pipeline runs (the site file's ``pose``/``fusion`` sections fill it).

    ``solver``: the pose solve. ``multi_frame``: averaging while static. ``prior``: where a
    solve's prior comes from first: ``"fused"`` (the pose graph at the frame-set's stamp, the
    service default) or ``"localization"`` (the robot's own localization nearest the stamp, the
    paper's protocol); without it, the newest camera estimate, then the other source (a prior
    is used only when stamped within the site's ``clock.max_age_ms`` of the frame-set).
    ``fuse_while_moving``: also fuse single-frame estimates while the robot moves (the paper
    fuses only the averages at static waypoints). Static detection: ``static_max_speed_mps``,
    ``static_max_yaw_rate_radps`` for ``static_dwell_s``. A pose older than ``clock.max_age_ms``
    when it would be published is dropped by the backend service (``stale_dropped``; the
    pipeline itself never reads the clock; see :class:`~backend_service.service.BackendNode`).
    ``max_input_delay_s``: the backend service sheds (counts, ``shed``) camera detections that
    waited longer than this in its input queue: when the host cannot keep up, the oldest
    frame-sets go first and the latency stays bounded instead of growing until every pose is
    stale. ``camera_health``: watching the cameras for a bump (the site file's
    ``camera_health`` section, :class:`~backend_service.camera_health.CameraHealthConfig`).
    ``association``: how unnamed detections are matched to robots on a site with several
    (:class:`~backend_service.association.AssociationConfig`).
    """

    solver: SolverConfig = dataclasses.field(default_factory=SolverConfig)
    multi_frame: MultiFrameConfig = dataclasses.field(default_factory=MultiFrameConfig)
    prior: str = "fused"
    fuse_while_moving: bool = True
    static_max_speed_mps: float = 0.01
    static_max_yaw_rate_radps: float = 0.02
    static_dwell_s: float = 1.0
    max_input_delay_s: float = 0.25
    camera_health: CameraHealthConfig = dataclasses.field(default_factory=CameraHealthConfig)
    association: AssociationConfig = dataclasses.field(default_factory=AssociationConfig)

    def __post_init__(self) -> None:
        if self.prior not in PRIOR_SOURCES:
            raise ValueError(f"PipelineConfig.prior {self.prior!r} not in {PRIOR_SOURCES}")
        if not self.max_input_delay_s > 0:
            raise ValueError("PipelineConfig.max_input_delay_s must be > 0")

    @classmethod
    def from_site(cls, site: Site, **overrides: object) -> PipelineConfig:
        """The site file's ``pose`` section (this class's scalar fields and
        :class:`SolverConfig`'s, in one flat mapping) and ``multi_frame`` section
        (:class:`MultiFrameConfig`), with the static-detection thresholds of ``thresholds``;
        ``camera_health`` section (:class:`~backend_service.camera_health.
        CameraHealthConfig`); ``association`` section (:class:`~backend_service.association.
        AssociationConfig`, a site with several robots); ``overrides`` (e.g. from command-line
        flags) win. Errors name the file and key."""
        th = site.thresholds
        reader = site.section_reader()
        pose = site.section("pose")
        own = {"prior", "fuse_while_moving", "max_input_delay_s"}
        solver_fields = {f.name for f in dataclasses.fields(SolverConfig)}
        reader.no_unknown("pose", pose, own | solver_fields)
        solver = reader.section("pose", {k: v for k, v in pose.items() if k in solver_fields},
                                SolverConfig, int_lo=1)
        multi_frame = reader.section("multi_frame", site.section("multi_frame"),
                                     MultiFrameConfig, int_lo=1,
                                     base=MultiFrameConfig(count=th.multi_frame_count))
        base = reader.section(
            "pose", {k: v for k, v in pose.items() if k in own}, cls,
            base=cls(solver=solver, multi_frame=multi_frame,
                     camera_health=CameraHealthConfig.from_site(site),
                     association=reader.section("association", site.section("association"),
                                                AssociationConfig, int_lo=1),
                     static_max_speed_mps=th.static_max_speed_mps,
                     static_max_yaw_rate_radps=th.static_max_yaw_rate_radps,
                     static_dwell_s=th.static_dwell_s))
        return dataclasses.replace(base, **overrides)  # type: ignore[arg-type]
