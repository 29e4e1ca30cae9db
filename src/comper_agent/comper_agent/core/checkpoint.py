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

__all__ = ["save_checkpoint", "load_checkpoint", "CHECKPOINT_FORMAT"]

CHECKPOINT_FORMAT = 1


def save_checkpoint(path: str | os.PathLike, state: dict) -> Path:
    """Write `state` atomically to `path` (its folder is created). Returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {"format": CHECKPOINT_FORMAT, "state": state}
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save(payload, f)
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


def load_checkpoint(path: str | os.PathLike, map_location: str | torch.device = "cpu") -> dict:
    payload = torch.load(Path(path), map_location=map_location, weights_only=True)
    if payload.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path}: checkpoint format {payload.get('format')}, expected {CHECKPOINT_FORMAT}")
    return payload["state"]
