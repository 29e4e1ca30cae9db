"""The write-ahead log's scan and start-up checks (issue 57, item 2): no acknowledged record is lost
without a loud refusal.

* scan_wal: a record whose payload checks out (CRC) is never taken for a torn tail, whatever happened
  to its magic or length field; only the start of a record cut by the end of the file is a torn tail;
  after lost bytes the scan resynchronises on the next intact record.
* start-up (CompactMemory, no ROS): a damaged last record after a clean stop is refused; a log emptied
  or cut below its mark (wal.mark) is refused naming the missing sequences; wal_accept_loss keeps
  every intact record after the damage and says what it dropped; a torn tail is dropped with a copy.
"""
from __future__ import annotations

import glob
import json
import os
import shutil

import numpy as np
import pytest

from comper_memory.core import CompactMemory, MemoryConfig, SnapshotError
from comper_memory.core import storage as wal
from comper_msgs_py.arrays import Transitions

HEAD = wal._HEAD.size


def make(j, n=4):
    rng = np.random.default_rng(j)
    s = rng.standard_normal((n, 6)).astype(np.float32)
    return Transitions(s, rng.uniform(-1, 1, (n, 2)).astype(np.float32), rng.standard_normal(n).astype(np.float32),
                       s + 1, np.zeros(n, bool), np.zeros(n, bool), value_labels=np.zeros(n, np.float32))


def log_file(tmp_path, n=6):
    """A WAL file of n store records (sequences 1..n) and the byte offset of each record."""
    path = str(tmp_path / "wal-0000000000000001.log")
    offs = []
    with open(path, "wb") as f:
        for seq in range(1, n + 1):
            offs.append(f.tell())
            f.write(wal.encode_arrays(seq, wal.WAL_STORE, {"states": np.full((seq, 3), seq, np.float32)}))
    return path, offs


def flip(path, pos, mask=0x01):
    raw = bytearray(open(path, "rb").read())
    raw[pos] ^= mask
    open(path, "wb").write(bytes(raw))
    return bytes(raw)


def seqs(scan):
    return [r[0] for r in scan.records]


# ----------------------------------------------------------------------------------------- scan_wal
@pytest.mark.parametrize("field,pos,mask", [("magic", 0, 0x01), ("magic", 3, 0xFF), ("length up", 4, 0x40),
                                            ("length down", 4, 0x04), ("length high byte", 7, 0x80)])
@pytest.mark.parametrize("which", ["last", "middle", "first"])
def test_a_record_whose_payload_checks_out_is_never_a_torn_tail(tmp_path, field, pos, mask, which):
    path, offs = log_file(tmp_path)
    k = {"last": 5, "middle": 2, "first": 0}[which]
    flip(path, offs[k] + pos, mask)
    scan = wal.scan_wal(path)
    assert scan.damage == "corrupt", (field, which)
    assert seqs(scan) == [1, 2, 3, 4, 5, 6] and not scan.lost      # every record found, none lost
    assert scan.repaired == [k] and scan.spans[k] == (offs[k], offs[k + 1] if k < 5 else scan.size)
    assert scan.good_end == offs[k] and scan.records_after == 5 - k
    assert "damaged header but its payload checks out" in scan.describe()


@pytest.mark.parametrize("cut", [1, 3, HEAD - 1, HEAD, HEAD + 5, -1])
def test_a_record_cut_by_the_end_of_the_file_is_a_torn_tail(tmp_path, cut):
    """What a write cut short leaves: the first `cut` bytes of the last record (-1: all but one)."""
    path, offs = log_file(tmp_path)
    size = os.path.getsize(path)
    keep = offs[5] + cut if cut > 0 else size + cut
    with open(path, "r+b") as f:
        f.truncate(keep)
    scan = wal.scan_wal(path)
    assert scan.damage == "torn" and seqs(scan) == [1, 2, 3, 4, 5]
    assert scan.good_end == offs[5] and scan.lost == [(offs[5], keep)] and scan.records_after == 0


def test_bytes_at_the_end_that_do_not_begin_a_record_are_corruption(tmp_path):
    path, offs = log_file(tmp_path)
    size = os.path.getsize(path)
    with open(path, "ab") as f:
        f.write(b"\x00" * 40)
    scan = wal.scan_wal(path)
    assert scan.damage == "corrupt" and seqs(scan) == [1, 2, 3, 4, 5, 6] and scan.lost == [(size, size + 40)]


def test_a_complete_last_record_whose_crc_fails_is_corruption(tmp_path):
    path, offs = log_file(tmp_path)
    size = os.path.getsize(path)
    flip(path, size - 2)
    scan = wal.scan_wal(path)
    assert scan.damage == "corrupt" and seqs(scan) == [1, 2, 3, 4, 5] and scan.lost == [(offs[5], size)]
    assert "sequence 6, a store of 6 transitions" in scan.describe()   # what its (unverified) header says


def test_the_scan_resynchronises_on_the_next_intact_record_after_lost_bytes(tmp_path):
    path, offs = log_file(tmp_path, n=8)
    flip(path, offs[2] + HEAD + 20)          # record 3's payload: lost
    flip(path, offs[5] + 1)                  # record 6's magic: header damaged, payload intact
    flip(path, offs[6] + HEAD + 30, 0x10)    # record 7's payload: lost
    scan = wal.scan_wal(path)
    assert scan.damage == "corrupt"
    assert seqs(scan) == [1, 2, 4, 5, 6, 8] and scan.repaired == [4]
    assert scan.lost == [(offs[2], offs[3]), (offs[6], offs[7])]
    assert scan.good_end == offs[2] and scan.records_after == 4 and scan.first_seq_after == 4
    text = scan.describe()
    assert f"bytes {offs[2]}-{offs[3]}" in text and "between sequences 2 and 4" in text
    assert f"bytes {offs[6]}-{offs[7]}" in text and "between sequences 6 and 8" in text


def test_an_intact_log_has_no_damage(tmp_path):
    path, offs = log_file(tmp_path)
    scan = wal.scan_wal(path)
    assert scan.damage is None and seqs(scan) == [1, 2, 3, 4, 5, 6] and scan.good_end == scan.size
    assert list(wal.read_wal(path)) and wal.scan_wal(str(tmp_path / "wal-0000000000000001.log")).size == scan.size


# ------------------------------------------------------------------------------ start-up (core)
def stored(tmp_path, n_ops=12, checkpoint_after=None, close=True):
    """A storage directory with n_ops stores of 4 (distinct transitions: ids 4j..4j+3)."""
    cfg = MemoryConfig(storage_dir=str(tmp_path), snapshot_every=0)
    mem = CompactMemory(cfg)
    for j in range(n_ops):
        mem.store(make(j))
        if checkpoint_after == j:
            mem.checkpoint()
    if close:
        mem.close()
    (path,) = glob.glob(str(tmp_path / "wal-*.log"))
    return cfg, path


def record_offsets(path):
    data, offs, off = open(path, "rb").read(), [], 0
    while off < len(data):
        offs.append(off)
        off += HEAD + wal._HEAD.unpack_from(data, off)[1]
    return offs


def all_back(mem, n_ops, missing=()):
    """Every store j not in `missing` is back (storing it again makes no identity)."""
    return all((mem.store(make(j)).new_identities == 0) == (j not in missing) for j in range(n_ops))


@pytest.mark.parametrize("field,pos", [("magic", 0), ("length", 5)])
def test_a_damaged_header_of_the_last_record_after_a_clean_stop_is_refused(tmp_path, field, pos):
    """The probe of issue 57: a flipped magic (or length) byte of the last record was cut as a torn
    tail ("never acknowledged") and its 4 identities were lost."""
    cfg, path = stored(tmp_path)
    damaged = flip(path, record_offsets(path)[-1] + pos)
    with pytest.raises(wal.WalCorruptError) as err:
        CompactMemory(cfg)
    msg = str(err.value)
    assert "payload checks out" in msg and "accepting loses nothing" in msg and "wal_accept_loss:=true" in msg
    assert open(path, "rb").read() == damaged
    warnings = []
    mem = CompactMemory(MemoryConfig(storage_dir=str(tmp_path), snapshot_every=0, wal_accept_loss=True),
                        log=warnings.append)
    assert mem.stats()["identities"] == 48 and mem.stats()["wal_sequence"] == 12
    assert any("dropped 0 logged operations;" in w for w in warnings), warnings
    assert open(glob.glob(path + ".damaged-*")[0], "rb").read() == damaged   # the copy, as it was
    mem.close()
    again = CompactMemory(cfg)            # the accepted start checkpointed: no damage left
    assert again.stats()["identities"] == 48 and all_back(again, 12)


def test_a_log_emptied_after_a_checkpoint_is_refused_naming_the_missing_sequences(tmp_path):
    cfg, path = stored(tmp_path, n_ops=12, checkpoint_after=3)     # snapshot at 4, 8 stores after it
    open(path, "wb").close()
    with pytest.raises(wal.WalMissingError) as err:
        CompactMemory(cfg)
    msg = str(err.value)
    assert "ends at sequence 4" in msg and "0 bytes" in msg, msg
    assert "8 acknowledged operations (sequences 5-12) are missing" in msg, msg
    assert "wal_accept_loss:=true" in msg and "backup" in msg
    assert (err.value.reached, err.value.expected) == (4, 12) and os.path.getsize(path) == 0
    warnings = []
    mem = CompactMemory(MemoryConfig(storage_dir=str(tmp_path), snapshot_every=0, wal_accept_loss=True),
                        log=warnings.append)
    assert mem.stats()["identities"] == 16 and any("sequences 5-12" in w for w in warnings), warnings
    mem.close()
    assert CompactMemory(cfg).stats()["identities"] == 16       # the new mark: starts without a word


def test_a_log_cut_at_a_record_boundary_below_its_mark_is_refused(tmp_path):
    """Cut cleanly between records, the file scans as intact: only the mark tells."""
    cfg, path = stored(tmp_path, n_ops=12, checkpoint_after=3)
    offs = record_offsets(path)
    with open(path, "r+b") as f:
        f.truncate(offs[5])                # keeps sequences 5-9 of 5-12
    with pytest.raises(wal.WalMissingError, match=r"sequence 9 .* 3 acknowledged operations \(sequences 10-12\)"):
        CompactMemory(cfg)
    mem = CompactMemory(MemoryConfig(storage_dir=str(tmp_path), snapshot_every=0, wal_accept_loss=True))
    assert mem.stats()["wal_sequence"] == 9 and all_back(mem, 12, missing=(9, 10, 11))


def test_a_log_file_named_after_a_later_checkpoint_than_the_snapshot_is_refused(tmp_path):
    """wal-<n>.log is opened at the checkpoint after sequence n - 1: an older snapshot put in place
    of that checkpoint's (with no mark to tell) leaves sequences out."""
    cfg, path = stored(tmp_path, n_ops=4, checkpoint_after=1)     # snapshot at 2
    old = tmp_path / "older"
    shutil.copytree(tmp_path / "snapshot", old)
    mem = CompactMemory(cfg)
    mem.checkpoint()                                              # snapshot at 4, wal-...5.log
    mem.close()
    shutil.rmtree(tmp_path / "snapshot")
    os.rename(old, tmp_path / "snapshot")
    os.remove(tmp_path / wal.MARK_FILE)
    with pytest.raises(wal.WalMissingError, match=r"ends at sequence 2 .*checkpoint \(as its file name says\).*"
                                                  r"2 acknowledged operations \(sequences 3-4\)"):
        CompactMemory(cfg)
    mem = CompactMemory(MemoryConfig(storage_dir=str(tmp_path), snapshot_every=0, wal_accept_loss=True))
    assert mem.stats()["wal_sequence"] == 2 and all_back(mem, 4, missing=(2, 3))
    del mem                                                      # killed: the accepted start checkpointed
    assert CompactMemory(cfg).stats()["wal_sequence"] == 6      # and the 4 stores after it


def test_a_killed_process_leaves_a_mark_its_log_always_reaches(tmp_path):
    """The mark is written at start, checkpoint and clean stop, after the log's bytes: after a kill
    the log is at or past it."""
    cfg, path = stored(tmp_path, n_ops=5, close=False)
    mark = json.loads(open(tmp_path / wal.MARK_FILE).read())
    assert mark["sequence"] == 0 and mark["when"] == "start"
    mem = CompactMemory(cfg)
    assert mem.stats()["wal_sequence"] == 5
    mem.checkpoint()
    mark = json.loads(open(tmp_path / wal.MARK_FILE).read())
    assert (mark["sequence"], mark["when"], mark["bytes"]) == (5, "checkpoint", 0)
    mem.close()
    mark = json.loads(open(tmp_path / wal.MARK_FILE).read())
    assert (mark["sequence"], mark["when"]) == (5, "stop")


def test_a_damaged_mark_is_refused_unless_loss_is_accepted(tmp_path):
    cfg, path = stored(tmp_path, n_ops=3)
    m = json.loads(open(tmp_path / wal.MARK_FILE).read())
    m["sequence"] = 1
    (tmp_path / wal.MARK_FILE).write_text(json.dumps(m))
    with pytest.raises(SnapshotError, match="mark is damaged"):
        CompactMemory(cfg)
    warnings = []
    mem = CompactMemory(MemoryConfig(storage_dir=str(tmp_path), wal_accept_loss=True), log=warnings.append)
    assert mem.stats()["wal_sequence"] == 3 and any("mark is damaged" in w for w in warnings)


def test_wal_accept_loss_keeps_every_intact_record_after_a_flipped_byte(tmp_path):
    """Issue 57: one flipped byte at 10 % dropped every record after it (6,976 identities)."""
    cfg, path = stored(tmp_path, n_ops=20)
    offs = record_offsets(path)
    damaged = flip(path, offs[3] - 10)                 # an array byte of sequence 3
    with pytest.raises(wal.WalCorruptError, match="17 intact records follow"):
        CompactMemory(cfg)
    warnings = []
    mem = CompactMemory(MemoryConfig(storage_dir=str(tmp_path), snapshot_every=0, wal_accept_loss=True),
                        log=warnings.append)
    assert mem.stats()["wal_sequence"] == 20 and mem.stats()["identities"] == 19 * 4
    text = "\n".join(warnings)
    assert f"bytes {offs[2]}-{offs[3]}" in text and "a store of 4 transitions" in text, text
    assert "dropped 1 logged operation (sequence 3)" in text and "other ids" in text, text
    (copy,) = glob.glob(path + ".damaged-*")
    assert copy.endswith(f".damaged-{offs[2]}") and open(copy, "rb").read() == damaged
    assert all_back(mem, 20, missing=(2,))
    mem.close()
    again = CompactMemory(cfg)
    assert again.stats()["identities"] == 20 * 4 and again.stats()["wal_sequence"] > 20


def test_a_genuine_torn_tail_is_dropped_with_a_copy_of_its_bytes(tmp_path):
    cfg, path = stored(tmp_path, n_ops=6, close=False)    # killed: no clean stop
    size = os.path.getsize(path)
    partial = wal.encode_arrays(7, wal.WAL_STORE, {"states": np.zeros((4, 6), np.float32)})[:30]
    with open(path, "ab") as f:
        f.write(partial)                                 # the write the kill cut short
    warnings = []
    mem = CompactMemory(cfg, log=warnings.append)
    assert mem.stats()["wal_sequence"] == 6 and os.path.getsize(path) == size
    assert len(warnings) == 1 and "torn" in warnings[0] and "never acknowledged" in warnings[0]
    assert open(f"{path}.torn-{size}", "rb").read() == partial
    assert all_back(mem, 6)


def test_a_torn_record_after_a_clean_stop_was_acknowledged_and_is_refused(tmp_path):
    """Cut inside the last record after a clean stop: it looks torn, but the mark says it was acknowledged."""
    cfg, path = stored(tmp_path, n_ops=6)
    with open(path, "r+b") as f:
        f.truncate(os.path.getsize(path) - 9)
    with pytest.raises(wal.WalMissingError, match="acknowledged operation 6 is missing"):
        CompactMemory(cfg)
