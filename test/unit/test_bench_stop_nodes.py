"""benchmarks/bench_args.stop_nodes: the benchmarks' way to stop the runs they started in sessions of their
own. Each gets SIGINT (its own Ctrl-C: final checkpoint) and the time to finish it; one that ignores it is
killed when the time is up, so a stopped benchmark never leaves a run behind."""
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))
from bench_args import stop_nodes  # noqa: E402

# a stand-in run: on SIGINT it "saves" (writes a file) and exits 0, or ignores SIGINT altogether
CHILD = """
import signal, sys, time
path, ignore = sys.argv[1], sys.argv[2] == "ignore"
def on_int(signum, frame):
    open(path, "w").write("saved")
    sys.exit(0)
signal.signal(signal.SIGINT, signal.SIG_IGN if ignore else on_int)
print("ready", flush=True)
while True:
    time.sleep(0.05)
"""


def _start(tmp_path, name, mode):
    p = subprocess.Popen([sys.executable, "-c", CHILD, str(tmp_path / name), mode], stdout=subprocess.PIPE,
                         text=True, start_new_session=True)
    assert p.stdout.readline().strip() == "ready"
    return p


def test_each_run_gets_its_ctrl_c_and_one_that_ignores_it_is_killed_at_the_timeout(tmp_path):
    polite = [_start(tmp_path, f"run{i}", "save") for i in range(2)]
    stubborn = _start(tmp_path, "stubborn", "ignore")
    t0 = time.monotonic()
    stop_nodes(polite + [stubborn], timeout=2.0)
    waited = time.monotonic() - t0
    assert [p.returncode for p in polite] == [0, 0]
    assert all((tmp_path / f"run{i}").read_text() == "saved" for i in range(2))
    assert stubborn.returncode == -9 and not (tmp_path / "stubborn").exists()
    assert waited >= 2.0                     # the stubborn one had its time before the kill
    stop_nodes(polite, timeout=2.0)         # runs that have ended already: nothing to do, no error
