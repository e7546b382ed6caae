"""``smartedge bench backend``'s stage breakdown: every stage measured on the deployed code, the
finite-difference peer computes the same covariance, and the wrapping leaves nothing behind."""

from __future__ import annotations

import numpy as np
import pytest

from backend_service import covariance, estimate, pipeline, sync
from lab.bench.backend_stages import (
    STAGES,
    finite_difference_extrinsic_jacobian,
    measure_stages,
)
from tests.backend_service.pose_synth import ROBOT, example_site


def test_the_peer_jacobian_is_the_closed_form_up_to_its_step() -> None:
    site = example_site()
    cams = list(site.cameras.values())
    pts = np.asarray(site.robot_model(ROBOT).keypoints_base_m) + np.array([10.0, 6.0, 0.0])
    uv, G = covariance.project_with_extrinsic_jacobian(cams, pts)
    uv_fd, G_fd = finite_difference_extrinsic_jacobian(cams, pts)
    front = np.isfinite(uv).all(axis=-1)
    np.testing.assert_allclose(uv_fd[front], uv[front], atol=1e-9)
    np.testing.assert_allclose(G_fd[front], G[front], rtol=2e-2, atol=0.05)


def test_every_stage_is_measured_and_the_originals_are_restored() -> None:
    originals = (sync.FrameSetSynchronizer.push, pipeline.estimate_pose,
                 estimate.propagate_correlated, covariance.project_with_extrinsic_jacobian)
    now = measure_stages(4, frames=6)
    before = measure_stages(4, frames=6, finite_difference=True)
    assert now.frame_sets == before.frame_sets == 6
    for fig in (now, before):
        assert set(fig.per_stage_ms) == set(STAGES)
        for stage in ("decode", "sync", "solve", "covariance", "publish"):
            assert fig.per_stage_ms[stage] > 0, (stage, fig)
    assert (sync.FrameSetSynchronizer.push, pipeline.estimate_pose,
            estimate.propagate_correlated, covariance.project_with_extrinsic_jacobian) == originals


def test_the_pnp_initialized_first_frame_set_is_reported_apart_from_the_steady_state() -> None:
    fig = measure_stages(4, frames=4)
    assert fig.frame_sets == 4
    assert np.isfinite(fig.first_solve_ms) and fig.first_solve_ms > 0
    # the first frame-set has no prior: PnP per view, several times a steady solve
    steady = fig.per_stage_ms["solve"] + fig.per_stage_ms["covariance"]
    assert fig.first_solve_ms > 2 * steady, fig
    with pytest.raises(ValueError, match="warmup"):
        measure_stages(4, frames=2, warmup=0)
