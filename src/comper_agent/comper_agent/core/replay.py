"""Plain uniform FIFO replay buffer (DDPG and DQN baselines), numpy, preallocated.

Stores s and s' separately (simple and correct across episode ends). Memory: capacity x 2 x
obs size; Atari single frame at 100,000: 1.4 GB; 4 stacked frames: 5.6 GB (use a smaller
capacity or a frame-deduplicating buffer there).
"""
from __future__ import annotations

import numpy as np

from comper_msgs_py.arrays import Transitions

__all__ = ["ReplayBuffer"]


class ReplayBuffer:
    def __init__(self, capacity: int, obs_shape: tuple, action_shape: tuple = (),
                 obs_dtype=np.float32, action_dtype=np.float32, seed: int | None = None):
        self.capacity = int(capacity)
        c = self.capacity
        self.states = np.zeros((c, *obs_shape), dtype=obs_dtype)
        self.next_states = np.zeros((c, *obs_shape), dtype=obs_dtype)
        self.actions = np.zeros((c, *action_shape), dtype=action_dtype)
        self.rewards = np.zeros(c, np.float32)
        self.terminated = np.zeros(c, bool)
        self.truncated = np.zeros(c, bool)
        self.pos = 0
        self.size = 0
        self.rng = np.random.default_rng(seed)

    def __len__(self) -> int:
        return self.size

    @property
    def nbytes(self) -> int:
        return int(sum(a.nbytes for a in (self.states, self.next_states, self.actions, self.rewards,
                                          self.terminated, self.truncated)))

    def add(self, batch: Transitions) -> None:
        """Append a batch (oldest entries are overwritten when full)."""
        n = len(batch)
        if n == 0:
            return
        if n > self.capacity:
            batch = batch.take(slice(n - self.capacity, n))
            n = self.capacity
        idx = (self.pos + np.arange(n)) % self.capacity
        self.states[idx] = batch.states
        self.next_states[idx] = batch.next_states
        self.actions[idx] = np.asarray(batch.actions).reshape((n, *self.actions.shape[1:]))
        self.rewards[idx] = batch.rewards
        self.terminated[idx] = batch.terminated
        self.truncated[idx] = batch.truncated
        self.pos = int((self.pos + n) % self.capacity)
        self.size = min(self.capacity, self.size + n)

    def sample(self, k: int) -> Transitions:
        """k transitions drawn uniformly with replacement."""
        if self.size == 0:
            raise ValueError("cannot sample from an empty replay buffer")
        idx = self.rng.integers(0, self.size, size=int(k))
        return Transitions(states=self.states[idx], actions=self.actions[idx],
                           rewards=self.rewards[idx], next_states=self.next_states[idx],
                           terminated=self.terminated[idx], truncated=self.truncated[idx])
