"""``check_covariance``'s symmetry test is ``np.allclose(cov, cov.T, rtol=1e-6, atol=1e-9 *
scale)`` written out: it accepts and refuses exactly what allclose does."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol.errors import ValidationError
from protocol.validation import check_covariance


def _allclose_rule(cov: np.ndarray) -> bool:
    scale = max(1.0, float(np.max(np.abs(cov))))
    return bool(np.allclose(cov, cov.T, rtol=1e-6, atol=1e-9 * scale))


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([1e-12, 1e-9, 1e-7, 1e-6, 1e-5, 1e-3]),
       st.sampled_from([1e-6, 1e-3, 1.0, 1e3, 1e6]))
def test_symmetry_test_is_allclose(seed: int, asymmetry: float, magnitude: float) -> None:
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(3, 3)) * magnitude
    cov = a @ a.T
    cov[0, 1] *= 1.0 + rng.choice([-1.0, 1.0]) * asymmetry
    cov[2, 1] += rng.normal() * asymmetry * magnitude
    try:
        check_covariance("cov", cov)
        accepted = True
    except ValidationError as exc:
        assert "not symmetric" in str(exc)
        accepted = False
    assert accepted == _allclose_rule(cov)


def test_refuses_asymmetric_and_negative_variances() -> None:
    with pytest.raises(ValidationError, match="not symmetric"):
        check_covariance("cov", np.array([[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]))
    with pytest.raises(ValidationError, match="negative variance"):
        check_covariance("cov", np.diag([1.0, -1.0, 1.0]))
    out = check_covariance("cov", np.eye(3))
    assert not out.flags.writeable and out.dtype == np.float64
