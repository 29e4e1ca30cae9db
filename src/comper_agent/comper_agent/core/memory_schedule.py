"""The learners' memory schedule, pure (no ROS): the rows an agent step leaves until they are
stored, when a reduction is due, and how many update batches one sample call fetches.

Both learner nodes (comper_node, comcact_node) use these, so the two algorithms' loops differ only
where the thesis's Algorithms 7 and 8 differ (COMPER counts agent steps between reductions,
COMCACT counts updates).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from comper_msgs_py.arrays import Transitions

__all__ = ["Row", "PendingRows", "NStepWindows", "rows_to_transitions", "reduce_due", "updates_before_reduce",
           "batches_per_sample", "sets_touched_per_reduction"]


@dataclass
class Row:
    """One agent step waiting to be stored (or published). ``label``: its value label once known
    (COMPER: max_a Q(s', a) from the next action choice; None until then or when the learner
    labels the whole batch at store time, as COMCACT does)."""
    state: np.ndarray
    action: Any                 # float32 [action_dim] or the discrete index
    reward: float
    next_state: np.ndarray
    terminated: bool
    truncated: bool
    step: int
    label: float | None = None


class PendingRows:
    """COMPER's agent steps waiting to be stored. A step's value label (next_value: max_a Q(s', a))
    comes from the Q-values computed to act at the next step, so the newest row may still wait for
    its label; only the labelled rows before it can be stored."""

    def __init__(self):
        self.rows: list[Row] = []

    def __len__(self) -> int:
        return len(self.rows)

    def append(self, row: Row) -> None:
        self.rows.append(row)

    def newest_unlabelled(self) -> Row | None:
        """The newest row if it still waits for its label, else None."""
        return self.rows[-1] if self.rows and self.rows[-1].label is None else None

    def labelled(self) -> int:
        """How many rows, oldest first, have their label."""
        n = len(self.rows)
        return n - 1 if self.newest_unlabelled() is not None else n

    def take_labelled(self) -> list[Row]:
        """Remove and return the labelled rows (oldest first)."""
        n = self.labelled()
        rows, self.rows = self.rows[:n], self.rows[n:]
        return rows


class NStepWindows:
    """COMPER's n-step transitions (``n_step`` > 1), built from an episode's labelled one-step rows in
    time order before they are stored. The window that starts at step t covers m <= n steps:

        (s_t, a_t, sum_j<m gamma^j clip(r_{t+j}), s_{t+m}, terminated, truncated, label of step t+m-1)

    The label is the last row's: max_a Q(s_{t+m}, a), 0 when terminated. The reward is the learning
    signal's (clipped per step with ``clip``, then discounted), so the learner bootstraps with
    gamma^n and does not clip again. m = n, except at a termination, which ends every window that
    reaches it (its bootstrap is masked, so m does not matter). A truncation (time limit, bootstrap
    kept) ends the window of length n that reaches it; the shorter windows it cuts are dropped
    (counted in ``dropped``): a stored transition carries no discount of its own, so their gamma^m
    could not reach the target. A run that stops mid-episode drops its last n - 1 windows the same way.
    """

    def __init__(self, n: int, gamma: float, clip):
        if int(n) < 2:
            raise ValueError(f"n-step windows need n >= 2, got {n}")
        self.n, self.gamma, self.clip = int(n), float(gamma), clip
        self.rows: list[Row] = []       # the episode's rows whose window is not complete yet
        self.dropped = 0

    def reset(self) -> None:
        """A new episode (or the run's end): windows still open are dropped."""
        self.dropped += len(self.rows)
        self.rows = []

    def _window(self, rows: list[Row]) -> Row:
        r = self.clip(np.asarray([x.reward for x in rows], np.float64))
        ret = float(np.sum(r * self.gamma ** np.arange(len(rows))))
        first, last = rows[0], rows[-1]
        return Row(first.state, first.action, ret, last.next_state, last.terminated, last.truncated,
                   first.step, last.label)

    def push(self, rows: list[Row]) -> list[Row]:
        """Labelled one-step rows of one episode, oldest first -> the windows they complete."""
        out: list[Row] = []
        for row in rows:
            if row.label is None:
                raise ValueError(f"step {row.step} has no value label yet: only labelled rows make windows")
            self.rows.append(row)
            if row.terminated:
                out += [self._window(self.rows[i:]) for i in range(len(self.rows))]
                self.rows = []
            elif len(self.rows) == self.n:
                out.append(self._window(self.rows))
                self.rows.pop(0)
            if row.truncated and not row.terminated:
                self.reset()
        return out


def rows_to_transitions(rows: list[Row], episode_id: int, run_id: str) -> Transitions:
    """One Transitions batch from rows of one episode; value_labels empty unless every row has one."""
    n = len(rows)
    labelled = n > 0 and all(r.label is not None for r in rows)
    return Transitions(states=np.stack([r.state for r in rows]),
                       actions=np.asarray([r.action for r in rows], np.float32),
                       rewards=np.asarray([r.reward for r in rows], np.float32),
                       next_states=np.stack([r.next_state for r in rows]),
                       terminated=np.asarray([r.terminated for r in rows], bool),
                       truncated=np.asarray([r.truncated for r in rows], bool),
                       value_labels=(np.asarray([r.label for r in rows], np.float32) if labelled
                                     else np.zeros(0, np.float32)),
                       episode_ids=np.full(n, episode_id, np.uint64),
                       steps=np.asarray([r.step for r in rows], np.uint64), run_id=run_id)


def reduce_due(since_reduce: int, reduce_every: int, rtm_size: int) -> bool:
    """A reduction is due when RTM is empty (nothing to sample) or reduce_every units (COMPER: agent
    steps, COMCACT: updates) have passed since the last one."""
    return rtm_size == 0 or since_reduce >= reduce_every


def updates_before_reduce(units_left: int, units_per_update: int = 1) -> int:
    """Updates until the next reduction (at least 1): units_left agent steps at one update per
    units_per_update steps (COMPER's train_frequency), or units_left updates (units_per_update 1)."""
    return max(1, -(-int(units_left) // max(1, int(units_per_update))))


def batches_per_sample(source: str, prefetch_batches: int, updates_left: int) -> int:
    """Batches one sample call fetches: from RTM, those of the updates before the next reduction (RTM
    does not change in between; each batch an independent uniform draw), at most prefetch_batches;
    from TM (while RTM is empty, or COMPER-M), one (a store changes TM between updates)."""
    if source != "rtm":
        return 1
    return max(1, min(int(prefetch_batches), int(updates_left)))


def sets_touched_per_reduction(reduce_every: int, batch_size: int, train_frequency: int, restore: bool) -> int:
    """COMPER: the most TM sets that receive a transition between two reductions (one new
    transition per agent step, plus each update's batch re-stored with fresh labels). A
    reduce_batch below it lets TM fall behind: sets wait ever longer for QT's next prediction."""
    per_update = int(batch_size) if restore else 0
    return int(reduce_every) * (1 + per_update // max(1, int(train_frequency)))
