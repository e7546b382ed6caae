"""The default robust loss keeps the pose near the Cramer-Rao bound with gross keypoint outliers
(``smartedge bench robust``'s Monte Carlo, small)."""

from __future__ import annotations

from backend_service.pose_solver import DEFAULT_ROBUST_LOSS, SolverConfig
from lab.bench.robust import run


def test_default_loss_is_near_the_bound_with_outliers_and_clean() -> None:
    assert SolverConfig().robust_loss == DEFAULT_ROBUST_LOSS == "cauchy"
    rows = run(60, 1.0, seed=3, counts=(2, 4), shares=(0.0, 0.05))
    by = {(r.cameras, r.outliers, r.loss): r for r in rows}
    for n in (2, 4):
        clean = by[(n, 0.0, DEFAULT_ROBUST_LOSS)]
        dirty = by[(n, 0.05, DEFAULT_ROBUST_LOSS)]
        assert clean.failed == 0 and dirty.failed == 0
        assert clean.mse_crlb_position < 1.35 and clean.mse_crlb_heading < 1.35, clean
        assert dirty.mse_crlb_position <= 1.5 and dirty.mse_crlb_heading <= 1.5, dirty
        # the outliers matter: plain least squares fails the gate or is far off
        plain = by[(n, 0.05, "none")]
        assert plain.failed > 10 or plain.mse_crlb_position > 3.0, plain
