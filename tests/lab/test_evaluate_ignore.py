"""``smartedge evaluate keypoints`` on real renders through the shipped pipeline: a robot no view
can measure (fewer than 3 keypoints visible) is an ignore region in the measurable AP, counted,
and still a miss in the AP over every robot."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

pytest.importorskip("onnxruntime")
pytest.importorskip("moderngl")

from edge_agent.models import RobotKeypointPipeline

SEED = 31
ALL = "AP@0.5"
SEEN = "AP@0.5 (>= 3 keypoints visible)"
IGNORED = "robots ignored (< 3 keypoints visible)"


def test_a_hidden_robot_is_ignored_not_missed() -> None:
    from lab.evaluation.keypoints import evaluate_set
    from simulation.dataset import SampleGenerator
    from simulation.scenario import load_scenario

    scenario = load_scenario()
    pipeline = RobotKeypointPipeline.for_robot(scenario.site.robot_model(scenario.robot_id),
                                               threads=2)
    gen = SampleGenerator(scenario, "site", seed=SEED)
    samples = []
    i = 0
    while len(samples) < 6 and i < 60:  # views of robots in plain sight
        s = gen(i)
        i += 1
        if s.robots[0].bbox_xyxy is not None and int(np.sum(s.robots[0].visible)) >= 6:
            samples.append(s)
    assert len(samples) == 6
    # the third view's robot made unmeasurable: its keypoints hidden and the image blanked, so
    # the detector cannot find it (checked)
    r = samples[2].robots[0]
    blank = np.full_like(samples[2].image_rgb, 128)
    hidden = dataclasses.replace(
        samples[2], image_rgb=blank,
        robots=(dataclasses.replace(r, visible=np.zeros_like(r.visible)),))
    assert pipeline(blank, min_score=0.05) == []
    others = samples[:2] + samples[3:]
    base = evaluate_set(pipeline, others)
    figures = evaluate_set(pipeline, [*samples[:2], hidden, *samples[3:]])
    assert base[IGNORED] == 0.0 and figures[IGNORED] == 1.0
    # ignored: the measurable AP is that of the other five views exactly...
    assert figures[SEEN] == pytest.approx(base[SEEN])
    # ...while over every robot it is a miss: recall stops at 5/6
    assert figures[ALL] <= 5 / 6 + 1e-9 < base[ALL]
