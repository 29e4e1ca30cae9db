"""The learners' 'qt_diagnostics' records (comper_node and comcact_node alike, no ROS).

Every ``diagnostics_every`` updates, on the update's own batch and before its QT target is used,
the learner measures QT's bootstrap against the one its own networks give (``qt_diagnostics`` of
ComperLearner / ComcactLearner: no parameter moves), and this adds what the sampled entries are
(age, set sizes). One record goes to metrics.jsonl, its numbers to TensorBoard under ``qt/``.
docs/comper.md and docs/comcact.md list the fields; benchmarks/qt_diagnostics.py plots them.
"""
from __future__ import annotations

import numpy as np

from comper_msgs_py.arrays import Transitions

__all__ = ["QTDiagnostics", "sampled_entry_stats", "sampled_set_sizes"]


def sampled_entry_stats(step: int, batch: Transitions, counts: np.ndarray) -> dict:
    """The sampled entries' age in agent steps since their transition was first stored (a re-store
    keeps the step, so with re-stores this is not the age of the newest label) and their set sizes
    (members per identity; uniform RTM draws, so the fraction with more than one member estimates
    RTM's). NaN where the batch carries no steps or no counts come with it."""
    age = step - np.asarray(batch.steps, np.float64)
    cnt = np.asarray(counts, np.float64)
    nan = float("nan")
    return {"label_age_mean": float(age.mean()) if age.size else nan,
            "label_age_max": float(age.max()) if age.size else nan,
            "set_size_mean": float(cnt.mean()) if cnt.size else nan,
            "multi_member_fraction": float((cnt > 1).mean()) if cnt.size else nan}


def sampled_set_sizes(counts: np.ndarray) -> dict:
    """The set sizes (members per identity) of the entries sampled since the last 'memory' record (comper_node)."""
    return {"sampled_set_size_mean": float(counts.mean()), "sampled_set_size_max": int(counts.max()),
            "sampled_set_size_p90": float(np.percentile(counts, 90)),
            "sampled_sets_with_similar": float((counts > 1).mean()), "sampled": int(counts.size)}


class QTDiagnostics:
    """Writes one record every ``every`` updates (0 = never) through the run's metrics and scalars."""

    def __init__(self, every: int, metrics, scalars, timers) -> None:
        self.every, self.metrics, self.scalars, self.timers = int(every), metrics, scalars, timers

    def due(self, updates: int) -> bool:
        return self.every > 0 and updates % self.every == 0

    def record(self, learner, batch: Transitions, counts: np.ndarray, targets: np.ndarray, *, step: int,
               update: int, x: int, **extra) -> dict:
        """Measure, write and return the record; `x` is the TensorBoard axis (agent steps or frames)."""
        with self.timers("learner"):
            rec = learner.qt_diagnostics(batch, targets)
        rec.update(sampled_entry_stats(step, batch, counts), **extra)
        self.metrics.write("qt_diagnostics", step=step, update=update, **rec)
        self.scalars.scalars({k: v for k, v in rec.items() if isinstance(v, float)}, x, prefix="qt/")
        return rec
