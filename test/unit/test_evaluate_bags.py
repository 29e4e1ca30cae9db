"""evaluate on bags it cannot use (issue 16, failure 9): a truncated bag, a bag without
metadata.yaml and an empty bag end in one line that names the bag and what to run (no traceback);
``evaluate --repair`` rebuilds the bag and the evaluation then succeeds. A byte flipped inside a
recorded message is caught by the MCAP chunk CRCs (issue 16, item 7)."""
from __future__ import annotations

import shutil

import pytest

from comper_agent.offline import evaluate
from scaffolding import synthetic_run
from comper_agent.recording.bags import ChunkedBagWriter
from scaffolding import write_run_bag


@pytest.fixture(scope="module")
def good_bag(tmp_path_factory):
    t, summ = synthetic_run(600, seed=1, run_id="r1")
    return write_run_bag(tmp_path_factory.mktemp("good") / "bag", t, summ, max_file_size_bytes=20000)


def _copy(good_bag, tmp_path):
    bag = tmp_path / "bag"
    shutil.copytree(good_bag, bag)
    return bag


def _run(capsys, *argv):
    rc = evaluate.main([str(a) for a in argv])
    out = capsys.readouterr()
    assert "Traceback" not in out.err
    return rc, out.out, out.err


def test_truncated_bag_names_the_bag_and_the_repair_then_repair_works(good_bag, tmp_path, capsys):
    bag = _copy(good_bag, tmp_path)
    last = sorted(bag.glob("*.mcap"))[-1]
    last.write_bytes(last.read_bytes()[: last.stat().st_size // 2])   # the recorder was killed
    rc, _, err = _run(capsys, bag, "--out", tmp_path / "r", "--no-plots")
    assert rc == 1 and f"cannot read bag {bag}" in err and "--repair" in err, err
    rc, out, _ = _run(capsys, bag, "--repair", "--out", "-")
    assert rc == 0 and f"repaired {bag}" in out and last.name in out
    assert (bag / ".open" / last.name).exists()
    rc, out, err = _run(capsys, bag, "--out", tmp_path / "r", "--no-plots")
    assert rc == 0 and "r1: comcact" in out, err


def test_bag_without_metadata_and_empty_bag(good_bag, tmp_path, capsys):
    bag = _copy(good_bag, tmp_path)
    (bag / "metadata.yaml").unlink()
    rc, _, err = _run(capsys, bag, "--out", tmp_path / "r", "--no-plots")
    assert rc == 1 and "no metadata.yaml" in err and "--repair" in err, err
    rc, out, err = _run(capsys, bag, "--repair", "--out", tmp_path / "r", "--no-plots")
    assert rc == 0 and "repaired" in out and "r1: comcact" in out, err
    with ChunkedBagWriter(tmp_path / "empty"):
        pass
    rc, _, err = _run(capsys, tmp_path / "empty", "--out", tmp_path / "r2", "--no-plots")
    assert rc == 1 and "hold no EpisodeSummary messages" in err, err
    rc, _, err = _run(capsys, tmp_path / "nothing-here", "--out", tmp_path / "r3")
    assert rc == 1 and "does not exist" in err


def _flip_in_message(bag, needle: bytes):
    """Flip one bit inside the recorded bytes of the message holding `needle` (an uncompressed bag)."""
    for f in sorted(bag.glob("*.mcap")):
        raw = bytearray(f.read_bytes())
        i = raw.find(needle)
        if i >= 0:
            raw[i + len(needle) // 2] ^= 0x04
            f.write_bytes(bytes(raw))
            return f, i + len(needle) // 2
    raise AssertionError("message bytes not found")


@pytest.mark.parametrize("compression", ["none", "zstd"])
def test_a_flipped_byte_inside_message_data_is_reported_as_corrupt(tmp_path, capsys, compression):
    t, summ = synthetic_run(600, seed=2, run_id="r2")
    bag = write_run_bag(tmp_path / "bag", t, summ, max_file_size_bytes=20000, compression=compression)
    rc, out, err = _run(capsys, bag, "--out", tmp_path / "ok", "--no-plots")    # intact: passes
    assert rc == 0 and "r2: comcact" in out and "0 mismatches" in out, err
    if compression == "none":   # the rewards of the third episode, as they are in the file
        k0, k1 = summ[0]["length"] + summ[1]["length"], summ[2]["length"]
        f, at = _flip_in_message(bag, t.rewards[k0:k0 + k1].tobytes())
    else:                       # compressed: a byte in the middle of the second file's chunk data
        f = sorted(bag.glob("*.mcap"))[1]
        raw = bytearray(f.read_bytes())
        at = len(raw) // 3
        raw[at] ^= 0x04
        f.write_bytes(bytes(raw))
    rc, _, err = _run(capsys, bag, "--out", tmp_path / "r", "--no-plots")
    lines = err.strip().splitlines()
    assert rc == 1 and len(lines) == 1, err
    assert f"bag {bag} is corrupt: {f.name} at byte " in err and "CRC32" in err and f"bag_repair {bag}" in err, err
    offset = int(err.split(" at byte ")[1].split(":")[0])
    assert offset < at     # the chunk record holding the flipped byte starts before it
    # bag_repair sets the file aside (untouched) and says why; the rest evaluates
    from comper_agent.recording import bag_tools
    assert bag_tools.bag_repair_main([str(bag)]) == 0
    out = capsys.readouterr().out
    assert f"{f.name} (corrupt chunk at byte {offset}" in out, out
    assert (bag / ".open" / f.name).exists()
    rc, out, err = _run(capsys, bag, "--out", tmp_path / "r", "--no-plots")
    assert rc == 0 and "r2: comcact" in out, err


def test_bag_tools_name_a_damaged_bag_and_bag_repair_main_repairs_it(good_bag, tmp_path, capsys):
    from comper_agent.recording import bag_tools
    bag = _copy(good_bag, tmp_path)
    last = sorted(bag.glob("*.mcap"))[-1]
    last.write_bytes(last.read_bytes()[:100])
    rc = bag_tools.export_dataset_main([str(bag), "--datasets-path", str(tmp_path / "ds")])
    err = capsys.readouterr().err
    assert rc == 1 and f"cannot read bag {bag}" in err and "--repair" in err and "Traceback" not in err, err
    assert bag_tools.bag_repair_main([str(bag)]) == 0
    assert f"repaired {bag}" in capsys.readouterr().out
    assert bag_tools.export_dataset_main([str(bag), "--datasets-path", str(tmp_path / "ds")]) == 0
