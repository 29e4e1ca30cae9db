"""evaluate on bags it cannot use (issue 16, failure 9): a truncated bag, a bag without
metadata.yaml and an empty bag end in one line that names the bag and what to run (no traceback);
``evaluate --repair`` rebuilds the bag and the evaluation then succeeds."""
from __future__ import annotations

import shutil

import pytest

from comper_agent import evaluate
from scaffolding import synthetic_run
from comper_agent.recording import ChunkedBagWriter
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


def test_bag_tools_name_a_damaged_bag_and_bag_repair_main_repairs_it(good_bag, tmp_path, capsys):
    from comper_agent import bag_tools
    bag = _copy(good_bag, tmp_path)
    last = sorted(bag.glob("*.mcap"))[-1]
    last.write_bytes(last.read_bytes()[:100])
    rc = bag_tools.export_dataset_main([str(bag), "--out", str(tmp_path / "ds")])
    err = capsys.readouterr().err
    assert rc == 1 and f"cannot read bag {bag}" in err and "--repair" in err and "Traceback" not in err, err
    assert bag_tools.bag_repair_main([str(bag)]) == 0
    assert f"repaired {bag}" in capsys.readouterr().out
    assert bag_tools.export_dataset_main([str(bag), "--out", str(tmp_path / "ds")]) == 0
