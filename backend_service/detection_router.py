"""The association applied to messages: :class:`DetectionRouter` returns each camera's
:class:`~protocol.messages.RobotDetections` with the detections that go to a robot named and the
others removed, and keeps the counters (transport-free).
"""

from __future__ import annotations

import collections
import copy
from collections.abc import Mapping, Sequence

import numpy as np

from backend_service.association import (
    Association,
    AssociationConfig,
    RobotPrediction,
    ViewCache,
    associate,
)
from backend_service.frame_set import image_scale, scale_detection
from core.site import Site
from protocol.messages import Detection, RobotDetections


class DetectionRouter:
    """Applies :func:`associate` to camera messages of a site: each message comes back with
    the detections that go to a robot carrying that robot's id and the others removed (so the
    synchronizer sees only named detections). Messages of unknown cameras or image sizes that
    are no exact scale of the calibration pass unchanged (the synchronizer counts them).

    ``counters``: ``detections_<reason>`` for every reason of :data:`REASONS` (a detection
    of a robot model the site has no robot of: ``detections_unknown_model``), and
    ``detections_routed.<robot>``; :attr:`last` is the latest :class:`Association` (tests,
    viewer). Not thread-safe: one worker loop.
    """

    def __init__(self, site: Site, config: AssociationConfig | None = None) -> None:
        self.site = site
        self.config = config or AssociationConfig()
        self.robot_ids: tuple[str, ...] = tuple(site.robots)
        self.keypoints_base_m: dict[str, np.ndarray] = {
            rid: site.robot_model(rid).keypoints_base_m for rid in self.robot_ids}
        #: robot id → its model's name (typed detections go to robots of their model only)
        self.robot_models: dict[str, str] = {rid: site.robots[rid] for rid in self.robot_ids}
        self.counters: collections.Counter[str] = collections.Counter()
        self.last: Association | None = None
        #: the robots that had no prediction for the latest routed image
        self.unpredicted: tuple[str, ...] = ()
        self.views = ViewCache(tuple(site.cameras.values()), self.config)
        self._outside_views: frozenset[str] = frozenset()  # cameras not in the view cache

    def serve_cameras(self, camera_ids: Sequence[str] | None) -> None:
        """Project the predicted views into ``camera_ids`` only (the cameras whose messages
        reach this router; ``None``: every camera of the site). A message of another camera is
        still routed, its view projected on its own."""
        ids = list(self.site.cameras) if camera_ids is None else list(camera_ids)
        unknown = sorted(set(ids) - set(self.site.cameras))
        if unknown:
            raise ValueError(f"cameras {unknown} are not in site {self.site.name!r}")
        self.views = ViewCache(tuple(self.site.cameras[c] for c in ids), self.config)
        self._outside_views = frozenset(self.site.cameras) - set(ids)

    def cameras_seeing(self, robot_id: str,
                       predictions: Mapping[str, RobotPrediction | None]
                       ) -> frozenset[str] | None:
        """The site's cameras whose images :meth:`route` can give unnamed detections of
        ``robot_id`` with ``predictions`` (robot id -> prediction, as for :meth:`route`): the
        cameras of the view cache in whose image the robot has a keypoint predicted, and every
        camera outside the cache. ``None``: any camera (the robot has no prediction, or is no
        robot of the site)."""
        kp = self.keypoints_base_m.get(robot_id)
        if kp is None or predictions.get(robot_id) is None:
            return None
        # the robots of its model in route's order: the group association_costs projects
        group = [p for rid in self.robot_ids
                 if (p := predictions.get(rid)) is not None and self.keypoints_base_m[rid] is kp]
        row = next(i for i, p in enumerate(group) if p.robot_id == robot_id)
        return self.views.cameras_seeing(kp, group, row) | self._outside_views

    def route(self, msg: RobotDetections,
              predictions: Mapping[str, RobotPrediction | None]) -> RobotDetections:
        """``msg`` with each detection named after the robot it goes to, the rest removed."""
        if not msg.detections:
            return msg
        cam = self.site.cameras.get(msg.camera_id)
        if cam is None:
            return msg
        scale = image_scale(msg.image_width, msg.image_height, cam.width, cam.height)
        if scale is None:
            return msg
        dets = msg.detections if scale == 1.0 else tuple(scale_detection(d, scale)
                                                         for d in msg.detections)
        preds = [p for rid in self.robot_ids
                 if (p := predictions.get(rid)) is not None]
        if len(preds) < len(self.robot_ids):
            self.unpredicted = tuple(r for r in self.robot_ids if predictions.get(r) is None)
        else:
            self.unpredicted = ()
        result = associate(cam, dets, preds, self.keypoints_base_m, self.config,
                           self.robot_ids, self.views, self.robot_models)
        self.last = result
        kept: list[Detection] = []
        for det, outcome in zip(msg.detections, result.outcomes, strict=True):
            self.counters[f"detections_{outcome.reason}"] += 1
            if not outcome.used:
                continue
            self.counters[f"detections_routed.{outcome.robot_id}"] += 1
            kept.append(det if det.robot_id == outcome.robot_id
                        else _renamed(det, outcome.robot_id))
        return _with_detections(msg, tuple(kept))


def _renamed(det: Detection, robot_id: str) -> Detection:
    """``det`` named ``robot_id`` (a robot of the site, so a valid id): a shallow copy, the
    validated arrays shared (they are read-only), without validating them again."""
    out = copy.copy(det)
    object.__setattr__(out, "robot_id", robot_id)
    return out


def _with_detections(msg: RobotDetections, detections: tuple[Detection, ...]
                     ) -> RobotDetections:
    """``msg`` with ``detections`` (a subset of its own, validated ones, renamed): a shallow
    copy, not validated again."""
    out = copy.copy(msg)
    object.__setattr__(out, "detections", detections)
    return out
