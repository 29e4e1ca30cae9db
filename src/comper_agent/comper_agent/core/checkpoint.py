"""Checkpoints: torch.save of plain state dicts (tensors, numbers, strings, lists, dicts only),
written to a temporary file in the same folder and renamed atomically; read back with
``torch.load(weights_only=True)`` (no arbitrary unpickling).

    save_checkpoint(path, {"learner": learner.state_dict(), "qt": qt.state_dict(),
                           "counters": {"step": step, "frames": frames}})
    state = load_checkpoint(path)
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

import torch

__all__ = ["save_checkpoint", "load_checkpoint", "save_arrays", "load_arrays", "write_atomic", "CHECKPOINT_FORMAT"]

CHECKPOINT_FORMAT = 1


def write_atomic(path: str | os.PathLike, write) -> Path:
    """write(f) into a temporary binary file beside `path` (its folder is created), fsync, rename; the
    temporary file is removed if anything fails. Returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    return path


def save_checkpoint(path: str | os.PathLike, state: dict) -> Path:
    """Write `state` atomically to `path` (its folder is created). Returns the path."""
    payload = {"format": CHECKPOINT_FORMAT, "state": state}
    return write_atomic(Path(path), lambda f: torch.save(payload, f))


def load_checkpoint(path: str | os.PathLike, map_location: str | torch.device = "cpu") -> dict:
    payload = torch.load(Path(path), map_location=map_location, weights_only=True)
    if payload.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path}: checkpoint format {payload.get('format')}, expected {CHECKPOINT_FORMAT}")
    return payload["state"]


def save_arrays(path: str | os.PathLike, arrays: dict) -> Path:
    """Write numpy arrays to the .npz file `path` atomically (no pickled objects). Returns the path."""
    import numpy as np
    return write_atomic(Path(path), lambda f: np.savez(f, **arrays))


def load_arrays(path: str | os.PathLike) -> dict:
    """The arrays of an .npz file written by :func:`save_arrays` (read fully; no pickled objects)."""
    import numpy as np
    with np.load(Path(path), allow_pickle=False) as z:
        return {k: z[k] for k in z.files}
