"""agent_node: what the learner nodes (comcact_node, comper_node) share.

:class:`AgentNode` - the learner node's lifecycle: parameters (``node_config``, ``declare_config``,
profiles), the run's outputs (:class:`~comper_agent.agent_run.AgentRun`), the embedded bring-up
(:mod:`comper_agent.bringup`), the memory link (:class:`~comper_agent.memory_link.MemoryLink`)
and the recording link (:class:`~comper_agent.recording_link.RecordingLink`), the sim client,
``~/episodes``, ``~/evaluations`` and ``~/transitions``, evaluation on a separate environment,
checkpoints, the run loop's start / stop / final save, the time split and shutdown. A subclass
supplies the algorithm through the hooks below (``_setup_learner``, ``_loop``, ``_start_line``,
``_progress_line``, checkpoint contents, ...). The entry point is :mod:`comper_agent.agent_main`.

Size: about half of AgentNode's methods are those hooks (each a few lines with its contract);
the parts that hold state of their own live in the modules named above.
"""
from __future__ import annotations

import functools
import threading
import time
from pathlib import Path

import numpy as np
from rclpy.node import Node

from comper_msgs.msg import EpisodeSummary, EvaluationResult, TransitionBatch
from comper_msgs_py.arrays import Transitions
from comper_msgs_py.convert import transitions_to_batch
from comper_msgs_py.params import config_to_dict
from comper_msgs_py.qos import RECORDED_QOS
from comper_msgs_py.ros_params import declare_config
from comper_msgs_py.service_client import ServiceError, wait_for_services
from comper_sim.client import SimClient
from comper_sim.core import episode_over

from . import run_io
from .agent_main import run_main
from .agent_run import AgentRun
from .bringup import START_HINTS, Spinner, make_embedded_nodes
from .recording_link import RecordingLink, record_topics
from .memory_link import MemoryLink
from .node_config import AgentRunConfig, redefault

__all__ = ["AgentNode", "AgentRunConfig", "run_main", "redefault", "episode_over", "SUMMARY_QOS"]

#: QoS of ~/episodes, ~/evaluations, ~/transitions (the recording contract, docs/recording.md)
SUMMARY_QOS = RECORDED_QOS


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
        self._configure()
        self._open_run_dir()

        # publishers / subscriptions (served by the background executor)
        self.episode_pub = self.create_publisher(EpisodeSummary, "~/episodes", SUMMARY_QOS)
        self.eval_pub = self.create_publisher(EvaluationResult, "~/evaluations", SUMMARY_QOS)
        self.transitions_pub = self.create_publisher(TransitionBatch, "~/transitions", SUMMARY_QOS)
        self.ep_parts: list[Transitions] = []     # the current training episode's stored transitions
        self.mem = (MemoryLink(self, p, reducer=self.reducer, uses_qt=self.uses_qt, timers=self.ptimers,
                               device=self.cfg.device, on_reduced=self._after_reduce)
                    if self.uses_memory else None)
        self._bring_up()

    # ------------------------------------------------------------------------------ hooks
    def _profile_overrides(self, values: dict) -> dict:
        """Defaults chosen by a named profile, for node and learner parameters alike; `values`: the
        node parameters declared so far (algorithm, env_id and profile come first). The command
        line and parameter files still win."""
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
        """The run directory (AgentRun); on resume, it and the run id come from the checkpoint."""
        self.outputs = AgentRun(self.p, int(self.cfg.seed))
        self.run_id, self.run_dir = self.outputs.run_id, self.outputs.dir

    def _bring_up(self) -> None:
        """The embedded nodes (bringup:=embedded), the recording link (record:=true), the executor
        threads, then the service clients."""
        p = self.p
        self.embedded = None
        self.recording = None
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
        try:
            if p.record:
                topics = record_topics(self.get_fully_qualified_name(), p.sim_node,
                                       p.memory_node if self.uses_memory else None)
                self.recording = RecordingLink(self, p, self.run_id, self.run_dir, topics)
                nodes += self.recording.nodes
        except BaseException:
            if self.embedded is not None:
                self.embedded.destroy()
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
        self._check_env(info)

    def _reset_counters(self) -> None:
        self.step = 0
        self.episodes = 0
        self.stored = 0            # transitions given to the memory / replay
        self.last_update: dict = {}
        if self.mem is not None:
            self.mem.reset()

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
        self.step, self.episodes = int(c["step"]), int(c["episodes"])
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
                "resumed_from": str(self.outputs.resume_path) if self.outputs.resume_state is not None else None}

    def wall_time(self) -> float:
        return self.outputs.wall_time()

    def save(self, final: bool = False) -> Path:
        with self.ptimers("io"):
            path = self.outputs.save(self._state(), self.step)
        self.log.info(f"{'final ' if final else ''}checkpoint: {path}")
        return path

    # ------------------------------------------------------------------------------ main loop
    def run(self) -> int:
        p = self.p
        self._reset_counters()
        self._setup_learner()
        run = self.outputs
        if run.resume_state is not None:
            self._restore(run.resume_state)
        run.open_logs(self._run_config(), self.CSV_COLUMNS, self._progress_total(), self.step)
        self.metrics, self.csv, self.scalars, self.progress = run.metrics, run.csv, run.scalars, run.progress
        start_step = self.step
        self.log.info(f"{self._start_line()}; run dir {run.dir.path}  (Ctrl-C stops and saves a checkpoint)")
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
                self.save(final=True)
            except Exception as exc:
                self.log.error(f"final checkpoint failed: {exc}")
            timers = self._report_timers(elapsed, self.step - start_step)
            self._finish(elapsed, self.step - start_step, timers)
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

    def _progress_total(self) -> int:
        return int(self.p.total_steps)

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

    def _transitions_wanted(self) -> bool:
        return self.p.publish_transitions and (self.recording is not None
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
        if self.recording is not None:
            topics = [self.episode_pub.topic_name] + ([self.transitions_pub.topic_name] if send_transitions else [])
            waited = self.recording.wait_window(topics, self.stop_event)
            if waited > 0:
                self.ptimers.add("record_wait", waited)
        with self.ptimers("publish"):
            if send_transitions:
                bm = transitions_to_batch(parts[0] if len(parts) == 1 else Transitions.concatenate(parts))
                bm.header.stamp = stamp
                self.transitions_pub.publish(bm)
                if self.recording is not None:
                    self.recording.sent(self.transitions_pub.topic_name)
            msg = EpisodeSummary(run_id=self.run_id, env_id=self.p.env_id, source="train",
                                 episode_id=self.episodes - 1, episode_return=float(self.ep_return),
                                 length=int(self.ep_len), frames=int(ep_frames), terminated=bool(terminated),
                                 truncated=bool(truncated), global_step=int(self.step),
                                 global_frames=int(global_frames), wall_time_s=float(self.wall_time()))
            msg.header.stamp = stamp
            self.episode_pub.publish(msg)
            if self.recording is not None:
                self.recording.sent(self.episode_pub.topic_name)
        self.metrics.write("episode", source="train", step=self.step, episode=self.episodes - 1,
                           ret=self.ep_return, length=self.ep_len, terminated=terminated, truncated=truncated,
                           wall_time_s=self.wall_time(), **fields)
        self.scalars.scalar("train/episode_return", self.ep_return, x)

    # ------------------------------------------------------------------------------ memory
    def _after_reduce(self, r) -> None:
        """Hook: after each reduction's answer (metrics)."""

    # ------------------------------------------------------------------------------ time split
    def _report_timers(self, elapsed: float, steps: int) -> dict:
        """Log the time split; estimate the ROS transport share from small probe calls."""
        calls = sum(self.ptimers.calls.get(k, 0) for k in self.TIMED_CALLS)
        probe = (None if self.stop_event.is_set() else
                 functools.partial(self.mem.memory.stats if self.mem is not None else self.sim.info, timeout=10.0))
        rec = self.outputs.time_split(self.ptimers, elapsed, steps, calls, probe, self.p.transport_probe_calls)
        split_note, estimate_note = self._timer_notes(rec, elapsed, steps)
        self.log.info(f"time split over {elapsed:.1f} s, {steps} steps ({rec['steps_per_s']:.1f} steps/s): "
                      + self.ptimers.summary(elapsed) + split_note)
        self.log.info(f"estimates: ROS round trip {rec['ros_round_trip_ms']:.2f} ms/call x {calls} calls = "
                      f"{rec['transport_estimate_s']:.1f} s transport" + estimate_note)
        self.metrics.write("timers", **rec)
        return rec

    # ------------------------------------------------------------------------------ shutdown
    def shutdown(self) -> None:
        eb = getattr(self, "eval_bridge", None)
        if eb is not None:
            eb.close()
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
