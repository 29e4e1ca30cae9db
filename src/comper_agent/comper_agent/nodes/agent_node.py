"""agent_node: what the learner nodes (comcact_node, comper_node) share.

:class:`AgentNode` - the learner node's lifecycle: parameters (``node_config``, ``declare_config``,
profiles), the embedded bring-up (:mod:`comper_agent.nodes.bringup`), the service clients, the run
(start, loop, stop, final save, time split), the checkpoint's contents and shutdown. A subclass
supplies the algorithm through the hooks below (``_setup_learner``, ``_loop``, ``_start_line``,
``_progress_line``, ...). The parts that hold state of their own are collaborators:
the run's outputs (:class:`~comper_agent.nodes.agent_run.AgentRun`), the experience saved with its checkpoints
(:class:`~comper_agent.nodes.experience_checkpoint.ExperienceCheckpoint`), the training episodes and the
recorded topics (:mod:`comper_agent.nodes.episodes`), evaluation (:mod:`comper_agent.nodes.evaluation`, opened
by the subclass with its policy), the memory link (:class:`~comper_agent.nodes.memory_link.MemoryLink`)
and the recording link (:class:`~comper_agent.recording.recording_link.RecordingLink`). The entry point is
:mod:`comper_agent.nodes.agent_main`.
"""
from __future__ import annotations

import functools
import threading
import time
from pathlib import Path

import numpy as np
from rclpy.node import Node

from comper_msgs_py.params import config_to_dict
from comper_msgs_py.qos import HAND_OVER_S
from comper_msgs_py.ros_params import declare_config, refuse_undeclared
from comper_msgs_py.service_client import ServiceError, wait_for_services
from comper_sim.client import SimClient
from comper_sim.core import episode_over

from comper_agent.nodes import run_io
from comper_agent.nodes.agent_main import run_main
from comper_agent.nodes.agent_run import AgentRun, changed_parameters
from comper_agent.nodes.bringup import START_HINTS, Spinner, make_embedded_nodes
from comper_agent.nodes.episodes import SUMMARY_QOS, LearnerTopics, TrainingEpisodes
from comper_agent.nodes.experience_checkpoint import ExperienceCheckpoint
from comper_agent.recording.recording_link import RecordingLink, record_topics
from comper_agent.nodes.memory_link import MemoryLink
from comper_agent.core.config import thesis_differences
from comper_agent.nodes.node_config import AgentRunConfig, redefault
from comper_agent.nodes.qt_diagnostics import QTDiagnostics

__all__ = ["AgentNode", "AgentRunConfig", "run_main", "redefault", "episode_over", "SUMMARY_QOS"]


class AgentNode(Node):
    """A learner node. Construction declares parameters, prepares the run directory and brings up the
    other nodes; ``run()`` trains (main thread) while a background executor serves ROS.

    Subclasses set NODE_NAME, CONFIG (their AgentRunConfig subclass), LEARNER_CONFIGS (algorithm ->
    learner hyper-parameter class; ``variant`` is set from ``algorithm``), OBS_DTYPE, CSV_COLUMNS, and
    implement the hooks below. ``_configure`` sets ``uses_memory``, ``uses_qt`` and ``reducer``
    (qt_trainer, memory or none), which decide the embedded nodes, clients and QT subscription, and
    ``embedded_params`` (extra parameters of the embedded sim, memory and QT trainer nodes).
    ``_check_env`` sets ``progress_total`` (the steps the progress line counts towards) and
    ``env_description`` (config.yaml's env). CONFIG also defines ``reduce_batch`` and ``qt_epochs``
    (their defaults and thesis values differ per algorithm), used here for the embedded QT trainer
    and the reduce calls.

    Collaborators, once constructed: ``outputs`` (AgentRun), ``topics`` (LearnerTopics), ``env``
    (TrainingEpisodes, after the bring-up), ``mem`` (MemoryLink or None), ``recording``
    (RecordingLink or None), ``evaluation`` (an Evaluation the subclass opens in ``_setup_learner``,
    or None)."""

    NODE_NAME = ""

    CONFIG: type = AgentRunConfig
    LEARNER_CONFIGS: dict = {}
    LEARNER_OVERRIDES = {"num_threads": 1}   # learner defaults of this node (both: measured, see their docs)
    OBS_DTYPE = np.float32
    CSV_COLUMNS: list = []
    QT_START_HINT = ""                       # extra arguments in the hint for starting a QT trainer
    PROFILES: dict = {}                      # profile -> {field: (value, source)} (core/config.py); {} = none
    #: (profile parameter, node parameters declared so far) -> the profile's name (resolves auto; refuses others)
    RESOLVE_PROFILE = None
    TIMED_CALLS = ("sim", "memory", "qt", "memory_reduce")   # phases made of service calls
    HAND_OVER_S = HAND_OVER_S   # comper_msgs_py.qos: the longest wait for the last results to be acknowledged

    uses_memory = False
    uses_qt = False
    reducer = "none"

    def __init__(self, node_name: str | None = None, **node_kwargs):
        super().__init__(node_name or self.NODE_NAME, **node_kwargs)
        self.p = p = declare_config(self, self.CONFIG, overrides=self._profile_overrides,
                                    declare_first=("algorithm", "env_id", "profile"))
        self.cfg = declare_config(self, self.LEARNER_CONFIGS[p.algorithm],
                                  overrides={"variant": p.algorithm, **self.LEARNER_OVERRIDES,
                                             **self._profile_overrides(config_to_dict(p))})
        if self.cfg.variant != p.algorithm:
            raise ValueError(f"variant:={self.cfg.variant} contradicts algorithm:={p.algorithm}; set algorithm only")
        self.stop_event = threading.Event()
        self.ptimers = run_io.PhaseTimers()
        self.log = self.get_logger()
        self.embedded_params: tuple[dict, dict, dict] = ({}, {}, {})
        self.evaluation = None
        self._configure()
        # the run directory; on resume, it and the run id come from the checkpoint
        self.outputs = AgentRun(self.p, int(self.cfg.seed))
        self.run_id, self.run_dir = self.outputs.run_id, self.outputs.dir

        # publishers / subscriptions (served by the background executor)
        self.topics = LearnerTopics(self, self.run_id, p.env_id, p.publish_transitions, self.ptimers,
                                    self.stop_event)
        self.mem = (MemoryLink(self, p, reducer=self.reducer, uses_qt=self.uses_qt, timers=self.ptimers,
                               device=self.cfg.device) if self.uses_memory else None)
        self.experience = ExperienceCheckpoint(self)
        self._bring_up()

    # ------------------------------------------------------------------------------ hooks
    def _profile_overrides(self, values: dict) -> dict:
        """Defaults chosen by a named profile (``PROFILES``), for node and learner parameters alike;
        `values`: the node parameters declared so far (algorithm, env_id and profile come first). The
        command line and parameter files still win."""
        if not self.PROFILES or "profile" not in values:
            return {}
        self.profile = self.RESOLVE_PROFILE(values["profile"], values)
        return {k: v for k, (v, _) in self.PROFILES[self.profile].items()}

    def _configure(self) -> None:
        """Algorithm flags, ``embedded_params`` and node-specific publishers (before the bring-up)."""

    def _check_env(self, info) -> None:
        """Refuse a sim whose task does not suit the algorithm; read what the learner needs; set
        ``progress_total`` and ``env_description``."""

    def _setup_learner(self) -> None:
        raise NotImplementedError

    def _before_loop(self) -> None:
        """After the logs are open, before the loop (outside its error handling)."""

    def _loop(self) -> None:
        raise NotImplementedError

    def _start_line(self) -> str:
        raise NotImplementedError

    def _timer_notes(self, rec: dict, elapsed: float, steps: int) -> tuple[str, str]:
        """Node-specific time-split notes: fields added to `rec`, texts appended to the two log lines."""
        return "", ""

    def _final_records(self, rc: int) -> None:
        """Before the final checkpoint."""

    def _finish(self, elapsed: float, steps: int, timers: dict) -> None:
        """After the time split, before the logs close: the run's last words."""

    # ------------------------------------------------------------------------------ set-up
    def _bring_up(self) -> None:
        """The embedded nodes (bringup:=embedded), the recording link (record:=true), the executor
        threads, then the service clients."""
        p = self.p
        self.embedded = None
        self.recording = None
        nodes: list[Node] = [self]
        if p.bringup == "embedded":
            sim, mem, qt = self.embedded_params
            if p.checkpoint_replay and self.uses_memory:     # checkpoints hold the memory: step_<N>.memory
                mem = {"snapshot_root": str(self.run_dir.checkpoints), **mem}
            self.embedded = make_embedded_nodes(
                self.context, sim_name=p.sim_node,
                sim_params={"env_id": p.env_id, "episode_end": p.episode_end, "run_id": self.run_id,
                            "seed": int(self.cfg.seed), **sim},
                memory_name=p.memory_node if self.uses_memory else None, memory_params=mem,
                qt_name=p.qt_trainer_node if self.reducer == "qt_trainer" else None,
                qt_params={"memory_node": p.memory_node, "reduce_batch": int(p.reduce_batch), **qt})
            nodes += self.embedded.all
        try:
            # every node built from this command line has declared its parameters: a -p none declares is a typo
            refuse_undeclared(nodes, self.NODE_NAME)
            if p.record:
                topics = record_topics(self.get_fully_qualified_name(), p.sim_node,
                                       p.memory_node if self.uses_memory else None)
                self.recording = self.topics.recording = RecordingLink(self, p, self.run_id, self.run_dir, topics)
                nodes += self.recording.nodes
        except BaseException:
            if self.embedded is not None:
                self.embedded.destroy()
            self.run_dir.remove_if_empty()      # a start refused here leaves no run directory behind
            raise
        self.spinner = Spinner(nodes, self.context).start()
        try:
            if self.recording is not None:
                self.recording.wait_subscribed()
            self._connect()
        except BaseException:
            self.shutdown()
            raise

    def _connect(self) -> None:
        """Service clients; wait for the services; check the sim's task."""
        p = self.p
        sim = p.sim_node.strip("/")
        self.sim = SimClient(self, f"/{sim}", timeout=p.service_timeout_s)
        # after a stop request a call whose server has gone (its bring-up stopping with this node) ends at
        # once instead of waiting out service_timeout_s
        for c in (self.sim, *((self.mem.memory, self.mem.reduction) if self.mem is not None else ())):
            c.stop = self.stop_event
        services = {"sim": self.sim.step_client(), **(self.mem.services() if self.mem is not None else {})}
        hints = {"sim": START_HINTS["sim"].format(name=sim),
                 "memory": START_HINTS["memory"].format(name=p.memory_node),
                 "qt_trainer": START_HINTS["qt_trainer"].format(name=p.qt_trainer_node) + self.QT_START_HINT}
        wait_for_services(services, p.startup_timeout_s, hints, self.stop_event)
        info = self.sim.info(timeout=p.startup_timeout_s)
        if info.env_id != p.env_id:
            raise ValueError(f"the sim node /{sim} serves {info.env_id}, not env_id:={p.env_id}; "
                             f"set -p env_id:={info.env_id} or restart the sim node")
        self.info = info
        self.episode_rule = info.episode_end or "standard"
        self.obs_shape = tuple(int(d) for d in info.observation_shape)
        self.env = TrainingEpisodes(self.sim, self.topics, self.outputs, self.ptimers, self.OBS_DTYPE)
        self._check_env(info)

    @property
    def rtm_size(self) -> int:
        return self.mem.rtm_size if self.mem is not None else 0

    @property
    def reductions(self) -> int:
        return self.mem.reductions if self.mem is not None else 0

    # ------------------------------------------------------------------------------ state
    def _restore(self, state: dict) -> None:
        self.learner.load_state_dict(state["learner"])
        c = state["counters"]
        self.step, self.env.count = int(c["step"]), int(c["episodes"])
        self.stored = int(c.get("stored", 0))
        if self.evaluation is not None:
            self.evaluation.records = list(state.get("evals", []))
        if self.mem is not None:
            self.mem.reductions = int(c.get("reductions", 0))
        self.outputs.wall_offset = float(c.get("wall_time_s", 0.0))
        run_io.set_rng_state(state["rng"])
        qt_state = state.get("qt_trainer")
        if qt_state and self.embedded is not None and self.embedded.qt_trainer is not None:
            self.embedded.qt_trainer.load_state_dict(qt_state)

    def _state(self) -> dict:
        st = {"run": {"run_id": self.run_id, "algorithm": self.p.algorithm, "env_id": self.p.env_id},
              "learner": self.learner.state_dict(),
              "counters": {"step": self.step, "episodes": self.env.count, "stored": self.stored,
                           "reductions": self.reductions, "wall_time_s": self.wall_time()},
              "evals": list(self.evaluation.records) if self.evaluation is not None else [],
              "rng": run_io.rng_state(),
              "config": {"learner": {k: (list(v) if isinstance(v, tuple) else v)
                                     for k, v in config_to_dict(self.cfg).items()},
                         "params": config_to_dict(self.p)}}
        if self.embedded is not None and self.embedded.qt_trainer is not None:
            st["qt_trainer"] = self.embedded.qt_trainer.state_dict()
        return st

    def _run_config(self) -> dict:
        """config.yaml: every parameter of the run, and the task (env_description, set in _check_env)."""
        e = self.embedded
        return {"algorithm": self.p.algorithm, "params": config_to_dict(self.p),
                "learner": config_to_dict(self.cfg), "reducer": self.reducer,
                "qt_trainer": config_to_dict(e.qt_trainer.qt_config) if e is not None and e.qt_trainer else None,
                "memory": (config_to_dict(e.memory.config) if e is not None and e.memory is not None
                           and hasattr(e.memory, "config") else None),
                "resumed_from": str(self.outputs.resume_path) if self.outputs.resume_state is not None else None,
                "env": self.env_description,
                **({"profile": {"name": self.profile, "values": {k: {"value": v, "source": src} for k, (v, src)
                                                                in self.PROFILES[self.profile].items()}}}
                   if self.PROFILES else {})}

    def wall_time(self) -> float:
        return self.outputs.wall_time()

    def save(self, final: bool = False, replay: bool = True, skipped: str = "") -> Path:
        """A checkpoint of this step: the replay's contents first (checkpoint_replay; `replay` False skips
        them, `skipped` says why), then the state that names them. A checkpoint without the contents its run
        saves is marked (run_io.REPLAY_SKIPPED): pruning keeps the newest one that holds them, and a resume of
        the run goes back to it (run_io.resume_checkpoint)."""
        kept = self.experience.kept
        with self.ptimers("io"):
            saved = self.experience.save(self.step) if replay and kept else None
            state = self._state()
            if saved is not None:
                state["replay"] = saved
            elif kept:
                state[run_io.REPLAY_SKIPPED] = skipped or self.experience.error or "not saved"
            path = self.outputs.save(state, self.step)
        self.log.info(f"{'final ' if final else ''}checkpoint: {path}"
                      + (f" (with {self.experience.describe(saved)})" if saved is not None else "")
                      + (f" (weights and counters only: {state[run_io.REPLAY_SKIPPED]}; a resume of the run goes "
                         "back to the newest checkpoint that holds the memory / replay contents)"
                         if replay is False and run_io.REPLAY_SKIPPED in state else ""))
        return path

    # ------------------------------------------------------------------------------ main loop
    def run(self) -> int:
        p = self.p
        self.step = 0
        self.env.count = 0
        self.stored = 0            # transitions given to the memory / replay
        self.last_update: dict = {}
        if self.mem is not None:
            self.mem.reset()
        self._setup_learner()
        run = self.outputs
        if run.resume_state is not None:
            if run.resume_note:
                self.log.warning(run.resume_note)
            self._restore(run.resume_state)
            changed = changed_parameters(run.resume_state.get("config") or {},
                                         {"params": config_to_dict(self.p), "learner": config_to_dict(self.cfg)})
            if changed:     # the command line's values apply; a profile or flag left out changes the run
                self.log.warning("resuming with parameters that differ from the checkpoint's: " + ", ".join(changed)
                                 + " (the values given now apply; pass the checkpoint's to continue the same run)")
            try:
                self.experience.restore(run.resume_state.get("replay"))
            except RuntimeError as exc:      # a missing or unfit snapshot: nothing of the run is written yet
                self.log.error(f"cannot resume: {exc}")
                return 1
        run.open_logs(self._run_config(), self.CSV_COLUMNS, self.progress_total, self.step)
        self.metrics, self.csv, self.scalars, self.progress = run.metrics, run.csv, run.scalars, run.progress
        self.diagnostics = QTDiagnostics(p.diagnostics_every, self.metrics, self.scalars, self.ptimers)
        start_step = self.step
        self.log.info(f"{self._start_line()}; run dir {run.dir.path}  (Ctrl-C stops and saves a checkpoint)")
        if self.PROFILES:
            diffs = thesis_differences(self.p, self.cfg, thesis=self.PROFILES["thesis"])
            self.log.info(f"profile {self.profile} (profile:=thesis is the thesis); differs from it in {len(diffs)} "
                          "values: " + ("; ".join(diffs) or "none"))
        if not self.scalars.available and p.tensorboard:
            self.log.warning(f"TensorBoard scalars off: {self.scalars.error}")
        self._before_loop()
        rc = 0
        try:
            self._loop()
        except ServiceError as exc:
            if not self.stop_event.is_set():
                self.log.error(f"stopping: {exc}")
                rc = 1
        except KeyboardInterrupt:
            self.log.warning("interrupted twice: stopping without waiting")
            rc = 130
        finally:
            elapsed = time.monotonic() - run.t_start
            if self.stop_event.is_set():
                self.log.info(f"stop requested at step {self.step}")
            if self.mem is not None and self.mem.in_flight is not None:   # its RTM and QT: final checkpoint
                try:
                    self.mem.collect(wait=True)
                except ServiceError as exc:
                    self.log.error(f"the reduction in flight did not finish: {exc}")
            self._final_records(rc)
            try:
                self.save(final=True, replay=rc == 0,   # a service failed or Ctrl-C twice: weights and counters only
                          skipped="a service failed" if rc == 1 else "interrupted twice")
            except Exception as exc:
                self.log.error(f"final checkpoint failed: {exc}")
            steps = self.step - start_step
            calls = sum(self.ptimers.calls.get(k, 0) for k in self.TIMED_CALLS)
            probe = (None if self.stop_event.is_set() else
                     functools.partial(self.mem.memory.stats if self.mem is not None else self.sim.info, timeout=10.0))
            timers = run.report_time_split(self.ptimers, elapsed, steps, calls, probe, p.transport_probe_calls,
                                           self._timer_notes, self.log)
            self._finish(elapsed, steps, timers)
            run.close_logs()
        return rc

    def _after_step(self) -> None:
        """In the loop, after each step: a checkpoint and a progress line when due."""
        if self.outputs.checkpoint_due(self.step):
            self.save()
        line = self.progress.tick(self.step)
        if line:
            self._progress_line(line)

    def _progress_line(self, line: str) -> None:
        raise NotImplementedError

    # ------------------------------------------------------------------------------ shutdown
    def shutdown(self) -> None:
        if getattr(self, "evaluation", None) is not None:
            self.evaluation.close()
        topics = getattr(self, "topics", None)
        if topics is not None and not topics.hand_over(self.HAND_OVER_S):
            self.log.warning(f"a subscriber of ~/episodes, ~/evaluations or ~/transitions had not acknowledged "
                             f"this run's last messages after {self.HAND_OVER_S:g} s; it may miss them")
        recording = getattr(self, "recording", None)
        if recording is not None:
            try:
                recording.stop([self] + (list(self.embedded.all) if self.embedded is not None else []))
            except Exception as exc:
                self.log.error(f"stopping the recorder process failed: {exc}")
        try:
            self.spinner.stop()
        except Exception:
            pass
        if self.embedded is not None:
            self.embedded.destroy()
        if recording is not None:
            recording.close_in_process()
        self.destroy_node()
