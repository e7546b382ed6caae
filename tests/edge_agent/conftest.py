"""Shared fixtures of the edge-agent tests: tiny detector + keypoint models trained once per
session with the real ``smartedge train`` command (render, train, validate, export, check)."""

from __future__ import annotations

from pathlib import Path

import pytest

#: the tiny run's arguments after ``smartedge train KIND --out DIR`` (about 10 s per kind)
TINY_ARGS: tuple[str, ...] = ("--steps", "5", "--train-views", "16", "--site-views", "8",
                              "--val-views", "8", "--tiny", "--workers", "1", "--threads", "1")


def train_tiny(kind: str, out: Path) -> int:
    """Run ``smartedge train KIND --out OUT`` with :data:`TINY_ARGS` in this process; returns
    its exit code."""
    from smartedge.cli import main

    return main(["train", kind, "--out", str(out), *TINY_ARGS])


@pytest.fixture(scope="session")
def tiny_models(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder with ``detector.*`` and ``keypoints.*`` (onnx, json, md, reference.npz, ckpt)
    and the render ``cache/`` of a tiny training run of both kinds."""
    pytest.importorskip("torch", reason="training the tiny models needs torch (train extra)")
    pytest.importorskip("moderngl", reason="rendering the training views needs moderngl")
    out = tmp_path_factory.mktemp("tiny_models")
    for kind in ("detector", "keypoints"):
        code = train_tiny(kind, out)
        assert code == 0, f"smartedge train {kind} (tiny) exited with {code}"
    return out


@pytest.fixture(scope="session")
def tiny_segmentation(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder with ``segmentation.*`` (onnx, json, md, reference.npz, ckpt) and the render
    ``cache/`` of a tiny ``smartedge train segmentation`` run (128x96 input, 64x48 output)."""
    pytest.importorskip("torch", reason="training the tiny model needs torch (train extra)")
    pytest.importorskip("moderngl", reason="rendering the training views needs moderngl")
    out = tmp_path_factory.mktemp("tiny_segmentation")
    code = train_tiny("segmentation", out)
    assert code == 0, f"smartedge train segmentation (tiny) exited with {code}"
    return out
