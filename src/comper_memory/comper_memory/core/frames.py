"""Observations by reference: each frame stored once, stacks kept as frame ids (``frame_store``).

Stacked Atari frames ([4, 84, 84] uint8) make a representative's s and s' 8 frames, 56 KB, though consecutive
transitions share all but one. Like Dopamine's circular replay, the memory then keeps each distinct frame once
(:class:`FrameStore`) and a representative the ids of its frames, gathered back into stacks. Frames are found by
content (CRC-32, confirmed byte for byte), not by step, so nothing is assumed about how the client stacks or pads:
a rebuilt observation is byte-identical to the one stored and never mixes two episodes.

The switch is :func:`frame_layout` (``frame_store``, ``frame_axis``, the observations' shape and dtype); both of
its branches are :class:`ObsColumns`. Frames live in one private anonymous map resized in place (mremap: nothing
copied, pages resident once written), so a gather is one ``np.take``. docs/memory.md, "Frame store".
"""
from __future__ import annotations

import mmap
import sys
import zlib
from dataclasses import dataclass

import numpy as np

__all__ = ["FrameLayout", "FrameStore", "ObsColumns", "frame_layout", "first_equal", "pack_obs", "unpack_obs",
           "check_snapshot_obs", "written_layout", "layout_meta", "FRAME_STORE_MODES", "AUTO_MIN_FRAME_BYTES",
           "FRAMES_ARRAY", "OBS_FIELDS", "FRAME_FIELDS"]

FRAME_STORE_MODES = ("auto", "on", "off")
AUTO_MIN_FRAME_BYTES = 1024      # auto: a frame must hold at least this many bytes (refs and index cost ~120 B)
FRAME_BLOCK = 1024               # the smallest growth of the frames' map (frames)
FRAME_GROWTH_MAX = 1 << 17       # the largest (0.9 GB of 84x84 frames): the map's size stays near its use
FRAMES_ARRAY = "frames"          # the snapshot array of the frame store
OBS_FIELDS = ("states", "next_states")            # slot columns of whole observations
FRAME_FIELDS = ("state_frames", "next_frames")    # slot columns of frame ids, with a frame layout
_CONVERT_ROWS = 4096             # rows converted at a time when a snapshot's observations are in the other layout
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
    """32 bits of CRC (a frame sharing it with other bytes is told apart by comparing them)."""
    return zlib.crc32(memoryview(frame).cast("B"))


def first_equal(frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(digests, src) of frames [m, ...] (C-contiguous): src[i] = the first row with the bytes of row i, found by
    digest and confirmed by one vectorised comparison (rows whose digest is shared by other bytes: one by one).
    A stack's frames recur in the next state and in the next transition, so a store's rows repeat."""
    m = len(frames)
    digests = np.fromiter((_digest(f) for f in frames), np.uint64, m)
    _, first, inv = np.unique(digests, return_index=True, return_inverse=True)
    src = first[inv]
    rows = frames.reshape(m, -1)
    for i in np.flatnonzero(~(rows == rows[src]).all(axis=1)).tolist():   # digest collisions
        same = np.flatnonzero((digests[:i] == digests[i]) & (rows[:i] == rows[i]).all(axis=1))
        src[i] = same[0] if len(same) else i
    return digests, src


def pack_obs(layout: FrameLayout, states: np.ndarray, next_states: np.ndarray) -> dict[str, np.ndarray]:
    """A store's observations as a WAL record holds them: its distinct frames once, and per transition the
    indices of its state's and next state's frames among them (:func:`unpack_obs` rebuilds them exactly)."""
    n, k = len(states), layout.stack
    frames = np.concatenate([layout.split(states), layout.split(next_states)], axis=1).reshape(-1, *layout.frame_shape)
    _, src = first_equal(frames)
    keep, idx = np.unique(src, return_inverse=True)
    idx = idx.reshape(n, 2 * k)
    return {FRAMES_ARRAY: frames[keep], "state_frames": idx[:, :k], "next_frames": idx[:, k:],
            "frame_axis": np.array([-1 if layout.axis is None else layout.axis], np.int64)}


def unpack_obs(record: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(states, next states) of a record written by :func:`pack_obs`."""
    frames = record[FRAMES_ARRAY]
    axis = int(record["frame_axis"][0])
    k = record["state_frames"].shape[1]
    shape = frames.shape[1:] if axis < 0 else (*frames.shape[1:axis + 1], k, *frames.shape[axis + 1:])
    layout = FrameLayout(tuple(shape), frames.dtype.str, None if axis < 0 else axis)
    return tuple(layout.join(frames[record[f]]) for f in ("state_frames", "next_frames"))


class FrameStore:
    """Distinct frames, each once, with a reference count per frame id; ids are reused once free.

    ``intern(frames)`` returns the id of each frame, adding it when no stored frame has its bytes, and
    counts one reference per row; ``release(ids)`` drops references (a frame without any is freed);
    ``gather(ids)`` returns the frames. Not thread-safe: the memory holds the lock."""

    def __init__(self, frame_shape: tuple, dtype):
        self.frame_shape = tuple(frame_shape)
        self.dtype = np.dtype(dtype)
        self.frame_bytes = self.dtype.itemsize * int(np.prod(self.frame_shape, dtype=np.int64))
        self._mm: mmap.mmap | None = None
        self.frames = np.zeros((0, *self.frame_shape), self.dtype)   # a view of _mm: [cap, *frame_shape]
        self.hi = 0                      # frame ids ever handed out (ids >= hi were never written)
        self.refs = np.zeros(0, np.int64)
        self.digests = np.zeros(0, np.uint64)
        self.free: list[int] = []
        self._by_digest: dict[int, int] = {}
        self._more: dict[int, list[int]] = {}   # other frames with a digest already in _by_digest (rare)

    @property
    def cap(self) -> int:
        return len(self.frames)

    @property
    def n_live(self) -> int:
        return self.hi - len(self.free)

    # ------------------------------------------------------------------ the frames' memory
    def _grow(self, need: int) -> None:
        """Room for ``need`` frames: the private anonymous map is resized in place (mremap: nothing copied, pages
        resident only once written); copied into a new map only while a view of the old one is held elsewhere
        (a snapshot's arrays)."""
        cap = max(need, self.cap + min(max(self.cap, FRAME_BLOCK), FRAME_GROWTH_MAX))
        size = max(1, cap * self.frame_bytes)
        old_cap, self.frames = self.cap, None          # our own view released: the map may be resized
        try:
            if self._mm is None:
                raise BufferError
            self._mm.resize(size)
        except BufferError:                             # none yet, or a view of it is held elsewhere
            mm = mmap.mmap(-1, size, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)
            if old_cap:
                count = old_cap * self.frame_bytes // self.dtype.itemsize
                np.frombuffer(mm, self.dtype, count=count)[:] = np.frombuffer(self._mm, self.dtype, count=count)
            self._mm = mm
        self.frames = np.frombuffer(self._mm, self.dtype, count=cap * self.frame_bytes // self.dtype.itemsize
                                    ).reshape(cap, *self.frame_shape)
        grow = cap - len(self.refs)
        self.refs = np.concatenate([self.refs, np.zeros(grow, np.int64)])
        self.digests = np.concatenate([self.digests, np.zeros(grow, np.uint64)])

    def gather(self, ids: np.ndarray) -> np.ndarray:
        """Frames of ``ids`` (any shape): [*ids.shape, *frame_shape]."""
        ids = np.asarray(ids, dtype=np.int64)
        return np.take(self.frames, ids.reshape(-1), axis=0).reshape(*ids.shape, *self.frame_shape)

    # ------------------------------------------------------------------ references
    def _find(self, digest: int, frame: np.ndarray) -> int:
        fid = self._by_digest.get(digest)
        if fid is None:
            return -1
        raw = frame.tobytes()
        for cand in [fid, *self._more.get(digest, ())]:
            if self.frames[cand].tobytes() == raw:
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
        each time). Rows repeated within the call are looked up once (:func:`first_equal`)."""
        m = len(frames)
        if self.hi + m > self.cap and len(self.free) < m:
            self._grow(self.hi + m)
        digests, src = first_equal(frames)
        ids = np.full(m, -1, np.int64)
        for i in np.unique(src).tolist():
            ids[i] = self._intern_one(int(digests[i]), frames[i])
        ids = ids[src]
        np.add.at(self.refs, ids, 1)
        return ids

    def _intern_one(self, d: int, f: np.ndarray) -> int:
        fid = self._find(d, f)
        if fid < 0:
            if self.free:
                fid = self.free.pop()
            else:
                fid = self.hi
                self.hi += 1
            self.frames[fid] = f
            self.digests[fid] = d
            self._index(d, fid)
        return fid

    def release(self, ids: np.ndarray) -> None:
        """One reference fewer for each of ``ids``; frames left without any are freed."""
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        if not len(ids):
            return
        np.subtract.at(self.refs, ids, 1)
        u = np.unique(ids)
        for fid in u[self.refs[u] == 0].tolist():
            self._unindex(int(self.digests[fid]), fid)
            self.free.append(fid)

    # ------------------------------------------------------------------ snapshots
    def arrays(self) -> dict[str, np.ndarray]:
        """The frames written, free ones included (a view: a snapshot streams it, no copy)."""
        return {FRAMES_ARRAY: self.frames[:self.hi]}

    def load(self, frames: np.ndarray, ref_ids: np.ndarray) -> None:
        """Fill an empty store from a snapshot's frames and every reference its slots hold (checked before:
        slots.check_snapshot_obs)."""
        self._grow(len(frames))
        if isinstance(frames, np.memmap) and frames.flags.c_contiguous:   # a large snapshot member (read_snapshot)
            _read_into(frames.filename, frames.offset, memoryview(self._mm)[:frames.nbytes])
        else:
            self.frames[:len(frames)] = frames
        self.hi = len(frames)
        ref_ids = np.asarray(ref_ids, dtype=np.int64).reshape(-1)
        self.refs[:] = 0
        self.refs[:self.hi] = np.bincount(ref_ids, minlength=self.hi)
        for fid in np.flatnonzero(self.refs[:self.hi]).tolist():
            d = _digest(self.frames[fid])
            self.digests[fid] = d
            self._index(d, fid)
        self.free = np.flatnonzero(self.refs[:self.hi] == 0)[::-1].tolist()

    def bytes_used(self) -> int:
        """Frames written (pages of the map never written are not resident), per-frame counts, the digest index."""
        return int(self.hi * self.frame_bytes + self.refs.nbytes + self.digests.nbytes + 8 * len(self.free)
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


def _read_into(path: str, offset: int, dest: memoryview) -> None:
    """Read a file's bytes from ``offset`` straight into ``dest`` (no mapping of the file: its pages never count
    in this process's RSS)."""
    with open(path, "rb", buffering=0) as f:
        f.seek(offset)
        done = 0
        while done < len(dest):
            got = f.readinto(dest[done:done + (1 << 30)])
            if not got:
                raise ValueError(f"{path}: ends {len(dest) - done} bytes early")
            done += got
    dest.release()


class ObsColumns:
    """The slot table's observation columns, the switch's two branches in one place: whole observations
    (OBS_FIELDS) when ``layout`` is None, else frame ids (FRAME_FIELDS) into ``frames``. ``a``: the table's
    columns, ``slots``: rows of them."""

    def __init__(self, obs_shape: tuple, obs_dtype, layout: FrameLayout | None):
        self.obs_shape, self.obs_dtype = tuple(obs_shape), np.dtype(obs_dtype)
        self.layout = layout
        self.frames = None if layout is None else FrameStore(layout.frame_shape, layout.dtype)

    def columns(self) -> dict[str, tuple[tuple, np.dtype, object]]:
        """(shape, dtype, fill) of each column, as SlotTable._field_spec gives them."""
        if self.layout is None:
            return {f: (self.obs_shape, self.obs_dtype, 0) for f in OBS_FIELDS}
        return {f: ((self.layout.stack,), np.dtype(np.int64), -1) for f in FRAME_FIELDS}

    def get(self, a: dict, slots: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(states, next states) of ``slots``, as they were stored."""
        if self.layout is None:
            return a["states"][slots], a["next_states"][slots]
        return tuple(self.layout.join(self.frames.gather(a[f][slots])) for f in FRAME_FIELDS)

    def put(self, a: dict, slots: np.ndarray, states: np.ndarray, next_states: np.ndarray) -> None:
        if self.layout is None:
            a["states"][slots], a["next_states"][slots] = states, next_states
            return
        for f, obs in zip(FRAME_FIELDS, (states, next_states)):
            ids = self.frames.intern(self.layout.split(obs).reshape(-1, *self.layout.frame_shape))
            a[f][slots] = ids.reshape(len(obs), self.layout.stack)

    def drop(self, a: dict, slots: np.ndarray) -> None:
        """``slots`` are freed: their frames lose a reference each."""
        if self.frames is not None:
            for f in FRAME_FIELDS:
                self.frames.release(a[f][slots])
                a[f][slots] = -1

    def rows(self, a: dict, slots: np.ndarray) -> dict[str, np.ndarray]:
        """The snapshot arrays of ``slots``: the observations, or their frame ids and the frames."""
        if self.layout is None:
            return {f: a[f][slots] for f in OBS_FIELDS}
        return {**{f: a[f][slots] for f in FRAME_FIELDS}, **self.frames.arrays()}

    def load(self, a: dict, slots: np.ndarray, arrays: dict[str, np.ndarray], written: FrameLayout | None) -> None:
        """Fill ``slots`` from a snapshot's rows held in ``written`` (checked before: :func:`check_snapshot_obs`);
        the other layout (a snapshot from before ``frame_store``, or of another setting) is converted,
        ``_CONVERT_ROWS`` rows at a time."""
        if self.layout is not None and self.layout == written:      # frames as written
            self.frames.load(arrays[FRAMES_ARRAY], np.concatenate([arrays[f].reshape(-1) for f in FRAME_FIELDS]))
            for f in FRAME_FIELDS:
                a[f][slots] = arrays[f]
        elif self.layout is None and written is None:
            for f in OBS_FIELDS:
                a[f][slots] = arrays[f]
        else:
            source = ObsColumns(self.obs_shape, self.obs_dtype, written)
            if written is not None:
                source.frames.load(arrays[FRAMES_ARRAY], np.concatenate([arrays[f].reshape(-1) for f in FRAME_FIELDS]))
            for i in range(0, len(slots), _CONVERT_ROWS):
                self.put(a, slots[i:i + _CONVERT_ROWS], *source.get(arrays, slice(i, i + _CONVERT_ROWS)))

    def bytes_used(self) -> int:
        return 0 if self.frames is None else self.frames.bytes_used()


def check_snapshot_obs(arrays: dict[str, np.ndarray], written: FrameLayout | None) -> str | None:
    """What is wrong with a snapshot's observations held in ``written`` (None: as observations), or None."""
    n = len(arrays["id"])
    fields = OBS_FIELDS if written is None else FRAME_FIELDS
    missing = [f for f in fields if f not in arrays]
    if missing:
        return f"lacks arrays {missing}"
    if written is None:
        return None
    if any(arrays[f].shape != (n, written.stack) or arrays[f].dtype.kind not in "iu" for f in fields):
        return f"frame references are not {n} x {written.stack} integers"
    frames = arrays.get(FRAMES_ARRAY)
    if frames is None or frames.dtype != np.dtype(written.dtype) or tuple(frames.shape[1:]) != written.frame_shape:
        return f"frames are not {np.dtype(written.dtype)}{list(written.frame_shape)}"
    total = len(frames)
    if n and any(arrays[f].size and (arrays[f].min() < 0 or arrays[f].max() >= total) for f in fields):
        return f"frame references point outside its {total} frames"
    return None
