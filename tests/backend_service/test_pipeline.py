"""The one backend pipeline: where the prior comes from, what the pose graph receives, bad
configuration."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

pytest.importorskip("gtsam")

from backend_service.pipeline import BackendPipeline
from backend_service.pipeline_config import PipelineConfig


@pytest.fixture
def stream(traj1_stream):
    return traj1_stream


def test_prior_comes_from_the_configured_source(stream) -> None:
    sc, messages = stream
    site = sc.site
    sources: dict[str, set[str]] = {}
    for prior in ("fused", "localization"):
        pipeline = BackendPipeline(site, PipelineConfig.from_site(site, prior=prior))
        seen: set[str] = set()
        for tm in messages:
            seen.update(r.prior_source for r in pipeline.step(tm.message, tm.arrival_ns).solves)
        sources[prior] = seen
    assert "localization" in sources["localization"] and "fused" not in sources["localization"]
    assert "fused" in sources["fused"]


def test_fuse_while_moving_off_fuses_only_averages(stream) -> None:
    sc, messages = stream
    site = sc.site
    counts = {}
    for moving in (True, False):
        config = dataclasses.replace(PipelineConfig.from_site(site), fuse_while_moving=moving)
        pipeline = BackendPipeline(site, config)
        estimates = averages = 0
        for tm in messages:
            for rec in pipeline.step(tm.message, tm.arrival_ns).solves:
                estimates += rec.result.ok
                averages += rec.averaged is not None
        fusion = pipeline.tracks[sc.robot_id].fusion
        counts[moving] = (fusion.counters["camera_received"], estimates, averages)  # type: ignore[union-attr]
    received, estimates, averages = counts[False]
    assert 0 < averages == received  # only the averages taken while static
    received, estimates, averages = counts[True]
    assert received > averages and received <= estimates


def test_bad_config_is_a_clear_error() -> None:
    with pytest.raises(ValueError, match="prior"):
        PipelineConfig(prior="gps")


def test_prior_covariance_is_passed_only_for_the_robots_localization(stream) -> None:
    sc, messages = stream
    site = sc.site
    for prior in ("fused", "localization"):
        pipeline = BackendPipeline(site, PipelineConfig.from_site(site, prior=prior))
        records = []
        for tm in messages:
            records += pipeline.step(tm.message, tm.arrival_ns).solves
        by_source = {r.prior_source for r in records}
        assert prior in by_source
        for r in records:
            if r.prior_source == "localization":
                # the simulated localization reports its own covariance: it reaches the solve
                assert r.prior_covariance is not None and r.prior_covariance.shape == (3, 3)
                assert np.all(np.linalg.eigvalsh(r.prior_covariance) > 0)
            else:  # the pose graph combines camera estimates itself: no double counting
                assert r.prior_covariance is None
            if r.result.ok and "map_prior" in r.result.estimate.flags:
                assert r.prior_source == "localization"
                assert "single_camera" in r.result.estimate.flags
