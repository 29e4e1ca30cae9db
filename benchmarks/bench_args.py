"""Command-line options and process handling shared by the benchmarks (imported from the scripts' own folder)."""
from __future__ import annotations

import argparse
import os
import signal
import subprocess
import time
from pathlib import Path


def add_blas_threads(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--blas-threads", type=int, default=0,
                    help="numpy's OpenBLAS threads (0: the library's default, as the recorded figures; "
                         "memory_node's blas_threads default is 1)")


def apply_blas_threads(args: argparse.Namespace) -> None:
    if args.blas_threads:
        from comper_msgs_py.blas import set_numpy_blas_threads
        print(f"[bench] numpy BLAS threads: {set_numpy_blas_threads(args.blas_threads)}", flush=True)


def stop_node(proc: subprocess.Popen, timeout: float = 20.0) -> None:
    """SIGINT to a node started with start_new_session=True (its whole process group), SIGKILL after timeout."""
    stop_nodes([proc], timeout)


def _signal_group(proc: subprocess.Popen, sig: int) -> None:
    try:
        os.killpg(proc.pid, sig)
    except ProcessLookupError:
        pass


def stop_nodes(procs: list[subprocess.Popen], timeout: float) -> None:
    """Stop nodes started with start_new_session=True (a terminal's Ctrl-C does not reach them): SIGINT to
    every process group at once, so each node saves its final checkpoint and summary as on its own Ctrl-C,
    then SIGKILL to any still running after `timeout` seconds. An interrupt while waiting sends a second
    SIGINT (the nodes' quick stop) and waits at most 30 s more."""
    live = [p for p in procs if p.poll() is None]
    for p in live:
        _signal_group(p, signal.SIGINT)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and any(p.poll() is None for p in live):
        try:
            time.sleep(0.2)
        except KeyboardInterrupt:
            for p in live:
                if p.poll() is None:
                    _signal_group(p, signal.SIGINT)
            deadline = min(deadline, time.monotonic() + 30.0)
    for p in live:
        if p.poll() is None:
            _signal_group(p, signal.SIGKILL)
            p.wait()


def stop_runs(procs: list[subprocess.Popen], timeout: float) -> None:
    """A benchmark's Ctrl-C or SIGTERM: the runs in progress get their own Ctrl-C (final checkpoint and
    summary) instead of running on without the benchmark in sessions of their own."""
    if procs:
        print(f"[bench] interrupted: stopping {len(procs)} run(s) in progress (each saves a final checkpoint; "
              f"up to {timeout:.0f} s, Ctrl-C again to stop them sooner)", flush=True)
        stop_nodes(procs, timeout)


def raise_on_sigterm() -> None:
    """SIGTERM ends a benchmark as Ctrl-C does (KeyboardInterrupt), so it stops its nodes first."""
    def _interrupt(signum, frame):
        raise KeyboardInterrupt(f"signal {signum}")
    signal.signal(signal.SIGTERM, _interrupt)


def rows_per_run(runs: list, measure, line, json_path=None) -> int:
    """The offline run tools' loop: measure(run) -> a row per run folder, printed with line(row); a run that
    cannot be read (OSError, ValueError, KeyError) is named on stderr and skipped. Writes the rows as JSON to
    json_path if given. Exit status 0 if any row was measured."""
    import json
    import sys
    rows = []
    for run in runs:
        try:
            rows.append(measure(run))
        except (OSError, ValueError, KeyError) as exc:
            print(f"{run}: skipped: {exc}", file=sys.stderr)
            continue
        print(line(rows[-1]), flush=True)
    if json_path is not None:
        json_path.write_text(json.dumps(rows, indent=1) + "\n")
    return 0 if rows else 1


def last_checkpoint(run, algorithms: tuple, why: str):
    """(config.yaml's dict, the last checkpoint's path, its state) of a finished run folder, for the offline run
    tools; a run of another algorithm is refused with ValueError ("<run>: algorithm X <why>")."""
    import yaml
    from comper_agent.core.checkpoint import load_checkpoint
    from comper_agent.nodes.run_io import resolve_checkpoint
    cfg = yaml.safe_load((Path(run) / "config.yaml").read_text())
    if cfg["algorithm"] not in algorithms:
        raise ValueError(f"{run}: algorithm {cfg['algorithm']} {why}")
    ckpt = resolve_checkpoint(run)
    return cfg, ckpt, load_checkpoint(ckpt)


def checkpoint_replay(ckpt: Path, state: dict) -> tuple[str, Path]:
    """(kind, path) of the replay contents saved with a checkpoint (run_io.RunOutputs.REPLAY_SUFFIXES): kind
    local -> the replay buffer's .npz, kind memory -> the memory snapshot folder (the recorded path, or the one
    beside the checkpoint when the run folder has moved since). ValueError when the checkpoint holds none."""
    replay = state.get("replay") or {}
    if replay.get("kind") == "local":
        return "local", ckpt.parent / replay["file"]
    if replay.get("kind") == "memory":
        snap = Path(replay["path"])
        return "memory", snap if snap.exists() else ckpt.parent / replay["request"]
    raise ValueError(f"{ckpt}: the checkpoint holds no replay contents (run with checkpoint_replay)")


def resume_status(run_dir: Path, budget: int | None = None) -> str:
    """What a second start of a split sweep does with a run folder: 'new' (no checkpoint yet: start it from
    nothing), 'done' (its last checkpoint is at or past ``budget``, counted in frames where the run counts
    frames, else agent steps; None: never done by this test) or 'continue' (a checkpoint before its budget
    that holds the memory / replay contents: start it with ``resume``). The checkpoint is the one the node's
    resume takes (run_io.resume_checkpoint: past a final checkpoint that a failed service left without them,
    to the newest that holds them). ValueError for a checkpoint before its budget without them (older code,
    or checkpoint_replay off): going on from an empty memory would change what the run learns from."""
    from comper_agent.nodes.run_io import resume_checkpoint
    if not (Path(run_dir) / "checkpoints" / "latest.pt").exists():
        return "new"
    _, state, _ = resume_checkpoint(run_dir)
    counters = state.get("counters") or {}
    if budget is not None and counters.get("frames", counters.get("step", 0)) >= budget:
        return "done"
    if "replay" not in state:
        raise ValueError(f"{run_dir} stopped before its budget and its checkpoint holds no memory / replay "
                         "contents; remove the folder to run it again from the start")
    return "continue"


def offline_parser(doc: str, runs_help: str) -> argparse.ArgumentParser:
    """The offline run tools' command line: run folders, --seed of their draws, --json for the rows."""
    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path, help=runs_help)
    ap.add_argument("--seed", type=int, default=0, help="seed of the draws")
    ap.add_argument("--json", type=Path, default=None, help="also write the rows here")
    return ap
