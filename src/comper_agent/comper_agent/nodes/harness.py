"""harness: the run plumbing a learner node calls; the learner node holds the algorithm and its loop.

A learner node (:mod:`comper_agent.nodes.comcact_node`, :mod:`comper_agent.nodes.comper_node`) is an rclpy
``Node`` that reads top to bottom: it declares its parameters (:func:`declare_learner_parameters`), decides what
its algorithm needs, builds a :class:`LearnerHarness` (bring-up, clients, run directory, topics, memory link),
then runs its own loop and calls the harness for what every learner does alike: resume, logs, checkpoints and
progress lines (:meth:`LearnerHarness.after_step`), the guarded loop and its end, summary, shutdown. Nothing here
calls into the algorithm but the functions a call passes (the task check, the checkpoint's state, the time
split's notes). Collaborators: :class:`~comper_agent.nodes.agent_run.AgentRun` (outputs),
:class:`~comper_agent.nodes.experience_checkpoint.ExperienceCheckpoint`, :mod:`comper_agent.nodes.episodes`,
:mod:`comper_agent.nodes.evaluation`, :class:`~comper_agent.nodes.memory_link.MemoryLink`,
:class:`~comper_agent.recording.recording_link.RecordingLink`; the entry point is :mod:`comper_agent.nodes.agent_main`.
"""
from __future__ import annotations

import functools
import json
import threading
import time
from pathlib import Path
from typing import Callable

from rclpy.node import Node

from comper_msgs_py.params import config_to_dict
from comper_msgs_py.qos import HAND_OVER_S
from comper_msgs_py.ros_params import declare_config, refuse_undeclared
from comper_msgs_py.service_client import ServiceError, wait_for_services
from comper_sim.client import SimClient

from comper_agent.core.config import thesis_differences
from comper_agent.nodes import run_io
from comper_agent.nodes.agent_run import AgentRun, changed_parameters
from comper_agent.nodes.bringup import START_HINTS, Spinner, make_embedded_nodes, seeded_sampling
from comper_agent.nodes.episodes import LearnerTopics, TrainingEpisodes
from comper_agent.nodes.evaluation import Evaluation
from comper_agent.nodes.experience_checkpoint import ExperienceCheckpoint
from comper_agent.nodes.memory_link import MemoryLink
from comper_agent.nodes.qt_diagnostics import QTDiagnostics
from comper_agent.recording.recording_link import RecordingLink, record_topics

__all__ = ["LearnerHarness", "declare_learner_parameters", "profile_overrides"]

#: phases made of service calls (the time split's transport estimate counts them)
TIMED_CALLS = ("sim", "memory", "qt", "memory_reduce")


def profile_overrides(spec, values: dict) -> tuple[str | None, dict]:
    """The profile a learner node's parameters name and the defaults it sets, for node and learner parameters
    alike. spec: the node class (``PROFILES``: profile -> {field: (value, source)}, ``RESOLVE_PROFILE``: resolves
    ``auto`` and refuses unknown names); values: the node parameters declared so far (algorithm, env_id and
    profile come first). (None, {}) before ``profile`` is declared or for a node without profiles."""
    if not spec.PROFILES or "profile" not in values:
        return None, {}
    name = spec.RESOLVE_PROFILE(values["profile"], values)
    return name, {k: v for k, (v, _) in spec.PROFILES[name].items()}


def declare_learner_parameters(node: Node, spec):
    """Declares a learner node's parameters: its node parameters (``spec.CONFIG``), then its learner's
    hyper-parameters (``spec.LEARNER_CONFIGS[algorithm]``, ``variant`` set from ``algorithm``, defaults from
    ``spec.LEARNER_OVERRIDES`` and the profile). The command line and parameter files win over a profile.
    Returns (node parameters, learner hyper-parameters, profile name or None)."""
    p = declare_config(node, spec.CONFIG, overrides=lambda values: profile_overrides(spec, values)[1],
                       declare_first=("algorithm", "env_id", "profile"))
    profile, defaults = profile_overrides(spec, config_to_dict(p))
    cfg = declare_config(node, spec.LEARNER_CONFIGS[p.algorithm],
                         overrides={"variant": p.algorithm, **spec.LEARNER_OVERRIDES, **defaults})
    if cfg.variant != p.algorithm:
        raise ValueError(f"variant:={cfg.variant} contradicts algorithm:={p.algorithm}; set algorithm only")
    return p, cfg, profile


class LearnerHarness:
    """The run plumbing of one learner node. Construction prepares the run directory, brings up the embedded
    nodes (``bringup:=embedded``) and the recorder (``record:=true``), starts the executor threads, connects
    the service clients and checks the task (`check_env(info)` -> config.yaml's env description; raising
    refuses the start and leaves no run directory).

    node: the learner's rclpy node; spec: its class (``NODE_NAME``, ``PROFILES``, ``QT_START_HINT``); p, cfg,
    profile: from :func:`declare_learner_parameters`; uses_memory / uses_qt / reducer ('qt_trainer', 'memory',
    'none'): what the algorithm talks to; embedded_params: extra parameters of the embedded sim, memory and QT
    trainer nodes; obs_dtype: the training observations' dtype. The learner uses ``p``, ``cfg``, ``log``,
    ``stop_event`` (the first Ctrl-C), ``ptimers``, ``run_id``, ``run_dir``, ``outputs``, ``topics``, ``sim``,
    ``episode_rule``, ``obs_shape``, ``env`` (TrainingEpisodes), ``mem`` (MemoryLink or None), ``experience``;
    once the logs are open ``metrics``, ``csv``, ``scalars``, ``progress``, ``diagnostics``."""

    HAND_OVER_S = HAND_OVER_S   # comper_msgs_py.qos: the longest wait for the last results to be acknowledged

    def __init__(self, node: Node, spec, p, cfg, profile: str | None, *, uses_memory: bool, uses_qt: bool,
                 reducer: str, check_env: Callable[[object], dict],
                 embedded_params: tuple[dict, dict, dict] = ({}, {}, {}), obs_dtype=None):
        self.node, self.p, self.cfg, self.profile, self.profiles = node, p, cfg, profile, spec.PROFILES
        self.program = spec.NODE_NAME
        self.uses_memory, self.reducer = uses_memory, reducer
        self.stop_event = threading.Event()
        self.ptimers = run_io.PhaseTimers()
        self.log = node.get_logger()
        self.evaluation = None
        # the run directory; on resume, it and the run id come from the checkpoint
        self.outputs = AgentRun(p, int(cfg.seed))
        self.run_id, self.run_dir = self.outputs.run_id, self.outputs.dir
        # publishers / subscriptions (served by the background executor)
        self.topics = LearnerTopics(node, self.run_id, p.env_id, p.publish_transitions, self.ptimers, self.stop_event)
        self.mem = (MemoryLink(node, p, reducer=reducer, uses_qt=uses_qt, timers=self.ptimers, device=cfg.device)
                    if uses_memory else None)
        self.experience = ExperienceCheckpoint(self)
        self._bring_up(embedded_params, obs_dtype, getattr(spec, "QT_START_HINT", ""), check_env)

    # ------------------------------------------------------------------------------ set-up
    def _bring_up(self, embedded_params, obs_dtype, qt_start_hint: str, check_env) -> None:
        """The embedded nodes (bringup:=embedded), the recording link (record:=true), the executor
        threads, then the service clients."""
        p, node = self.p, self.node
        self.embedded = None
        self.recording = None
        nodes: list[Node] = [node]
        if p.bringup == "embedded":
            sim, mem, qt = embedded_params
            if p.checkpoint_replay and self.uses_memory:     # checkpoints hold the memory: step_<N>.memory
                mem = {"snapshot_root": str(self.run_dir.checkpoints), **mem}
            mem = seeded_sampling(mem, int(self.cfg.seed), node._parameter_overrides)
            self.embedded = make_embedded_nodes(
                node.context, sim_name=p.sim_node,
                sim_params={"env_id": p.env_id, "episode_end": p.episode_end, "run_id": self.run_id,
                            "seed": int(self.cfg.seed), **sim},
                memory_name=p.memory_node if self.uses_memory else None, memory_params=mem,
                qt_name=p.qt_trainer_node if self.reducer == "qt_trainer" else None,
                qt_params={"memory_node": p.memory_node, "reduce_batch": int(p.reduce_batch), **qt})
            nodes += self.embedded.all
        try:
            # every node built from this command line has declared its parameters: a -p none declares is a typo
            refuse_undeclared(nodes, self.program)
            if p.record:
                topics = record_topics(node.get_fully_qualified_name(), p.sim_node,
                                       p.memory_node if self.uses_memory else None)
                self.recording = self.topics.recording = RecordingLink(node, p, self.run_id, self.run_dir, topics)
                nodes += self.recording.nodes
        except BaseException:
            if self.embedded is not None:
                self.embedded.destroy()
            self.run_dir.remove_if_empty()      # a start refused here leaves no run directory behind
            raise
        self.spinner = Spinner(nodes, node.context).start()
        try:
            if self.recording is not None:
                self.recording.wait_subscribed()
            self._connect(obs_dtype, qt_start_hint, check_env)
        except BaseException:
            self.shutdown()
            raise

    def _connect(self, obs_dtype, qt_start_hint: str, check_env) -> None:
        """Service clients; wait for the services; check the sim's task."""
        p = self.p
        sim = p.sim_node.strip("/")
        self.sim = SimClient(self.node, f"/{sim}", timeout=p.service_timeout_s)
        # after a stop request a call whose server has gone (its bring-up stopping with this node) ends at
        # once instead of waiting out service_timeout_s
        for c in (self.sim, *((self.mem.memory, self.mem.reduction) if self.mem is not None else ())):
            c.stop = self.stop_event
        services = {"sim": self.sim.step_client(), **(self.mem.services() if self.mem is not None else {})}
        hints = {"sim": START_HINTS["sim"].format(name=sim),
                 "memory": START_HINTS["memory"].format(name=p.memory_node),
                 "qt_trainer": START_HINTS["qt_trainer"].format(name=p.qt_trainer_node) + qt_start_hint}
        wait_for_services(services, p.startup_timeout_s, hints, self.stop_event)
        info = self.sim.info(timeout=p.startup_timeout_s)
        if info.env_id != p.env_id:
            raise ValueError(f"the sim node /{sim} serves {info.env_id}, not env_id:={p.env_id}; "
                             f"set -p env_id:={info.env_id} or restart the sim node")
        self.episode_rule = info.episode_end or "standard"
        self.obs_shape = tuple(int(d) for d in info.observation_shape)
        self.env = TrainingEpisodes(self.sim, self.topics, self.outputs, self.ptimers, obs_dtype)
        self.env_description = check_env(info)

    def open_evaluation(self, policy, on_record, frame_skip: int = 1, **sim_params) -> Evaluation:
        """The evaluation on a separate environment (closed at shutdown)."""
        self.evaluation = Evaluation(self, policy, on_record, frame_skip, **sim_params)
        return self.evaluation

    rtm_size = property(lambda self: self.mem.rtm_size if self.mem is not None else 0)
    reductions = property(lambda self: self.mem.reductions if self.mem is not None else 0)

    def wall_time(self) -> float:
        return self.outputs.wall_time()

    # ------------------------------------------------------------------------------ checkpoints
    def state(self, learner, *, step: int, stored: int, **counters) -> dict:
        """What every learner's checkpoint holds: the run, the learner's weights, the counters (with `counters`),
        the evaluations, the random generators, the configuration and the embedded QT trainer."""
        ev = self.evaluation
        st = {"run": {"run_id": self.run_id, "algorithm": self.p.algorithm, "env_id": self.p.env_id},
              "learner": learner.state_dict(),
              "counters": {"step": step, "episodes": self.env.count, "stored": stored,
                           "reductions": self.reductions, "wall_time_s": self.wall_time(), **counters},
              "evals": list(ev.records) if ev is not None else [],
              "rng": run_io.rng_state(),
              "config": {"learner": {k: (list(v) if isinstance(v, tuple) else v)
                                     for k, v in config_to_dict(self.cfg).items()},
                         "params": config_to_dict(self.p)}}
        if self.embedded is not None and self.embedded.qt_trainer is not None:
            st["qt_trainer"] = self.embedded.qt_trainer.state_dict()
        return st

    def restore(self, state: dict, learner) -> dict:
        """The part of :meth:`state` every learner restores the same way; returns the counters."""
        learner.load_state_dict(state["learner"])
        c = state["counters"]
        self.env.count = int(c["episodes"])
        if self.evaluation is not None:
            self.evaluation.records = list(state.get("evals", []))
        if self.mem is not None:
            self.mem.reductions = int(c.get("reductions", 0))
        self.outputs.wall_offset = float(c.get("wall_time_s", 0.0))
        run_io.set_rng_state(state["rng"])
        qt_state = state.get("qt_trainer")
        if qt_state and self.embedded is not None and self.embedded.qt_trainer is not None:
            self.embedded.qt_trainer.load_state_dict(qt_state)
        return c

    def resume(self, restore: Callable[[dict], None]) -> bool:
        """On resume (``-p resume``): `restore(state)` puts the checkpoint back into the learner, a warning names
        the parameters that differ from the checkpoint's, the memory's or replay's contents come back. False
        when they cannot (the start ends with exit 1; nothing of the run is written yet)."""
        run = self.outputs
        if run.resume_state is None:
            return True
        if run.resume_note:
            self.log.warning(run.resume_note)
        restore(run.resume_state)
        changed = changed_parameters(run.resume_state.get("config") or {},
                                     {"params": config_to_dict(self.p), "learner": config_to_dict(self.cfg)})
        if changed:     # the command line's values apply; a profile or flag left out changes the run
            self.log.warning("resuming with parameters that differ from the checkpoint's: " + ", ".join(changed)
                             + " (the values given now apply; pass the checkpoint's to continue the same run)")
        try:
            self.experience.restore(run.resume_state.get("replay"))
        except RuntimeError as exc:      # a missing or unfit snapshot
            self.log.error(f"cannot resume: {exc}")
            return False
        return True

    def save(self, state: Callable[[], dict], step: int, final: bool = False, replay: bool = True,
             skipped: str = "") -> Path:
        """A checkpoint of `step`: the replay's contents first (checkpoint_replay; `replay` False skips them,
        `skipped` says why), then `state()` (taken after them: saving them may store steps still held) that
        names them. A checkpoint without the contents its run saves is marked (run_io.REPLAY_SKIPPED): pruning
        keeps the newest one that holds them, and a resume of the run goes back to it."""
        kept = self.experience.kept
        with self.ptimers("io"):
            saved = self.experience.save(step) if replay and kept else None
            st = state()
            if saved is not None:
                st["replay"] = saved
            elif kept:
                st[run_io.REPLAY_SKIPPED] = skipped or self.experience.error or "not saved"
            path = self.outputs.save(st, step)
        self.log.info(f"{'final ' if final else ''}checkpoint: {path}"
                      + (f" (with {self.experience.describe(saved)})" if saved is not None else "")
                      + (f" (weights and counters only: {st[run_io.REPLAY_SKIPPED]}; a resume of the run goes "
                         "back to the newest checkpoint that holds the memory / replay contents)"
                         if replay is False and run_io.REPLAY_SKIPPED in st else ""))
        return path

    # ------------------------------------------------------------------------------ the run
    def open_logs(self, config: dict, csv_columns: list, progress_total: int, step: int, start_line: str) -> None:
        """config.yaml (every parameter, the task, the profile, with `config`), metrics.jsonl, progress.csv,
        TensorBoard and the console's progress; the start line and the profile's differences from the thesis."""
        p, e, run = self.p, self.embedded, self.outputs
        run.open_logs({"algorithm": p.algorithm, "params": config_to_dict(p), "learner": config_to_dict(self.cfg),
                       "reducer": self.reducer,
                       "qt_trainer": config_to_dict(e.qt_trainer.qt_config) if e is not None and e.qt_trainer else None,
                       "memory": (config_to_dict(e.memory.config) if e is not None and e.memory is not None
                                  and hasattr(e.memory, "config") else None),
                       "resumed_from": str(run.resume_path) if run.resume_state is not None else None,
                       "env": self.env_description,
                       **({"profile": {"name": self.profile, "values": {
                           k: {"value": v, "source": src} for k, (v, src) in self.profiles[self.profile].items()}}}
                          if self.profiles else {}),
                       **config}, csv_columns, progress_total, step)
        self.metrics, self.csv, self.scalars, self.progress = run.metrics, run.csv, run.scalars, run.progress
        self.diagnostics = QTDiagnostics(p.diagnostics_every, self.metrics, self.scalars, self.ptimers)
        self.start_step = step
        self.log.info(f"{start_line}; run dir {run.dir.path}  (Ctrl-C stops and saves a checkpoint)")
        if self.profiles:
            diffs = thesis_differences(p, self.cfg, thesis=self.profiles["thesis"])
            self.log.info(f"profile {self.profile} (profile:=thesis is the thesis); differs from it in {len(diffs)} "
                          "values: " + ("; ".join(diffs) or "none"))
        if not self.scalars.available and p.tensorboard:
            self.log.warning(f"TensorBoard scalars off: {self.scalars.error}")

    def after_step(self, step: int, state: Callable[[], dict]) -> str | None:
        """In the loop, after each step: a checkpoint when due; the progress line when due (else None)."""
        if self.outputs.checkpoint_due(step):
            self.save(state, step)
        return self.progress.tick(step)

    def progress_record(self, line: str, step: int, x: int, last_update: dict, **fields) -> None:
        """The progress line on the console, its 'progress' record (`fields`, the last update's losses) and
        steps/s on TensorBoard at `x`."""
        self.log.info(line)
        self.metrics.write("progress", step=step, steps_per_s=self.progress.rate, wall_time_s=self.wall_time(),
                           **fields, **{k: v for k, v in last_update.items() if isinstance(v, float)})
        self.scalars.scalar("perf/steps_per_s", self.progress.rate, x)

    def memory_record(self, step: int, rec: dict, x: int | None = None, **fields) -> None:
        """A 'memory' record (`rec`: :meth:`experience_stats` and more) in metrics.jsonl, with `fields`; with `x`,
        its numbers on TensorBoard under memory/ at `x`."""
        self.metrics.write("memory", step=step, **fields, wall_time_s=self.wall_time(), **rec)
        if x is not None:
            self.scalars.scalars({k: v for k, v in rec.items() if isinstance(v, (int, float))}, x, prefix="memory/")

    def experience_stats(self, replay) -> dict:
        """What the learner samples from, for the 'memory' records: the memory's statistics (identities,
        transitions stored, bytes held, evictions, ...) or the size of the local `replay`."""
        if self.mem is None:
            return {"replay_size": len(replay), "replay_bytes": replay.nbytes}
        with self.ptimers("memory"):
            return self.mem.stats()

    def guard(self, loop: Callable[[], None]) -> int:
        """Runs the learner's loop: 0 when it ended (or a stop was requested), 1 when a service failed, 130 on
        a second Ctrl-C. Other exceptions propagate (the learner's ``finally`` still ends the run)."""
        try:
            loop()
        except ServiceError as exc:
            if not self.stop_event.is_set():
                self.log.error(f"stopping: {exc}")
                return 1
        except KeyboardInterrupt:
            self.log.warning("interrupted twice: stopping without waiting")
            return 130
        return 0

    def settle(self, step: int) -> None:
        """After the loop: the stop request named, the reduction in flight finished (its RTM and QT go into the
        final checkpoint)."""
        self.elapsed = time.monotonic() - self.outputs.t_start
        if self.stop_event.is_set():
            self.log.info(f"stop requested at step {step}")
        if self.mem is not None and self.mem.in_flight is not None:
            try:
                self.mem.collect(wait=True)
            except ServiceError as exc:
                self.log.error(f"the reduction in flight did not finish: {exc}")

    def finish(self, rc: int, state: Callable[[], dict], step: int,
               notes: Callable[[dict, float, int], tuple[str, str]]) -> dict:
        """The end of the session after :meth:`settle` and the learner's last records: the final checkpoint
        (weights and counters only when a service failed or Ctrl-C came twice), the time split (with the
        learner's `notes`), the logs closed. Returns the time split record."""
        try:
            self.save(state, step, final=True, replay=rc == 0,
                      skipped="a service failed" if rc == 1 else "interrupted twice")
        except Exception as exc:
            self.log.error(f"final checkpoint failed: {exc}")
        steps = step - self.start_step
        calls = sum(self.ptimers.calls.get(k, 0) for k in TIMED_CALLS)
        probe = (None if self.stop_event.is_set() else
                 functools.partial(self.mem.memory.stats if self.mem is not None else self.sim.info, timeout=10.0))
        timers = self.outputs.report_time_split(self.ptimers, self.elapsed, steps, calls, probe,
                                                self.p.transport_probe_calls, notes, self.log)
        self.outputs.close_logs()
        return timers

    def write_summary(self, step: int, timers: dict, **fields) -> Path:
        """summary.json at the end of the session: the run (id, algorithm, task, profile, seed), the learner's
        `fields`, the evaluations, the wall clock and this session's rate, the time split `timers`."""
        p, ev, elapsed = self.p, self.evaluation.records if self.evaluation is not None else [], self.elapsed
        summary = {"run_id": self.run_id, "algorithm": p.algorithm, "env_id": p.env_id, "profile": self.profile,
                   "seed": int(self.cfg.seed), "steps": int(step), "reductions": int(self.reductions), **fields,
                   "evaluations": [{k: e[k] for k in ("step", "mean_return", "std_return")} for e in ev],
                   "wall_time_s": self.wall_time(), "session_elapsed_s": elapsed,
                   "session_steps_per_s": (step - self.start_step) / elapsed if elapsed > 0 else None, "timers": timers}
        return run_io.write_text_atomic(self.run_dir.file("summary.json"), json.dumps(summary, indent=1, default=float))

    # ------------------------------------------------------------------------------ shutdown
    def shutdown(self) -> None:
        node = self.node
        if self.evaluation is not None:
            self.evaluation.close()
        if not self.topics.hand_over(self.HAND_OVER_S):
            self.log.warning(f"a subscriber of ~/episodes, ~/evaluations or ~/transitions had not acknowledged "
                             f"this run's last messages after {self.HAND_OVER_S:g} s; it may miss them")
        if self.recording is not None:
            try:
                self.recording.stop([node] + (list(self.embedded.all) if self.embedded is not None else []))
            except Exception as exc:
                self.log.error(f"stopping the recorder process failed: {exc}")
        try:
            self.spinner.stop()
        except Exception:
            pass
        if self.embedded is not None:
            self.embedded.destroy()
        if self.recording is not None:
            self.recording.close_in_process()
        node.destroy_node()
