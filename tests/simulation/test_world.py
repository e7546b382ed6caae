"""Ray/box occlusion tests."""

from __future__ import annotations

import numpy as np

from simulation.scenario import Box
from simulation.world import World


class _Sc:
    def __init__(self, boxes):
        self.obstacles = tuple(boxes)
        self.room_min_xy_m = np.array([0.0, 0.0])
        self.room_max_xy_m = np.array([10.0, 10.0])


def test_segments_blocked_by_box() -> None:
    box = Box("b", np.array([5.0, 5.0]), np.array([1.0, 1.0, 2.0]), yaw_rad=0.3)
    w = World(_Sc([box]))  # type: ignore[arg-type]
    origin = np.array([0.0, 5.0, 1.0])
    pts = np.array([[9.0, 5.0, 1.0],   # straight through the box
                    [9.0, 5.0, 3.5],   # passes above (box is 2 m high)... at x=5 z~2.4
                    [4.0, 5.0, 1.0],   # stops before the box
                    [9.0, 9.0, 1.0],   # passes beside
                    [5.0, 5.0, 1.0]])  # ends inside
    assert w.segments_blocked(origin, pts).tolist() == [True, False, False, False, True]


def test_no_boxes_never_blocks() -> None:
    w = World(_Sc([]))  # type: ignore[arg-type]
    assert not w.segments_blocked(np.zeros(3), np.ones((3, 3))).any()
    assert w.footprint_collides(np.array([0.1, 5.0]), 0.2)
    assert not w.footprint_collides(np.array([5.0, 5.0]), 0.2)
