"""The paper's experiments (Sec. IV of the ICRA 2023 paper) on the simulated lab, as
``smartedge evaluate paper`` runs them. Every experiment drives the backend's one pipeline
(:class:`backend_service.pipeline.BackendPipeline`), the object the backend service runs.

=================================================  ==========================================
paper                                              module
=================================================  ==========================================
settings, the pipeline set up for the paper's      :mod:`lab.experiments.config`
protocol, the detection source (noise or CNN)
experiment 1: accuracy of the pose estimates       :mod:`lab.experiments.accuracy`
(Sec. IV-B, Table I/II, Fig. 6)
experiment 2: correction feedback (Sec. IV-B,      :mod:`lab.experiments.feedback`
Fig. 7); experiment 3: robustness (Sec. IV-D,
Table III)
experiment 4: collaborative semantic mapping       :mod:`lab.experiments.mapping`
(Sec. III-C, IV-C, Fig. 7-8)
identical robots crossing paths, each scored       :mod:`lab.experiments.fleet`
against the robot alone (``smartedge evaluate
fleet``)
the site calibration measured against the          :mod:`lab.experiments.calibration`
simulator's true cameras (``smartedge evaluate
calibration``)
the paper's reference figures; finished runs       :mod:`lab.experiments.comparison`
side by side (``smartedge evaluate compare``)
independent runs in worker processes (``--jobs``)  :mod:`lab.experiments.parallel`
all of them in order, ``report.md``                :mod:`lab.experiments.paper`
=================================================  ==========================================

The names below are importable from the package. Experiment 4's names are not: they come from
:mod:`lab.experiments.mapping`, which imports Open3D (the mapper's ICP), so that
experiments 1-3 and ``evaluate compare`` do not load it. Nor are those of
:mod:`lab.experiments.fleet`, :mod:`lab.experiments.calibration` and
:mod:`lab.experiments.parallel`: import them from their modules.

Part of the lab wing: may import every other package.
"""

from __future__ import annotations

from lab.experiments.accuracy import (
    CAMERA_GROUPS,
    SOURCES,
    AccuracyTables,
    RunResult,
    SourceErrors,
    StopSample,
    accuracy_by_camera_count,
    accuracy_tables,
    nees_table,
    rms_by_trajectory,
    run_once,
    run_pose_accuracy,
    source_errors,
)
from lab.experiments.comparison import PAPER_FIGURES, compare_markdown, compare_rows
from lab.experiments.config import (
    CNN_RATE_HZ,
    DETECTION_MODES,
    LOCALIZATION_RATE_HZ,
    PaperConfig,
    default_fusion_factory,
    make_detector,
    paper_pipeline_config,
)
from lab.experiments.feedback import (
    EMERGENCY_STOP,
    SUCCESS,
    WP_NOT_REACHED,
    AppliedCorrection,
    FailureModel,
    FeedbackRun,
    failure_model,
    feedback_table,
    robustness_table,
    run_correction_feedback,
    run_feedback,
    run_robustness,
)
from lab.experiments.paper import PaperReport, run_paper

__all__ = [
    "CAMERA_GROUPS",
    "CNN_RATE_HZ",
    "DETECTION_MODES",
    "EMERGENCY_STOP",
    "LOCALIZATION_RATE_HZ",
    "PAPER_FIGURES",
    "SOURCES",
    "SUCCESS",
    "WP_NOT_REACHED",
    "AccuracyTables",
    "AppliedCorrection",
    "FailureModel",
    "FeedbackRun",
    "PaperConfig",
    "PaperReport",
    "RunResult",
    "SourceErrors",
    "StopSample",
    "accuracy_by_camera_count",
    "accuracy_tables",
    "compare_markdown",
    "compare_rows",
    "default_fusion_factory",
    "failure_model",
    "feedback_table",
    "make_detector",
    "nees_table",
    "paper_pipeline_config",
    "rms_by_trajectory",
    "robustness_table",
    "run_correction_feedback",
    "run_feedback",
    "run_once",
    "run_paper",
    "run_pose_accuracy",
    "run_robustness",
    "source_errors",
]
