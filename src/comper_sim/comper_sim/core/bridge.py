"""SimBridge: lock-step reset / step / step_many / info over a SimEnv (pure: no ROS imports).

Every request is validated completely before anything changes: a refused request raises
:class:`SimError` with a readable message and leaves the environment, the episode and all
counters exactly as they were.

Episodes: ids count from 0 (one per reset). ``episode_end`` (method.md 6.3) chooses which signal
ends an episode; ``terminated`` and ``truncated`` are always reported as the environment gives
them and are never merged. After the episode has ended, ``step`` is refused until ``reset``;
``step_many(..., autoreset=True)`` resets by itself and goes on.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from comper_msgs_py.arrays import Transitions

from .config import EPISODE_END_RULES, SimConfig, episode_over
from .envs import SimEnv, make_env

__all__ = ["SimError", "SimBridge", "StepResult", "StepManyResult", "EpisodeRecord", "EnvInfo"]


class SimError(ValueError):
    """A request was refused (bad action, wrong state); nothing changed."""


@dataclass
class EpisodeRecord:
    """One finished episode (the node publishes it as comper_msgs/EpisodeSummary)."""
    episode_id: int
    episode_return: float
    length: int                 # agent steps
    frames: int                 # emulator frames including skipped ones (== length for vector tasks)
    terminated: bool
    truncated: bool
    global_step: int            # agent steps of the run when it ended
    global_frames: int
    wall_time_s: float          # since the bridge was created


@dataclass
class StepResult:
    observation: np.ndarray     # s_{t+1}
    reward: float
    terminated: bool
    truncated: bool
    episode_id: int
    episode_step: int           # agent steps in this episode so far
    frames: int                 # emulator frames in this episode so far
    episode_over: bool          # the episode ended (by the episode_end rule): call reset
    episode: EpisodeRecord | None = None


@dataclass
class StepManyResult:
    transitions: Transitions    # [<= K], value_labels empty, episode_ids and steps filled
    observation: np.ndarray     # where the next call continues from
    episodes_ended: int
    episodes: list[EpisodeRecord] = field(default_factory=list)


@dataclass
class EnvInfo:
    env_id: str
    observation_shape: tuple[int, ...]
    observation_dtype: np.dtype
    discrete: bool
    num_actions: int
    action_shape: tuple[int, ...]
    action_low: np.ndarray
    action_high: np.ndarray
    max_episode_steps: int
    frame_skip: int
    episode_end: str
    spec: dict[str, Any]


class SimBridge:
    """Lock-step access to one environment; see the module docstring."""

    def __init__(self, config: SimConfig | None = None, env: SimEnv | None = None):
        self.config = config if config is not None else SimConfig()
        self.env = env if env is not None else make_env(self.config)
        self._clip = self.config.action_out_of_range == "clip"
        rule = self.config.episode_end
        if rule not in EPISODE_END_RULES:
            raise SimError(f"episode_end must be standard, truncation_only or termination_only, got {rule!r}")
        self._rule = rule
        self._start_time = time.monotonic()
        self._seeded = False
        self.episode_id = -1          # no episode yet
        self.episode_step = 0
        self.episode_frames = 0
        self.episode_return = 0.0
        self.total_steps = 0
        self.total_frames = 0
        self.needs_reset = True
        self._ended_by: str = "not started"
        self.observation: np.ndarray | None = None

    # --- validation -------------------------------------------------------------------------
    def _as_numeric(self, action, what: str) -> np.ndarray:
        try:
            arr = np.asarray(action)
        except Exception as exc:  # ragged lists and the like
            raise SimError(f"{what} is not an array of numbers: {exc}") from None
        if arr.dtype.kind not in "iuf":
            raise SimError(f"{what} must be numeric, got dtype {arr.dtype}")
        return arr

    def _check_values(self, arr: np.ndarray, what: str, batch: bool) -> np.ndarray:
        """arr: [*action_shape] or [K, *action_shape] (batch) -> the action(s) to apply."""
        env = self.env

        def where(mask: np.ndarray) -> str:
            if not batch:
                return ""
            rows = mask.reshape(mask.shape[0], -1).any(axis=1)
            return f" (first at row {int(np.flatnonzero(rows)[0])})"

        if arr.dtype.kind == "f":
            bad = ~np.isfinite(arr)
            if bad.any():
                raise SimError(f"{what} holds NaN or Inf{where(bad)}")
        if env.discrete:
            if arr.dtype.kind == "f":
                frac = arr != np.floor(arr)
                if frac.any():
                    raise SimError(f"{what}: a discrete action must be a whole number{where(frac)}, "
                                   f"got {float(arr[frac].reshape(-1)[0]):g}")
            out = (arr < 0) | (arr >= env.num_actions)
            if out.any():
                raise SimError(f"{what}: discrete action {float(arr[out].reshape(-1)[0]):g} is outside "
                               f"[0, {env.num_actions}){where(out)}")
            return arr.astype(np.int64)
        arr = arr.astype(np.float32)
        low, high = env.action_low, env.action_high
        out = (arr < low) | (arr > high)
        if out.any():
            if self._clip:
                return np.clip(arr, low, high)
            raise SimError(
                f"{what}: a value is outside the action bounds [{np.array2string(low, precision=4)}, "
                f"{np.array2string(high, precision=4)}]{where(out)}: got {float(arr[out].reshape(-1)[0]):g} "
                "(set action_out_of_range:=clip to clip instead)")
        return arr

    def validate_action(self, action) -> np.ndarray | int:
        """One action -> what the environment gets; raises SimError."""
        arr = self._as_numeric(action, "action")
        env = self.env
        if env.discrete:
            if arr.size != 1 or arr.ndim > 1:
                raise SimError(f"action: a discrete action is one index (shape [] or [1]), got shape {list(arr.shape)}")
            return int(self._check_values(arr.reshape(()), "action", batch=False))
        if arr.shape != env.action_shape:
            raise SimError(f"action must have shape {list(env.action_shape)}, got {list(arr.shape)}")
        return self._check_values(arr, "action", batch=False)

    def validate_actions(self, actions) -> np.ndarray:
        """K actions -> [K] int64 (discrete) or [K, *action_shape] float32; raises SimError."""
        arr = self._as_numeric(actions, "actions")
        env = self.env
        expected = "[K]" if env.discrete else f"[K, {', '.join(map(str, env.action_shape))}]"
        if env.discrete:
            if arr.ndim == 2 and arr.shape[1] == 1:
                arr = arr.reshape(-1)
            ok = arr.ndim == 1
        else:
            ok = arr.ndim == 1 + len(env.action_shape) and arr.shape[1:] == env.action_shape
        if not ok:
            raise SimError(f"actions must have shape {expected}, got {list(arr.shape)}")
        if arr.shape[0] == 0:
            raise SimError("actions is empty (K = 0)")
        return self._check_values(arr, "actions", batch=True)

    def _check_can_step(self) -> None:
        if self.needs_reset:
            if self.episode_id < 0:
                raise SimError("no episode in progress: call reset first")
            raise SimError(f"episode {self.episode_id} has ended ({self._ended_by}): call reset first")

    # --- operations -------------------------------------------------------------------------
    def reset(self, seed: int | None = None) -> tuple[np.ndarray, int]:
        """Start a new episode; seed None or < 0 continues the random stream (the very first
        reset uses config.seed when that is >= 0). Returns (observation, episode_id)."""
        if seed is not None:
            try:
                seed = int(seed)
            except (TypeError, ValueError):
                raise SimError(f"seed must be an integer, got {seed!r}") from None
            if seed < 0:
                seed = None
        if seed is None and not self._seeded and self.config.seed >= 0:
            seed = self.config.seed
        obs = self.env.reset(seed)
        self._seeded = True
        self.observation = obs
        self.episode_id += 1
        self.episode_step = 0
        self.episode_frames = 0
        self.episode_return = 0.0
        self.needs_reset = False
        self._ended_by = ""
        return obs, self.episode_id

    def _advance(self, action) -> tuple[np.ndarray, float, bool, bool, EpisodeRecord | None]:
        obs, reward, terminated, truncated, frames = self.env.step(action)
        self.observation = obs
        self.episode_step += 1
        self.episode_frames += frames
        self.total_steps += 1
        self.total_frames += frames
        self.episode_return += reward
        over = episode_over(self._rule, terminated, truncated)
        if not over and self.env.game_over_ends_episode and (terminated or truncated):
            over = True   # ALE: the emulator cannot continue after game over or its frame cap
        record = None
        if over:
            self.needs_reset = True
            self._ended_by = "terminated" if terminated else "truncated"
            record = EpisodeRecord(
                episode_id=self.episode_id, episode_return=self.episode_return, length=self.episode_step,
                frames=self.episode_frames, terminated=terminated, truncated=truncated,
                global_step=self.total_steps, global_frames=self.total_frames,
                wall_time_s=time.monotonic() - self._start_time)
        return obs, reward, terminated, truncated, record

    def step(self, action) -> StepResult:
        """Apply one action (validated first; SimError leaves everything unchanged)."""
        self._check_can_step()
        a = self.validate_action(action)
        obs, reward, terminated, truncated, record = self._advance(a)
        return StepResult(observation=obs, reward=reward, terminated=terminated, truncated=truncated,
                          episode_id=self.episode_id, episode_step=self.episode_step,
                          frames=self.episode_frames, episode_over=record is not None, episode=record)

    def play_episode(self, policy, seed: int | None = None) -> tuple[float, int, StepResult]:
        """One whole episode from reset(seed), each action policy(observation) (an evaluation
        episode: nothing stored). Returns (return, steps, the last StepResult)."""
        obs, _ = self.reset(seed)
        ret, n = 0.0, 0
        while True:
            res = self.step(policy(obs))
            ret += float(res.reward)
            n += 1
            obs = res.observation
            if res.episode_over:
                return ret, n, res

    def step_many(self, actions, autoreset: bool = True) -> StepManyResult:
        """Apply K actions; return the transitions taken. Without autoreset stepping stops at the
        end of the episode (fewer than K transitions)."""
        self._check_can_step()
        acts = self.validate_actions(actions)
        k = acts.shape[0]
        env = self.env
        states = np.empty((k, *env.observation_shape), dtype=env.observation_dtype)
        next_states = np.empty_like(states)
        rewards = np.empty(k, dtype=np.float32)
        terminated = np.zeros(k, dtype=bool)
        truncated = np.zeros(k, dtype=bool)
        episode_ids = np.empty(k, dtype=np.uint64)
        steps = np.empty(k, dtype=np.uint64)
        episodes: list[EpisodeRecord] = []
        advance = self._advance
        obs = self.observation
        n = k
        for i in range(k):
            states[i] = obs
            episode_ids[i] = self.episode_id
            steps[i] = self.total_steps
            nxt, rewards[i], terminated[i], truncated[i], record = advance(acts[i] if not env.discrete else int(acts[i]))
            next_states[i] = nxt
            obs = nxt
            if record is not None:
                episodes.append(record)
                if not autoreset:
                    n = i + 1
                    break
                obs, _ = self.reset(None)
        t = Transitions(states=states[:n], actions=acts[:n].astype(np.float32), rewards=rewards[:n],
                        next_states=next_states[:n], terminated=terminated[:n], truncated=truncated[:n],
                        episode_ids=episode_ids[:n], steps=steps[:n], run_id=self.config.run_id)
        return StepManyResult(transitions=t, observation=self.observation, episodes_ended=len(episodes),
                              episodes=episodes)

    def info(self) -> EnvInfo:
        env = self.env
        continuous = not env.discrete
        spec = dict(env.spec())
        spec.update({"seed": self.config.seed, "action_out_of_range": self.config.action_out_of_range,
                     "episode_end": self._rule})
        return EnvInfo(
            env_id=env.env_id, observation_shape=tuple(env.observation_shape),
            observation_dtype=np.dtype(env.observation_dtype), discrete=env.discrete,
            num_actions=env.num_actions if env.discrete else 0,
            action_shape=tuple(env.action_shape) if continuous else (),
            action_low=env.action_low if continuous else np.zeros(0, np.float32),
            action_high=env.action_high if continuous else np.zeros(0, np.float32),
            max_episode_steps=env.max_episode_steps, frame_skip=env.frame_skip,
            episode_end=self._rule, spec=spec)

    def close(self) -> None:
        self.env.close()
