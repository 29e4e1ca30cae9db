"""Run outputs shared by the learner nodes (COMCACT now, COMPER later); no ROS imports.

A run directory ``<runs_root>/<run_id>/`` holds:

* ``config.yaml``     every parameter of the run (written once at start; rewritten on resume)
* ``metrics.jsonl``   one JSON object per event: ``{"kind": "episode"|"eval"|"progress"|"timers", ...}``
* ``progress.csv``    one row per evaluation point (step, wall time, mean/std return, ...)
* ``tb/``             TensorBoard scalars (if tensorboard is importable)
* ``checkpoints/``    ``step_<N>.pt`` and ``latest.pt``, written atomically, loadable with
  ``torch.load(path, weights_only=True)`` (see :mod:`comper_agent.core.checkpoint`)

Pieces: :class:`RunDir`, :class:`MetricsLog`, :class:`CsvLog`, :class:`ScalarLog`,
:class:`Progress` (rate-limited console line with steps/s and ETA), :class:`PhaseTimers`,
:func:`resolve_checkpoint`, :func:`resume_checkpoint`, :func:`rng_state` / :func:`set_rng_state`,
:func:`default_run_id`.
"""
from __future__ import annotations

import csv
import json
import math
import os
import random
import shutil
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Callable

import numpy as np

__all__ = ["RunDir", "MetricsLog", "CsvLog", "ScalarLog", "Progress", "PhaseTimers",
           "resolve_checkpoint", "resume_checkpoint", "REPLAY_SKIPPED", "rng_state", "set_rng_state",
           "default_run_id", "format_duration", "write_text_atomic"]


def default_run_id(algorithm: str, env_id: str, seed: int, now: float | None = None) -> str:
    """``<algorithm>-<env>-s<seed>-<YYYYmmdd-HHMMSS>`` with the env id made path-safe."""
    stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime(now))
    env = env_id.replace("/", "_")
    return f"{algorithm}-{env}-s{seed}-{stamp}"


def format_duration(seconds: float) -> str:
    if not math.isfinite(seconds) or seconds < 0:
        return "?"
    seconds = int(round(seconds))
    h, rem = divmod(seconds, 3600)
    m, s = divmod(rem, 60)
    return f"{h}h{m:02d}m" if h else (f"{m}m{s:02d}s" if m else f"{s}s")


def write_text_atomic(path: str | os.PathLike, text: str) -> Path:
    from comper_agent.core.checkpoint import write_atomic
    return write_atomic(path, lambda f: f.write(text.encode("utf-8")))


def _plain(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    return x


class RunDir:
    """The folder of one run: paths, config.yaml, checkpoint names."""

    def __init__(self, root: str | os.PathLike, run_id: str):
        self.run_id = run_id
        self.path = Path(root) / run_id
        self.path.mkdir(parents=True, exist_ok=True)
        self.checkpoints = self.path / "checkpoints"

    def remove_if_empty(self) -> None:
        """Remove the run directory if nothing was written into it (empty sub-folders count as nothing)."""
        for d in sorted((x for x in self.path.rglob("*") if x.is_dir()), key=lambda x: -len(x.parts)):
            if not any(d.iterdir()):
                d.rmdir()
        if self.path.is_dir() and not any(self.path.iterdir()):
            self.path.rmdir()

    def file(self, name: str) -> Path:
        return self.path / name

    def write_config(self, config: dict) -> Path:
        import yaml
        return write_text_atomic(self.path / "config.yaml",
                                 yaml.safe_dump(_plain(config), sort_keys=True, default_flow_style=None))

    def checkpoint_path(self, step: int) -> Path:
        return self.checkpoints / f"step_{int(step):09d}.pt"

    #: a checkpoint's replay contents beside step_<N>.pt: kind local (a learner's own replay buffer) ->
    #: step_<N>.replay.npz, kind memory (the snapshot folder an embedded memory node writes; its snapshot_root
    #: is the checkpoints folder) -> step_<N>.memory
    REPLAY_SUFFIXES = {"local": ".replay.npz", "memory": ".memory"}

    def replay_path(self, step: int, kind: str) -> Path:
        """Where the checkpoint of `step` keeps its replay contents of `kind` (REPLAY_SUFFIXES)."""
        return self.checkpoint_path(step).with_suffix(self.REPLAY_SUFFIXES[kind])

    def companions(self, checkpoint: Path) -> list[Path]:
        """The replay contents' paths beside `checkpoint` (one per kind, :meth:`replay_path`), present or not."""
        return [checkpoint.with_suffix(x) for x in self.REPLAY_SUFFIXES.values()]

    def save_checkpoint(self, state: dict, step: int, keep_last: int = 3) -> Path:
        """Write ``step_<N>.pt`` and ``latest.pt`` atomically; keep the newest `keep_last` step files
        (and their replay contents, :meth:`replay_path`), and the newest step file whose replay contents
        are beside it, so that a run whose last checkpoints could not save them (:data:`REPLAY_SKIPPED`)
        keeps one to resume from."""
        from comper_agent.core.checkpoint import save_checkpoint
        path = save_checkpoint(self.checkpoint_path(step), state)
        save_checkpoint(self.checkpoints / "latest.pt", state)
        if keep_last > 0:
            steps = sorted(self.checkpoints.glob("step_*.pt"))
            with_replay = [p for p in steps if any(c.exists() for c in self.companions(p))]
            for p in steps[:-keep_last]:
                if with_replay and p == with_replay[-1]:
                    continue
                for companion in (p, *self.companions(p)):
                    if companion.is_dir():
                        shutil.rmtree(companion, ignore_errors=True)
                    else:
                        companion.unlink(missing_ok=True)
        return path


#: the key of a checkpoint written without the experience its run saves (a service failed, so the final
#: checkpoint holds weights and counters only, or the memory node gave no snapshot): its value says why
REPLAY_SKIPPED = "replay_skipped"


def resume_checkpoint(path: str | os.PathLike) -> tuple[Path, dict, str | None]:
    """The checkpoint a run continues from, loaded: ``(file, state, note)``. A run directory or checkpoints
    folder resolves to ``latest.pt``, except where that checkpoint was written without its run's experience
    (:data:`REPLAY_SKIPPED`: a service failed at the end) and an older ``step_<N>.pt`` of the folder holds
    it: the newest such one, so that the weights and the memory / replay contents the run continues with are
    from the same step (the steps after it are run again); `note` then says so. A file given by name is
    loaded as it is."""
    from comper_agent.core.checkpoint import load_checkpoint
    ck = resolve_checkpoint(path)
    state = load_checkpoint(ck)
    if Path(path).expanduser().is_file() or REPLAY_SKIPPED not in state:
        return ck, state, None
    for older in sorted(ck.parent.glob("step_*.pt"), reverse=True):
        older_state = load_checkpoint(older)
        if "replay" in older_state:
            return older, older_state, (
                f"{ck.name} (step {state.get('counters', {}).get('step')}) holds no memory / replay contents "
                f"({state[REPLAY_SKIPPED]}); continuing from {older.name}, the newest checkpoint that holds them")
    return ck, state, None


def resolve_checkpoint(path: str | os.PathLike) -> Path:
    """A checkpoint file, or a run directory (-> its checkpoints/latest.pt), or a checkpoints folder.

    Raises FileNotFoundError with a message saying what was looked for."""
    p = Path(path).expanduser()
    candidates = [p] if p.is_file() else [p / "checkpoints" / "latest.pt", p / "latest.pt"]
    for c in candidates:
        if c.is_file():
            return c
    raise FileNotFoundError(
        f"no checkpoint at {p}: give a .pt file or a run directory holding checkpoints/latest.pt "
        f"(looked for {', '.join(str(c) for c in candidates)})")


class MetricsLog:
    """Append-only JSON-lines log; each line is flushed (a killed run keeps what it wrote)."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f = open(self.path, "a", buffering=1)

    def write(self, kind: str, **fields) -> None:
        if self._f.closed:
            return
        rec = {"kind": kind, **_plain(fields)}
        self._f.write(json.dumps(rec, allow_nan=True) + "\n")

    def flush(self) -> None:
        if not self._f.closed:
            self._f.flush()
            os.fsync(self._f.fileno())

    def close(self) -> None:
        if not self._f.closed:
            self.flush()
            self._f.close()

    @staticmethod
    def read(path: str | os.PathLike, kind: str | None = None, *, missing_ok: bool = False) -> list[dict]:
        """Records of `kind` (all when None); missing_ok: [] for a file not written yet (a run starting)."""
        out = []
        if missing_ok and not os.path.exists(path):
            return out
        with open(path) as f:
            for line in f:
                line = line.strip()
                if not line:
                    continue
                try:
                    rec = json.loads(line)
                except json.JSONDecodeError:   # a torn last line after a crash
                    continue
                if kind is None or rec.get("kind") == kind:
                    out.append(rec)
        return out


class CsvLog:
    """A CSV file with fixed columns (header written once; appending to an existing file keeps it)."""

    def __init__(self, path: str | os.PathLike, columns: list[str]):
        self.path = Path(path)
        self.columns = list(columns)
        new = not self.path.exists() or self.path.stat().st_size == 0
        self._f = open(self.path, "a", newline="", buffering=1)
        self._w = csv.DictWriter(self._f, fieldnames=self.columns, extrasaction="ignore")
        if new:
            self._w.writeheader()

    def write(self, **row) -> None:
        if not self._f.closed:
            self._w.writerow(_plain(row))

    def close(self) -> None:
        if not self._f.closed:
            self._f.flush()
            self._f.close()


class ScalarLog:
    """TensorBoard scalars; a no-op (with `available` False) when tensorboard cannot be imported."""

    def __init__(self, logdir: str | os.PathLike | None, flush_secs: int = 10):
        self.writer = None
        self.error = ""
        if logdir is None:
            return
        try:
            from torch.utils.tensorboard import SummaryWriter
            self.writer = SummaryWriter(str(logdir), flush_secs=flush_secs)
        except Exception as exc:   # tensorboard missing or broken: logging must not stop a run
            self.error = f"{type(exc).__name__}: {exc}"

    @property
    def available(self) -> bool:
        return self.writer is not None

    def scalar(self, tag: str, value: float, step: int) -> None:
        if self.writer is not None and value is not None and math.isfinite(float(value)):
            self.writer.add_scalar(tag, float(value), int(step))

    def scalars(self, values: dict, step: int, prefix: str = "") -> None:
        for k, v in values.items():
            if isinstance(v, (int, float, np.floating, np.integer)):
                self.scalar(prefix + k, float(v), step)

    def flush(self) -> None:
        if self.writer is not None:
            self.writer.flush()

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None


class Progress:
    """Rate-limited progress line: step/total, steps/s (recent window), last episode and eval return, ETA.

    ``tick(step)`` returns the line when `period_s` has passed since the last one (else None); the
    caller logs it. ``clock`` is injectable for tests."""

    def __init__(self, total_steps: int, period_s: float = 5.0, start_step: int = 0,
                 clock: Callable[[], float] = time.monotonic):
        self.total = int(total_steps)
        self.period = float(period_s)
        self.clock = clock
        self.t0 = clock()
        self.step0 = int(start_step)
        self._last_t = self.t0
        self._last_step = int(start_step)
        self.rate = float("nan")
        self.last_episode_return: float | None = None
        self.episodes = 0
        self.last_eval: float | None = None
        self.extra: dict[str, str] = {}

    def episode(self, ret: float) -> None:
        self.episodes += 1
        self.last_episode_return = float(ret)

    def evaluation(self, mean_return: float) -> None:
        self.last_eval = float(mean_return)

    def overall_rate(self, step: int) -> float:
        dt = self.clock() - self.t0
        return (step - self.step0) / dt if dt > 0 else float("nan")

    def line(self, step: int) -> str:
        now = self.clock()
        dt = now - self._last_t
        if dt > 0 and step > self._last_step:
            self.rate = (step - self._last_step) / dt
        self._last_t, self._last_step = now, step
        rate = self.rate if math.isfinite(self.rate) and self.rate > 0 else self.overall_rate(step)
        eta = (self.total - step) / rate if rate and math.isfinite(rate) and rate > 0 else float("nan")
        ep = "-" if self.last_episode_return is None else f"{self.last_episode_return:.1f}"
        ev = "-" if self.last_eval is None else f"{self.last_eval:.1f}"
        parts = [f"step {step}/{self.total} ({100.0 * step / max(1, self.total):.0f}%)",
                 f"{rate:.0f} steps/s" if math.isfinite(rate) else "? steps/s",
                 f"episodes {self.episodes}", f"last return {ep}", f"last eval {ev}",
                 f"ETA {format_duration(eta)}"]
        parts += [f"{k} {v}" for k, v in self.extra.items()]
        return " | ".join(parts)

    def tick(self, step: int) -> str | None:
        if self.clock() - self._last_t >= self.period:
            return self.line(step)
        return None


class PhaseTimers:
    """Accumulated wall time and call counts per named phase.

        with timers("sim"): ...
        timers.add("ros_transport", 0.01)
        timers.summary(total_s)  -> "sim 40.1% (12.0 s, 5000 x 2.4 ms) | ..."
    """

    def __init__(self):
        self.seconds: dict[str, float] = {}
        self.calls: dict[str, int] = {}

    @contextmanager
    def __call__(self, name: str):
        t = time.perf_counter()
        try:
            yield
        finally:
            self.add(name, time.perf_counter() - t)

    def add(self, name: str, seconds: float, calls: int = 1) -> None:
        self.seconds[name] = self.seconds.get(name, 0.0) + float(seconds)
        self.calls[name] = self.calls.get(name, 0) + int(calls)

    def as_dict(self) -> dict:
        return {k: {"seconds": self.seconds[k], "calls": self.calls.get(k, 0)} for k in self.seconds}

    def summary(self, total_s: float | None = None) -> str:
        total = total_s if total_s and total_s > 0 else sum(self.seconds.values())
        parts = []
        for k, s in sorted(self.seconds.items(), key=lambda kv: -kv[1]):
            n = self.calls.get(k, 0)
            per = f", {n} x {1000.0 * s / n:.2f} ms" if n else ""
            parts.append(f"{k} {100.0 * s / total if total else 0:.1f}% ({s:.1f} s{per})")
        return " | ".join(parts)


def rng_state() -> dict:
    """Python, numpy (global) and torch CPU generator states, in weights_only-loadable form."""
    import torch
    py = random.getstate()
    npst = np.random.get_state()
    return {"python": [py[0], list(py[1]), py[2]],
            "numpy": {"name": npst[0], "keys": torch.from_numpy(np.asarray(npst[1]).astype(np.int64)),
                      "pos": int(npst[2]), "has_gauss": int(npst[3]), "cached_gaussian": float(npst[4])},
            "torch": torch.get_rng_state()}


def set_rng_state(state: dict) -> None:
    import torch
    py = state["python"]
    random.setstate((py[0], tuple(py[1]), py[2]))
    n = state["numpy"]
    np.random.set_state((n["name"], n["keys"].numpy().astype(np.uint32), n["pos"], n["has_gauss"],
                         n["cached_gaussian"]))
    torch.set_rng_state(state["torch"])
