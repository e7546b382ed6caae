"""Execution providers of the edge's networks (#28 item 5): ``--providers`` names → the list
onnxruntime gets (TensorRT with its engine and timing caches in the state directory and FP16
as an option, CUDA then CPU as fallbacks), and the same choice for the detector, the keypoint
network and the segmentation network.

onnxruntime here is the CPU-only build: the option building is checked as a pure function
(with the providers a Jetson build has), and the fallback with real sessions: asked TensorRT,
every network gets the CPU, the log says so once, and the status names it.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

import numpy as np
import pytest

ort = pytest.importorskip("onnxruntime")
cv2 = pytest.importorskip("cv2")

from core.site import load_site  # noqa: E402
from edge_agent import providers as providers_module  # noqa: E402
from edge_agent.model_cards import ModelError  # noqa: E402
from edge_agent.models import RobotKeypointPipeline  # noqa: E402
from edge_agent.networks import SemanticSegmenter  # noqa: E402
from edge_agent.providers import (  # noqa: E402
    CPU,
    CUDA,
    ENGINE_CACHE_ENV,
    TENSORRT,
    ExecutionProviders,
    engine_cache_dir,
    execution_providers,
    provider_names,
)
from edge_agent.service import EdgeAgentNode, build_cloud_maker, build_node, build_parser  # noqa: E402
from edge_agent.sources import execution_providers_from_args  # noqa: E402
from protocol.errors import UsageError  # noqa: E402
from tests.conftest import REPO_ROOT  # noqa: E402

SITE = REPO_ROOT / "simulation" / "sites" / "paper_lab.yaml"
JETSON_BUILD = (TENSORRT, CUDA, CPU)  # what onnxruntime-gpu for JetPack reports


# --------------------------------------------------------------------------------------------
# names → providers list (pure)
# --------------------------------------------------------------------------------------------


def test_tensorrt_brings_its_caches_fp16_and_the_cuda_then_cpu_fallbacks(tmp_path: Path) -> None:
    cache = tmp_path / "state" / "trt_engines"
    chosen = execution_providers("tensorrt", fp16=True, engine_cache=cache,
                                 available=JETSON_BUILD)
    assert chosen.names == [TENSORRT, CUDA, CPU]
    assert chosen.asked == (TENSORRT,) and chosen.missing == ()
    trt_options = chosen.chain[0][1]
    assert trt_options == {
        "trt_engine_cache_enable": "True", "trt_engine_cache_path": str(cache / "fp16"),
        "trt_timing_cache_enable": "True", "trt_timing_cache_path": str(cache),
        "trt_fp16_enable": "True"}
    assert (cache / "fp16").is_dir() and chosen.engine_cache == cache / "fp16"
    assert chosen.for_session() == [(TENSORRT, trt_options), CUDA, CPU]
    fp32 = execution_providers("TensorrtExecutionProvider", engine_cache=cache,
                               available=JETSON_BUILD)
    assert fp32.chain[0][1]["trt_fp16_enable"] == "False"
    assert fp32.chain[0][1]["trt_engine_cache_path"] == str(cache / "fp32")  # never mixed


@pytest.mark.parametrize(("spec", "expected"), [
    ("cuda", [CUDA, CPU]),
    ("cpu", [CPU]),
    ("CUDA, cpu", [CUDA, CPU]),
    ("auto", [TENSORRT, CUDA, CPU]),
    (["trt"], [TENSORRT, CUDA, CPU]),
])
def test_names_and_fallback_order(spec: str | list[str], expected: list[str],
                                  tmp_path: Path) -> None:
    chosen = execution_providers(spec, engine_cache=tmp_path / "c", available=JETSON_BUILD)
    assert chosen.names == expected
    assert (tmp_path / "c").exists() == (TENSORRT in expected)  # created only for TensorRT


def test_auto_on_a_cpu_only_build_is_the_cpu_and_not_a_fallback(tmp_path: Path) -> None:
    chosen = execution_providers("auto", engine_cache=tmp_path / "c", available=[CPU])
    assert chosen.names == [CPU] and chosen.missing == ()
    assert not chosen.fell_back([CPU]) and chosen.describe([CPU]) == "cpu"
    assert not (tmp_path / "c").exists()


def test_missing_providers_are_left_out_and_named(tmp_path: Path) -> None:
    chosen = execution_providers("tensorrt", engine_cache=tmp_path / "c",
                                 available=["AzureExecutionProvider", CPU])
    assert chosen.names == [CPU]
    assert chosen.missing == (TENSORRT, CUDA)
    assert chosen.fell_back([CPU])
    assert chosen.describe([CPU]) == ("cpu (asked tensorrt; this onnxruntime lacks "
                                      "TensorrtExecutionProvider, CUDAExecutionProvider)")
    # a build that has TensorRT but whose session still got the CPU (e.g. no libnvinfer)
    jetson = execution_providers("tensorrt", engine_cache=tmp_path / "c", available=JETSON_BUILD)
    assert jetson.describe([CUDA, CPU]).startswith("cuda+cpu (asked tensorrt; the provider "
                                                   "failed to start")
    assert jetson.describe([TENSORRT, CUDA, CPU]) == "tensorrt+cuda+cpu"


@pytest.mark.parametrize("bad", ["tensorflow", "gpu", "auto,cpu"])
def test_unknown_provider_names_are_refused_with_the_accepted_ones(bad: str) -> None:
    with pytest.raises(ValueError, match=r"tensorrt, trt, cuda, cpu|auto stands alone"):
        provider_names(bad)


def test_engine_cache_is_in_the_state_directory(tmp_path: Path) -> None:
    state = str(tmp_path / "var" / "lib" / "smartedge")
    assert engine_cache_dir({ENGINE_CACHE_ENV: "/x/engines", "STATE_DIRECTORY": state}) == \
        Path("/x/engines")
    assert engine_cache_dir({"STATE_DIRECTORY": f"{state}:/other"}) == \
        Path(state) / "trt_engines"
    assert engine_cache_dir({"XDG_CACHE_HOME": str(tmp_path)}) == \
        tmp_path / "smartedge" / "trt_engines"


def test_cache_folder_that_cannot_be_made_is_a_clear_error(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    with pytest.raises(ModelError, match="TensorRT engine cache"):
        execution_providers("tensorrt", engine_cache=blocker, available=JETSON_BUILD)


def test_cli_options_build_the_choice(tmp_path: Path) -> None:
    args = build_parser().parse_args(["--camera", "cam1", "--providers", "tensorrt", "--fp16",
                                      "--trt-cache", str(tmp_path / "engines")])
    chosen = execution_providers_from_args(args)
    assert chosen.asked == (TENSORRT,) and chosen.fp16
    bad = build_parser().parse_args(["--camera", "cam1", "--providers", "tpu"])
    with pytest.raises(UsageError, match="unknown execution provider 'tpu'"):
        execution_providers_from_args(bad)


# --------------------------------------------------------------------------------------------
# real sessions on this CPU-only onnxruntime
# --------------------------------------------------------------------------------------------


@pytest.fixture
def fresh_report_log(monkeypatch: pytest.MonkeyPatch) -> None:
    """The once-per-process asked/got log starts empty."""
    monkeypatch.setattr(providers_module, "REPORTED_FALLBACKS", set())


def test_asked_tensorrt_every_network_gets_the_cpu_and_the_log_says_so_once(
        tmp_path: Path, caplog: pytest.LogCaptureFixture, fresh_report_log: None) -> None:
    assert TENSORRT not in ort.get_available_providers()  # the premise of this test
    chosen = execution_providers("tensorrt", engine_cache=tmp_path / "c")
    caplog.set_level(logging.INFO, logger="edge_agent.models")
    pipe = RobotKeypointPipeline(threads=1, providers=chosen)
    seg = SemanticSegmenter(threads=1, providers=chosen)
    assert pipe.detector.providers_used == [CPU]
    assert pipe.keypoints.providers_used == [CPU]
    assert seg.providers_used == [CPU]
    assert pipe.execution is chosen and seg.execution is chosen
    assert "asked tensorrt" in pipe.providers_note()
    warnings = [r for r in caplog.records if "asked tensorrt" in r.getMessage()]
    assert len(warnings) == 1 and warnings[0].levelno == logging.WARNING
    # the networks still run
    boxes = pipe.detector.detect(np.zeros((96, 128, 3), np.uint8))
    assert boxes.shape[1] == 5


def test_names_given_as_a_list_still_work_for_older_callers(fresh_report_log: None) -> None:
    pipe = RobotKeypointPipeline(threads=1, providers=["CPUExecutionProvider"])
    assert pipe.providers == [CPU] and pipe.providers_used == [CPU]
    assert not pipe.execution.fell_back(pipe.providers_used)
    default = SemanticSegmenter(threads=1)
    assert isinstance(default.execution, ExecutionProviders) and default.providers_used == [CPU]


def test_segmentation_gets_the_agents_provider_choice(tmp_path: Path,
                                                      fresh_report_log: None) -> None:
    """The cloud maker's segmentation network is built from the same ``--providers``,
    ``--fp16`` and ``--trt-cache`` as the detector (it ignored them before)."""
    args = build_parser().parse_args(["--site", str(SITE), "--camera", "cam1", "--threads", "1",
                                      "--providers", "tensorrt", "--fp16", "--trt-cache",
                                      str(tmp_path / "engines")])
    site = load_site(SITE)
    depth_source = argparse.Namespace(provides_depth=True, label="rgbd")
    maker = build_cloud_maker(args, site, "cam1", depth_source)
    assert maker is not None
    segmenter = maker.segmenter
    assert segmenter.execution == execution_providers_from_args(args)
    assert segmenter.execution.asked == (TENSORRT,) and segmenter.execution.fp16
    assert segmenter.providers_used == [CPU]


def test_status_names_what_the_session_got(tmp_path: Path, fresh_report_log: None) -> None:
    """``--source camera --providers tensorrt`` on a CPU-only onnxruntime: the agent runs, its
    status says ``providers=cpu (asked tensorrt; ...)`` and is ``degraded``; asked for the CPU,
    it is ``ok``."""
    folder = tmp_path / "images"
    folder.mkdir()
    rng = np.random.default_rng(3)
    for i in range(2):
        assert cv2.imwrite(str(folder / f"{i}.png"),
                           rng.integers(0, 255, (480, 848, 3), dtype=np.uint8))
    node: EdgeAgentNode = build_node(build_parser().parse_args(
        ["--site", str(SITE), "--camera", "cam1", "--source", "camera", "--threads", "1",
         "--images", str(folder), "--rate", "0", "--providers", "tensorrt",
         "--trt-cache", str(tmp_path / "engines")]))
    try:
        deadline = time.monotonic() + 10.0
        while node.source.reader.status().state != "ok" and time.monotonic() < deadline:
            time.sleep(0.01)
        state, detail = node.state()
        assert "providers=cpu (asked tensorrt; this onnxruntime lacks TensorrtExecutionProvider" \
            in detail, detail
        assert "source=images:" in detail
        # a board that runs on less than it was asked for is not "ok"
        assert state == "degraded" and detail.endswith("run on less than was asked"), detail
    finally:
        node.close()
    cpu: EdgeAgentNode = build_node(build_parser().parse_args(
        ["--site", str(SITE), "--camera", "cam1", "--source", "camera", "--threads", "1",
         "--images", str(folder), "--rate", "0", "--loop", "--providers", "cpu"]))
    try:
        deadline = time.monotonic() + 10.0
        while cpu.source.reader.status().state != "ok" and time.monotonic() < deadline:
            time.sleep(0.01)
        assert cpu.state() == ("ok", cpu.state()[1]) and "providers=cpu" in cpu.state()[1]
        assert "asked" not in cpu.state()[1]
    finally:
        cpu.close()
