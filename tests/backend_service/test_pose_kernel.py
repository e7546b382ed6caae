"""The compiled per-camera Gauss-Newton kernel: the same numbers as CasADi's virtual machine
for every loss, DoF and lens model, built once per machine (a kept library is reused, never
rebuilt), and the virtual machine whenever it is switched off, no compiler exists or the
build fails."""

from __future__ import annotations

import logging
import shutil

import numpy as np
import pytest

from backend_service import pose_solver
from backend_service.compiled_functions import JIT_ENV, KERNEL_CACHE_ENV, forget_compiled_kernels
from backend_service.estimate import SolverConfig, estimate_pose
from backend_service.pose_solver import PoseProblem
from backend_service.pose_symbolic import compiled_camera_kernel, compiled_residual_kernel
from core.camera import CameraModel
from core.pose import PlanarPose
from tests.backend_service.pose_synth import (
    ROBOT,
    example_site,
    make_frame_set,
    pose_error,
    random_pose,
)

SITE = example_site()
CAMS = sorted(SITE.cameras)
KP = SITE.robot_model(ROBOT).keypoints_base_m
needs_compiler = pytest.mark.skipif(shutil.which("cc") is None and shutil.which("gcc") is None,
                                    reason="no C compiler on this machine")


def _forget_kernels() -> None:
    """As in a new process: the kernels are looked up (and built if need be) again."""
    forget_compiled_kernels()


def _kernels_ready(dof: int, loss: str, num_keypoints: int = len(KP)) -> None:
    assert compiled_camera_kernel(num_keypoints, dof, loss, wait=True) is not None
    assert compiled_residual_kernel(num_keypoints, dof, wait=True) is not None


@pytest.fixture(autouse=True)
def _fresh_kernels():
    _forget_kernels()
    yield
    _forget_kernels()


def _cameras(rational: bool) -> list[CameraModel]:
    cams = [SITE.camera(c) for c in CAMS[:3]]
    if rational:  # the full 8-coefficient model, and a skewed pixel grid
        cams = [CameraModel(c.camera_id, c.width, c.height,
                            c.K + np.array([[0.0, 0.8, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]),
                            np.concatenate([np.resize(c.dist, 5), [0.01, -0.02, 0.005]]),
                            c.T_cam_world.copy()) for c in cams]
    return cams


def _params(problem: PoseProblem, rng: np.random.Generator) -> np.ndarray:
    n = problem.num_cameras * problem.num_keypoints
    return problem.pack(rng.uniform(50.0, 600.0, (problem.num_cameras, problem.num_keypoints, 2)),
                        rng.uniform(0.0, 1.0, (problem.num_cameras, problem.num_keypoints))
                        * (rng.random(n).reshape(problem.num_cameras, -1) > 0.1), 4.0)


@needs_compiler
@pytest.mark.parametrize("rational", [False, True])
@pytest.mark.parametrize("dof", [3, 6])
@pytest.mark.parametrize("loss", ["none", "huber", "cauchy"])
def test_compiled_kernel_gives_the_virtual_machines_numbers(dof: int, loss: str,
                                                            rational: bool) -> None:
    _kernels_ready(dof, loss)
    problem = PoseProblem(_cameras(rational), KP, dof, loss)
    compiled = problem.normal_equations_function()
    reference = problem.normal_equations_vm()
    assert compiled.n_instructions() < reference.n_instructions() / 10  # really the kernel
    rng = np.random.default_rng(dof * 10 + len(loss) + rational)
    truth = random_pose(rng)
    for _ in range(5):
        q = truth.as_array() + rng.normal(0.0, [0.2, 0.2, 0.2])
        if dof == 6:
            q = np.array([q[0], q[1], rng.normal(0, 0.05), rng.normal(0, 0.05),
                          rng.normal(0, 0.05), q[2]])
        p = _params(problem, rng)
        got = np.asarray(compiled(q, p)).reshape(-1)
        want = np.asarray(reference(q, p)).reshape(-1)
        np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-10 * np.abs(want).max())
        # the residual kernel (hand-chained Jacobian) against automatic differentiation
        r, J, z = problem.evaluate(q, p)
        r_ad, J_ad, z_ad = (np.asarray(v) for v in problem.residual_fn(q, p))
        np.testing.assert_allclose(r, r_ad.reshape(-1), rtol=1e-10, atol=1e-9)
        np.testing.assert_allclose(J, J_ad, rtol=1e-9, atol=1e-9 * np.abs(J_ad).max())
        np.testing.assert_allclose(z, z_ad.reshape(-1), rtol=1e-12, atol=1e-12)
    assert problem._residual_eval is not problem.residual_fn  # the kernel evaluated them


@needs_compiler
def test_solves_agree_with_and_without_the_compiled_kernel(monkeypatch) -> None:
    rng = np.random.default_rng(7)
    truth = random_pose(rng)
    fs = make_frame_set(SITE, truth, CAMS, sigma_px=2.0, rng=rng)
    prior = PlanarPose(truth.x + 0.3, truth.y - 0.2, truth.theta + 0.3)
    pose_solver._CACHE.clear()
    _kernels_ready(3, SolverConfig().robust_loss)
    compiled = estimate_pose(fs, SITE, prior, SolverConfig())
    monkeypatch.setenv(JIT_ENV, "0")
    _forget_kernels()
    pose_solver._CACHE.clear()
    vm = estimate_pose(fs, SITE, prior, SolverConfig())
    pose_solver._CACHE.clear()
    assert compiled.ok and vm.ok
    dp, dth = pose_error(compiled.pose, vm.pose)
    assert dp < 1e-9 and dth < 1e-9
    np.testing.assert_allclose(compiled.estimate.covariance, vm.estimate.covariance, rtol=1e-7)


@needs_compiler
def test_a_kept_library_is_reused_not_rebuilt(tmp_path, monkeypatch, caplog) -> None:
    monkeypatch.setenv(KERNEL_CACHE_ENV, str(tmp_path))
    with caplog.at_level(logging.INFO, logger="backend_service.compiled_functions"):
        assert compiled_camera_kernel(5, 3, "none", wait=True) is not None
    libraries = list(tmp_path.glob("pose_camera_kernel_m5_dof3_none_*.so"))
    assert len(libraries) == 1, list(tmp_path.iterdir())
    assert "compiled" in caplog.text and "pose_camera_kernel_m5_dof3_none_" in caplog.text
    built_at = libraries[0].stat().st_mtime_ns
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".build-")]  # cleaned up
    _forget_kernels()  # a new process, as far as the kernels know
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="backend_service.compiled_functions"):
        assert compiled_camera_kernel(5, 3, "none") is not None  # at once: nothing to build
    assert "compiled" not in caplog.text
    assert libraries[0].stat().st_mtime_ns == built_at


def test_switched_off_no_compiler_or_a_failing_one_mean_the_virtual_machine(
        tmp_path, monkeypatch, caplog) -> None:
    monkeypatch.setenv(KERNEL_CACHE_ENV, str(tmp_path))
    monkeypatch.setenv(JIT_ENV, "0")
    assert compiled_camera_kernel(12, 3, "cauchy") is None
    monkeypatch.delenv(JIT_ENV)
    _forget_kernels()
    # a compiler that fails: warned, nothing kept, and the problem still solves
    failing = shutil.which("false")
    assert failing is not None
    monkeypatch.setenv("CC", failing)
    with caplog.at_level(logging.WARNING, logger="backend_service.compiled_functions"):
        assert compiled_camera_kernel(12, 3, "cauchy", wait=True) is None
    assert "compiling pose_camera_kernel_m12_dof3_cauchy_" in caplog.text
    assert "returned non-zero exit status" in caplog.text
    assert not list(tmp_path.glob("*.so"))
    _forget_kernels()
    # no compiler at all
    empty = tmp_path / "no-tools"
    empty.mkdir()
    monkeypatch.setenv("CC", "no-such-compiler")
    monkeypatch.setenv("PATH", str(empty))
    assert compiled_camera_kernel(12, 3, "cauchy") is None
    problem = PoseProblem(_cameras(False), KP, 3, "cauchy")
    assert problem.normal_equations_function().n_instructions() == \
        problem.normal_equations_vm().n_instructions()
    problem.evaluate(np.zeros(3), _params(problem, np.random.default_rng(0)))
    assert problem._residual_eval is problem.residual_fn
    rng = np.random.default_rng(3)
    truth = random_pose(rng)
    fs = make_frame_set(SITE, truth, CAMS[:3], sigma_px=1.0, rng=rng)
    pose_solver._CACHE.clear()
    res = estimate_pose(fs, SITE, PlanarPose(truth.x + 0.2, truth.y, truth.theta), SolverConfig())
    pose_solver._CACHE.clear()
    assert res.ok
    dp, _ = pose_error(res.pose, truth)
    assert dp < 0.05


@needs_compiler
def test_a_build_in_progress_never_stalls_a_solve(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv(KERNEL_CACHE_ENV, str(tmp_path))  # nothing built yet
    problem = PoseProblem(_cameras(False), KP, 3, "huber")
    rng = np.random.default_rng(4)
    p = _params(problem, rng)
    q = random_pose(rng).as_array()
    # the compiler runs in the background: meanwhile the virtual machine answers
    first = problem.normal_equations_function()
    assert first.n_instructions() == problem.normal_equations_vm().n_instructions()
    r_vm, J_vm, _ = problem.evaluate(q, p)
    assert problem._residual_eval is problem.residual_fn
    assert compiled_camera_kernel(len(KP), 3, "huber", wait=True) is not None
    assert compiled_residual_kernel(len(KP), 3, wait=True) is not None
    # ... and the problem takes the kernels up as soon as they are there
    later = problem.normal_equations_function()
    assert later.n_instructions() < first.n_instructions() / 10
    np.testing.assert_allclose(np.asarray(later(q, p)), np.asarray(first(q, p)), rtol=1e-10)
    r, J, _ = problem.evaluate(q, p)
    assert problem._residual_eval is not problem.residual_fn
    np.testing.assert_allclose(r, r_vm, rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(J, J_vm, rtol=1e-9, atol=1e-9 * np.abs(J_vm).max())
