"""Transition keys and the exact distance every similarity decision is made with."""
from __future__ import annotations

import numpy as np

from comper_msgs_py.arrays import Transitions

__all__ = ["transition_keys", "key_size_of", "exact_sq_dist", "DEFAULT_FRAME_SCALE"]

DEFAULT_FRAME_SCALE = 1.0 / 255.0


def _obs_part(obs: np.ndarray, n: int, frame_scale: float) -> np.ndarray:
    flat = obs.reshape(n, -1)
    if flat.dtype == np.uint8:
        return flat.astype(np.float32) * np.float32(frame_scale)
    return flat.astype(np.float32, copy=False)


def transition_keys(t: Transitions, frame_scale: float = DEFAULT_FRAME_SCALE) -> np.ndarray:
    """Keys [N, key_dim] float32 = concat(s.flatten, a, r, s'.flatten).

    uint8 observations (Atari frames) are scaled once by ``frame_scale`` (1/255 -> [0, 1]);
    float observations are used raw. Discrete actions ([N]) contribute one value each.
    Atari single frame 84x84: 7056 + 1 + 1 + 7056 = 14114.
    """
    n = len(t)
    a = np.asarray(t.actions).reshape(n, -1).astype(np.float32, copy=False)
    r = np.asarray(t.rewards).reshape(n, 1).astype(np.float32, copy=False)
    return np.concatenate([_obs_part(t.states, n, frame_scale), a, r,
                           _obs_part(t.next_states, n, frame_scale)], axis=1)


def key_size_of(obs_shape: tuple[int, ...], action_dim: int) -> int:
    """Key length for observations of ``obs_shape`` and ``action_dim`` action values (1 if discrete)."""
    return 2 * int(np.prod(obs_shape, dtype=np.int64)) + int(action_dim) + 1


def exact_sq_dist(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise squared L2 distance in float64: the reference for every similarity decision.

    a, b: [n, d] (or broadcastable). Differences of float32 values are exact in float64; each
    row is summed with numpy's pairwise summation, whose result depends only on the row's
    values (not on its position in the batch), so every caller gets bit-identical distances.
    """
    d = np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64)
    d *= d
    return d.sum(axis=-1)
