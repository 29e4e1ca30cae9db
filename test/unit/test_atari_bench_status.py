"""benchmarks/atari_bench.py: which runs a second start of a split sweep does again. A complete run is done;
one stopped before its budget continues from its checkpoint when that holds the memory / replay contents,
and is refused (not silently continued from an empty memory) when it does not."""
import importlib.util
import json
import sys
from pathlib import Path

import pytest

from comper_agent.core.checkpoint import save_checkpoint

ROOT = Path(__file__).resolve().parents[2]


def _bench():
    sys.path.insert(0, str(ROOT / "benchmarks"))          # atari_bench imports learning_bench
    try:
        spec = importlib.util.spec_from_file_location("atari_bench", ROOT / "benchmarks" / "atari_bench.py")
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))
    return mod


def _run(out: Path, rid: str, complete=None, replay=None) -> None:
    d = out / "runs" / rid
    d.mkdir(parents=True)
    if complete is not None:
        (d / "summary.json").write_text(json.dumps({"complete": complete}))
    if replay is not False:
        save_checkpoint(d / "checkpoints" / "latest.pt",
                        {"counters": {"step": 10}, **({"replay": replay} if replay else {})})


def test_split_runs_continue_only_from_a_checkpoint_with_their_memory(tmp_path):
    b = _bench()
    _run(tmp_path, "done", complete=True)
    _run(tmp_path, "stopped", complete=False, replay={"kind": "memory", "request": "step_000000010.memory"})
    _run(tmp_path, "killed", replay={"kind": "local", "file": "step_000000010.replay.npz"})
    _run(tmp_path, "early", replay=False)
    _run(tmp_path, "old", complete=False)
    assert b.run_status(tmp_path, "done") == "done"
    assert b.run_status(tmp_path, "stopped") == "continue" and b.run_status(tmp_path, "killed") == "continue"
    assert b.run_status(tmp_path, "early") == "new" and b.run_status(tmp_path, "absent") == "new"
    with pytest.raises(ValueError, match="holds no memory / replay contents"):
        b.run_status(tmp_path, "old")
