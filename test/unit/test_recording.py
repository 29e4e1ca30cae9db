"""ChunkedBagWriter: split rosbag2 bags that open with a plain rosbags reader, types from the bag only."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from comper_agent.recording.bags import (ChunkedBagWriter, bag_info, bag_typestore, check_mcap_file, comper_typestore,
                                    make_qos, parse_topic_spec, repair_bag)
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import Reader

TB = "comper_msgs/msg/TransitionBatch"
ES = "comper_msgs/msg/EpisodeSummary"


def _episode(ts, i, ret):
    T = ts.types
    return T[ES](header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=i, nanosec=7), frame_id="f"),
                 run_id="r0", env_id="Hopper-v4", source="train", episode_id=i, episode_return=ret, length=10 + i,
                 frames=10 + i, terminated=True, truncated=False, global_step=100 * i, global_frames=100 * i,
                 wall_time_s=0.5 * i)


def _batch(ts, n, seed=0):
    T = ts.types
    rng = np.random.default_rng(seed)
    A = T["comper_msgs/msg/Array"]

    def arr(x):
        x = np.asarray(x)
        u8 = x.dtype == np.uint8
        return A(dtype=1 if u8 else 0, shape=np.array(x.shape, np.uint32),
                 data_f32=np.zeros(0, np.float32) if u8 else x.astype(np.float32).ravel(),
                 data_u8=x.ravel() if u8 else np.zeros(0, np.uint8))
    H = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=1, nanosec=2), frame_id="")
    return T[TB](header=H, run_id="r0", states=arr(rng.standard_normal((n, 11))), actions=arr(rng.uniform(-1, 1, (n, 3))),
                 rewards=rng.standard_normal(n).astype(np.float32), next_states=arr(rng.standard_normal((n, 11))),
                 terminated=np.zeros(n, bool), truncated=np.zeros(n, bool), value_labels=np.ones(n, np.float32),
                 episode_ids=np.zeros(n, np.uint64), steps=np.arange(n, dtype=np.uint64))


@pytest.mark.parametrize("storage,compression", [("mcap", "zstd"), ("sqlite3", "zstd"), ("mcap", "none"),
                                                 ("sqlite3", "none")])
def test_round_trip_types_from_bag_only(tmp_path, storage, compression):
    ts = comper_typestore()
    bag = tmp_path / "bag"
    with ChunkedBagWriter(bag, storage=storage, compression=compression, max_file_duration_s=0,
                          custom_data={"run_id": "r0"}) as w:
        he = w.add_topic("/agent/episodes", ES, [make_qos()])
        ht = w.add_topic("/agent/transitions", TB, [make_qos()])
        for i in range(6):
            w.write(he, 1_000 + i, ts.serialize_cdr(_episode(ts, i, 1.25 * i + 1e-9), ES))
            w.write(ht, 1_000 + i, ts.serialize_cdr(_batch(ts, 7, i), TB))
            if i in (1, 3):
                w.split()
    files = sorted(p.name for p in bag.iterdir())
    suffix = ".mcap" if storage == "mcap" else ".db3"
    assert files == [f"bag_0{suffix}", f"bag_1{suffix}", f"bag_2{suffix}", "metadata.yaml"]
    with Reader(bag) as r:
        assert r.message_count == 12
        assert bag_info(bag)["custom_data"]["run_id"] == "r0"
        store = bag_typestore(r.connections)          # nothing from the workspace
        got = [store.deserialize_cdr(d, c.msgtype) for c, _, d in r.messages()]
    eps = [m for m in got if m.__msgtype__ == ES]
    assert [m.episode_return for m in eps] == [1.25 * i + 1e-9 for i in range(6)]
    assert eps[3].header.stamp.sec == 3 and eps[3].header.stamp.nanosec == 7
    tb = [m for m in got if m.__msgtype__ == TB]
    np.testing.assert_array_equal(tb[2].states.data_f32, _batch(ts, 7, 2).states.data_f32)
    # AnyReader (rosbags' own bag-only type registration) also decodes, hashes verified
    with AnyReader([bag]) as ar:
        n = sum(1 for c, t, d in ar.messages() if ar.deserialize(d, c.msgtype) is not None)
    assert n == 12
    # metadata as rosbag2 writes it: the distro, and rosbag2-level compression only where the storage has
    # none of its own (MCAP compresses its chunks, which metadata.yaml does not list)
    info = bag_info(bag)
    assert info["ros_distro"] == "jazzy"
    per_message = storage == "sqlite3" and compression == "zstd"
    assert (info["compression_format"], info["compression_mode"]) == (("zstd", "message") if per_message else ("", ""))
    if storage == "mcap":
        for f in sorted(bag.glob("*.mcap")):
            raw = f.read_bytes()
            chk = check_mcap_file(f)
            assert chk.ok and chk.chunks >= 1 and chk.unverified == 0, chk   # every chunk has a CRC
            assert (b"zstd" in raw) == (compression == "zstd")                # the chunk records' compression
            assert b"ros_distro: jazzy" in raw and b"ros_distro: rosbags" not in raw   # embedded metadata


def test_zstd_makes_transition_batches_smaller(tmp_path):
    """Atari-like frames (runs of equal bytes) shrink under zstd; the decoded data is the same."""
    ts = comper_typestore()
    rng = np.random.default_rng(0)
    frames = np.repeat(rng.integers(0, 8, (20, 4, 21, 84), dtype=np.uint8), 4, axis=2)   # [n, 4, 84, 84]
    from scaffolding import transitions_cdr
    from comper_msgs_py.arrays import Transitions
    n = len(frames)
    t = Transitions(frames, np.zeros(n, np.float32), np.ones(n, np.float32), frames, np.zeros(n, bool),
                    np.zeros(n, bool), run_id="a")
    data = transitions_cdr(ts, t)
    sizes = {}
    for comp in ("none", "zstd"):
        with ChunkedBagWriter(tmp_path / comp, compression=comp) as w:
            w.write(w.add_topic("/a/transitions", TB), 1, data)
        sizes[comp] = (tmp_path / comp / "bag_0.mcap").stat().st_size
        with Reader(tmp_path / comp) as r:
            ((_, _, got),) = list(r.messages())
        assert bytes(got) == data
    assert sizes["zstd"] * 4 < sizes["none"], sizes


def test_embedded_definition_is_complete(tmp_path):
    ts = comper_typestore()
    bag = tmp_path / "bag"
    with ChunkedBagWriter(bag) as w:
        h = w.add_topic("/a/transitions", TB)
        w.write(h, 1, ts.serialize_cdr(_batch(ts, 2), TB))
    with Reader(bag) as r:
        (c,) = r.connections
        text = c.msgdef.data
    for part in ("MSG: comper_msgs/Array", "MSG: std_msgs/Header", "MSG: builtin_interfaces/Time", "float32[] data_f32"):
        assert part in text
    # the RIHS01 hash equals the one rosidl generated for the installed interface
    import json
    from comper_agent.recording.bags import find_msg_dir
    hashes = json.loads((find_msg_dir() / "TransitionBatch.json").read_text())["type_hashes"]
    assert c.digest == next(h["hash_string"] for h in hashes if h["type_name"] == TB)


def test_decoding_in_a_process_without_the_workspace(tmp_path):
    """A bare python with only rosbags on the path (no comper_msgs, no AMENT paths) decodes the bag."""
    ts = comper_typestore()
    bag = tmp_path / "bag"
    with ChunkedBagWriter(bag) as w:
        h = w.add_topic("/a/episodes", ES)
        w.write(h, 5, ts.serialize_cdr(_episode(ts, 4, 3.5), ES))
    code = textwrap.dedent(f"""
        import sys
        sys.path[:] = [p for p in sys.path if 'install' not in p and '/src/' not in p]
        try:
            import comper_msgs
            raise SystemExit('comper_msgs importable')
        except ImportError:
            pass
        from rosbags.rosbag2 import Reader
        from rosbags.typesys import Stores, get_typestore, get_types_from_msg
        with Reader({str(bag)!r}) as r:
            st = get_typestore(Stores.EMPTY)
            for c in r.connections:
                st.register(get_types_from_msg(c.msgdef.data, c.msgtype))
            for c, t, d in r.messages():
                m = st.deserialize_cdr(d, c.msgtype)
                print(m.episode_return, m.header.stamp.sec)
    """)
    env = {"PATH": os.environ["PATH"], "_ROS_WHEELS_BOOTSTRAP_COMPLETE": "1"}   # no AMENT/PYTHONPATH
    out = subprocess.run([sys.executable, "-I", "-c", code], env=env, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["3.5", "4"]


def test_rclpy_serialized_bytes_decode_with_bag_types(tmp_path):
    """The recorder stores rclpy's serialized CDR bytes verbatim: they decode with the bag's types."""
    ser = pytest.importorskip("rclpy.serialization")
    from comper_msgs.msg import EpisodeSummary, TransitionBatch
    from comper_msgs_py.convert import transitions_to_batch
    from scaffolding import synthetic_run
    t, summaries = synthetic_run(300, seed=1)
    m = EpisodeSummary(run_id="x", env_id="Hopper-v4", source="train", episode_id=3, episode_return=summaries[0]["episode_return"])
    bag = tmp_path / "bag"
    with ChunkedBagWriter(bag) as w:
        he, ht = w.add_topic("/a/episodes", ES), w.add_topic("/a/transitions", TB)
        w.write(he, 1, ser.serialize_message(m))
        w.write(ht, 2, ser.serialize_message(transitions_to_batch(t)))
    with Reader(bag) as r:
        st = bag_typestore(r.connections)
        msgs = {c.msgtype: st.deserialize_cdr(d, c.msgtype) for c, _, d in r.messages()}
    assert msgs[ES].episode_return == summaries[0]["episode_return"]
    np.testing.assert_array_equal(msgs[TB].states.data_f32.reshape(t.states.shape), t.states)
    np.testing.assert_array_equal(msgs[TB].terminated, t.terminated)


def test_duration_split_and_unlisted_open_file(tmp_path):
    ts = comper_typestore()
    now = [0.0]
    bag = tmp_path / "bag"
    w = ChunkedBagWriter(bag, max_file_duration_s=2.0, clock=lambda: now[0])
    h = w.add_topic("/a/episodes", ES)
    for i in range(5):
        w.write(h, i, ts.serialize_cdr(_episode(ts, i, float(i)), ES))
        now[0] += 1.0
        w.maybe_split()
    # two files closed (at t=2 and t=4), one message still in the open file
    assert w.stats.files_closed == 2
    with Reader(bag) as r:   # what a reader sees while the writer is alive (or after a SIGKILL)
        assert r.message_count == 4
    w.close()
    with Reader(bag) as r:
        assert r.message_count == 5
    assert not (bag / ".open").exists()


def test_size_split(tmp_path):
    ts = comper_typestore()
    bag = tmp_path / "bag"
    data = ts.serialize_cdr(_batch(ts, 500), TB)
    with ChunkedBagWriter(bag, max_file_size_bytes=3 * len(data), max_file_duration_s=0) as w:
        h = w.add_topic("/a/transitions", TB)
        for i in range(10):
            w.write(h, i, data)
    with Reader(bag) as r:
        assert len(bag_info(bag)["files"]) == 4 and r.message_count == 10


def test_refuses_existing_bag_and_unknown_type(tmp_path):
    (tmp_path / "bag").mkdir()
    (tmp_path / "bag" / "x").write_text("")
    with pytest.raises(FileExistsError):
        ChunkedBagWriter(tmp_path / "bag")
    w = ChunkedBagWriter(tmp_path / "b2")
    with pytest.raises(KeyError):
        w.add_topic("/x", "nope_msgs/msg/Nope")
    w.close()


def test_repair_rebuilds_metadata(tmp_path):
    ts = comper_typestore()
    bag = tmp_path / "bag"
    with ChunkedBagWriter(bag, max_file_duration_s=0, custom_data={"run_id": "r9"}) as w:
        h = w.add_topic("/a/episodes", ES)
        for i in range(4):
            w.write(h, 10 + i, ts.serialize_cdr(_episode(ts, i, float(i)), ES))
            w.split()
    (bag / "metadata.yaml").unlink()
    (bag / "bag_4.mcap").write_bytes(b"\x89MCAP0\r\n truncated")   # a half-written file
    res = repair_bag(bag)
    assert res["files"] == [f"bag_{i}.mcap" for i in range(4)] and res["skipped"] == ["bag_4.mcap"]
    assert "truncated" in res["reasons"]["bag_4.mcap"]
    with Reader(bag) as r:
        assert r.message_count == 4
    assert bag_info(bag)["ros_distro"] == "jazzy"


def test_repair_keeps_per_message_compression(tmp_path):
    """A sqlite3 bag with per-message zstd is still read as compressed after its metadata is rebuilt."""
    ts = comper_typestore()
    bag = tmp_path / "bag"
    with ChunkedBagWriter(bag, storage="sqlite3", max_file_duration_s=0) as w:
        h = w.add_topic("/a/episodes", ES)
        for i in range(3):
            w.write(h, 10 + i, ts.serialize_cdr(_episode(ts, i, 0.5 + i), ES))
            w.split()
    (bag / "metadata.yaml").unlink()
    repair_bag(bag)
    assert (bag_info(bag)["compression_format"], bag_info(bag)["compression_mode"]) == ("zstd", "message")
    with Reader(bag) as r:
        st = bag_typestore(r.connections)
        assert [st.deserialize_cdr(d, c.msgtype).episode_return for c, _, d in r.messages()] == [0.5, 1.5, 2.5]


def test_parse_topic_spec():
    assert parse_topic_spec("/comcact_node/transitions") == ("/comcact_node/transitions", TB)
    assert parse_topic_spec("memory_node/stats") == ("memory_node/stats", "comper_msgs/msg/MemoryStats")
    assert parse_topic_spec("/x:std_msgs/String") == ("/x", "std_msgs/msg/String")
    assert parse_topic_spec("/x") == ("/x", None)
