"""AgentRun: one learner run's outputs, with no ROS in it: the run directory (fresh, or the
checkpoint's on resume), its logs (metrics.jsonl, progress.csv, TensorBoard scalars, console
progress), checkpoints when due, the wall clock across resumes, and the time split at the end.
Files and formats: :mod:`comper_agent.nodes.run_io`.
"""
from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Callable

from comper_msgs_py.service_client import ServiceError

from comper_agent.nodes import run_io

__all__ = ["AgentRun", "next_due", "resume_text", "changed_parameters", "unaccounted_notes"]


def next_due(step: int, every: int) -> int | None:
    """The first multiple of `every` after `step` (None when every is 0: never)."""
    return (step // every + 1) * every if every > 0 else None


def resume_text(step: int) -> str:
    """How a run starts, for the start line: 'resuming at step N' or 'fresh run'."""
    return f"resuming at step {step}" if step else "fresh run"


def unaccounted_notes(rec: dict, elapsed: float, steps: int) -> tuple[str, str]:
    """Time split notes (:meth:`AgentRun.report_time_split`): the session's time that no phase accounts for
    (the loop, logging), added to `rec` as ``unaccounted_s``."""
    accounted = sum(v["seconds"] for k, v in rec["phases"].items()
                    if not k.endswith("_server") and k != "qt_model_rebuild")
    rec["unaccounted_s"] = elapsed - accounted
    return (f" | unaccounted (loop, logging) {elapsed - accounted:.1f} s",
            " (part of the sim / memory / qt phases); qt_server = time inside the QT trainer's reductions "
            "(part of qt); qt_model_rebuild runs in the executor thread")


#: parameters a resume is expected to change (where the run goes on from, and how far)
RESUME_CHANGES = frozenset({"resume", "run_id", "runs_root", "total_steps", "total_frames", "max_steps"})


def changed_parameters(saved: dict, now: dict, ignore=RESUME_CHANGES) -> list[str]:
    """'name old -> new' for each parameter of ``now`` whose value differs from the checkpoint's
    ``saved`` config ({"params": ..., "learner": ...}; older checkpoints without it: none). Lists and
    tuples compare by value."""
    def norm(v):
        return list(v) if isinstance(v, (list, tuple)) else v

    out = []
    for part in ("params", "learner"):
        old, new = saved.get(part) or {}, now.get(part) or {}
        out += [f"{k} {old[k]!r} -> {new[k]!r}" for k in sorted(new)
                if k in old and k not in ignore and norm(old[k]) != norm(new[k])]
    return out


class AgentRun:
    """p: the node's AgentRunConfig (runs_root, run_id, resume, keep_checkpoints, tensorboard,
    progress_period_s); seed: the learner's seed (for the default run id). Resolving ``resume``
    loads the checkpoint (``resume_state``), whose algorithm and task must match."""

    def __init__(self, p, seed: int):
        self.p = p
        self.resume_state = None
        self.resume_path = None
        self.resume_note = None      # why resume goes back past latest.pt (run_io.resume_checkpoint), for the log
        run_id, runs_root = p.run_id, Path(p.runs_root)
        if p.resume:
            ck, self.resume_state, self.resume_note = run_io.resume_checkpoint(p.resume)
            meta = self.resume_state["run"]
            if meta["algorithm"] != p.algorithm or meta["env_id"] != p.env_id:
                raise ValueError(f"{ck} is a {meta['algorithm']} run on {meta['env_id']}; start with "
                                 f"-p algorithm:={meta['algorithm']} -p env_id:={meta['env_id']}")
            run_id = meta["run_id"]
            runs_root = ck.parent.parent.parent
            self.resume_path = ck
        self.run_id = run_id or run_io.default_run_id(p.algorithm, p.env_id, seed)
        self.dir = run_io.RunDir(runs_root, self.run_id)
        self.wall_offset = 0.0
        self.t_start = time.monotonic()
        self.next_ck: int | None = None
        self.ck_every = 0

    # --- logs -------------------------------------------------------------------------------
    def open_logs(self, config: dict, csv_columns: list, progress_total: int, start_step: int) -> None:
        """config.yaml, then the logs; the wall clock of this session starts here."""
        d = self.dir
        d.write_config(config)
        self.metrics = run_io.MetricsLog(d.file("metrics.jsonl"))
        self.csv = run_io.CsvLog(d.file("progress.csv"), csv_columns)
        self.scalars = run_io.ScalarLog(d.file("tb") if self.p.tensorboard else None)
        self.progress = run_io.Progress(progress_total, self.p.progress_period_s, start_step=start_step)
        self.t_start = time.monotonic()

    def close_logs(self) -> None:
        self.metrics.close()
        self.csv.close()
        self.scalars.close()

    def wall_time(self) -> float:
        """Seconds of training over every session of this run (resumes included)."""
        return self.wall_offset + (time.monotonic() - self.t_start)

    # --- checkpoints ------------------------------------------------------------------------
    def save(self, state: dict, step: int) -> Path:
        path = self.dir.save_checkpoint(state, step, self.p.keep_checkpoints)
        self.metrics.flush()
        return path

    def schedule_checkpoints(self, every: int, step: int) -> None:
        self.ck_every = every
        self.next_ck = next_due(step, every)

    def checkpoint_due(self, step: int) -> bool:
        """True (once per period) when a periodic checkpoint is due at `step`."""
        if self.next_ck is None or step < self.next_ck:
            return False
        self.next_ck += self.ck_every
        return True

    # --- time split -------------------------------------------------------------------------
    def report_time_split(self, timers: run_io.PhaseTimers, elapsed: float, steps: int, calls: int,
                          probe: Callable[[], object] | None, probe_calls: int,
                          notes: Callable[[dict, float, int], tuple[str, str]], log) -> dict:
        """The time split at the end of a session: :meth:`time_split`, completed by the node's
        `notes(rec, elapsed, steps)` (fields added to rec, texts appended to the two log lines), on
        the console (`log`) and in metrics.jsonl ('timers'). Returns the record."""
        rec = self.time_split(timers, elapsed, steps, calls, probe, probe_calls)
        split_note, estimate_note = notes(rec, elapsed, steps)
        log.info(f"time split over {elapsed:.1f} s, {steps} steps ({rec['steps_per_s']:.1f} steps/s): "
                 + timers.summary(elapsed) + split_note)
        log.info(f"estimates: ROS round trip {rec['ros_round_trip_ms']:.2f} ms/call x {calls} calls = "
                 f"{rec['transport_estimate_s']:.1f} s transport" + estimate_note)
        self.metrics.write("timers", **rec)
        return rec

    def time_split(self, timers: run_io.PhaseTimers, elapsed: float, steps: int, calls: int,
                   probe: Callable[[], object] | None, probe_calls: int) -> dict:
        """The time split record: phases, rate, and the ROS transport share estimated from
        `probe_calls` small service calls (`probe`; None or a failing probe = not estimated)."""
        probe_ms = float("nan")
        if probe is not None and probe_calls > 0:
            try:
                t0 = time.perf_counter()
                for _ in range(probe_calls):
                    probe()
                probe_ms = 1000.0 * (time.perf_counter() - t0) / probe_calls
            except ServiceError:     # no answer, refused, or the context shut down: no estimate
                pass
        transport_s = probe_ms / 1000.0 * calls if math.isfinite(probe_ms) else float("nan")
        rate = steps / elapsed if elapsed > 0 else float("nan")
        return {"elapsed_s": elapsed, "steps": steps, "steps_per_s": rate, "phases": timers.as_dict(),
                "ros_round_trip_ms": probe_ms, "service_calls": calls, "transport_estimate_s": transport_s}
