"""Environments behind the simulation bridge (pure: no ROS imports).

``make_env(config)`` returns a :class:`SimEnv`:

* :class:`VectorEnv` wraps a gymnasium task with a Box observation (MuJoCo, classic control):
  raw observations as float32, the registered time limit unless overridden.
* :class:`AtariEnv` runs an ALE game under the Machado et al. (2018) protocol (method.md 5). The
  gymnasium env is made with ``frameskip=1`` and grayscale observations and this class does the
  skip itself, calling ``ale.act`` once per emulator frame: sticky actions
  (``repeat_action_probability``, default 0.25) are then drawn by ALE at every frame, as in the
  paper, and only the last two frames of the skip are read for the colour averaging. ALE's
  grayscale screen is the luminance of the NTSC palette; luminance is linear in RGB, so the
  average of two luminance frames is the luminance of the averaged colours. The average is resized
  to ``obs_size`` x ``obs_size`` by exact area averaging (two small matrix products, the same
  weights as an INTER_AREA/box downscale) and rounded to uint8. ``frame_pooling: max`` takes the
  per-pixel maximum of the two luminance frames instead (the DQN baseline's Table 35 setting, done on
  grayscale frames as Dopamine's Atari preprocessing does).

``SimEnv.step`` takes an action that the bridge has already validated.
"""
from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from .config import SimConfig

__all__ = ["EnvError", "SimEnv", "VectorEnv", "AtariEnv", "make_env", "area_resize_matrix", "AreaResize"]


class EnvError(RuntimeError):
    """The environment cannot be made (unknown id, missing dependency, unsupported spaces)."""


def _gym():
    import gymnasium as gym
    return gym


_ALE_REGISTERED = False


def _register_ale() -> None:
    global _ALE_REGISTERED
    if not _ALE_REGISTERED:
        import ale_py
        _gym().register_envs(ale_py)
        _ALE_REGISTERED = True


def _make_error(env_id: str, exc: BaseException) -> EnvError:
    text = str(exc).strip() or type(exc).__name__
    return EnvError(f"cannot make environment '{env_id}': {text}")


class SimEnv:
    """What the bridge needs from an environment. Attributes are set by the subclasses."""

    env_id: str
    observation_shape: tuple[int, ...]
    observation_dtype: np.dtype
    discrete: bool
    num_actions: int = 0                       # discrete only
    action_shape: tuple[int, ...] = ()         # continuous only
    action_low: np.ndarray | None = None       # continuous only, float32
    action_high: np.ndarray | None = None
    max_episode_steps: int = -1                # -1: none
    frame_skip: int = 1
    game_over_ends_episode: bool = False       # ALE: the emulator cannot continue after game over

    def reset(self, seed: int | None) -> np.ndarray:
        raise NotImplementedError

    def step(self, action) -> tuple[np.ndarray, float, bool, bool, int]:
        """(observation, reward, terminated, truncated, emulator frames taken)."""
        raise NotImplementedError

    def spec(self) -> dict[str, Any]:
        """Protocol settings, JSON-serialisable (EnvInfo.spec_json)."""
        raise NotImplementedError

    def close(self) -> None:
        env = getattr(self, "env", None)
        if env is not None:
            env.close()


class VectorEnv(SimEnv):
    """A gymnasium task with a Box observation: MuJoCo and classic control."""

    def __init__(self, config: SimConfig):
        gym = _gym()
        self.env_id = config.env_id
        try:
            spec = gym.spec(config.env_id)
            if config.max_episode_steps < 0:
                spec = dataclasses.replace(spec, max_episode_steps=None)
                self.env = gym.make(spec)
            elif config.max_episode_steps > 0:
                self.env = gym.make(spec, max_episode_steps=config.max_episode_steps)
            else:
                self.env = gym.make(spec)
        except Exception as exc:  # gymnasium raises many kinds (NameNotFound, DependencyNotInstalled, ...)
            raise _make_error(config.env_id, exc) from exc
        obs_space, act_space = self.env.observation_space, self.env.action_space
        if not isinstance(obs_space, gym.spaces.Box):
            self.env.close()
            raise EnvError(f"environment '{config.env_id}' has a {type(obs_space).__name__} observation space; "
                           "only Box observations are supported")
        self.observation_shape = tuple(int(d) for d in obs_space.shape)
        self.observation_dtype = np.dtype(np.float32)
        if isinstance(act_space, gym.spaces.Discrete):
            self.discrete = True
            self.num_actions = int(act_space.n)
            self._start = int(act_space.start)
        elif isinstance(act_space, gym.spaces.Box):
            self.discrete = False
            self.action_shape = tuple(int(d) for d in act_space.shape)
            self.action_low = np.asarray(act_space.low, dtype=np.float32)
            self.action_high = np.asarray(act_space.high, dtype=np.float32)
            self._act_dtype = act_space.dtype
        else:
            self.env.close()
            raise EnvError(f"environment '{config.env_id}' has a {type(act_space).__name__} action space; "
                           "only Box and Discrete actions are supported")
        limit = self.env.spec.max_episode_steps if self.env.spec is not None else None
        self.max_episode_steps = int(limit) if limit is not None else -1

    def reset(self, seed: int | None) -> np.ndarray:
        obs, _ = self.env.reset(seed=seed)
        return np.asarray(obs, dtype=np.float32)

    def step(self, action):
        if self.discrete:
            action = int(action) + self._start
        else:
            action = np.asarray(action, dtype=self._act_dtype)
        obs, reward, terminated, truncated, _ = self.env.step(action)
        return np.asarray(obs, dtype=np.float32), float(reward), bool(terminated), bool(truncated), 1

    def spec(self) -> dict[str, Any]:
        return {"kind": "vector", "observation": "raw float32", "frame_skip": 1,
                "max_episode_steps": self.max_episode_steps}


def area_resize_matrix(n_in: int, n_out: int) -> np.ndarray:
    """[n_out, n_in] weights of an exact area (box) downscale: each output cell averages the input
    cells it covers, fractional cells weighted by their covered fraction. Rows sum to 1."""
    if n_out > n_in:
        raise ValueError(f"area resize only downscales ({n_in} -> {n_out})")
    scale = n_in / n_out
    w = np.zeros((n_out, n_in), dtype=np.float64)
    for o in range(n_out):
        lo, hi = o * scale, (o + 1) * scale
        for i in range(int(np.floor(lo)), min(int(np.ceil(hi)), n_in)):
            w[o, i] = max(0.0, min(hi, i + 1) - max(lo, i))
    return w / scale


class AreaResize:
    """Exact area downscale of a 2-d frame without BLAS (numpy's threaded matmul is slow and
    contended on small frames): each output row/column is a weighted sum of at most a few input
    rows/columns, applied as gathers. Same result as ``R @ x @ C.T`` with
    :func:`area_resize_matrix` weights (up to float rounding)."""

    def __init__(self, in_shape: tuple[int, int], out_shape: tuple[int, int], gain: float = 1.0):
        self.rows = self._taps(gain * area_resize_matrix(in_shape[0], out_shape[0]))
        self.cols = self._taps(area_resize_matrix(in_shape[1], out_shape[1]))

    @staticmethod
    def _taps(w: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        nonzero = [np.flatnonzero(r > 0) for r in w]
        taps = max(len(z) for z in nonzero)
        out = []
        for k in range(taps):
            idx = np.array([z[k] if k < len(z) else z[0] for z in nonzero], dtype=np.intp)
            wk = np.array([w[o, z[k]] if k < len(z) else 0.0 for o, z in enumerate(nonzero)], dtype=np.float32)
            out.append((idx, wk))
        return out

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """x: float32 [H, W] -> float32 [h, w] (not rounded)."""
        (i0, w0), *rest = self.rows
        r = x[i0] * w0[:, None]
        for i, w in rest:
            r += x[i] * w[:, None]
        (i0, w0), *rest = self.cols
        o = r[:, i0] * w0
        for i, w in rest:
            o += r[:, i] * w
        return o


class AtariEnv(SimEnv):
    """An ALE game under the Machado et al. (2018) protocol; see the module docstring."""

    game_over_ends_episode = True

    def __init__(self, config: SimConfig):
        gym = _gym()
        self.env_id = config.env_id
        try:
            _register_ale()
            self.env = gym.make(config.env_id, frameskip=1,
                                repeat_action_probability=float(config.repeat_action_probability),
                                full_action_space=bool(config.full_action_space), obs_type="grayscale",
                                max_num_frames_per_episode=int(config.max_episode_frames))
        except Exception as exc:
            raise _make_error(config.env_id, exc) from exc
        self.ale_env = self.env.unwrapped
        self.ale = self.ale_env.ale
        self._action_set = list(self.ale_env._action_set)
        self.discrete = True
        self.num_actions = len(self._action_set)
        self.frame_skip = int(config.frame_skip)
        self.max_episode_steps = int(config.max_episode_steps) if config.max_episode_steps > 0 else -1
        self.frame_stack = int(config.frame_stack)
        self.preprocessing = config.preprocessing
        self.frame_pooling = config.frame_pooling
        self.repeat_action_probability = float(config.repeat_action_probability)
        self.max_episode_frames = int(config.max_episode_frames)
        h, w = self.ale.getScreenDims()
        self._screens = np.zeros((2, h, w), dtype=np.uint8)   # the last two frames of the skip
        if self.preprocessing == "standard":
            n = int(config.obs_size)
            # gain 0.5 folds the average of the two frames into the row weights
            self._resize = AreaResize((h, w), (n, n), gain=0.5)
            frame_shape = (n, n)
        else:
            frame_shape = (h, w)
        self._frame_shape = frame_shape
        self.observation_shape = frame_shape if self.frame_stack == 1 else (self.frame_stack, *frame_shape)
        self.observation_dtype = np.dtype(np.uint8)
        self._stack = np.zeros((self.frame_stack, *frame_shape), dtype=np.uint8)
        self._episode_step = 0

    def _frame(self, newest: int, count: int) -> np.ndarray:
        """The observation frame from the screens captured in this step (newest = index of the
        last captured one; count = how many were captured, 1 or 2)."""
        last = self._screens[newest]
        if self.preprocessing != "standard":
            return last.copy()
        prev = self._screens[1 - newest] if count >= 2 else last
        if self.frame_pooling == "max":
            total = np.maximum(last, prev).astype(np.float32)
            total *= 2.0                     # the resize's gain 0.5 expects the sum of two frames
        else:
            total = last.astype(np.float32)
            total += prev
        out = self._resize(total)
        np.rint(out, out=out)
        return out.astype(np.uint8)

    def _observe(self, frame: np.ndarray, fill: bool) -> np.ndarray:
        if self.frame_stack == 1:
            return frame
        if fill:
            self._stack[:] = frame
        else:
            self._stack[:-1] = self._stack[1:]
            self._stack[-1] = frame
        return self._stack.copy()

    def reset(self, seed: int | None) -> np.ndarray:
        self.env.reset(seed=seed)
        self._episode_step = 0
        self.ale.getScreenGrayscale(self._screens[0])
        return self._observe(self._frame(0, 1), fill=True)

    def step(self, action):
        ale, screens, skip = self.ale, self._screens, self.frame_skip
        a = self._action_set[int(action)]
        reward = 0.0
        frames = 0
        captured = 0
        while frames < skip:
            reward += ale.act(a)             # one emulator frame; ALE draws the sticky action here
            frames += 1
            over = ale.game_over()           # game over or the emulator's frame cap
            if frames >= skip - 1 or over:   # only the last two frames of the skip are averaged
                ale.getScreenGrayscale(screens[frames & 1])
                captured += 1
            if over:                         # a game over inside the skip ends the step there; if it
                break                        # comes before frame skip-1 the last frame is used alone
        self._episode_step += 1
        terminated = bool(ale.game_over(with_truncation=False))
        truncated = bool(ale.game_truncated())
        if 0 < self.max_episode_steps <= self._episode_step:
            truncated = True
        obs = self._observe(self._frame(frames & 1, min(captured, 2)), fill=False)
        return obs, reward, terminated, truncated, frames

    def spec(self) -> dict[str, Any]:
        return {"kind": "ale", "protocol": "Machado et al. 2018",
                "frame_skip": self.frame_skip,
                "repeat_action_probability": float(self.ale.getFloat("repeat_action_probability")),
                "full_action_space": self.num_actions == 18 and len(self.ale.getLegalActionSet()) == 18,
                "num_actions": self.num_actions,
                "preprocessing": self.preprocessing,
                "colour_averaging": self.preprocessing == "standard" and self.frame_pooling == "average",
                "frame_pooling": self.frame_pooling if self.preprocessing == "standard" else "none",
                "luminance": True, "frame_shape": list(self._frame_shape),
                "frame_stack": self.frame_stack,
                "max_episode_frames": self.max_episode_frames,
                "max_episode_steps": self.max_episode_steps,
                "life_loss_signal": False, "episode_ends": "game over"}


def make_env(config: SimConfig) -> SimEnv:
    """The environment `config.env_id` with the protocol of its family (raises EnvError)."""
    if config.is_atari:
        return AtariEnv(config)
    return VectorEnv(config)
