"""Numpy-side representation of comper_msgs transition batches (no ROS imports).

`Transitions` is what the cores (memory, agents, simulation) exchange; the node modules turn
it into ``comper_msgs/TransitionBatch`` and back with :mod:`comper_msgs_py.convert`.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields, replace

import numpy as np

__all__ = ["Transitions", "TransitionError"]


class TransitionError(ValueError):
    """A batch of transitions is malformed (shapes, dtypes, non-finite values)."""


def _empty_u64() -> np.ndarray:
    return np.zeros(0, dtype=np.uint64)


def _empty_f32() -> np.ndarray:
    return np.zeros(0, dtype=np.float32)


@dataclass
class Transitions:
    """N transitions, columnar.

    states / next_states: [N, *obs_shape], float32 (MuJoCo, raw) or uint8 (Atari frames).
    actions: [N, action_dim] float32 (continuous) or [N] (discrete indices, any int/float dtype).
    rewards: [N] float32. terminated / truncated: [N] bool, kept separate end to end.
    value_labels: [N] float32 or empty. episode_ids / steps: [N] uint64 or empty.
    """

    states: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    next_states: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    value_labels: np.ndarray = field(default_factory=_empty_f32)
    episode_ids: np.ndarray = field(default_factory=_empty_u64)
    steps: np.ndarray = field(default_factory=_empty_u64)
    run_id: str = ""

    def __len__(self) -> int:
        return int(self.rewards.shape[0])

    @property
    def obs_shape(self) -> tuple[int, ...]:
        return tuple(self.states.shape[1:])

    @property
    def is_discrete(self) -> bool:
        return self.actions.ndim == 1

    def validate(self, *, require_labels: bool = False, require_finite: bool = True) -> "Transitions":
        """Check shapes, dtypes and finiteness; raise TransitionError with a clear message."""
        n = len(self)
        if self.rewards.ndim != 1:
            raise TransitionError(f"rewards must be 1-d, got shape {self.rewards.shape}")
        for name in ("states", "actions", "next_states", "terminated", "truncated"):
            arr = getattr(self, name)
            if arr.shape[:1] != (n,):
                raise TransitionError(f"{name} has leading dimension {arr.shape[:1]}, expected ({n},)")
        if self.states.shape != self.next_states.shape:
            raise TransitionError(
                f"states {self.states.shape} and next_states {self.next_states.shape} differ in shape")
        if self.states.dtype != self.next_states.dtype or self.states.dtype not in (np.float32, np.uint8):
            raise TransitionError(
                f"states/next_states must both be float32 or uint8, got {self.states.dtype}/{self.next_states.dtype}")
        if self.actions.ndim not in (1, 2):
            raise TransitionError(f"actions must be [N] or [N, action_dim], got {self.actions.shape}")
        for name in ("value_labels", "episode_ids", "steps"):
            arr = getattr(self, name)
            if arr.size not in (0, n) or arr.ndim != 1:
                raise TransitionError(f"{name} must be empty or have shape ({n},), got {arr.shape}")
        if require_labels and self.value_labels.size != n:
            raise TransitionError(f"value_labels: expected {n} values, got {self.value_labels.size}")
        if require_finite:
            for name in ("states", "actions", "rewards", "next_states", "value_labels"):
                arr = getattr(self, name)
                if arr.dtype.kind == "f" and arr.size and not np.isfinite(arr).all():
                    bad = int(np.flatnonzero(~np.isfinite(arr.reshape(n, -1)).all(axis=1))[0]) if n else 0
                    raise TransitionError(f"{name} holds NaN or Inf (first at transition {bad})")
        return self

    def take(self, index: np.ndarray | slice) -> "Transitions":
        """Rows `index` of every per-transition column (a copy for fancy indices, a view for slices)."""
        def pick(a: np.ndarray) -> np.ndarray:
            return a[index] if a.size else a
        return replace(self, **{f.name: pick(getattr(self, f.name))
                                for f in fields(self) if f.name != "run_id"})

    @staticmethod
    def concatenate(parts: "list[Transitions]") -> "Transitions":
        if not parts:
            raise TransitionError("cannot concatenate an empty list of batches")
        out = {}
        for f in fields(Transitions):
            if f.name == "run_id":
                continue
            arrays = [getattr(p, f.name) for p in parts]
            if any(a.size == 0 for a in arrays) and f.name in ("value_labels", "episode_ids", "steps"):
                arrays = arrays if all(a.size == len(p) for a, p in zip(arrays, parts)) else [arrays[0][:0]]
            out[f.name] = np.concatenate(arrays)
        return Transitions(**out, run_id=parts[0].run_id)
