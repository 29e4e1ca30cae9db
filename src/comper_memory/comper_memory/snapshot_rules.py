"""The rules for named snapshots under a memory node's ``snapshot_root`` (file system only, no ROS):
which names a ``~/snapshot`` request may use, and the quota that bounds how many there are and how
much disk they take.

A name is the path of the snapshot relative to ``snapshot_root``: at most :data:`NAME_PARTS` parts
joined by ``/``, at most :data:`NAME_MAX` characters in all, each part made of letters, digits,
``.``, ``_`` and ``-`` and starting with a letter, a digit or ``_`` (so no hidden names, no ``..``,
no option-like names). A part may not end like the node's own temporary copies (``.tmp-<pid>``,
``.old-<pid>``). The learner's checkpoint names (``step_<N>.memory``, ``<run_id>/step_<N>.memory``)
follow these rules.

The quota counts every directory under the root (at most :data:`NAME_PARTS` levels down, links not
followed) that holds a snapshot (:func:`~comper_memory.core.storage.is_snapshot_dir`), and the bytes
of their files. A save is checked before anything is written, against a bound of its size computed
from the arrays it will write (:func:`size_bound`); the target it replaces does not count.
"""
from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass

import numpy as np

from .core.storage import SnapshotError, is_snapshot_dir

__all__ = ["NAME_MAX", "NAME_PARTS", "NAME_RULE", "check_name", "usage", "size_bound", "SnapshotQuota"]

#: most characters of a snapshot name (its path relative to snapshot_root)
NAME_MAX = 200
#: most parts of a name (``<run_id>/step_<N>.memory`` has two)
NAME_PARTS = 4
NAME_RULE = (f"a snapshot name is its path under snapshot_root: up to {NAME_PARTS} parts joined by '/', "
             f"at most {NAME_MAX} characters in all, each part of letters, digits, '.', '_' and '-', "
             "starting with a letter, a digit or '_'")
_PART = re.compile(r"[A-Za-z0-9_][A-Za-z0-9._-]*\Z")
_RESERVED = re.compile(r".*\.(tmp|old)-[0-9]+\Z")     # write_snapshot's temporary and set-aside copies


def check_name(name: str) -> None:
    """Refuse (SnapshotError, with the rule) a name that breaks the rules above."""
    if len(name) > NAME_MAX:
        raise SnapshotError(f"snapshot: a name of {len(name)} characters is refused ({NAME_RULE})")
    parts = name.split("/")
    if len(parts) > NAME_PARTS:
        raise SnapshotError(f"snapshot: name {name!r} has {len(parts)} parts; refused ({NAME_RULE})")
    for part in parts:
        if not _PART.match(part):
            bad = sorted({c for c in part if not (c.isascii() and (c.isalnum() or c in "._-"))})
            why = (f"holds {''.join(bad)!r}" if bad else "is empty" if not part else f"starts with {part[0]!r}")
            raise SnapshotError(f"snapshot: name {name!r} refused: part {part!r} {why} ({NAME_RULE})")
        if _RESERVED.match(part):
            raise SnapshotError(f"snapshot: name {name!r} refused: part {part!r} ends like the node's temporary "
                                "copies (.tmp-<n>, .old-<n>)")


def usage(root: str, exclude: str | None = None) -> tuple[int, int]:
    """(count, bytes) of the snapshots under ``root`` but the one at ``exclude``: directories that hold a
    snapshot, found at most NAME_PARTS levels down without following links (not looked into further)."""
    count = size = 0
    todo = [(root, 0)]
    while todo:
        folder, depth = todo.pop()
        try:
            entries = list(os.scandir(folder))
        except OSError:
            continue
        for e in entries:
            if not e.is_dir(follow_symlinks=False):
                continue
            if is_snapshot_dir(e.path):
                if e.path != exclude:
                    count += 1
                    size += _files_bytes(e.path)
            elif depth + 1 < NAME_PARTS:
                todo.append((e.path, depth + 1))
    return count, size


def _files_bytes(folder: str) -> int:
    total = 0
    try:
        with os.scandir(folder) as it:
            for e in it:
                if e.is_file(follow_symlinks=False):
                    total += e.stat(follow_symlinks=False).st_size
    except OSError:
        pass
    return total


def size_bound(arrays: dict[str, np.ndarray], meta: dict) -> int:
    """At least the bytes the snapshot of (arrays, meta) takes on disk: state.npz (numpy's uncompressed
    zip: each array's bytes, its .npy header and its zip records) and manifest.json."""
    npz = sum(int(np.asarray(a).nbytes) + 512 + 2 * len(name) for name, a in arrays.items()) + 1024
    manifest = 2 * len(json.dumps({"arrays": sorted(arrays), "meta": meta}, indent=1, sort_keys=True)) + 1024
    return npz + manifest


def _gib(n: int) -> str:
    return f"{n / 2**30:.2f} GiB"


@dataclass(frozen=True)
class SnapshotQuota:
    """The bounds of the named snapshots under one root; 0 = that bound is off."""

    max_count: int = 0
    max_bytes: int = 0
    min_free_bytes: int = 0

    def check(self, root: str, target: str, count: int, used: int, new_bytes: int) -> None:
        """Refuse (SnapshotError saying how to free or raise the bound) a save of at most ``new_bytes`` to
        ``target`` when ``count`` snapshots of ``used`` bytes are there besides it."""
        name = os.path.relpath(target, root)
        free_hint = (f"delete named snapshots under {root} that are no longer needed (each is a directory "
                     "holding manifest.json and state.npz; a save to an existing name replaces it)")
        if self.max_count and count + 1 > self.max_count:
            raise SnapshotError(
                f"snapshot: save of {name!r} refused: {root} holds {count} named snapshots besides it, and "
                f"snapshot_max_count is {self.max_count}; {free_hint}, or restart the node with a larger "
                "-p snapshot_max_count:=N (0 = no limit)")
        if self.max_bytes and used + new_bytes > self.max_bytes:
            raise SnapshotError(
                f"snapshot: save of {name!r} refused: it would take the named snapshots under {root} to up to "
                f"{_gib(used + new_bytes)} ({_gib(used)} there besides it, at most {_gib(new_bytes)} for this "
                f"one), beyond snapshot_max_bytes {_gib(self.max_bytes)}; {free_hint}, or restart the node with "
                "a larger -p snapshot_max_bytes:=N (0 = no limit)")
        if self.min_free_bytes:
            try:
                st = os.statvfs(_existing_parent(target))
            except OSError:
                return
            free = st.f_bavail * st.f_frsize
            if free - new_bytes < self.min_free_bytes:
                raise SnapshotError(
                    f"snapshot: save of {name!r} refused: it needs up to {_gib(new_bytes)} and {_gib(free)} are "
                    f"free on the file system of {root}, which must keep snapshot_min_free_bytes "
                    f"{_gib(self.min_free_bytes)} free; {free_hint}, free space there, or restart the node with a "
                    "smaller -p snapshot_min_free_bytes:=N (0 = no check)")


def _existing_parent(path: str) -> str:
    while not os.path.isdir(path):
        parent = os.path.dirname(path)
        if parent == path:
            break
        path = parent
    return path
