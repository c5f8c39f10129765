"""Evaluation protocol (paper §4, Table 1): episode specs, rollouts, resumable runner, report with bootstrap
intervals and paired differences (``topocut.eval.stats``).

Pure numpy at import time; the simulator, topology and reward modules are imported when an
episode runs.
"""
from topocut.eval.config import EvalConfig, smoke
from topocut.eval.protocol import (
                                   EpisodeResult,
                                   EpisodeSpec,
                                   episode_specs,
                                   evaluate_episode,
                                   make_observe_fn,
                                   run_evaluation,
)
from topocut.eval.report import PAPER_TABLE1, summarize, write_report
from topocut.eval.stats import Interval, bootstrap_mean, paired_difference

__all__ = ["EvalConfig", "smoke", "EpisodeSpec", "EpisodeResult", "episode_specs", "evaluate_episode",
           "make_observe_fn", "run_evaluation", "PAPER_TABLE1", "summarize", "write_report", "Interval",
           "bootstrap_mean", "paired_difference"]
