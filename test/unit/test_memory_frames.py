"""Observations by reference (``frame_store``, core/frames.py): each frame stored once, stacks rebuilt byte for
byte, decisions and samples identical to whole observations per identity, snapshots and the WAL carry it, a
snapshot of the previous layout is converted, bad input leaves nothing stored."""
import glob
import os

import numpy as np
import pytest

from comper_memory.core import CompactMemory, MemoryConfig, MemoryInputError, SnapshotError
from comper_memory.core import frames as frames_mod
from comper_memory.core.frames import FrameStore, frame_layout
from comper_memory.core.storage import WAL_STORE, read_snapshot, read_wal, write_snapshot
from comper_msgs_py.arrays import Transitions
from comper_sim.core import SimBridge, SimConfig

STACK = 4


@pytest.fixture(scope="module")
def atari_stream():
    """300 Freeway transitions from the suite's ALE pipeline, stacked by the sim (4 frames, oldest first, an
    episode's first stack filled with its first frame), episodes truncated at 60 steps and one cut short by a
    second reset (so episode boundaries and repeated reset frames are in the stream)."""
    b = SimBridge(SimConfig(env_id="ALE/Freeway-v5", frame_stack=STACK, max_episode_steps=60))
    b.reset(seed=3)
    rng = np.random.default_rng(3)
    parts = [b.step_many(np.where(rng.random(150) < 0.7, 1, rng.integers(0, 18, 150)).astype(np.float32)).transitions]
    b.reset(seed=3)                       # the same first frame again: one frame for both episodes
    parts.append(b.step_many(rng.integers(0, 18, 150).astype(np.float32)).transitions)
    b.close()
    t = Transitions.concatenate(parts)
    n = len(t)
    return Transitions(t.states, t.actions.astype(np.int64), t.rewards, t.next_states, t.terminated, t.truncated,
                       value_labels=rng.standard_normal(n).astype(np.float32), episode_ids=t.episode_ids,
                       steps=t.steps)


def comper_pattern(mem, t, seed=0):
    """comper_node's store pattern: every 4 steps the 4 new transitions and 32 re-stores of earlier ones."""
    rng = np.random.default_rng(seed)
    ids = []
    for i in range(0, len(t), 4):
        old = rng.integers(0, i, 32) if i >= 32 else np.zeros(0, np.int64)
        ids.append(mem.store(t.take(np.concatenate([np.arange(i, min(i + 4, len(t))), old]))).identity_ids)
    return np.concatenate(ids)


def assert_same_transitions(a, b):
    for f in ("states", "next_states", "actions", "rewards", "terminated", "truncated", "value_labels",
              "episode_ids", "steps"):
        x, y = getattr(a, f), getattr(b, f)
        assert x.dtype == y.dtype and np.array_equal(x, y), f


def refs_consistent(mem):
    """Every frame's count equals the references the live identities hold, and only those frames are indexed."""
    fs = mem.slots.obs.frames
    slots = mem.slots.slots_sorted
    refs = np.concatenate([mem.a["state_frames"][slots].ravel(), mem.a["next_frames"][slots].ravel()])
    assert np.array_equal(fs.refs[:fs.hi], np.bincount(refs, minlength=fs.hi))
    assert fs.n_live == len(np.unique(refs)) == len(fs._by_digest) + sum(map(len, fs._more.values()))


def test_the_switch():
    u8 = np.uint8
    assert frame_layout("auto", 0, (4, 84, 84), u8).stack == 4                    # stacked Atari frames
    assert frame_layout("auto", 0, (84, 84), u8) is None                          # one frame: as before
    assert frame_layout("auto", 0, (4, 84, 84), np.float32) is None               # float observations
    assert frame_layout("auto", 0, (17,), np.float32) is None                     # vector observations
    assert frame_layout("auto", 0, (64, 64, 3), u8) is None                       # 192-byte slices
    assert frame_layout("auto", 2, (84, 84, 4), u8).frame_shape == (84, 84)       # channels last
    assert frame_layout("on", -1, (64, 64, 3), u8).stack == 1                     # a camera image, one frame
    assert frame_layout("on", 0, (84, 84), u8).axis is None
    assert frame_layout("off", 0, (4, 84, 84), u8) is None
    with pytest.raises(ValueError, match="frame_axis 3"):
        frame_layout("on", 3, (4, 84, 84), u8)


def test_decisions_samples_and_keys_equal_whole_observations_on_an_atari_stream(atari_stream):
    t = atari_stream
    mems = {m: CompactMemory(MemoryConfig(frame_store=m, rtm_capacity=200, tm_capacity=200, max_store_batch=64))
            for m in ("off", "auto")}
    ids = {m: comper_pattern(mem, t) for m, mem in mems.items()}
    off, on = mems["off"], mems["auto"]
    assert on.slots.obs.layout is not None and off.slots.obs.layout is None
    np.testing.assert_array_equal(ids["auto"], ids["off"])                       # identity ids match
    assert on.stats()["evictions"] == off.stats()["evictions"] > 0
    live = off.slots.ids_sorted
    np.testing.assert_array_equal(on.slots.ids_sorted, live)
    np.testing.assert_array_equal(on.slots.keys_of(live), off.slots.keys_of(live))   # the same keys, exactly
    for source in ("tm", "rtm"):
        if source == "rtm":
            for mem in mems.values():
                mem.reduce(max_sets=10_000)
        a, b = (mem.sample(64, source=source, seed=5) for mem in (off, on))
        np.testing.assert_array_equal(a.identity_ids, b.identity_ids)
        assert_same_transitions(a.transitions, b.transitions)
    # each frame once: about one new frame per transition, not eight
    fs = on.slots.obs.frames
    assert fs.n_live < 2 * on.slots.n_live
    refs_consistent(on)
    assert on.bytes_used() * 4 < off.bytes_used()


def test_rebuilt_stacks_are_the_ones_stored_across_episode_boundaries(atari_stream):
    t = atari_stream
    mem = CompactMemory(MemoryConfig(delta=0.0))
    ids = mem.store(t.take(np.arange(64))).identity_ids
    for i in range(64, len(t), 64):
        ids = np.concatenate([ids, mem.store(t.take(np.arange(i, min(i + 64, len(t))))).identity_ids])
    first = np.unique(ids, return_index=True)[1]          # each identity's representative: its first transition
    got = mem.slots.reps(mem.slots.slots_of(np.unique(ids)), np.zeros(len(first), np.float32))
    np.testing.assert_array_equal(got.states, t.states[first])
    np.testing.assert_array_equal(got.next_states, t.next_states[first])
    ends = np.flatnonzero(t.terminated | t.truncated)
    assert len(ends) >= 3 and t.truncated.any()
    for e in ends[ends + 1 < len(t)]:                     # the stack after an episode end holds only its first frame
        s = mem.slots.reps(mem.slots.slots_of(ids[e + 1:e + 2]), np.zeros(1, np.float32)).states[0]
        assert all(np.array_equal(s[0], s[k]) for k in range(STACK))
    refs_consistent(mem)
    # the two resets with seed 3 give the same first frame: stored once
    fs = mem.slots.obs.frames
    assert fs.n_live < len(np.unique(ids)) + STACK * (len(ends) + 2)


def test_evictions_free_frames_and_reuse_them():
    rng = np.random.default_rng(1)
    frames = rng.integers(0, 256, (2_000, 84, 84), dtype=np.uint8)
    mem = CompactMemory(MemoryConfig(delta=0.0, rtm_capacity=256, removal="fifo", max_store_batch=64))
    for i in range(0, 1_900, 64):
        k = np.arange(i, i + 64)
        s = frames[k[:, None] + np.arange(STACK)]
        mem.store(Transitions(s, np.zeros(64, np.int64), np.zeros(64, np.float32), frames[k[:, None] + 1 +
                  np.arange(STACK)], np.zeros(64, bool), np.zeros(64, bool), value_labels=np.zeros(64, np.float32)))
        refs_consistent(mem)
    fs = mem.slots.obs.frames
    assert mem.slots.n_live == 256 and fs.n_live == 256 + STACK
    assert fs.hi <= 256 + STACK + 64 * (STACK + 1) + 64      # freed frames are reused, the store does not grow


def test_digest_collisions_are_told_apart_by_the_bytes(monkeypatch):
    monkeypatch.setattr(frames_mod, "_digest", lambda f: 7)
    fs = FrameStore((3, 5), np.uint8)
    rng = np.random.default_rng(0)
    f = rng.integers(0, 256, (6, 3, 5), dtype=np.uint8)
    ids = fs.intern(np.concatenate([f, f[::-1]]))
    np.testing.assert_array_equal(ids[:6], ids[6:][::-1])
    np.testing.assert_array_equal(fs.gather(ids), np.concatenate([f, f[::-1]]))
    fs.release(ids[:6])
    fs.release(ids[[6, 8]])                     # frames 5 and 3 left without references
    assert fs.n_live == 4 and sorted(fs.free) == sorted(ids[[6, 8]])
    again = fs.intern(f[[0, 5]])              # f[0] still held; f[5] stored again in a freed frame
    assert again[0] == ids[0] and again[1] in ids[[6, 8]] and fs.n_live == 5
    np.testing.assert_array_equal(fs.gather(again), f[[0, 5]])


def test_snapshot_round_trip_and_the_previous_layout_converted(tmp_path, atari_stream):
    t = atari_stream
    cfg = dict(rtm_capacity=150, tm_capacity=150, max_store_batch=100)
    on = CompactMemory(MemoryConfig(**cfg))
    off = CompactMemory(MemoryConfig(frame_store="off", **cfg))
    head, tail = t.take(np.arange(200)), t.take(np.arange(200, len(t)))
    for mem in (on, off):
        comper_pattern(mem, head)
        mem.reduce(max_sets=100)
    on.save_snapshot(str(tmp_path / "on"))
    off.save_snapshot(str(tmp_path / "off"))
    arrays, meta = read_snapshot(str(tmp_path / "on"))
    assert "states" not in arrays and "frames" in arrays and meta["schema"]["frames"] == {"axis": 0, "stack": 4}
    size = {k: os.path.getsize(tmp_path / k / "state.npz") for k in ("on", "off")}
    assert size["on"] * 3 < size["off"]
    # each snapshot into each layout: the previous layout (observations) is converted when it is loaded
    ids_after = off.store(tail).identity_ids
    for snap in ("on", "off"):
        for mode in ("auto", "off"):
            mem = CompactMemory(MemoryConfig(frame_store=mode, **cfg))
            mem.load_snapshot(str(tmp_path / snap))
            assert (mem.slots.obs.layout is None) == (mode == "off")
            np.testing.assert_array_equal(mem.store(tail).identity_ids, ids_after)
            a, b = mem.sample(32, source="tm", seed=2), off.sample(32, source="tm", seed=2)
            np.testing.assert_array_equal(a.identity_ids, b.identity_ids)
            assert_same_transitions(a.transitions, b.transitions)
            if mode == "auto":
                refs_consistent(mem)


def test_wal_recovery_rebuilds_the_frame_store(tmp_path, atari_stream):
    t = atari_stream
    cfg = MemoryConfig(storage_dir=str(tmp_path / "store"), snapshot_every=7, rtm_capacity=150, tm_capacity=150,
                       max_store_batch=64)
    mem = CompactMemory(cfg)
    ids = comper_pattern(mem, t)
    mem.reduce(max_sets=50)
    expected = mem.export_state()[0]
    hist = mem.slots.histories(mem.slots.slots_sorted)
    reps = mem.slots.reps(mem.slots.slots_sorted, np.zeros(len(hist[1])))
    assert len(np.unique(ids)) > mem.slots.n_live             # evictions happened
    # the log's store records carry each distinct frame of a store once, and indices
    stores = [arr for log in sorted(glob.glob(str(tmp_path / "store" / "wal-*.log")))
              for _, kind, arr in read_wal(log, repair=False) if kind == WAL_STORE]
    assert stores and all("states" not in r and "frames" in r for r in stores)
    assert sum(len(r["frames"]) for r in stores) * 2 < sum(8 * len(r["rewards"]) for r in stores)   # re-stores too
    del mem                                                  # no clean stop: recovery replays the log
    again = CompactMemory(cfg)
    got = again.export_state()[0]
    for name in ("id", "count", "rtm_pred", "tm_order", "rtm_order"):
        np.testing.assert_array_equal(got[name], expected[name])
    for x, y in zip(again.slots.histories(again.slots.slots_sorted), hist):
        np.testing.assert_array_equal(x, y)
    assert_same_transitions(again.slots.reps(again.slots.slots_sorted, np.zeros(len(hist[1]))), reps)
    refs_consistent(again)
    again.close()


def test_bad_input_leaves_nothing_stored(tmp_path, atari_stream):
    t = atari_stream.take(np.arange(40))
    with pytest.raises(MemoryInputError, match="frame_axis 5"):
        CompactMemory(MemoryConfig(frame_store="on", frame_axis=5)).store(t)
    mem = CompactMemory(MemoryConfig())
    mem.store(t.take(np.arange(20)))
    before = (mem.slots.obs.frames.hi, mem.slots.obs.frames.n_live, mem.stats()["identities"])
    bad = Transitions(t.states[:, :3], t.actions, t.rewards, t.next_states[:, :3], t.terminated, t.truncated,
                      value_labels=t.value_labels)
    with pytest.raises(MemoryInputError, match="differ from the memory"):
        mem.store(bad)
    assert (mem.slots.obs.frames.hi, mem.slots.obs.frames.n_live, mem.stats()["identities"]) == before
    # a snapshot whose frame references point outside its frames is refused, the state untouched
    mem.save_snapshot(str(tmp_path / "s"))
    arrays, meta = read_snapshot(str(tmp_path / "s"))
    arrays["next_frames"] = arrays["next_frames"] + 10_000
    write_snapshot(str(tmp_path / "bad"), arrays, meta)
    with pytest.raises(SnapshotError, match="outside its"):
        mem.load_snapshot(str(tmp_path / "bad"))
    assert (mem.slots.obs.frames.hi, mem.slots.obs.frames.n_live, mem.stats()["identities"]) == before
    refs_consistent(mem)


def test_the_frames_map_grows_in_place_unless_a_view_of_it_is_held():
    fs = FrameStore((84, 84), np.uint8)
    f = np.random.default_rng(2).integers(0, 256, (3_000, 84, 84), dtype=np.uint8)
    ids = fs.intern(f[:1_000])
    mm = fs._mm
    ids = np.concatenate([ids, fs.intern(f[1_000:2_100])])
    assert fs._mm is mm and fs.cap >= 2_100                   # resized in place (mremap), nothing copied
    held = fs.arrays()["frames"]                              # a snapshot's view of the map
    ids = np.concatenate([ids, fs.intern(f[2_100:])])
    assert fs._mm is not mm                                   # copied into a new map; the view stays valid
    np.testing.assert_array_equal(fs.gather(ids), f)
    np.testing.assert_array_equal(held, f[:2_100])


def test_large_snapshot_frames_are_read_into_the_map_not_held_twice(tmp_path, atari_stream, monkeypatch):
    from comper_memory.core import storage
    mem = CompactMemory(MemoryConfig(max_store_batch=100))
    mem.store(atari_stream.take(np.arange(100)))
    mem.save_snapshot(str(tmp_path / "s"))
    monkeypatch.setattr(storage, "MAP_MEMBER_BYTES", 1 << 16)   # the frames (~0.8 MB) count as large here
    arrays, _ = read_snapshot(str(tmp_path / "s"))
    assert isinstance(arrays["frames"], np.memmap) and not isinstance(arrays["id"], np.memmap)
    again = CompactMemory(MemoryConfig(max_store_batch=100))
    again.load_snapshot(str(tmp_path / "s"))
    a, b = (m.sample(50, source="tm", seed=1) for m in (mem, again))
    assert_same_transitions(a.transitions, b.transitions)
    refs_consistent(again)
