"""Durability: write-ahead log and checksummed snapshots (no pickles anywhere).

WAL file: a sequence of records ``MAGIC | u32 payload length | u32 crc32(payload) | payload``
with payload ``u64 sequence | u8 kind | u32 header length | JSON header | raw array bytes``.
A record is written (and flushed / fsynced, per ``durability``) before the operation it logs
is acknowledged. A torn last record (process killed mid-write) fails its length or CRC check:
it was never acknowledged, so reading stops there and the file is truncated to the last good
record.

Snapshot: a directory with ``state.npz`` (numpy arrays, written and read with
``allow_pickle=False``) and ``manifest.json`` (format version, metadata, sha256 and size of
``state.npz``). It is written into a temporary directory which is then renamed into place, so
a reader sees either the old or the new snapshot. A snapshot whose checksum, size or manifest
does not match is refused with :class:`SnapshotError` before anything is loaded.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import struct
import zlib
from typing import Iterator

import numpy as np

__all__ = ["WriteAheadLog", "read_wal", "write_snapshot", "read_snapshot", "SnapshotError",
           "WAL_STORE", "WAL_COMMIT"]

MAGIC = b"CMW1"
_HEAD = struct.Struct("<4sII")
_PAY = struct.Struct("<QBI")
WAL_STORE = 1
WAL_COMMIT = 2
SNAPSHOT_FORMAT = 1


class SnapshotError(RuntimeError):
    """A snapshot is missing, corrupted, truncated or incompatible; nothing was loaded."""


def encode_arrays(seq: int, kind: int, arrays: dict[str, np.ndarray]) -> bytes:
    header, blobs = [], []
    for name, arr in arrays.items():
        arr = np.ascontiguousarray(arr)
        header.append([name, arr.dtype.str, list(arr.shape)])
        blobs.append(arr.tobytes())
    hj = json.dumps(header).encode()
    payload = _PAY.pack(seq, kind, len(hj)) + hj + b"".join(blobs)
    return _HEAD.pack(MAGIC, len(payload), zlib.crc32(payload)) + payload


def decode_payload(payload: bytes) -> tuple[int, int, dict[str, np.ndarray]]:
    seq, kind, hlen = _PAY.unpack_from(payload, 0)
    off = _PAY.size
    header = json.loads(payload[off:off + hlen])
    off += hlen
    out = {}
    for name, dt, shape in header:
        dtype = np.dtype(dt)
        if dtype.hasobject:
            raise ValueError("object arrays are not allowed in the WAL")
        nbytes = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
        out[name] = np.frombuffer(payload, dtype=dtype, count=int(np.prod(shape, dtype=np.int64)),
                                  offset=off).reshape(shape).copy()
        off += nbytes
    return seq, kind, out


class WriteAheadLog:
    """Append-only log file; ``append`` returns once the record is durable per ``durability``."""

    def __init__(self, path: str, durability: str = "flush"):
        self.path = path
        self.durability = durability
        self._f = open(path, "ab", buffering=1 << 16)

    def append(self, seq: int, kind: int, arrays: dict[str, np.ndarray]) -> None:
        self._f.write(encode_arrays(seq, kind, arrays))
        if self.durability != "none":
            self._f.flush()
            if self.durability == "fsync":
                os.fsync(self._f.fileno())

    def close(self) -> None:
        if not self._f.closed:
            self._f.flush()
            if self.durability == "fsync":
                os.fsync(self._f.fileno())
            self._f.close()


def read_wal(path: str, *, repair: bool = True) -> Iterator[tuple[int, int, dict[str, np.ndarray]]]:
    """Yield (sequence, kind, arrays) for each intact record; stop at the first torn/corrupt one
    and (repair=True) truncate the file there so later appends start on a record boundary."""
    with open(path, "rb") as f:
        data = f.read()
    off = 0
    good = 0
    while off + _HEAD.size <= len(data):
        magic, length, crc = _HEAD.unpack_from(data, off)
        end = off + _HEAD.size + length
        if magic != MAGIC or end > len(data):
            break
        payload = data[off + _HEAD.size:end]
        if zlib.crc32(payload) != crc:
            break
        try:
            rec = decode_payload(payload)
        except Exception:
            break
        off = good = end
        yield rec
    if repair and good < len(data):
        with open(path, "r+b") as f:
            f.truncate(good)


def _sha256_file(path: str) -> tuple[str, int]:
    h = hashlib.sha256()
    size = 0
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
            size += len(chunk)
    return h.hexdigest(), size


def _fsync_dir(path: str) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def write_snapshot(path: str, arrays: dict[str, np.ndarray], meta: dict) -> None:
    """Write a snapshot directory atomically (temp dir + rename)."""
    path = os.path.abspath(path)
    parent = os.path.dirname(path)
    os.makedirs(parent, exist_ok=True)
    tmp = f"{path}.tmp-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    os.makedirs(tmp)
    npz = os.path.join(tmp, "state.npz")
    with open(npz, "wb") as f:
        np.savez(f, **arrays)
        f.flush()
        os.fsync(f.fileno())
    digest, size = _sha256_file(npz)
    manifest = {"format": SNAPSHOT_FORMAT, "state_sha256": digest, "state_bytes": size,
                "arrays": sorted(arrays), "meta": meta}
    with open(os.path.join(tmp, "manifest.json"), "w") as f:
        json.dump(manifest, f, indent=1, sort_keys=True)
        f.flush()
        os.fsync(f.fileno())
    _fsync_dir(tmp)
    old = None
    if os.path.exists(path):
        old = f"{path}.old-{os.getpid()}"
        shutil.rmtree(old, ignore_errors=True)
        os.rename(path, old)
    os.rename(tmp, path)
    _fsync_dir(parent)
    if old:
        shutil.rmtree(old, ignore_errors=True)


def read_snapshot(path: str) -> tuple[dict[str, np.ndarray], dict]:
    """Read and verify a snapshot; raise SnapshotError (nothing loaded) on any mismatch."""
    mpath = os.path.join(path, "manifest.json")
    npz = os.path.join(path, "state.npz")
    try:
        with open(mpath) as f:
            manifest = json.load(f)
    except (OSError, ValueError) as e:
        raise SnapshotError(f"snapshot {path!r}: cannot read manifest.json ({e})") from None
    if not isinstance(manifest, dict) or manifest.get("format") != SNAPSHOT_FORMAT:
        raise SnapshotError(f"snapshot {path!r}: unknown manifest format")
    try:
        digest, size = _sha256_file(npz)
    except OSError as e:
        raise SnapshotError(f"snapshot {path!r}: cannot read state.npz ({e})") from None
    if size != manifest.get("state_bytes") or digest != manifest.get("state_sha256"):
        raise SnapshotError(f"snapshot {path!r}: state.npz checksum mismatch (corrupted or truncated)")
    try:
        with np.load(npz, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except Exception as e:  # noqa: BLE001 - any decoding problem means a bad snapshot
        raise SnapshotError(f"snapshot {path!r}: cannot decode state.npz ({e})") from None
    if sorted(arrays) != manifest.get("arrays"):
        raise SnapshotError(f"snapshot {path!r}: arrays differ from the manifest")
    return arrays, manifest["meta"]
