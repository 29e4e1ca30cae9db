"""Transition keys and the exact distance every similarity decision is made with."""
from __future__ import annotations

import numpy as np

from comper_msgs_py.arrays import Transitions

__all__ = ["transition_keys", "key_size_of", "exact_sq_dist", "sq_dist_matrix", "DEFAULT_FRAME_SCALE"]

DEFAULT_FRAME_SCALE = 1.0 / 255.0


def _put_obs(obs: np.ndarray, n: int, frame_scale: float, out: np.ndarray) -> None:
    flat = obs.reshape(n, -1)
    if flat.dtype == np.uint8:      # uint8 -> float32 is exact, then one float32 product, written in place
        np.multiply(flat, np.float32(frame_scale), out=out, dtype=np.float32)
    else:
        out[...] = flat


def transition_keys(t: Transitions, frame_scale: float = DEFAULT_FRAME_SCALE,
                    out: np.ndarray | None = None) -> np.ndarray:
    """Keys [N, key_dim] float32 = concat(s.flatten, a, r, s'.flatten).

    uint8 observations (Atari frames) are scaled once by ``frame_scale`` (1/255 -> [0, 1]);
    float observations are used raw (cast to float32). Discrete actions ([N]) contribute one value each.
    Atari single frame 84x84: 7056 + 1 + 1 + 7056 = 14114.

    Each part is written straight into the result (one allocation: 3,300 sets of 4-frame keys are 745 MB,
    and a cast, a scaled copy and a concatenation made three). out: a float32 C-contiguous [N, key_dim]
    array to fill and return instead of a new one (a kept buffer: no fresh pages to map)."""
    n = len(t)
    a = np.asarray(t.actions).reshape(n, -1)
    s_dim = int(np.prod(t.states.shape[1:], dtype=np.int64))
    a_dim = a.shape[1]
    dim = 2 * s_dim + a_dim + 1
    if t.next_states.reshape(n, -1).shape[1] != s_dim:
        raise ValueError(f"states have {s_dim} values per row, next_states "
                         f"{t.next_states.reshape(n, -1).shape[1]}")
    if out is None:
        out = np.empty((n, dim), np.float32)
    elif out.shape != (n, dim) or out.dtype != np.float32 or not out.flags.c_contiguous:
        raise ValueError(f"out must be a C-contiguous float32 array of shape {(n, dim)}, got "
                         f"{out.dtype} {out.shape}")
    _put_obs(t.states, n, frame_scale, out[:, :s_dim])
    out[:, s_dim:s_dim + a_dim] = a
    out[:, s_dim + a_dim] = np.asarray(t.rewards).reshape(n)
    _put_obs(t.next_states, n, frame_scale, out[:, s_dim + a_dim + 1:])
    return out


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


def sq_dist_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """[n, m] squared L2 distances of every row of a [n, d] to every row of b [m, d] in float64, by
    |a|^2 + |b|^2 - 2 a.b (one matrix product; rounding can leave near-equal pairs slightly below 0). For
    estimates of spread and density only: similarity decisions use :func:`exact_sq_dist`."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return (a * a).sum(1)[:, None] + (b * b).sum(1)[None, :] - 2.0 * a @ b.T
