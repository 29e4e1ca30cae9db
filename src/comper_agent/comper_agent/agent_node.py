"""agent_node: what the learner nodes (comcact_node, comper_node) share.

* :class:`AgentRunConfig` - the run set-up parameters every learner node declares (bring-up,
  outputs, recording, node names, timeouts); each node subclasses it with its algorithm's own
  parameters (:class:`comper_agent.comcact_node.ComcactNodeConfig`,
  :class:`comper_agent.comper_node.ComperNodeConfig`).
* :class:`AgentNode` - the learner node's machinery: parameters (``declare_config``), the run
  directory and resume, the embedded bring-up (``bringup:=embedded``) with an optional in-process
  recorder (``record:=true``), service clients, the QTModel subscription, ``~/episodes`` and
  ``~/transitions`` per training episode, checkpoints, the run loop's start / stop / final save,
  the time split and shutdown. A subclass supplies the algorithm: ``_setup_learner``,
  ``_before_loop``, ``_loop``, ``_start_line``, ``_progress_line``, checkpoint contents.
* :func:`run_main` - an entry point's signal handling: the first Ctrl-C / SIGTERM finishes the
  current step, saves a final checkpoint and exits 0; a second one aborts (130); a node that cannot
  start logs one ``cannot start: ...`` line and exits 1. ``--help`` lists the parameters.
"""
from __future__ import annotations

import ctypes
import dataclasses
import functools
import json
import math
import os
import signal
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rclpy
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions

from comper_msgs.msg import EpisodeSummary, EvaluationResult, TransitionBatch
from comper_msgs.msg import QTModel as QTModelMsg
from comper_memory.client import MemoryClient, MemoryServiceError, ReductionClient
from comper_msgs_py.arrays import Transitions
from comper_msgs_py.convert import transitions_to_batch
from comper_msgs_py.params import config_to_dict, describe, param, spec_of
from comper_msgs_py.ros_params import declare_config
from comper_msgs_py.service_client import PendingCall, ServiceError, wait_for_services
from comper_sim.client import SimClient

from . import run_io
from .bringup import START_HINTS, Spinner, make_embedded_nodes
from .qt_trainer_node import QT_MODEL_QOS, msg_to_qt

__all__ = ["AgentNode", "AgentRunConfig", "run_main", "redefault", "episode_over", "SUMMARY_QOS",
           "EPISODE_END_RULES"]

#: QoS of ~/episodes, ~/evaluations, ~/transitions (the recording contract, docs/recording.md)
SUMMARY_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                         reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)

EPISODE_END_RULES = ("standard", "truncation_only", "termination_only")


def episode_over(rule: str, terminated: bool, truncated: bool) -> bool:
    """Whether a step ends the episode under the sim's episode end rule (method.md 6.3)."""
    if rule == "truncation_only":
        return bool(truncated)
    if rule == "termination_only":
        return bool(terminated)
    return bool(terminated or truncated)


def redefault(cls, name: str, default):
    """A config field of `cls` (description, thesis, range) with another default, for a subclass:
    ``progress_period_s: float = redefault(AgentRunConfig, "progress_period_s", 10.0)``."""
    (f,) = [f for f in dataclasses.fields(cls) if f.name == name]
    return dataclasses.field(default=default, metadata=f.metadata)


@dataclass(frozen=True)
class AgentRunConfig:
    """Run set-up shared by the learner nodes; a node's config subclasses it with its algorithm's
    parameters (and redefines algorithm, env_id and the defaults that differ)."""

    algorithm: str = param("", "learning algorithm (each node lists its own)")
    bringup: str = param(
        "embedded", "embedded: build the sim, memory and QT trainer nodes in this process; external: use "
        "nodes started separately, named by sim_node, memory_node, qt_trainer_node",
        choices=("embedded", "external"))
    env_id: str = param("", "gymnasium task (embedded: given to the sim node; external: must match the "
                            "running sim node)")
    episode_end: str = param(
        "standard", "embedded sim node's episode end rule (method.md 6.3; only terminated masks the "
        "bootstrap; an ALE game over always ends the episode). External: the sim's rule is used",
        choices=EPISODE_END_RULES)
    runs_root: str = param("runs", "folder holding the run directories")
    run_id: str = param("", "run directory name; '' = <algorithm>-<env>-s<seed>-<timestamp>")
    resume: str = param(
        "", "checkpoint file or run directory to continue from ('' = fresh run). The run continues in "
        "the checkpoint's run directory with its step count; the memory / replay contents are not in "
        "the checkpoint and refill from the resumed step, which starts a new episode")
    keep_checkpoints: int = param(3, "step_<N>.pt files kept besides latest.pt (0 = keep all)", minimum=0)
    progress_period_s: float = param(5.0, "seconds between console progress lines", minimum=0.0)
    tensorboard: bool = param(True, "write TensorBoard scalars to <run dir>/tb")
    record: bool = param(
        False, "record this run's topics (transitions, episodes, evaluations, memory stats, sim episodes) "
        "into a rosbag2 bag in <run dir>/bag with a recorder_node (docs/recording.md)")
    record_storage: str = param("mcap", "bag storage when record is on", choices=("mcap", "sqlite3"))
    record_process: str = param(
        "child", "where record:=true runs its recorder_node: 'child' = a child process (its work runs on "
        "another core; the agent waits until it has subscribed, hands every message over before stopping it, "
        "and if the agent dies, even by SIGKILL, the recorder gets SIGTERM and closes the bag; its log is "
        "<run dir>/recorder.log), 'in_process' = a node on this process's executor (one process; costs "
        "~4-5 percent of the training throughput on Hopper-v4, docs/recording.md)", choices=("child", "in_process"))
    record_window: int = param(
        50, "record:=true: most training episodes published but not yet written by the recorder; the agent waits "
        "beyond it (flow control from the recorder's ~/status). Below the topics' history depth (100), so no "
        "reliable queue drops an episode when the agent outpaces the recorder", minimum=1, maximum=99)
    record_wait_s: float = param(
        60.0, "record:=true: longest wait for the recorder to catch up; after it the backlog is written off with "
        "a warning and training goes on", minimum=0.0)
    publish_transitions: bool = param(
        True, "publish each finished training episode's transitions (with the labels stored) on "
        "~/transitions, before its ~/episodes summary, while someone subscribes (record:=true does)")
    prefetch_batches: int = param(
        32, "most update batches fetched from the memory in one sample call. Only the batches of the updates "
        "before the next reduction are fetched (RTM does not change in between), each an independent uniform "
        "draw, so the batches are those of one call per update; sampling from TM (while RTM is empty, or "
        "COMPER-M) stays one call per update. 1 = one sample call per update",
        thesis="one draw per update (Algorithms 7 and 8); same distribution", minimum=1)
    reduce_overlap: bool = param(
        False, "send each reduction and go on learning (acting, updates from the current RTM, targets from the "
        "current QT) while the QT trainer and the memory reduce, on the other core; at most one reduction in "
        "flight (the next one waits for it), the first (RTM empty) is waited for; the new RTM and QT are used "
        "from the step their answer arrives (variants that reduce)",
        thesis="the agent waits for each reduction (Algorithms 7 and 8: reduce, then learn)",
        deviation="on = updates between a reduction's request and its answer use the RTM and QT of the "
        "previous reduction")
    qt_wait_s: float = param(2.0, "after a reduction, seconds to wait for the QTModel of that version to "
                                  "arrive (variants with a QT target)", minimum=0.0)
    eval_episodes: int = param(10, "full episodes per evaluation (greedy policy, a separate environment in "
                                   "this process)", thesis="10 (chapter 6)", minimum=1)
    eval_seed: int = param(
        -1, "seed of the evaluation environment's resets (episode k of every evaluation starts from seed "
        "eval_seed + k); -1 = seed + 1000", minimum=-1)
    sim_node: str = param("sim_node", "name of the simulation node")
    memory_node: str = param("memory_node", "name of the memory node (not used by the baselines)")
    qt_trainer_node: str = param("qt_trainer_node", "name of the QT trainer node (variants that train QT)")
    service_timeout_s: float = param(120.0, "seconds to wait for any one service answer", minimum=0.0)
    startup_timeout_s: float = param(30.0, "seconds to wait for the nodes' services at start", minimum=0.0)
    transport_probe_calls: int = param(
        200, "at the end, this many small service calls measure the ROS round trip for the time split "
        "(0 = skip)", minimum=0)


class AgentNode(Node):
    """A learner node. Construction declares parameters, prepares the run directory and brings up the
    other nodes; ``run()`` trains (main thread) while a background executor serves ROS.

    Subclasses set CONFIG (their AgentRunConfig subclass), LEARNER_CONFIGS (algorithm -> learner
    hyper-parameter class; ``variant`` is set from ``algorithm``), OBS_DTYPE, CSV_COLUMNS, and
    implement the hooks below. ``_configure`` sets ``uses_memory``, ``uses_qt`` and ``reducer``
    (qt_trainer, memory or none), which decide the embedded nodes, clients and QT subscription.
    CONFIG also defines ``reduce_batch`` and ``qt_epochs`` (their defaults and thesis values differ
    per algorithm), used here for the embedded QT trainer and the reduce calls."""

    CONFIG: type = AgentRunConfig
    LEARNER_CONFIGS: dict = {}
    LEARNER_OVERRIDES = {"num_threads": 1}   # learner defaults of this node (both: measured, see their docs)
    OBS_DTYPE = np.float32
    CSV_COLUMNS: list = []
    QT_START_HINT = ""                       # extra arguments in the hint for starting a QT trainer
    TIMED_CALLS = ("sim", "memory", "qt", "memory_reduce")   # phases made of service calls

    uses_memory = False
    uses_qt = False
    reducer = "none"

    def __init__(self, node_name: str, **node_kwargs):
        super().__init__(node_name, **node_kwargs)
        self.p = p = declare_config(self, self.CONFIG)
        self.cfg = declare_config(self, self.LEARNER_CONFIGS[p.algorithm],
                                  overrides={"variant": p.algorithm, **self.LEARNER_OVERRIDES,
                                             **self._profile_overrides()})
        if self.cfg.variant != p.algorithm:
            raise ValueError(f"variant:={self.cfg.variant} contradicts algorithm:={p.algorithm}; set algorithm only")
        self.stop_event = threading.Event()
        self.ptimers = run_io.PhaseTimers()
        self.log = self.get_logger()
        self._configure()
        self._open_run_dir()

        # publishers / subscriptions (served by the background executor)
        self.episode_pub = self.create_publisher(EpisodeSummary, "~/episodes", SUMMARY_QOS)
        self.eval_pub = self.create_publisher(EvaluationResult, "~/evaluations", SUMMARY_QOS)
        self.transitions_pub = self.create_publisher(TransitionBatch, "~/transitions", SUMMARY_QOS)
        self.ep_parts: list[Transitions] = []     # the current training episode's stored transitions
        self.qt_local = None
        self.qt_cond = threading.Condition()
        self.qt_received = 0
        if self.uses_qt:
            self.create_subscription(QTModelMsg, f"/{p.qt_trainer_node.strip('/')}/qt_model",
                                     self._on_qt_model, QT_MODEL_QOS)
        self._bring_up()

    # ------------------------------------------------------------------------------ hooks
    def _profile_overrides(self) -> dict:
        """Learner defaults chosen by a named profile (before the learner's parameters are declared);
        the command line and parameter files still win."""
        return {}

    def _configure(self) -> None:
        """Algorithm flags and node-specific publishers (before the bring-up)."""

    def _embedded_params(self) -> tuple[dict, dict, dict]:
        """Extra parameters of the embedded sim, memory and QT trainer nodes."""
        return {}, {}, {}

    def _check_env(self, info) -> None:
        """Refuse a sim whose task does not suit the algorithm; read what the learner needs."""

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
    def _open_run_dir(self) -> None:
        """The run directory; on resume, it and the run id come from the checkpoint."""
        p = self.p
        self.resume_state = None
        self.resume_path = None
        run_id = p.run_id
        runs_root = Path(p.runs_root)
        if p.resume:
            from .core.checkpoint import load_checkpoint
            ck = run_io.resolve_checkpoint(p.resume)
            self.resume_state = load_checkpoint(ck)
            meta = self.resume_state["run"]
            if meta["algorithm"] != p.algorithm or meta["env_id"] != p.env_id:
                raise ValueError(f"{ck} is a {meta['algorithm']} run on {meta['env_id']}; start with "
                                 f"-p algorithm:={meta['algorithm']} -p env_id:={meta['env_id']}")
            run_id = meta["run_id"]
            runs_root = ck.parent.parent.parent
            self.resume_path = ck
        if not run_id:
            run_id = run_io.default_run_id(p.algorithm, p.env_id, self.cfg.seed)
        self.run_id = run_id
        self.run_dir = run_io.RunDir(runs_root, run_id)

    def _bring_up(self) -> None:
        p = self.p
        self.embedded = None
        self.recorder = None
        nodes: list[Node] = [self]
        if p.bringup == "embedded":
            sim, mem, qt = self._embedded_params()
            self.embedded = make_embedded_nodes(
                self.context, sim_name=p.sim_node,
                sim_params={"env_id": p.env_id, "episode_end": p.episode_end, "run_id": self.run_id,
                            "seed": int(self.cfg.seed), **sim},
                memory_name=p.memory_node if self.uses_memory else None, memory_params=mem,
                qt_name=p.qt_trainer_node if self.reducer == "qt_trainer" else None,
                qt_params={"memory_node": p.memory_node, "reduce_batch": int(p.reduce_batch), **qt})
            nodes += self.embedded.all
        self.recorder_proc = None
        self.flow = None
        if p.record and p.record_process == "in_process":
            nodes.append(self._make_recorder(self.run_id))
        try:
            if p.record and p.record_process == "child":
                self._start_recorder_process(self.run_id)
            if p.record:
                from .recorder_node import RecordingFlow
                self.flow = RecordingFlow(self, self.recorder_name, window=p.record_window, timeout_s=p.record_wait_s)
        except BaseException:
            if self.embedded is not None:
                self.embedded.destroy()
            raise
        self.spinner = Spinner(nodes, self.context).start()
        try:
            if self.recorder_proc is not None:
                self._wait_recorder_subscribed()
            self._connect()
        except BaseException:
            self.shutdown()
            raise

    def _record_topics(self) -> list[str]:
        """The topics record:=true bags: this node's contract topics, the sim's episodes, memory stats."""
        me = self.get_fully_qualified_name()
        topics = [f"{me}/transitions", f"{me}/episodes", f"{me}/evaluations",
                  f"/{self.p.sim_node.strip('/')}/episodes"]
        if self.uses_memory:
            topics.append(f"/{self.p.memory_node.strip('/')}/stats")
        return topics

    def _recorder_params(self, run_id: str) -> dict:
        return {"run_id": run_id, "algorithm": self.p.algorithm, "output_dir": str(self.run_dir.path.parent),
                "storage": self.p.record_storage, "topics": self._record_topics()}

    def _make_recorder(self, run_id: str) -> Node:
        """An in-process recorder_node bagging this run's topics into <run dir>/bag."""
        from rclpy.parameter import Parameter

        from .recorder_node import RecorderNode
        self.recorder = RecorderNode(context=self.context, parameter_overrides=[
            Parameter(k, value=v) for k, v in self._recorder_params(run_id).items()])
        self.recorder_name = self.recorder.get_fully_qualified_name()
        return self.recorder

    def _start_recorder_process(self, run_id: str) -> None:
        """record_process:=child: recorder_node as a child process (started before this process's
        executor threads; _wait_recorder_subscribed waits for it)."""
        import subprocess
        topics = self._record_topics()
        self._subscribers_before = {t: self.count_subscribers(t) for t in topics}
        self.recorder_name = f"/{self.get_name()}_recorder"     # no namespace given: at the root
        cmd = [sys.executable, "-m", "comper_agent.recorder_node", "--ros-args",
               "-r", f"__node:={self.recorder_name[1:]}"]
        for k, v in self._recorder_params(run_id).items():
            cmd += ["-p", f"{k}:={json.dumps(v)}"]   # JSON is YAML: strings stay strings, lists lists
        log_path = self.run_dir.file("recorder.log")
        with open(log_path, "ab") as log:
            # own session: a terminal's Ctrl-C reaches the agent only, which hands over and stops the
            # recorder; PR_SET_PDEATHSIG: the recorder gets SIGTERM when the agent dies (even SIGKILL)
            self.recorder_proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=os.environ.copy(),
                                                  start_new_session=True,
                                                  preexec_fn=functools.partial(_die_with_parent, os.getpid()))

    def _wait_recorder_subscribed(self) -> None:
        """Return once the recorder process has subscribed to every recorded topic (the first episode
        must not be published before)."""
        before, log_path = self._subscribers_before, self.run_dir.file("recorder.log")
        topics = list(before)
        deadline = time.monotonic() + self.p.startup_timeout_s
        while any(self.count_subscribers(t) <= before[t] for t in topics):
            rc = self.recorder_proc.poll()
            if rc is not None:
                tail = log_path.read_text(errors="replace")[-2000:]
                raise RuntimeError(f"the recorder process exited with {rc} before subscribing; {log_path}:\n{tail}")
            if time.monotonic() > deadline:
                raise RuntimeError(f"the recorder process did not subscribe to {topics} within "
                                   f"startup_timeout_s={self.p.startup_timeout_s:g} s (see {log_path})")
            time.sleep(0.02)
        self.log.info(f"recording into {self.run_dir.path / 'bag'} by a recorder process (pid "
                      f"{self.recorder_proc.pid}, log {log_path})")

    def _stop_recorder_process(self) -> None:
        """Wait until the recorder has every message this process published on the recorded topics
        (reliable QoS acknowledgements), then stop it (SIGINT: it takes what it still holds and closes
        the bag)."""
        from rclpy.duration import Duration
        proc, self.recorder_proc = self.recorder_proc, None
        topics = set(self._record_topics())
        nodes = [self] + (list(self.embedded.all) if self.embedded is not None else [])
        for node in nodes if proc.poll() is None else []:     # a dead recorder acknowledges nothing
            for pub in node.publishers:
                if pub.topic_name in topics:
                    try:
                        pub.wait_for_all_acked(Duration(seconds=5.0))
                    except Exception:   # a destroyed publisher or a shut-down context: nothing to wait for
                        pass
        proc.send_signal(signal.SIGINT)
        try:
            rc = proc.wait(timeout=30.0)
        except Exception:
            proc.kill()
            rc = proc.wait()
        if rc != 0:
            self.log.error(f"the recorder process ended with {rc}; see {self.run_dir.file('recorder.log')}")

    def _connect(self) -> None:
        """Service clients; wait for the services; check the sim's task."""
        p = self.p
        sim = p.sim_node.strip("/")
        self.sim = SimClient(self, f"/{sim}", timeout=p.service_timeout_s)
        services = {"sim": self.sim.step_client()}
        self.memory = self.reducer_client = None
        if self.uses_memory:
            mem = p.memory_node.strip("/")
            self.memory = MemoryClient(self, f"/{mem}", timeout=p.service_timeout_s)
            services["memory"] = self.memory.store_client()
            if self.reducer == "qt_trainer":
                self.reducer_client = ReductionClient(self, f"/{p.qt_trainer_node.strip('/')}",
                                                      timeout=p.service_timeout_s)
                services["qt_trainer"] = self.reducer_client.reduce_client()
            else:
                self.reducer_client = ReductionClient(self, f"/{mem}", timeout=p.service_timeout_s)
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
        self._check_env(info)

    def _reset_counters(self) -> None:
        self.step = 0
        self.episodes = 0
        self.stored = 0            # transitions given to the memory / replay
        self.reductions = 0
        self.rtm_size = 0
        self.tm_sets = 0
        self.wall_offset = 0.0
        self.last_update: dict = {}
        self.last_reduce: dict = {}
        self.sample_calls = 0
        self.prefetched: list = []   # (batch, counts) drawn from the current RTM for the next updates, next last
        self.reduce_pending: PendingCall | None = None   # reduce_overlap: the reduction in flight

    # ------------------------------------------------------------------------------ ROS callbacks
    def _on_qt_model(self, msg: QTModelMsg) -> None:
        try:
            t0 = time.perf_counter()
            model = msg_to_qt(msg, device=self.cfg.device)
            self.ptimers.add("qt_model_rebuild", time.perf_counter() - t0)
        except Exception as exc:
            self.log.error(f"cannot rebuild the published QTModel v{msg.version}: {exc}")
            return
        with self.qt_cond:
            if self.qt_local is None or model.version >= self.qt_local.version:
                self.qt_local = model
            self.qt_received += 1
            self.qt_cond.notify_all()

    # ------------------------------------------------------------------------------ state
    def _restore(self, state: dict) -> None:
        self.learner.load_state_dict(state["learner"])
        c = state["counters"]
        self.step, self.episodes = int(c["step"]), int(c["episodes"])
        self.reductions = int(c.get("reductions", 0))
        self.wall_offset = float(c.get("wall_time_s", 0.0))
        run_io.set_rng_state(state["rng"])
        qt_state = state.get("qt_trainer")
        if qt_state and self.embedded is not None and self.embedded.qt_trainer is not None:
            self.embedded.qt_trainer.load_state_dict(qt_state)

    def _state(self) -> dict:
        st = {"run": {"run_id": self.run_id, "algorithm": self.p.algorithm, "env_id": self.p.env_id},
              "learner": self.learner.state_dict(),
              "counters": {"step": self.step, "episodes": self.episodes, "stored": self.stored,
                           "reductions": self.reductions, "wall_time_s": self.wall_time()},
              "rng": run_io.rng_state(),
              "config": {"learner": {k: (list(v) if isinstance(v, tuple) else v)
                                     for k, v in config_to_dict(self.cfg).items()},
                         "params": config_to_dict(self.p)}}
        if self.embedded is not None and self.embedded.qt_trainer is not None:
            st["qt_trainer"] = self.embedded.qt_trainer.state_dict()
        return st

    def _run_config(self) -> dict:
        """config.yaml: every parameter of the run (the node adds its env description)."""
        e = self.embedded
        return {"algorithm": self.p.algorithm, "params": config_to_dict(self.p),
                "learner": config_to_dict(self.cfg), "reducer": self.reducer,
                "qt_trainer": config_to_dict(e.qt_trainer.qt_config) if e is not None and e.qt_trainer else None,
                "memory": (config_to_dict(e.memory.config) if e is not None and e.memory is not None
                           and hasattr(e.memory, "config") else None),
                "resumed_from": str(self.resume_path) if self.resume_state is not None else None}

    def wall_time(self) -> float:
        return self.wall_offset + (time.monotonic() - self.t_start)

    def save(self, final: bool = False) -> Path:
        with self.ptimers("io"):
            path = self.run_dir.save_checkpoint(self._state(), self.step, self.p.keep_checkpoints)
            self.metrics.flush()
        self.log.info(f"{'final ' if final else ''}checkpoint: {path}")
        return path

    # ------------------------------------------------------------------------------ main loop
    def run(self) -> int:
        p = self.p
        self._reset_counters()
        self._setup_learner()
        if self.resume_state is not None:
            self._restore(self.resume_state)
        rd = self.run_dir
        rd.write_config(self._run_config())
        self.metrics = run_io.MetricsLog(rd.file("metrics.jsonl"))
        self.csv = run_io.CsvLog(rd.file("progress.csv"), self.CSV_COLUMNS)
        self.scalars = run_io.ScalarLog(rd.file("tb") if p.tensorboard else None)
        self.progress = run_io.Progress(self._progress_total(), p.progress_period_s, start_step=self.step)
        self.t_start = time.monotonic()
        start_step = self.step
        self.log.info(f"{self._start_line()}; run dir {rd.path}  (Ctrl-C stops and saves a checkpoint)")
        if not self.scalars.available and p.tensorboard:
            self.log.warning(f"TensorBoard scalars off: {self.scalars.error}")
        self.pending: list = []
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
            elapsed = time.monotonic() - self.t_start
            if self.stop_event.is_set():
                self.log.info(f"stop requested at step {self.step}")
            if self.reduce_pending is not None:     # its RTM and QT belong in the final checkpoint
                try:
                    self._reduce_collect(wait=True)
                except ServiceError as exc:
                    self.log.error(f"the reduction in flight did not finish: {exc}")
            self._final_records(rc)
            try:
                self.save(final=True)
            except Exception as exc:
                self.log.error(f"final checkpoint failed: {exc}")
            timers = self._report_timers(elapsed, self.step - start_step)
            self._finish(elapsed, self.step - start_step, timers)
            self.metrics.close()
            self.csv.close()
            self.scalars.close()
        return rc

    def _next_due(self, every: int) -> int | None:
        """The first multiple of `every` after the current step (None when every is 0)."""
        return (self.step // every + 1) * every if every > 0 else None

    def _schedule_checkpoints(self, every: int) -> None:
        self.ck_every = every
        self.next_ck = self._next_due(every)

    def _after_step(self) -> None:
        """In the loop, after each step: a checkpoint and a progress line when due."""
        if self.next_ck is not None and self.step >= self.next_ck:
            self.save()
            self.next_ck += self.ck_every
        line = self.progress.tick(self.step)
        if line:
            self._progress_line(line)

    def _progress_line(self, line: str) -> None:
        raise NotImplementedError

    def _progress_total(self) -> int:
        return int(self.p.total_steps)

    def _resume_text(self) -> str:
        return f"resuming at step {self.step}" if self.step else "fresh run"

    # ------------------------------------------------------------------------------ evaluation
    def _open_eval_env(self, **sim_params) -> None:
        """The evaluation environment: a second environment of the task inside this learner (the
        protocol's "separate environment"), reset from eval_seed + k for episode k."""
        from comper_sim.core import SimBridge, SimConfig
        p = self.p
        self.eval_seed = p.eval_seed if p.eval_seed >= 0 else self.cfg.seed + 1000
        self.eval_bridge = SimBridge(SimConfig(env_id=p.env_id, seed=self.eval_seed, episode_end="standard",
                                               run_id=self.run_id, **sim_params))
        self.evals: list[dict] = []

    def _eval_action(self, obs: np.ndarray):
        """The evaluated (greedy) policy's action."""
        raise NotImplementedError

    def _eval_recorded(self, rec: dict) -> None:
        """After an evaluation is logged: the node's progress.csv row."""

    def evaluate(self) -> dict:
        """eval_episodes full episodes of the greedy policy; published on ~/evaluations and ~/episodes
        (source eval), logged to metrics.jsonl, TensorBoard and the console."""
        p = self.p
        rets, lens = [], []
        skip = max(1, int(getattr(self, "frame_skip", 1)))
        with self.ptimers("eval"):
            for k in range(p.eval_episodes):
                ret, n, res = self.eval_bridge.play_episode(self._eval_action, self.eval_seed + k)
                rets.append(ret)
                lens.append(n)
                ep = EpisodeSummary(run_id=self.run_id, env_id=p.env_id, source="eval", episode_id=k,
                                    episode_return=ret, length=n, frames=n * skip, terminated=bool(res.terminated),
                                    truncated=bool(res.truncated), global_step=self.step,
                                    global_frames=int(getattr(self, "frames", self.step)),
                                    wall_time_s=self.wall_time())
                ep.header.stamp = self.get_clock().now().to_msg()
                self.episode_pub.publish(ep)
        mean, std = float(np.mean(rets)), float(np.std(rets))
        msg = EvaluationResult(run_id=self.run_id, algorithm=p.algorithm, env_id=p.env_id,
                               global_step=self.step, episode_returns=[float(r) for r in rets],
                               episode_lengths=[int(n) for n in lens], mean_return=mean, std_return=std)
        msg.header.stamp = self.get_clock().now().to_msg()
        self.eval_pub.publish(msg)
        rec = {"step": self.step, "mean_return": mean, "std_return": std, "returns": rets,
               "lengths": lens, "wall_time_s": self.wall_time()}
        self.evals.append(rec)
        self.metrics.write("eval", **rec)
        self._eval_recorded(rec)
        self.scalars.scalar("eval/mean_return", mean, self.step)
        self.scalars.scalar("eval/std_return", std, self.step)
        self.progress.evaluation(mean)
        self.log.info(f"evaluation at step {self.step}: return {mean:.1f} +- {std:.1f} over "
                      f"{len(rets)} episodes (lengths {min(lens)}-{max(lens)})")
        return rec

    # ------------------------------------------------------------------------------ sim
    def _reset_env(self) -> np.ndarray:
        with self.ptimers("sim"):
            obs = self.sim.reset(-1, dtype=self.OBS_DTYPE)
        self.ep_return, self.ep_len = 0.0, 0
        self.ep_parts = []
        return obs

    def _sim_step(self, action: np.ndarray):
        """``<sim>/step``; adds the reward and the step to the episode. Returns (StepReply, next obs)."""
        with self.ptimers("sim"):
            r = self.sim.step(action, dtype=self.OBS_DTYPE)
        self.ep_return += r.reward
        self.ep_len += 1
        return r, r.observation

    def _episode_over(self, terminated: bool, truncated: bool) -> bool:
        return episode_over(self.episode_rule, terminated, truncated)

    def _transitions_wanted(self) -> bool:
        return self.p.publish_transitions and (self.recorder is not None
                                               or self.transitions_pub.get_subscription_count() > 0)

    def _publish_episode(self, terminated: bool, truncated: bool, *, ep_frames: int, global_frames: int,
                         x: int, **fields) -> None:
        """Count a finished training episode, publish its TransitionBatch (the stored transitions,
        labels included) and then its EpisodeSummary (recording contract), and log it; `fields` go to
        the metrics record, `x` is the TensorBoard step."""
        self.episodes += 1
        self.progress.episode(self.ep_return)
        stamp = self.get_clock().now().to_msg()
        parts, self.ep_parts = self.ep_parts, []
        send_transitions = bool(parts) and self._transitions_wanted()
        if self.flow is not None:
            self._wait_for_recorder(send_transitions)
        with self.ptimers("publish"):
            if send_transitions:
                bm = transitions_to_batch(parts[0] if len(parts) == 1 else Transitions.concatenate(parts))
                bm.header.stamp = stamp
                self.transitions_pub.publish(bm)
                if self.flow is not None:
                    self.flow.sent(self.transitions_pub.topic_name)
            msg = EpisodeSummary(run_id=self.run_id, env_id=self.p.env_id, source="train",
                                 episode_id=self.episodes - 1, episode_return=float(self.ep_return),
                                 length=int(self.ep_len), frames=int(ep_frames), terminated=bool(terminated),
                                 truncated=bool(truncated), global_step=int(self.step),
                                 global_frames=int(global_frames), wall_time_s=float(self.wall_time()))
            msg.header.stamp = stamp
            self.episode_pub.publish(msg)
            if self.flow is not None:
                self.flow.sent(self.episode_pub.topic_name)
        self.metrics.write("episode", source="train", step=self.step, episode=self.episodes - 1,
                           ret=self.ep_return, length=self.ep_len, terminated=terminated, truncated=truncated,
                           wall_time_s=self.wall_time(), **fields)
        self.scalars.scalar("train/episode_return", self.ep_return, x)

    def _wait_for_recorder(self, with_transitions: bool) -> None:
        """record:=true: wait while record_window episodes are not yet in the bag (RecordingFlow)."""
        if self.recorder_proc is not None and self.recorder_proc.poll() is not None:
            self.log.error(f"the recorder process ended with {self.recorder_proc.returncode}; this run is no longer "
                           f"recorded (see {self.run_dir.file('recorder.log')})")
            self.flow = None
            return
        topics = [self.episode_pub.topic_name] + ([self.transitions_pub.topic_name] if with_transitions else [])
        waited, ok = self.flow.wait(*topics, stop=self.stop_event)   # Ctrl-C is not held up
        if waited > 0:
            self.ptimers.add("record_wait", waited)
        if not ok:
            self.log.warning(f"the recorder has not written {self.p.record_window} or more of this run's episodes "
                             f"for record_wait_s={self.p.record_wait_s:g} s; they are written off (the bag may "
                             f"miss them) and training goes on")

    # ------------------------------------------------------------------------------ memory
    def _get_stats(self) -> dict:
        d = self.memory.stats()
        self.rtm_size, self.tm_sets = d["rtm_size"], d["tm_sets"]
        return d

    def _next_batch(self, k: int, source: str, updates_before_reduce: int):
        """(batch, counts) for the next update: a prefetched one, or one sample call that draws the
        batches of min(prefetch_batches, updates_before_reduce) updates from RTM (one batch from TM).
        None when the memory refuses (fewer entries than k: evictions, TM drained); the caller
        refreshes its sizes. ``_reduce_finish`` drops what is left when the RTM changes."""
        if self.prefetched:
            return self.prefetched.pop()
        n = 1
        if source == "rtm":
            n = max(1, min(int(self.p.prefetch_batches), int(updates_before_reduce)))
        with self.ptimers("memory"):
            try:
                t, _, counts = self.memory.sample(int(k), source, num_batches=n)
            except MemoryServiceError:
                return None
        self.sample_calls += 1
        if n == 1:
            return t, counts
        self.prefetched = [(t.take(slice(i * k, (i + 1) * k)), counts[i * k:(i + 1) * k])
                           for i in reversed(range(n))]
        return self.prefetched.pop()

    def _reduce_call(self):
        """One blocking ``<reducer>/reduce`` call (reduce_batch sets, qt_epochs): counters, last_reduce."""
        return self._reduce_finish(self._reduce_send())

    def _reduce_send(self) -> PendingCall:
        return self.reducer_client.send(int(self.p.reduce_batch), int(self.p.qt_epochs))

    def _reduce_overlapped(self) -> bool:
        """reduce_overlap: wait for the reduction in flight (if any), send the next one and return True (the
        caller goes on learning). False = reduce synchronously (overlap off, or RTM still empty)."""
        self._reduce_collect(wait=True)          # at most one in flight
        if not self.p.reduce_overlap or self.rtm_size == 0:
            return False
        self.reduce_pending = self._reduce_send()
        return True

    def _reduce_collect(self, wait: bool):
        """Finish the overlapped reduction if it has answered (wait: block until it has); its response, or
        None. Calls the node's ``_after_reduce(response)``."""
        pending = self.reduce_pending
        if pending is None or not (wait or pending.done()):
            return None
        self.reduce_pending = None
        with self.ptimers("reduce_wait" if not pending.done() else "reduce_collect"):
            r = self._reduce_finish(pending)
        self._after_reduce(r)
        return r

    def _after_reduce(self, r) -> None:
        """Hook: after each reduction's answer (metrics)."""

    def _reduce_finish(self, pending: PendingCall):
        r = self.reducer_client.reply(pending)
        self.prefetched.clear()     # drawn from the RTM this reduction changed: not used
        self.ptimers.add("qt_server" if self.reducer == "qt_trainer" else "memory_reduce_server", r.duration_s, 0)
        self.rtm_size = r.rtm_size
        self.reductions += 1
        self.last_reduce = {"sets": r.sets_reduced, "qt_version": r.qt_version,
                            "qt_loss": r.qt_loss, "duration_s": r.duration_s}
        return r

    def _wait_qt_model(self, version: int) -> None:
        """Wait up to qt_wait_s for the QTModel of `version` to arrive on qt_model."""
        deadline = time.monotonic() + self.p.qt_wait_s
        with self.qt_cond:
            while (self.qt_local is None or self.qt_local.version < version) and time.monotonic() < deadline:
                self.qt_cond.wait(max(0.0, deadline - time.monotonic()))

    # ------------------------------------------------------------------------------ time split
    def _report_timers(self, elapsed: float, steps: int) -> dict:
        """Log the time split; estimate the ROS transport share from small probe calls."""
        p = self.p
        probe_ms = float("nan")
        calls = sum(self.ptimers.calls.get(k, 0) for k in self.TIMED_CALLS)
        if p.transport_probe_calls > 0 and not self.stop_event.is_set():
            probe = functools.partial(self.memory.stats if self.uses_memory else self.sim.info, timeout=10.0)
            try:
                t0 = time.perf_counter()
                for _ in range(p.transport_probe_calls):
                    probe()
                probe_ms = 1000.0 * (time.perf_counter() - t0) / p.transport_probe_calls
            except ServiceError:
                pass
        transport_s = probe_ms / 1000.0 * calls if math.isfinite(probe_ms) else float("nan")
        rate = steps / elapsed if elapsed > 0 else float("nan")
        rec = {"elapsed_s": elapsed, "steps": steps, "steps_per_s": rate, "phases": self.ptimers.as_dict(),
               "ros_round_trip_ms": probe_ms, "service_calls": calls, "transport_estimate_s": transport_s}
        split_note, estimate_note = self._timer_notes(rec, elapsed, steps)
        self.log.info(f"time split over {elapsed:.1f} s, {steps} steps ({rate:.1f} steps/s): "
                      + self.ptimers.summary(elapsed) + split_note)
        self.log.info(f"estimates: ROS round trip {probe_ms:.2f} ms/call x {calls} calls = {transport_s:.1f} s "
                      "transport" + estimate_note)
        self.metrics.write("timers", **rec)
        return rec

    # ------------------------------------------------------------------------------ shutdown
    def shutdown(self) -> None:
        eb = getattr(self, "eval_bridge", None)
        if eb is not None:
            eb.close()
        if getattr(self, "recorder_proc", None) is not None:
            try:
                self._stop_recorder_process()
            except Exception as exc:
                self.log.error(f"stopping the recorder process failed: {exc}")
        try:
            self.spinner.stop()
        except Exception:
            pass
        if self.embedded is not None:
            self.embedded.destroy()
        if self.recorder is not None:
            try:
                self.recorder.close()
            finally:
                self.recorder.destroy_node()
        self.destroy_node()

    # ------------------------------------------------------------------------------ --help
    @classmethod
    def help_text(cls) -> str:
        """The module's usage text and every parameter with its default and description."""
        doc = (sys.modules[cls.__module__].__doc__ or "").strip()
        lines = [doc, "", "Node parameters (--ros-args -p name:=value, or --params-file; read-only):"]
        lines += [f"  {f.name} (default {d!r}): {describe(f)}" for f, d, _ in spec_of(cls.CONFIG)]
        algorithm = {f.name: d for f, d, _ in spec_of(cls.CONFIG)}["algorithm"]
        lcls = cls.LEARNER_CONFIGS[algorithm]
        others = sorted({f"{c.__name__} for {a}" for a, c in cls.LEARNER_CONFIGS.items() if c is not lcls})
        lines += ["", f"Learner hyper-parameters ({lcls.__name__}, algorithm {algorithm}"
                  + (f"; {', '.join(others)}" if others else "") + "):"]
        for f, d, _ in spec_of(lcls):
            if f.name != "variant":
                lines.append(f"  {f.name} (default {cls.LEARNER_OVERRIDES.get(f.name, d)!r}): {describe(f)}")
        lines += ["", "In the embedded bring-up, command-line parameters also reach the embedded sim, memory "
                  "and QT trainer nodes that declare them (docs/sim.md, docs/memory.md, docs/comcact.md)."]
        return "\n".join(lines)


try:   # loaded here, not in the forked child (no imports between fork and exec)
    _LIBC = ctypes.CDLL(None, use_errno=True) if sys.platform.startswith("linux") else None
except OSError:
    _LIBC = None


def _die_with_parent(parent_pid: int) -> None:
    """preexec_fn of the recorder process: SIGTERM when the parent (the agent) dies (Linux prctl).
    A parent that died between fork and prctl sends nothing: then the child exits here (the
    documented race of PR_SET_PDEATHSIG)."""
    if _LIBC is not None:
        _LIBC.prctl(1, int(signal.SIGTERM))   # PR_SET_PDEATHSIG = 1
        if os.getppid() != parent_pid:
            os._exit(1)


def run_main(node_cls: type, name: str, args=None) -> int:
    """An agent node's entry point: 0 done (or stopped with Ctrl-C / SIGTERM after saving), 1 cannot
    start / failed, 130 aborted by a second Ctrl-C. ``--help`` prints the parameters."""
    argv = sys.argv if args is None else args
    if "-h" in argv[1:] or "--help" in argv[1:]:
        print(node_cls.help_text())
        return 0
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    logger = rclpy.logging.get_logger(name)
    node = None
    stop = threading.Event()

    def on_signal(signum, _frame):
        if stop.is_set():
            raise KeyboardInterrupt
        stop.set()
        if node is not None:
            node.stop_event.set()
        logger.warning("stop requested: finishing the current step, then saving a checkpoint "
                       "(Ctrl-C again to abort)")

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    rc = 0
    try:
        try:
            node = node_cls()
            if stop.is_set():
                node.stop_event.set()
        except Exception as exc:   # bad parameter, unknown task, missing nodes: one readable message
            logger.error(f"cannot start: {exc}")
            return 1
        rc = node.run()
    except KeyboardInterrupt:
        rc = 130
    finally:
        if node is not None:
            node.shutdown()
        rclpy.try_shutdown()
    return rc
