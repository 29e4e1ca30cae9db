"""MemoryReplayBuffer: the memory service as a plain replay buffer for any Python learner.

numpy in, numpy out; no ROS types in its interface::

    from comper_memory.replay_buffer import MemoryReplayBuffer

    with MemoryReplayBuffer("memory_node") as buffer:          # a running memory_node
        buffer.add(obs, action, reward, next_obs, terminated, truncated)
        buffer.extend(obs_batch, action_batch, ...)             # [N, ...] arrays
        if len(buffer) >= 64:
            b = buffer.sample(64)                               # dict of numpy arrays
            loss = td_loss(b["obs"], b["action"], b["reward"], b["next_obs"], b["terminated"])

What it does with the memory (docs/memory-service.md, "The memory as a replay buffer"):

- ``add`` / ``extend`` collect transitions and send them in one ``~/store`` call per
  ``store_every`` transitions, and before every ``sample`` (a sample always sees every transition
  added before it).
- The memory groups similar transitions (squared distance of [s, a, r, s'] <= the node's
  ``delta``) into one identity. Before a sample that follows new stores the buffer asks the memory
  node to reduce (``~/reduce``: each new or grown set becomes one RTM entry), then samples RTM
  uniformly. So a draw is uniform over *identities*, not over transitions: near-duplicates count
  once, which is the compact memory's point. With continuous states and the default delta 1e-4
  practically every transition is its own identity and the buffer behaves as a uniform one.
- ``len(buffer)`` is the number of live identities (the memory's ``identities``); the memory's
  ``rtm_capacity`` and ``tm_capacity`` bound it (least recently updated identities are evicted).
- **Labels are optional.** COMPER and COMCACT store a value label with each transition (the
  bootstrap value Q(s', .) of the learner, 0 when terminated) and read it back as QT's target. A
  learner that gives none gets ``default_label`` (0.0) stored. The memory node's own reduction
  predicts each set's newest label, so ``sample()["label"]`` is then that constant: harmless for a
  learner that computes its own targets (DQN, DDPG, TD3, SAC: the labels are never read), but a
  learner that wants QT's targets from this memory must give real labels and reduce through the QT
  trainer node instead.

Several learners (or actors and a learner) may share one memory node; the node's rate limiter
(``samples_per_insert``) holds them to a ratio, and ``store``/``sample`` then wait in this client
(``rate_limit_timeout``).
"""
from __future__ import annotations

import numpy as np

from comper_msgs_py.arrays import Transitions

from .client import MemoryClient

__all__ = ["MemoryReplayBuffer", "DEFAULT_LABEL"]

#: the value label stored for a transition a learner gives none for (module text)
DEFAULT_LABEL = 0.0


def _obs_array(x) -> np.ndarray:
    """Observations as the memory keeps them: uint8 frames as they are, anything else float32."""
    x = np.asarray(x)
    return x if x.dtype == np.uint8 else x.astype(np.float32, copy=False)


class MemoryReplayBuffer:
    """A replay buffer backed by a memory node (module text).

    memory: a MemoryClient, or the memory node's name (a standalone client is then created and
    closed with the buffer). store_every: transitions collected per store call (a sample flushes
    first). default_label: the label stored when ``add``/``extend`` get none. source: ``rtm``
    (reduce, then sample the reduced memory; the default) or ``tm`` (sample the not-yet-reduced
    sets and never reduce: the COMPER-M ablation's view). run_id: written with the transitions
    (bags, provenance)."""

    def __init__(self, memory: MemoryClient | str = "memory_node", *, store_every: int = 1,
                 default_label: float = DEFAULT_LABEL, source: str = "rtm", run_id: str = "",
                 timeout: float = 30.0, wait_for_service_s: float = 30.0):
        if source not in ("rtm", "tm"):
            raise ValueError(f"source must be 'rtm' or 'tm', got {source!r}")
        if store_every < 1:
            raise ValueError(f"store_every must be >= 1, got {store_every}")
        if not np.isfinite(default_label):
            raise ValueError(f"default_label must be finite, got {default_label}")
        self._owned = isinstance(memory, str)
        self.memory = MemoryClient.standalone(memory, timeout=timeout) if self._owned else memory
        if wait_for_service_s > 0 and not self.memory.wait_for_service(wait_for_service_s):
            name = self.memory.memory_node
            self.close()
            raise RuntimeError(f"no memory node {name!r} answered within {wait_for_service_s:g} s "
                               f"(start one with: ros2 run comper_memory memory_node --ros-args -r __node:={name})")
        self.store_every = int(store_every)
        self.default_label = float(default_label)
        self.source = source
        self.run_id = run_id
        self._pending: list[Transitions] = []
        self._pending_n = 0
        self._reduced = True       # nothing stored since the last reduction
        self._size: int | None = None   # RTM entries after this buffer's last reduction
        self.added = 0             # transitions given to add / extend

    # --- writing ------------------------------------------------------------------------------
    def add(self, obs, action, reward, next_obs, terminated, truncated=False, label=None) -> None:
        """One transition (arrays without a batch dimension)."""
        self.extend(np.asarray(obs)[None], np.asarray(action)[None], np.asarray([reward]),
                    np.asarray(next_obs)[None], np.asarray([terminated]), np.asarray([truncated]),
                    None if label is None else np.asarray([label]))

    def extend(self, obs, action, reward, next_obs, terminated, truncated=None, label=None) -> None:
        """N transitions: obs/next_obs [N, *obs_shape], action [N, *action_shape], reward,
        terminated, truncated, label [N] (truncated None: all False; label None: default_label).
        Bad input raises ValueError here, before anything is sent."""
        obs, next_obs = _obs_array(obs), _obs_array(next_obs)
        n = int(obs.shape[0]) if obs.ndim else 0
        if n == 0:
            return
        action = np.asarray(action)
        action = action.astype(np.int64) if action.dtype.kind in "iub" else action.astype(np.float32)
        reward = np.asarray(reward, np.float32).reshape(-1)
        lab = (np.full(n, self.default_label, np.float32) if label is None
               else np.asarray(label, np.float32).reshape(-1))
        t = Transitions(states=obs, actions=action, rewards=reward, next_states=next_obs,
                        terminated=np.asarray(terminated, bool).reshape(-1),
                        truncated=(np.zeros(n, bool) if truncated is None else np.asarray(truncated, bool).reshape(-1)),
                        value_labels=lab, run_id=self.run_id)
        t.validate()
        self._pending.append(t)
        self._pending_n += n
        self.added += n
        if self._pending_n >= self.store_every:
            self.flush()

    def flush(self) -> None:
        """Send what add/extend collected (one store call)."""
        if not self._pending:
            return
        parts, self._pending, self._pending_n = self._pending, [], 0
        self.memory.store(parts[0] if len(parts) == 1 else Transitions.concatenate(parts))
        self._reduced = False

    # --- reading ------------------------------------------------------------------------------
    def sample(self, batch_size: int, seed: int | None = None, *, fill: bool = False) -> dict:
        """batch_size distinct identities, uniformly (module text): a dict of numpy arrays
        obs, action, reward, next_obs, terminated, truncated, label, identity_id, count.

        Fewer identities than batch_size: MemoryServiceError, or with fill=True every identity once
        and the rest of the batch drawn from them uniformly with replacement (what a buffer that
        samples with replacement, like Stable-Baselines3's, gives its learner early on)."""
        self.flush()
        if self.source == "rtm" and not self._reduced:
            self._size = self.memory.reduce().rtm_size
            self._reduced = True
        k = int(batch_size)
        if fill:
            size = self._size if self.source == "rtm" and self._size is not None else \
                int(self.memory.stats()["rtm_size" if self.source == "rtm" else "tm_sets"])
            k = min(k, size)
        t, ids, counts = self.memory.sample(k, self.source, seed)
        if k < batch_size and k > 0:
            rng = np.random.default_rng(seed)
            pick = np.concatenate([np.arange(k), rng.integers(0, k, int(batch_size) - k)])
            t, ids, counts = t.take(pick), ids[pick], counts[pick]
        return {"obs": t.states, "action": t.actions, "reward": t.rewards, "next_obs": t.next_states,
                "terminated": t.terminated, "truncated": t.truncated, "label": t.value_labels,
                "identity_id": ids, "count": counts}

    def __len__(self) -> int:
        """Live identities in the memory (after sending what is collected)."""
        self.flush()
        return int(self.memory.stats()["identities"])

    # --- life -------------------------------------------------------------------------------
    def close(self) -> None:
        """Send what is collected (if the node still answers) and close an owned client."""
        try:
            if self._pending and self.memory is not None:
                self.flush()
        finally:
            if self._owned and self.memory is not None:
                self.memory.close()
            self.memory = None if self._owned else self.memory

    def __enter__(self) -> "MemoryReplayBuffer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
