"""Message helpers beyond construction: :meth:`PoseEstimate.numbered` (what a publisher sets on
an estimate it sends) equals a full re-construction and still checks what it changes."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from protocol.errors import ValidationError
from protocol.messages import PoseEstimate


def _estimate() -> PoseEstimate:
    cov = np.diag([1e-4, 2e-4, 3e-5])
    return PoseEstimate("hsr", 1_700_000_000_000_000_000, 0, 1.5, -2.0, 0.3, cov, "cameras",
                        ("cam1", "cam2"), 0.4, ("multi_frame",), "map")


def test_numbered_equals_a_replaced_copy() -> None:
    est = _estimate()
    out = est.numbered(17, "site_map")
    assert out == dataclasses.replace(est, seq=17, frame_id="site_map")
    assert type(out) is PoseEstimate and out is not est
    assert (est.seq, est.frame_id) == (0, "map")  # the original is unchanged
    assert not out.covariance.flags.writeable
    with pytest.raises(dataclasses.FrozenInstanceError):
        out.seq = 3  # type: ignore[misc]


def test_numbered_checks_what_it_changes() -> None:
    est = _estimate()
    with pytest.raises(ValidationError, match="seq"):
        est.numbered(-1, "map")
    with pytest.raises(ValidationError, match="frame_id"):
        est.numbered(1, "bad frame/id")
