"""The one place that converts comper_msgs messages to numpy arrays and back.

Message array fields of rclpy are ``array.array`` objects; reading them with ``np.frombuffer``
is a zero-copy view and writing them from ``ndarray.tobytes()`` is one memcpy, which is what
keeps large batches (Atari frames) cheap. Never convert element by element.
"""
from __future__ import annotations

import array as _pyarray

import numpy as np

from comper_msgs.msg import Array, TransitionBatch

from .arrays import TransitionError, Transitions

__all__ = [
    "array_to_numpy", "numpy_to_array", "batch_to_transitions", "transitions_to_batch",
    "seq_to_numpy", "numpy_to_seq",
]

_TYPECODE = {np.dtype(np.float32): "f", np.dtype(np.uint8): "B", np.dtype(np.uint32): "I",
             np.dtype(np.uint64): "Q", np.dtype(np.float64): "d", np.dtype(np.int64): "q",
             np.dtype(np.int32): "i"}


def seq_to_numpy(seq, dtype) -> np.ndarray:
    """A message sequence field (array.array, list or numpy) as a 1-d numpy array, no copy if possible."""
    dtype = np.dtype(dtype)
    if isinstance(seq, (_pyarray.array, np.ndarray, bytes, bytearray, memoryview)):
        out = np.frombuffer(seq, dtype=dtype) if not isinstance(seq, np.ndarray) else seq.astype(dtype, copy=False)
        return out
    return np.asarray(seq, dtype=dtype)


def numpy_to_seq(arr: np.ndarray, dtype):
    """A numpy array as an ``array.array`` suitable for a message sequence field (one memcpy)."""
    dtype = np.dtype(dtype)
    flat = np.ascontiguousarray(arr, dtype=dtype).reshape(-1)
    out = _pyarray.array(_TYPECODE[dtype])
    out.frombytes(flat.tobytes())
    return out


def _bool_seq(arr: np.ndarray) -> list:
    # rclpy accepts only lists of bool for bool[]; N is small (one per transition).
    return np.asarray(arr, dtype=bool).tolist()


def array_to_numpy(msg: Array) -> np.ndarray:
    """comper_msgs/Array -> ndarray with its shape (a read-only view of the message buffer)."""
    shape = tuple(int(d) for d in msg.shape)
    if msg.dtype == Array.DTYPE_FLOAT32:
        data, dtype = msg.data_f32, np.float32
    elif msg.dtype == Array.DTYPE_UINT8:
        data, dtype = msg.data_u8, np.uint8
    else:
        raise TransitionError(f"unknown Array dtype {msg.dtype}")
    flat = seq_to_numpy(data, dtype)
    expected = int(np.prod(shape, dtype=np.int64)) if shape else 1
    if flat.size != expected:
        raise TransitionError(f"Array of shape {list(shape)} needs {expected} values, got {flat.size}")
    return flat.reshape(shape)


def numpy_to_array(arr, out: Array | None = None) -> Array:
    """ndarray -> comper_msgs/Array. uint8 stays uint8; anything else is sent as float32."""
    arr = np.asarray(arr)
    msg = out if out is not None else Array()
    msg.shape = [int(d) for d in arr.shape]
    if arr.dtype == np.uint8:
        msg.dtype = Array.DTYPE_UINT8
        msg.data_u8 = numpy_to_seq(arr, np.uint8)
    else:
        msg.dtype = Array.DTYPE_FLOAT32
        msg.data_f32 = numpy_to_seq(arr, np.float32)
    return msg


def batch_to_transitions(msg: TransitionBatch, *, validate: bool = True) -> Transitions:
    """comper_msgs/TransitionBatch -> Transitions (views, no per-element work)."""
    t = Transitions(
        states=array_to_numpy(msg.states),
        actions=array_to_numpy(msg.actions),
        rewards=seq_to_numpy(msg.rewards, np.float32),
        next_states=array_to_numpy(msg.next_states),
        terminated=np.asarray(msg.terminated, dtype=bool),
        truncated=np.asarray(msg.truncated, dtype=bool),
        value_labels=seq_to_numpy(msg.value_labels, np.float32),
        episode_ids=seq_to_numpy(msg.episode_ids, np.uint64),
        steps=seq_to_numpy(msg.steps, np.uint64),
        run_id=msg.run_id,
    )
    return t.validate(require_finite=False) if validate else t


def transitions_to_batch(t: Transitions, out: TransitionBatch | None = None) -> TransitionBatch:
    """Transitions -> comper_msgs/TransitionBatch (one memcpy per column)."""
    msg = out if out is not None else TransitionBatch()
    msg.run_id = t.run_id
    numpy_to_array(t.states, msg.states)
    numpy_to_array(np.asarray(t.actions, dtype=np.float32), msg.actions)
    msg.rewards = numpy_to_seq(t.rewards, np.float32)
    numpy_to_array(t.next_states, msg.next_states)
    msg.terminated = _bool_seq(t.terminated)
    msg.truncated = _bool_seq(t.truncated)
    msg.value_labels = numpy_to_seq(t.value_labels, np.float32)
    msg.episode_ids = numpy_to_seq(t.episode_ids, np.uint64)
    msg.steps = numpy_to_seq(t.steps, np.uint64)
    return msg
