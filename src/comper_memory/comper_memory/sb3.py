"""CompactReplayBuffer: the memory service as a Stable-Baselines3 replay buffer.

    from stable_baselines3 import TD3
    from comper_memory.sb3 import CompactReplayBuffer

    model = TD3("MlpPolicy", "Hopper-v4", replay_buffer_class=CompactReplayBuffer,
                replay_buffer_kwargs={"memory_node": "memory_node"})
    model.learn(50_000)
    model.replay_buffer.close()

Works with SB3's off-policy algorithms that use a plain ``ReplayBuffer`` (DDPG, TD3, SAC, DQN) and
Box or Discrete spaces. Transitions go to a running memory node (``ros2 run comper_memory
memory_node``), in this or another process or host, through :class:`~.replay_buffer.MemoryReplayBuffer`;
samples are uniform over the memory's identities (near-duplicate transitions count once; with
continuous states and delta 1e-4 that is every transition), and every transition added before a
sample is in its draw. Stores go in batches of ``store_every`` and batches are fetched ``prefetch``
at a time in the background, the transitions added since mixed in exactly (replay_buffer's module
text), so the learner rarely waits for the node. ``seed`` (default: drawn from numpy's global
generator, which SB3 seeds with the model's ``seed`` just before it builds the buffer) makes the
draws reproducible: the same model seed on a fresh memory node gives the same batches, and with
SB3's own determinism the same policy. ``TimeLimit.truncated`` is kept apart:
the stored ``terminated`` is ``done and not truncated``, and the ``dones`` SB3 receives from
``sample`` are those terminations, as SB3's own buffer with ``handle_timeout_termination``.

Not supported (a clear error at construction): ``optimize_memory_usage`` and Dict observation
spaces. ``buffer_size`` is not used: the memory node's ``rtm_capacity`` / ``tm_capacity`` bound what it
keeps. SB3's ``save_replay_buffer`` would pickle a ROS client: save the memory with the node's
``~/snapshot`` service instead (``MemoryClient.snapshot``).

Stable-Baselines3 is a test / benchmark extra of this workspace (requirements-extras.lock), not a
runtime dependency: importing this module needs it.
"""
from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import spaces
from stable_baselines3.common.buffers import BaseBuffer
from stable_baselines3.common.type_aliases import ReplayBufferSamples

from .client import MemoryClient
from .replay_buffer import DEFAULT_LABEL, DEFAULT_PREFETCH, DEFAULT_STORE_EVERY, MemoryReplayBuffer

__all__ = ["CompactReplayBuffer"]


class CompactReplayBuffer(BaseBuffer):
    """SB3 replay buffer backed by a memory node (module text). SB3 passes the first six
    arguments; ``replay_buffer_kwargs`` may give memory_node (its name) or memory (a MemoryClient),
    store_every (transitions per store call, default DEFAULT_STORE_EVERY), prefetch (batches per
    request, default DEFAULT_PREFETCH; 0: one request per sample), seed (the buffer's sampling
    stream; default from numpy's global generator, i.e. the model's seed), timeout, rate_limit_timeout."""

    def __init__(self, buffer_size: int, observation_space: spaces.Space, action_space: spaces.Space,
                 device: Any = "auto", n_envs: int = 1, optimize_memory_usage: bool = False,
                 handle_timeout_termination: bool = True, *, memory_node: str = "memory_node",
                 memory: MemoryClient | None = None, store_every: int = DEFAULT_STORE_EVERY,
                 prefetch: int = DEFAULT_PREFETCH, seed: int | None = None, timeout: float = 30.0,
                 rate_limit_timeout: float | None = None, default_label: float = DEFAULT_LABEL):
        if optimize_memory_usage:
            raise ValueError("CompactReplayBuffer: optimize_memory_usage is not supported (the memory node "
                             "stores each transition's next state itself)")
        if isinstance(observation_space, spaces.Dict):
            raise ValueError("CompactReplayBuffer: Dict observation spaces are not supported")
        if not isinstance(action_space, (spaces.Box, spaces.Discrete)):
            raise ValueError(f"CompactReplayBuffer: action space {action_space} is not Box or Discrete")
        super().__init__(buffer_size, observation_space, action_space, device, n_envs=n_envs)
        self.handle_timeout_termination = handle_timeout_termination
        self.discrete = isinstance(action_space, spaces.Discrete)
        if seed is None:   # SB3 calls set_random_seed(model seed) before it builds its buffer
            seed = int(np.random.randint(0, 2**31 - 1))
        client = memory if memory is not None else MemoryClient.standalone(
            memory_node, timeout=timeout, rate_limit_timeout=rate_limit_timeout)
        try:
            self.buffer = MemoryReplayBuffer(client, store_every=store_every, prefetch=prefetch, seed=seed,
                                             default_label=default_label, run_id="sb3")
        except Exception:
            if memory is None:
                client.close()
            raise
        self._owns_client = memory is None

    def add(self, obs: np.ndarray, next_obs: np.ndarray, action: np.ndarray, reward: np.ndarray,
            done: np.ndarray, infos: list[dict[str, Any]]) -> None:
        n = self.n_envs
        done = np.asarray(done, bool).reshape(n)
        truncated = np.array([bool(info.get("TimeLimit.truncated", False)) for info in infos])
        terminated = done & ~truncated if self.handle_timeout_termination else done
        action = np.asarray(action).reshape(n) if self.discrete else np.asarray(action).reshape(n, self.action_dim)
        self.buffer.extend(np.asarray(obs).reshape(n, *self.obs_shape), action, np.asarray(reward).reshape(n),
                           np.asarray(next_obs).reshape(n, *self.obs_shape), terminated, done & truncated)
        self.pos += 1
        if self.pos == self.buffer_size:
            self.full, self.pos = True, 0

    def size(self) -> int:
        """Live identities in the memory."""
        return len(self.buffer)

    def sample(self, batch_size: int, env=None) -> ReplayBufferSamples:
        b = self.buffer.sample(batch_size, fill=True)   # SB3 samples with replacement: early batches repeat
        actions = b["action"].reshape(-1, 1) if self.discrete else b["action"].reshape(-1, self.action_dim)
        data = (self._normalize_obs(b["obs"], env), actions, self._normalize_obs(b["next_obs"], env),
                b["terminated"].astype(np.float32).reshape(-1, 1),
                self._normalize_reward(b["reward"].reshape(-1, 1), env))
        return ReplayBufferSamples(*tuple(map(self.to_torch, data)))

    def _get_samples(self, batch_inds: np.ndarray, env=None) -> ReplayBufferSamples:
        raise NotImplementedError("CompactReplayBuffer draws in the memory node: use sample()")

    def close(self) -> None:
        """Send what is collected, stop the buffer's background thread and close the client (if this
        buffer created it). Idempotent."""
        client = self.buffer.memory
        try:
            self.buffer.close()
        finally:
            if self._owns_client and client is not None:
                self._owns_client = False
                client.close()

    def __getstate__(self):
        raise TypeError("CompactReplayBuffer holds a ROS client and cannot be pickled; save the memory with "
                        "its node's ~/snapshot service (MemoryClient.snapshot) instead")
