"""Uniform replay buffers of the baselines, numpy, preallocated: :class:`ReplayBuffer` (DDPG, DQN on
vector tasks) and :class:`FrameReplay` (DQN on stacked Atari frames, each frame stored once).

ReplayBuffer stores s and s' separately (simple and correct across episode ends). Memory: capacity
x 2 x obs size; Atari single frame at 100,000: 1.4 GB; 4 stacked frames: 5.6 GB, which is why the
DQN baseline uses FrameReplay on frames.

Both buffers give their contents as plain arrays (:meth:`state_arrays`, only the filled part) and take
them back (:meth:`load_state_arrays`), so a checkpoint can carry the replay and a resumed run samples
what the interrupted one would have (the same transitions and the same random stream).
"""
from __future__ import annotations

from dataclasses import dataclass

import json

import numpy as np

from comper_msgs_py.arrays import Transitions

__all__ = ["ReplayBuffer", "FrameReplay", "NStepRewards"]


@dataclass
class NStepRewards:
    """The n-step part of a batch drawn with ``n_step > 1``: each drawn transition starts a window of up to
    n consecutive transitions of its episode. rewards: [k, n] raw rewards of the window (0 after its end);
    lengths: [k] transitions in the window (1..n). The batch's next_states / terminated / truncated are those
    of the window's last transition, so the target is sum_j gamma^j clip(r_j) + gamma^length Q(s_last')."""

    rewards: np.ndarray
    lengths: np.ndarray


class _Ring:
    """What both buffers share: a ring of time-ordered transitions (one writer, so positions that follow
    each other hold consecutive steps until an episode ends), uniform draws, and n-step windows."""

    capacity: int
    pos: int
    size: int
    rewards: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    rng: np.random.Generator

    #: the per-transition arrays of the ring (first axis = capacity)
    RING_FIELDS: tuple = ()
    #: the integer counters saved with them
    COUNTERS: tuple = ("pos", "size")

    def __len__(self) -> int:
        return self.size

    def _geometry(self) -> dict:
        """What must match between a saved replay and the buffer that loads it."""
        return {"class": type(self).__name__, "capacity": self.capacity,
                **{f: list(getattr(self, f).shape[1:]) + [str(getattr(self, f).dtype)] for f in self.RING_FIELDS}}

    def _saved_arrays(self) -> dict[str, np.ndarray]:
        """Subclass extras (e.g. the frame store), the filled part only."""
        return {}

    def _check_saved(self, arrays: dict[str, np.ndarray], counters: dict) -> None:
        """Subclass extras: ValueError if they do not fit (before anything is written)."""

    def _load_saved(self, arrays: dict[str, np.ndarray], counters: dict) -> None:
        pass

    def state_arrays(self) -> dict[str, np.ndarray]:
        """The buffer's contents as arrays (the filled positions, counters, the sampling RNG's state):
        ``np.savez``-able without pickling."""
        n = self.size
        out = {f: getattr(self, f)[:n].copy() for f in self.RING_FIELDS}
        out.update(self._saved_arrays())
        out["counters"] = np.array([int(getattr(self, c)) for c in self.COUNTERS], np.int64)
        out["geometry"] = np.array(json.dumps(self._geometry()))
        out["rng"] = np.array(json.dumps(self.rng.bit_generator.state))
        return out

    def load_state_arrays(self, arrays: dict[str, np.ndarray]) -> None:
        """Replace the contents by those of :meth:`state_arrays` of a buffer of the same class, capacity
        and shapes (ValueError otherwise, the buffer untouched)."""
        try:
            geometry = json.loads(str(arrays["geometry"]))
            counters = [int(c) for c in np.asarray(arrays["counters"]).reshape(-1)]
            rng_state = json.loads(str(arrays["rng"]))
        except (KeyError, ValueError) as exc:
            raise ValueError(f"not a saved replay buffer: {exc}") from None
        if geometry != self._geometry():
            raise ValueError(f"the saved replay buffer does not fit this one: saved {geometry}, "
                             f"this run's {self._geometry()}")
        values = dict(zip(self.COUNTERS, counters))
        n = values.get("size", -1)
        if len(counters) != len(self.COUNTERS) or not 0 <= n <= self.capacity \
                or any(np.shape(arrays.get(f, ())) != (n, *getattr(self, f).shape[1:]) for f in self.RING_FIELDS):
            raise ValueError("the saved replay buffer is inconsistent (its counters and arrays disagree)")
        try:
            type(self.rng.bit_generator)().state = rng_state
        except (TypeError, ValueError) as exc:
            raise ValueError(f"the saved replay buffer's random state is unusable: {exc}") from None
        self._check_saved(arrays, values)
        for f in self.RING_FIELDS:
            getattr(self, f)[:n] = arrays[f]
        self._load_saved(arrays, values)
        for c, v in values.items():
            setattr(self, c, v)
        self.rng.bit_generator.state = rng_state

    def _draw(self, k: int) -> np.ndarray:
        if self.size == 0:
            raise ValueError("cannot sample from an empty replay buffer")
        return self.rng.integers(0, self.size, size=int(k))

    def _starts_episode(self, p: np.ndarray) -> np.ndarray:
        return np.zeros(p.shape, bool)

    def _windows(self, idx: np.ndarray, n: int) -> tuple[NStepRewards, np.ndarray]:
        """Each start position's window: up to n transitions, ending at the first episode end (terminated or
        truncated), before a transition that starts an episode, or at the newest stored transition.
        Returns the rewards and lengths, and each window's last position."""
        k = idx.shape[0]
        newest = (self.pos - 1) % self.capacity
        left = (newest - idx) % self.capacity        # transitions stored after the start
        rewards = np.zeros((k, n), np.float32)
        rewards[:, 0] = self.rewards[idx]
        lengths = np.ones(k, np.int64)
        last = idx.copy()
        open_ = ~(self.terminated[idx] | self.truncated[idx])
        for j in range(1, n):
            p = (idx + j) % self.capacity
            open_ &= (j <= left) & ~self._starts_episode(p)
            if not open_.any():
                break
            rewards[open_, j] = self.rewards[p[open_]]
            lengths[open_] += 1
            last[open_] = p[open_]
            open_ &= ~(self.terminated[p] | self.truncated[p])
        return NStepRewards(rewards, lengths), last


class ReplayBuffer(_Ring):
    RING_FIELDS = ("states", "next_states", "actions", "rewards", "terminated", "truncated")

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

    @property
    def nbytes(self) -> int:
        return int(sum(a.nbytes for a in (self.states, self.next_states, self.actions, self.rewards,
                                          self.terminated, self.truncated)))

    def add_step(self, state: np.ndarray, action, reward: float, next_state: np.ndarray, terminated: bool,
                 truncated: bool, new_episode: bool = False) -> None:
        """One agent step (the signature of :meth:`FrameReplay.add`; `new_episode` changes nothing here)."""
        self.add(Transitions(states=state[None], actions=np.array([action], np.float32),
                             rewards=np.array([reward], np.float32), next_states=next_state[None],
                             terminated=np.array([terminated]), truncated=np.array([truncated])))

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

    def sample(self, k: int, n_step: int = 1) -> Transitions | tuple[Transitions, NStepRewards]:
        """k transitions drawn uniformly with replacement; with n_step > 1 also their n-step windows
        (:class:`NStepRewards`; the transitions then end where their windows end)."""
        idx = self._draw(k)
        nsr, last = self._windows(idx, int(n_step)) if n_step > 1 else (None, idx)
        batch = Transitions(states=self.states[idx], actions=self.actions[idx],
                            rewards=self.rewards[idx], next_states=self.next_states[last],
                            terminated=self.terminated[last], truncated=self.truncated[last])
        return batch if nsr is None else (batch, nsr)


class FrameReplay(_Ring):
    """Uniform replay for stacked uint8 frames that stores each frame once (DQN baseline).

    A transition keeps the ids of its state's and next state's frames; within an episode the next
    state's first C-1 frames are the state's last C-1 frames (the sim stacks oldest first), so each
    step adds one frame; an episode's first transition adds its state's C frames. Frame ids are
    global counters into a ring of `capacity + frame_margin` frames; a transition whose oldest frame
    was overwritten is no longer drawn. Reconstruction is exact (checked in the unit tests)."""

    RING_FIELDS = ("s_ids", "ns_ids", "actions", "rewards", "terminated", "truncated", "starts")
    COUNTERS = ("pos", "size", "frames_written")

    def __init__(self, capacity: int, frame_shape: tuple, stack: int, seed: int | None = None,
                 frame_margin: int | None = None):
        self.capacity = int(capacity)
        self.stack = int(stack)
        self.frame_shape = tuple(frame_shape)          # one frame: (84, 84)
        self.n_frames = self.capacity + (frame_margin if frame_margin is not None
                                         else max(64, self.capacity // 8))
        self.frames = np.zeros((self.n_frames, *self.frame_shape), np.uint8)
        self.frames_written = 0
        c = self.capacity
        self.s_ids = np.zeros((c, self.stack), np.int64)
        self.ns_ids = np.zeros((c, self.stack), np.int64)
        self.actions = np.zeros(c, np.float32)
        self.rewards = np.zeros(c, np.float32)
        self.terminated = np.zeros(c, bool)
        self.truncated = np.zeros(c, bool)
        self.starts = np.zeros(c, bool)                 # the transition starts an episode
        self.pos = 0
        self.size = 0
        self._last_ns: np.ndarray | None = None         # frame ids of the previous transition's s'
        self.rng = np.random.default_rng(seed)

    @property
    def nbytes(self) -> int:
        return int(self.frames.nbytes + self.s_ids.nbytes + self.ns_ids.nbytes)

    def _push(self, frame: np.ndarray) -> int:
        i = self.frames_written
        self.frames[i % self.n_frames] = frame
        self.frames_written += 1
        return i

    def _stacked(self, obs: np.ndarray) -> np.ndarray:
        return obs.reshape(self.stack, *self.frame_shape)

    def add(self, state: np.ndarray, action: int, reward: float, next_state: np.ndarray,
            terminated: bool, truncated: bool, new_episode: bool) -> None:
        s = self._stacked(state)
        ns = self._stacked(next_state)
        starts = new_episode or self._last_ns is None
        if starts:
            s_ids = np.array([self._push(f) for f in s], np.int64)
        else:
            s_ids = self._last_ns
        ns_ids = np.concatenate([s_ids[1:], [self._push(ns[-1])]]) if self.stack > 1 \
            else np.array([self._push(ns[-1])], np.int64)
        p = self.pos
        self.s_ids[p], self.ns_ids[p] = s_ids, ns_ids
        self.actions[p], self.rewards[p] = action, reward
        self.terminated[p], self.truncated[p] = terminated, truncated
        self.starts[p] = starts
        self._last_ns = ns_ids
        self.pos = (p + 1) % self.capacity
        self.size = min(self.capacity, self.size + 1)

    add_step = add      # one agent step, as ReplayBuffer.add_step

    def end_episode(self) -> None:
        self._last_ns = None

    def _geometry(self) -> dict:
        return {**super()._geometry(), "frames": [self.n_frames, *self.frame_shape], "stack": self.stack}

    def _saved_arrays(self) -> dict[str, np.ndarray]:
        """The frames still kept, oldest first (a resumed run starts a new episode: _last_ns is not kept)."""
        first = max(0, self.frames_written - self.n_frames)
        ids = np.arange(first, self.frames_written)
        return {"frames": self.frames[ids % self.n_frames]}

    def _check_saved(self, arrays: dict[str, np.ndarray], counters: dict) -> None:
        frames = arrays.get("frames")
        written = counters["frames_written"]
        if (frames is None or frames.shape != (min(written, self.n_frames), *self.frame_shape)
                or frames.dtype != np.uint8 or written < 0):
            raise ValueError("the saved replay buffer's frames do not match its frame count")

    def _load_saved(self, arrays: dict[str, np.ndarray], counters: dict) -> None:
        frames, written = arrays["frames"], counters["frames_written"]
        ids = np.arange(written - frames.shape[0], written)
        self.frames[ids % self.n_frames] = frames
        self._last_ns = None

    def _valid(self, idx: np.ndarray) -> np.ndarray:
        return self.s_ids[idx].min(axis=1) >= self.frames_written - self.n_frames

    def _starts_episode(self, p: np.ndarray) -> np.ndarray:
        return self.starts[p]

    def sample(self, k: int, n_step: int = 1) -> Transitions | tuple[Transitions, NStepRewards]:
        """k transitions drawn uniformly (with replacement) among those whose frames are all kept; with
        n_step > 1 also their n-step windows (:class:`NStepRewards`; the transitions then end where their
        windows end: a window's later frames are newer, so they are kept too)."""
        idx = self._draw(k)
        for _ in range(100):
            bad = ~self._valid(idx)
            if not bad.any():
                break
            idx[bad] = self.rng.integers(0, self.size, size=int(bad.sum()))
        if n_step <= 1:
            return self.take(idx)
        nsr, last = self._windows(idx, int(n_step))
        return self.take(idx, last), nsr

    def take(self, idx, last=None) -> Transitions:
        """The transitions at ring positions idx; with `last`, each one's next state and episode flags are
        those of the transition at last (the end of its n-step window)."""
        idx = np.asarray(idx)
        last = idx if last is None else np.asarray(last)
        squeeze = self.stack == 1
        st = self.frames[self.s_ids[idx] % self.n_frames]
        nst = self.frames[self.ns_ids[last] % self.n_frames]
        if squeeze:
            st, nst = st[:, 0], nst[:, 0]
        return Transitions(states=st, actions=self.actions[idx], rewards=self.rewards[idx], next_states=nst,
                           terminated=self.terminated[last], truncated=self.truncated[last])
