"""Observations by reference: each frame stored once, stacks kept as frame ids (``frame_store``).

A representative holds its state and next state. With stacked Atari frames ([4, 84, 84] uint8) that is 8
frames, 56 KB per identity, although consecutive transitions share all but one frame: s' is the next s, and
s' holds s's last three frames. Like Dopamine's circular replay (and DQN's original buffer), the memory then
keeps every distinct frame once and a representative keeps the ids of its frames (:class:`FrameStore`); a
stack is rebuilt by gathering its ids. Unlike a ring indexed by step, frames are found by their content
(a 64-bit digest, confirmed byte for byte), so nothing is assumed about how the client stacks or pads at an
episode start: the rebuilt observation is byte-identical to the one stored, a stack never mixes two episodes
(it holds the frames that were sent for it), and a frame seen again (an episode's first frame) is kept once.

The switch is :func:`frame_layout`, the one place that decides from ``frame_store`` and ``frame_axis``
(MemoryConfig) and the observations' shape and dtype; ``None`` keeps the observations in the slot table as
before (vector observations, single 2-D frames under ``auto``).

Frames live in blocks that are never copied when the store grows (a block of each doubling of the capacity;
untouched pages of the newest block are not resident), so a million frames never need twice their size.
"""
from __future__ import annotations

import sys
import zlib
from dataclasses import dataclass

import numpy as np

__all__ = ["FrameLayout", "FrameStore", "frame_layout", "FRAME_STORE_MODES", "AUTO_MIN_FRAME_BYTES",
           "FRAME_BLOCK"]

FRAME_STORE_MODES = ("auto", "on", "off")
AUTO_MIN_FRAME_BYTES = 1024      # auto: a frame must hold at least this many bytes (refs and index cost ~120 B)
FRAME_BLOCK = 1024               # frames in the first block; later blocks double the capacity
_DICT_ENTRY_BYTES = 64           # a digest -> id entry's two int objects (the table: sys.getsizeof)


@dataclass(frozen=True)
class FrameLayout:
    """How an observation of ``obs_shape`` is cut into frames: along ``axis`` (None: the whole observation
    is one frame)."""
    obs_shape: tuple
    dtype: str
    axis: int | None

    @property
    def stack(self) -> int:
        return 1 if self.axis is None else int(self.obs_shape[self.axis])

    @property
    def frame_shape(self) -> tuple:
        if self.axis is None:
            return tuple(self.obs_shape)
        return tuple(d for i, d in enumerate(self.obs_shape) if i != self.axis)

    def split(self, obs: np.ndarray) -> np.ndarray:
        """[k, *obs_shape] -> [k, stack, *frame_shape], C-contiguous."""
        k = len(obs)
        if self.axis is None:
            return np.ascontiguousarray(obs).reshape(k, 1, *self.frame_shape)
        return np.ascontiguousarray(np.moveaxis(obs, self.axis + 1, 1))

    def join(self, frames: np.ndarray) -> np.ndarray:
        """[k, stack, *frame_shape] -> [k, *obs_shape]."""
        k = len(frames)
        if self.axis is None:
            return frames.reshape(k, *self.obs_shape)
        return np.ascontiguousarray(np.moveaxis(frames, 1, self.axis + 1))


def frame_layout(mode: str, axis: int, obs_shape: tuple, dtype) -> FrameLayout | None:
    """The switch (module text): 'off' -> None; 'on' -> frames along ``axis`` (-1 or an observation of fewer
    than 3 dimensions: the whole observation is one frame); 'auto' -> as 'on' for uint8 observations with a stack
    axis (3 or more dimensions, ``axis`` >= 0) whose frames hold at least AUTO_MIN_FRAME_BYTES, else None."""
    if mode not in FRAME_STORE_MODES:
        raise ValueError(f"frame_store {mode!r} is not one of {', '.join(FRAME_STORE_MODES)}")
    obs_shape = tuple(int(d) for d in obs_shape)
    if mode == "off":
        return None
    stacked = len(obs_shape) >= 3 and axis >= 0
    if stacked and axis >= len(obs_shape):
        raise ValueError(f"frame_axis {axis} is outside observations of shape {list(obs_shape)}")
    layout = FrameLayout(obs_shape, np.dtype(dtype).str, int(axis) if stacked else None)
    if mode == "auto":
        frame_bytes = int(np.prod(layout.frame_shape, dtype=np.int64)) * np.dtype(dtype).itemsize
        if np.dtype(dtype) != np.uint8 or not stacked or frame_bytes < AUTO_MIN_FRAME_BYTES:
            return None
    return layout


def _digest(frame: np.ndarray) -> int:
    view = memoryview(frame).cast("B")
    return (zlib.crc32(view) << 32) | zlib.adler32(view)


class FrameStore:
    """Distinct frames, each once, with a reference count per frame id; ids are reused once free.

    ``intern(frames)`` returns the id of each frame, adding it when no stored frame has its bytes, and
    counts one reference per row; ``release(ids)`` drops references (a frame without any is freed);
    ``gather(ids)`` returns the frames. Not thread-safe: the memory holds the lock."""

    def __init__(self, frame_shape: tuple, dtype):
        self.frame_shape = tuple(frame_shape)
        self.dtype = np.dtype(dtype)
        self._blocks: list[np.ndarray] = []
        self._starts = np.zeros(0, np.int64)
        self.cap = 0                     # frames the blocks hold
        self.hi = 0                      # frame ids ever handed out (ids >= hi were never written)
        self.refs = np.zeros(0, np.int64)
        self.digests = np.zeros(0, np.uint64)
        self.free: list[int] = []
        self._by_digest: dict[int, int] = {}
        self._more: dict[int, list[int]] = {}   # other frames with a digest already in _by_digest (rare)

    @property
    def n_live(self) -> int:
        return self.hi - len(self.free)

    # ------------------------------------------------------------------ blocks
    def _add_block(self, block: np.ndarray) -> None:
        self._blocks.append(block)
        self._starts = np.append(self._starts, self.cap)
        self.cap += len(block)
        if len(self.refs) < self.cap:
            grow = self.cap - len(self.refs)
            self.refs = np.concatenate([self.refs, np.zeros(grow, np.int64)])
            self.digests = np.concatenate([self.digests, np.zeros(grow, np.uint64)])

    def _frame(self, fid: int) -> np.ndarray:
        j = int(np.searchsorted(self._starts, fid, side="right")) - 1
        return self._blocks[j][fid - int(self._starts[j])]

    def gather(self, ids: np.ndarray) -> np.ndarray:
        """Frames of ``ids`` (any shape): [*ids.shape, *frame_shape]."""
        ids = np.asarray(ids, dtype=np.int64)
        flat = ids.reshape(-1)
        out = np.empty((len(flat), *self.frame_shape), self.dtype)
        if len(self._blocks) == 1:
            np.take(self._blocks[0], flat, axis=0, out=out)
        elif len(flat):
            b = np.searchsorted(self._starts, flat, side="right") - 1
            for j in np.unique(b):
                m = b == j
                out[m] = self._blocks[j][flat[m] - self._starts[j]]
        return out.reshape(*ids.shape, *self.frame_shape)

    # ------------------------------------------------------------------ references
    def _find(self, digest: int, frame: np.ndarray) -> int:
        fid = self._by_digest.get(digest)
        if fid is None:
            return -1
        raw = frame.tobytes()
        for cand in [fid, *self._more.get(digest, ())]:
            if self._frame(cand).tobytes() == raw:
                return cand
        return -1

    def _index(self, digest: int, fid: int) -> None:
        if digest in self._by_digest:
            self._more.setdefault(digest, []).append(fid)
        else:
            self._by_digest[digest] = fid

    def _unindex(self, digest: int, fid: int) -> None:
        more = self._more.get(digest)
        if self._by_digest.get(digest) == fid:
            if more:
                self._by_digest[digest] = more.pop()
            else:
                del self._by_digest[digest]
        elif more is not None:
            more.remove(fid)
        if more is not None and not more:
            del self._more[digest]

    def intern(self, frames: np.ndarray) -> np.ndarray:
        """Ids of ``frames`` ([m, *frame_shape], C-contiguous), one more reference each (a row repeated counts
        each time)."""
        m = len(frames)
        ids = np.empty(m, np.int64)
        for i in range(m):
            f = frames[i]
            d = _digest(f)
            fid = self._find(d, f)
            if fid < 0:
                if self.free:
                    fid = self.free.pop()
                else:
                    if self.hi == self.cap:
                        self._add_block(np.empty((max(FRAME_BLOCK, self.cap), *self.frame_shape), self.dtype))
                    fid = self.hi
                    self.hi += 1
                j = int(np.searchsorted(self._starts, fid, side="right")) - 1
                self._blocks[j][fid - int(self._starts[j])] = f
                self.digests[fid] = d
                self._index(d, fid)
            ids[i] = fid
        np.add.at(self.refs, ids, 1)
        return ids

    def release(self, ids: np.ndarray) -> None:
        """One reference fewer for each of ``ids``; frames left without any are freed."""
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        if not len(ids):
            return
        np.subtract.at(self.refs, ids, 1)
        for fid in np.unique(ids)[self.refs[np.unique(ids)] == 0].tolist():
            self._unindex(int(self.digests[fid]), fid)
            self.free.append(fid)

    # ------------------------------------------------------------------ snapshots
    def arrays(self) -> dict[str, np.ndarray]:
        """The written part of each block (views: a snapshot streams them, no copy); free frames included."""
        out = {}
        for j, block in enumerate(self._blocks):
            start = int(self._starts[j])
            if start >= self.hi:
                break
            out[f"frames_{j:03d}"] = block[:self.hi - start]
        return out

    @staticmethod
    def block_names(arrays: dict) -> list[str]:
        return sorted(k for k in arrays if k.startswith("frames_"))

    def load(self, arrays: dict[str, np.ndarray], ref_ids: np.ndarray) -> None:
        """Fill an empty store from snapshot blocks (adopted, not copied) and every reference the slots hold;
        ValueError if they do not fit together."""
        for name in self.block_names(arrays):
            block = arrays[name]
            if block.dtype != self.dtype or tuple(block.shape[1:]) != self.frame_shape:
                raise ValueError(f"{name} holds {block.dtype}{list(block.shape[1:])} frames, the memory "
                                 f"{self.dtype}{list(self.frame_shape)}")
            self._add_block(np.ascontiguousarray(block))
        self.hi = self.cap
        ref_ids = np.asarray(ref_ids, dtype=np.int64).reshape(-1)
        if len(ref_ids) and (ref_ids.min() < 0 or ref_ids.max() >= self.hi):
            raise ValueError(f"frame references outside the {self.hi} frames of the snapshot")
        self.refs[:] = 0
        self.refs[:self.hi] = np.bincount(ref_ids, minlength=self.hi)
        for fid in range(self.hi):
            if self.refs[fid]:
                d = _digest(self._frame(fid))
                self.digests[fid] = d
                self._index(d, fid)
        self.free = np.flatnonzero(self.refs[:self.hi] == 0)[::-1].tolist()

    def bytes_used(self) -> int:
        """Frames written (untouched block pages are not resident), per-frame counts and the digest index."""
        return int(self.hi * self.dtype.itemsize * int(np.prod(self.frame_shape, dtype=np.int64))
                   + self.refs.nbytes + self.digests.nbytes + 8 * len(self.free)
                   + sys.getsizeof(self._by_digest) + _DICT_ENTRY_BYTES * len(self._by_digest))


def layout_meta(layout: FrameLayout | None) -> dict | None:
    """What a schema (and so a snapshot's metadata) records of a layout."""
    return None if layout is None else {"axis": layout.axis, "stack": layout.stack}


def written_layout(schema: dict) -> FrameLayout | None:
    """The layout a snapshot's observations were written in (None: as observations, also before frame_store)."""
    meta = schema.get("frames")
    if meta is None:
        return None
    axis = meta.get("axis") if isinstance(meta, dict) else None
    if axis is not None and not (isinstance(axis, int) and 0 <= axis < len(schema["obs_shape"])):
        raise ValueError(f"its frame axis {axis!r} does not fit observations {list(schema['obs_shape'])}")
    return FrameLayout(tuple(int(d) for d in schema["obs_shape"]), np.dtype(schema["obs_dtype"]).str, axis)
