"""smartedge: marker-less mobile robot localization from static smart edge cameras.

This package holds the ``smartedge`` command line; the system lives in ``protocol``,
``edge_agent``, ``backend_service``, ``robot_bridge`` and ``simulation``."""

from __future__ import annotations

import logging

__version__ = "0.1.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())
