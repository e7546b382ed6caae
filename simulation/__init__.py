"""Simulated site: room, cameras, robot model and motion, odometry drift, detection noise.

A sensor and robot source that produces the same ``protocol`` messages real sensors do."""

from __future__ import annotations

import logging

logging.getLogger(__name__).addHandler(logging.NullHandler())
