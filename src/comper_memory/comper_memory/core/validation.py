"""Validation of store requests, and the schema a memory takes from its first store."""
from __future__ import annotations

import numpy as np

from comper_msgs_py.arrays import TransitionError, Transitions

from .config import MemoryConfig
from .keys import key_size_of, transition_keys
from .results import MemoryInputError

__all__ = ["validate_store", "schema_of", "index_key_size"]

_KEY_ABS_MAX = MemoryConfig.__dataclass_fields__["max_key_abs"].metadata["maximum"]


def schema_of(t: Transitions) -> dict:
    """obs_shape, obs_dtype, action_shape, action_dtype and key_size of a validated batch."""
    discrete = t.actions.ndim == 1
    action_shape = () if discrete else (int(t.actions.shape[1]),)
    return {"obs_shape": tuple(int(x) for x in t.obs_shape), "obs_dtype": t.states.dtype.str,
            "action_shape": action_shape, "action_dtype": "<i8" if discrete else "<f4",
            "key_size": index_key_size(t.obs_shape, action_shape)}


def index_key_size(obs_shape: tuple, action_shape: tuple) -> int:
    """Key length of a schema's shapes (a discrete action, shape (), is one value)."""
    return key_size_of(obs_shape, int(np.prod(action_shape, dtype=np.int64)))


def validate_store(t: Transitions, config: MemoryConfig, schema: dict | None,
                   expected_key_size: int | None, replay: bool = False) -> tuple[Transitions, np.ndarray]:
    """(clean batch, float32 keys) of a store request, or MemoryInputError naming what is wrong.

    schema: the memory's (None before its first store); replay: a WAL record (accepted once
    under its own max_key_abs, so the bound is not re-checked)."""
    if not isinstance(t, Transitions):
        raise MemoryInputError(f"store expects a Transitions batch, got {type(t).__name__}")
    n = len(t)
    if n == 0:
        raise MemoryInputError("store: empty batch")
    if n > config.max_store_batch:
        raise MemoryInputError(f"store: batch of {n} exceeds max_store_batch ({config.max_store_batch})")
    try:
        t.validate(require_labels=True, require_finite=True)
    except TransitionError as e:
        raise MemoryInputError(f"store: {e}") from None
    if not np.isfinite(t.rewards.astype(np.float64)).all():
        raise MemoryInputError("store: rewards hold NaN or Inf")
    discrete = t.actions.ndim == 1
    if discrete:
        if t.actions.dtype.kind not in "iuf" or (t.actions.dtype.kind == "f" and
                                                  not np.array_equal(t.actions, np.round(t.actions))):
            raise MemoryInputError("store: discrete actions must be integer-valued")
        actions = t.actions.astype(np.int64)
    else:
        if t.actions.dtype.kind not in "iuf":
            raise MemoryInputError(f"store: actions of dtype {t.actions.dtype} are not numeric")
        actions = t.actions.astype(np.float32)
    s = schema
    if s is not None:
        if tuple(t.obs_shape) != tuple(s["obs_shape"]) or t.states.dtype.str != s["obs_dtype"]:
            raise MemoryInputError(
                f"store: observations {t.states.dtype}{list(t.obs_shape)} differ from the memory's "
                f"{np.dtype(s['obs_dtype'])}{list(s['obs_shape'])}")
        if tuple(actions.shape[1:]) != tuple(s["action_shape"]):
            raise MemoryInputError(f"store: action shape {actions.shape[1:]} differs from the memory's "
                                   f"{tuple(s['action_shape'])}")
    key = key_size_of(t.obs_shape, 1 if discrete else actions.shape[1])
    expected = s["key_size"] if s is not None else expected_key_size
    if expected is not None and key != expected:
        raise MemoryInputError(f"store: key size {key} differs from the memory's key size {expected}")
    u64 = np.uint64
    clean = Transitions(
        np.ascontiguousarray(t.states), actions, t.rewards.astype(np.float32),
        np.ascontiguousarray(t.next_states), t.terminated.astype(bool), t.truncated.astype(bool),
        value_labels=t.value_labels.astype(np.float32),
        episode_ids=t.episode_ids.astype(u64) if t.episode_ids.size else np.zeros(n, u64),
        steps=t.steps.astype(u64) if t.steps.size else np.zeros(n, u64), run_id=t.run_id)
    keys = transition_keys(clean, config.frame_scale)
    if not np.isfinite(keys).all():
        raise MemoryInputError("store: keys hold NaN or Inf (values overflow float32)")
    bound = config.max_key_abs
    if not replay and keys.size:  # replay: the record was accepted under its own bound
        # compared in float64: a float32 comparison rounds the bound (3e38 -> 3.0000000054977558e38),
        # so the check and the position it names would disagree
        mag = np.abs(keys).max(axis=1).astype(np.float64)
        if float(mag.max()) > bound:
            i = int(np.argmax(mag > bound))
            j = int(np.argmax(np.abs(keys[i]).astype(np.float64) > bound))
            obs = int(np.prod(t.obs_shape, dtype=np.int64))
            part = ("state" if j < obs else "action" if j < key - obs - 1 else
                    "reward" if j == key - obs - 1 else "next_state")
            raise MemoryInputError(
                f"store: transition {i} has key value {float(keys[i, j]):g} ({part}, key position "
                f"{j}) beyond max_key_abs ({bound:g}); nothing of this batch was stored (raise "
                f"max_key_abs, at most {_KEY_ABS_MAX:g}, or rescale the observations)")
    return clean, keys
