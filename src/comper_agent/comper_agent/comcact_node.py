"""comcact_node: the COMCACT learner (thesis Algorithm 8; method.md section 4) and the DDPG baseline.

    ros2 run comper_agent comcact_node                      # InvertedPendulum-v4, everything in-process
    ros2 run comper_agent comcact_node --ros-args -p env_id:=Hopper-v4 -p total_steps:=50000
    ros2 run comper_agent comcact_node --ros-args -p algorithm:=ddpg
    ros2 run comper_agent comcact_node --ros-args -p bringup:=external -p sim_node:=sim_node \
        -p memory_node:=memory_node -p qt_trainer_node:=qt_trainer_node
    ros2 run comper_agent comcact_node --ros-args -p resume:=runs/<run_id>
    ros2 run comper_agent comcact_node --ros-args --params-file src/comper_agent/config/comcact.yaml

Bring-up. ``embedded`` (default) builds the simulation, memory and QT trainer nodes in this
process (separate node objects, one MultiThreadedExecutor in a background thread); the learner
loop runs in the main thread and talks to them only through ROS services and topics.
``external`` uses nodes started separately (``ros2 run comper_sim sim_node`` ...), by name.
Command-line parameters reach every embedded node that declares them (``-p delta:=1e-3`` sets the
memory's threshold; ``-p seed:=1`` seeds simulation and learner).

One agent step (COMCACT): act with OU noise (per action dimension, reset each episode), clipped to
the bounds -> ``<sim>/step`` -> store the transition with its value label in the memory ->
sample ``batch_size`` from RTM (TM while RTM is empty, Algorithm 8 lines 14-17) -> DDPG critic
and actor update -> reduce when due (every ``reduce_every`` updates and whenever RTM is empty:
``<qt_trainer>/reduce``) -> extra critic step towards r + gamma (1 - terminated) QT(tau), QT being
the local copy of the latest published QTModel -> soft target updates. ``algorithm:=ddpg``: plain
uniform replay in this process, no QT step, no memory or QT trainer needed.

Evaluation: every ``eval_every`` steps, ``eval_episodes`` full deterministic episodes (no noise) on
a separate environment instance inside this learner (a second gymnasium env, the "separate
environment" of the protocol), published on ``~/evaluations`` (EvaluationResult) and
``~/episodes`` (EpisodeSummary, source eval; training episodes have source train).

Outputs in ``<runs_root>/<run_id>/``: config.yaml, metrics.jsonl, progress.csv, tb/ (TensorBoard),
checkpoints/ (see :mod:`comper_agent.run_io`). Ctrl-C stops after the current step, saves a final
checkpoint and flushes the logs (a second Ctrl-C aborts).
"""
from __future__ import annotations

import math
import os
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np
import rclpy
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions

from comper_msgs.msg import EpisodeSummary, EvaluationResult, TransitionBatch
from comper_msgs.msg import QTModel as QTModelMsg
from comper_msgs.srv import EnvInfo, GetStats, Reduce, Reset, Sample, Step, StepMany, Store
from comper_msgs_py.arrays import Transitions
from comper_msgs_py.convert import (array_to_numpy, batch_to_transitions, numpy_to_array,
                                    numpy_to_seq, seq_to_numpy, transitions_to_batch)
from comper_msgs_py.params import config_to_dict
from comper_msgs_py.ros_params import declare_config

from . import run_io
from .bringup import (START_HINTS, ServiceError, Spinner, call, make_embedded_nodes,
                      wait_for_services)
from .core.config import ComcactConfig, DDPGConfig
from .qt_trainer_node import QT_MODEL_QOS, msg_to_qt

__all__ = ["ComcactNode", "LearnerParams", "main", "SUMMARY_QOS"]

SUMMARY_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                         reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)

# name, default, description (thesis value where there is one)
LEARNER_PARAMS = [
    ("algorithm", "comcact", "comcact (Algorithm 8: memory + QT step) or ddpg (baseline: plain uniform "
     "replay in this process, no QT step, no memory / QT trainer nodes)"),
    ("bringup", "embedded", "embedded: build sim, memory and QT trainer nodes in this process; external: "
     "use nodes started separately (names below)"),
    ("env_id", "InvertedPendulum-v4", "gymnasium task (continuous actions): InvertedPendulum-v4, Hopper-v4, "
     "Walker2d-v4, HalfCheetah-v4, InvertedDoublePendulum-v4, Pendulum-v1, ... (embedded: given to the "
     "sim node; external: must match the running sim node)"),
    ("episode_end", "standard", "embedded sim node's episode end rule: standard | truncation_only | "
     "termination_only (method.md 6.3; only terminated masks the bootstrap). External: the sim's rule is used"),
    ("total_steps", 50_000, "agent (environment) steps of the run. Thesis: 50,000 (chapter 6)"),
    ("warmup_steps", 0, "steps of uniformly random actions before the policy acts (sent in batches "
     "with step_many; no updates meanwhile); 0 = act with mu + noise from the first step. Thesis: not "
     "given (Algorithm 8 acts with the policy from step 1)"),
    ("store_every", 1, "agent steps per memory store call (labels are computed when stored; an "
     "episode end always flushes). Thesis: every step"),
    ("reduce_every", 10, "DDPG updates between reductions (a reduction also runs whenever RTM is empty). "
     "Thesis: every iteration (1; Algorithm 8 line 27-28). Default chosen by measurement (docs/comcact.md)"),
    ("reduce_batch", 50_000, "most sets popped from TM per reduction. Thesis: 50,000 (appendix B)"),
    ("qt_epochs", 0, "QT training passes per reduction; 0 = the QT trainer's qt_epochs parameter "
     "(default 1, Keras fit default). Thesis: not given"),
    ("qt_targets", "local", "where QT(tau) for the extra critic step comes from: local = predict with the "
     "latest QTModel received (Algorithm 8 lines 29-30); rtm = the prediction the RTM stored at the "
     "entry's last reduction (returned by sample)"),
    ("qt_wait_s", 2.0, "after a reduction, seconds to wait for the QTModel of that version to arrive"),
    ("eval_every", 5_000, "steps between evaluations (0 = never). Thesis: 5,000 (chapter 6)"),
    ("eval_episodes", 10, "full deterministic episodes per evaluation. Thesis: 10 (chapter 6)"),
    ("eval_seed", -1, "seed of the evaluation environment's resets (episode k of every evaluation "
     "starts from seed eval_seed + k); -1 = seed + 1000"),
    ("runs_root", "runs", "folder holding the run directories"),
    ("run_id", "", "run directory name; '' = <algorithm>-<env>-s<seed>-<timestamp>"),
    ("resume", "", "checkpoint file or run directory to continue from ('' = fresh run). The run "
     "continues in the checkpoint's run directory with its step count; the memory / replay contents "
     "are not in the checkpoint and refill from the resumed step"),
    ("checkpoint_every", 0, "steps between checkpoints (0 = at every evaluation point); a final one is "
     "always written"),
    ("keep_checkpoints", 3, "step_<N>.pt files kept besides latest.pt"),
    ("progress_period_s", 5.0, "seconds between console progress lines"),
    ("record", False, "record this run's topics (transitions, episodes, evaluations, memory stats, sim "
     "episodes) into a rosbag2 bag in <run dir>/bag with an in-process recorder_node (docs/recording.md)"),
    ("record_storage", "mcap", "bag storage when record is on: mcap | sqlite3"),
    ("tensorboard", True, "write TensorBoard scalars to <run dir>/tb"),
    ("sim_node", "sim_node", "name of the simulation node"),
    ("memory_node", "memory_node", "name of the memory node (comcact)"),
    ("qt_trainer_node", "qt_trainer_node", "name of the QT trainer node (comcact)"),
    ("service_timeout_s", 120.0, "seconds to wait for any one service answer"),
    ("startup_timeout_s", 30.0, "seconds to wait for the nodes' services at start"),
    ("transport_probe_calls", 200, "at the end, this many small service calls measure the ROS round "
     "trip for the time split (0 = skip)"),
]


class LearnerParams:
    """The learner node's own parameters as attributes."""

    def __init__(self, node: Node):
        for name, default, text in LEARNER_PARAMS:
            # dynamic typing + coercion: `-p startup_timeout_s:=60` (an integer) is fine for a float
            value = node.declare_parameter(name, default, ParameterDescriptor(
                description=text, read_only=True, dynamic_typing=True)).value
            try:
                value = type(default)(value) if not isinstance(default, bool) else _as_bool(value)
            except (TypeError, ValueError):
                raise ValueError(f"parameter '{name}': cannot use {value!r} as {type(default).__name__} "
                                 f"({text})") from None
            setattr(self, name, value)

    def as_dict(self) -> dict:
        return {name: getattr(self, name) for name, _, _ in LEARNER_PARAMS}


def _as_bool(value) -> bool:
    if isinstance(value, str):
        if value.lower() in ("true", "1", "yes"):
            return True
        if value.lower() in ("false", "0", "no"):
            return False
        raise ValueError(value)
    return bool(value)


def _episode_over(rule: str, terminated: bool, truncated: bool) -> bool:
    if rule == "truncation_only":
        return bool(truncated)
    if rule == "termination_only":
        return bool(terminated)
    return bool(terminated or truncated)


class ComcactNode(Node):
    """The learner node. Construction declares parameters and brings up the other nodes; ``run()``
    trains (main thread) while a background executor serves ROS."""

    def __init__(self, node_name: str = "comcact_node", **node_kwargs):
        super().__init__(node_name, **node_kwargs)
        self.p = p = LearnerParams(self)
        if p.algorithm not in ("comcact", "ddpg"):
            raise ValueError(f"algorithm must be comcact or ddpg, got {p.algorithm!r}")
        if p.bringup not in ("embedded", "external"):
            raise ValueError(f"bringup must be embedded or external, got {p.bringup!r}")
        if p.qt_targets not in ("local", "rtm"):
            raise ValueError(f"qt_targets must be local or rtm, got {p.qt_targets!r}")
        for name in ("total_steps", "store_every", "reduce_every", "eval_episodes"):
            if getattr(p, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(p, name)}")
        cls = ComcactConfig if p.algorithm == "comcact" else DDPGConfig
        # num_threads 1: the 400/300 nets at batch 64 gain nothing from a second intra-op thread on the
        # 2-core machine, and the ROS executor threads need the other core (docs/comcact.md)
        self.cfg = declare_config(self, cls, overrides={"variant": p.algorithm, "num_threads": 1})
        if self.cfg.variant != p.algorithm:
            raise ValueError(f"variant:={self.cfg.variant} contradicts algorithm:={p.algorithm}; set algorithm only")
        self.comcact = p.algorithm == "comcact"
        self.stop_event = threading.Event()
        self.ptimers = run_io.PhaseTimers()
        self.log = self.get_logger()

        # resume: the run directory and id come from the checkpoint
        self.resume_state = None
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

        # publishers / subscriptions (served by the background executor)
        self.eval_pub = self.create_publisher(EvaluationResult, "~/evaluations", SUMMARY_QOS)
        self.episode_pub = self.create_publisher(EpisodeSummary, "~/episodes", SUMMARY_QOS)
        # one TransitionBatch per finished training episode, labels as stored (recording contract)
        self.transitions_pub = self.create_publisher(TransitionBatch, "~/transitions", SUMMARY_QOS)
        self.ep_parts: list[Transitions] = []
        self.qt_local = None
        self.qt_cond = threading.Condition()
        self.qt_received = 0
        if self.comcact:
            self.create_subscription(QTModelMsg, f"/{p.qt_trainer_node.strip('/')}/qt_model",
                                     self._on_qt_model, QT_MODEL_QOS)

        # bring-up
        self.embedded = None
        nodes: list[Node] = [self]
        if p.bringup == "embedded":
            self.embedded = make_embedded_nodes(
                self.context, sim_name=p.sim_node,
                sim_params={"env_id": p.env_id, "episode_end": p.episode_end, "run_id": run_id,
                            "seed": int(self.cfg.seed)},
                memory_name=p.memory_node if self.comcact else None, memory_params={},
                qt_name=p.qt_trainer_node if self.comcact else None,
                qt_params={"memory_node": p.memory_node, "reduce_batch": int(p.reduce_batch)})
            nodes += self.embedded.all
        self.recorder = None
        if p.record:
            nodes.append(self._make_recorder(run_id))
        self.spinner = Spinner(nodes, self.context, num_threads=4).start()
        try:
            self._connect()
        except BaseException:
            self.shutdown()
            raise

    def _make_recorder(self, run_id: str) -> Node:
        from rclpy.parameter import Parameter

        from .recorder_node import RecorderNode
        me = self.get_fully_qualified_name()
        topics = [f"{me}/transitions", f"{me}/episodes", f"{me}/evaluations",
                  f"/{self.p.sim_node.strip('/')}/episodes"]
        if self.comcact:
            topics.append(f"/{self.p.memory_node.strip('/')}/stats")
        self.recorder = RecorderNode(context=self.context, parameter_overrides=[
            Parameter("run_id", value=run_id), Parameter("algorithm", value=self.p.algorithm),
            Parameter("output_dir", value=str(self.run_dir.path.parent)),
            Parameter("storage", value=self.p.record_storage), Parameter("topics", value=topics)])
        return self.recorder

    def _connect(self) -> None:
        p = self.p
        sim = p.sim_node.strip("/")
        self.c_reset = self.create_client(Reset, f"/{sim}/reset")
        self.c_step = self.create_client(Step, f"/{sim}/step")
        self.c_step_many = self.create_client(StepMany, f"/{sim}/step_many")
        self.c_info = self.create_client(EnvInfo, f"/{sim}/info")
        clients = {"sim": self.c_step}
        if self.comcact:
            mem = p.memory_node.strip("/")
            self.c_store = self.create_client(Store, f"/{mem}/store")
            self.c_sample = self.create_client(Sample, f"/{mem}/sample")
            self.c_stats = self.create_client(GetStats, f"/{mem}/get_stats")
            self.c_reduce = self.create_client(Reduce, f"/{p.qt_trainer_node.strip('/')}/reduce")
            clients.update({"memory": self.c_store, "qt_trainer": self.c_reduce})
        hints = {"sim": START_HINTS["sim"].format(name=sim),
                 "memory": START_HINTS["memory"].format(name=p.memory_node),
                 "qt_trainer": START_HINTS["qt_trainer"].format(name=p.qt_trainer_node)}
        wait_for_services(clients, p.startup_timeout_s, hints, self.stop_event)

        info = call(self.c_info, EnvInfo.Request(), p.startup_timeout_s, check=False)
        if info.discrete:
            raise ValueError(f"{info.env_id} has discrete actions; COMCACT/DDPG need a continuous task "
                             "(use comper_node for Atari)")
        if info.env_id != p.env_id:
            raise ValueError(f"the sim node /{sim} serves {info.env_id}, not env_id:={p.env_id}; "
                             f"set -p env_id:={info.env_id} or restart the sim node")
        self.info = info
        self.episode_rule = info.episode_end or "standard"
        self.obs_shape = tuple(int(d) for d in info.observation_shape)
        self.low = seq_to_numpy(info.action_low, np.float32).copy()
        self.high = seq_to_numpy(info.action_high, np.float32).copy()
        self.action_dim = int(self.low.size)

    # ------------------------------------------------------------------------------ ROS callbacks
    def _on_qt_model(self, msg: QTModelMsg) -> None:
        try:
            model = msg_to_qt(msg, device=self.cfg.device)
        except Exception as exc:
            self.log.error(f"cannot rebuild the published QTModel v{msg.version}: {exc}")
            return
        with self.qt_cond:
            if self.qt_local is None or model.version >= self.qt_local.version:
                self.qt_local = model
            self.qt_received += 1
            self.qt_cond.notify_all()

    # ------------------------------------------------------------------------------ setup
    def _setup_learner(self) -> None:
        from .core.comcact import ComcactLearner
        from .core.networks import configure_torch
        from .core.replay import ReplayBuffer
        configure_torch(self.cfg.num_threads)
        obs_dim = int(np.prod(self.obs_shape))
        self.learner = ComcactLearner(self.cfg, obs_dim, self.low, self.high)
        self.replay = None
        if not self.comcact:
            self.replay = ReplayBuffer(self.cfg.replay_size, self.obs_shape, (self.action_dim,),
                                       seed=self.cfg.seed)
        from comper_sim.core import SimBridge, SimConfig
        p = self.p
        self.eval_seed = p.eval_seed if p.eval_seed >= 0 else self.cfg.seed + 1000
        self.eval_bridge = SimBridge(SimConfig(env_id=p.env_id, seed=self.eval_seed, episode_end="standard",
                                               action_out_of_range="clip", run_id=self.run_id))
        self.rng = np.random.default_rng(self.cfg.seed + 7)   # warm-up actions
        # counters
        self.step = 0
        self.episodes = 0
        self.stored = 0            # transitions given to the memory / replay
        self.since_reduce = 0
        self.rtm_size = 0
        self.reductions = 0
        self.last_reduce: dict = {}
        self.evals: list[dict] = []
        self.wall_offset = 0.0
        self.last_update: dict = {}
        self.update_count = 0

    def _restore(self, state: dict) -> None:
        self.learner.load_state_dict(state["learner"])
        c = state["counters"]
        self.step, self.episodes = int(c["step"]), int(c["episodes"])
        self.wall_offset = float(c.get("wall_time_s", 0.0))
        self.evals = list(state.get("evals", []))
        self.rng.bit_generator.state = state["warmup_rng"]
        run_io.set_rng_state(state["rng"])
        qt_state = state.get("qt_trainer")
        if self.comcact and qt_state and self.embedded is not None and self.embedded.qt_trainer is not None:
            self.embedded.qt_trainer.load_state_dict(qt_state)

    def _state(self) -> dict:
        st = {"run": {"run_id": self.run_id, "algorithm": self.p.algorithm, "env_id": self.p.env_id},
              "learner": self.learner.state_dict(),
              "counters": {"step": self.step, "episodes": self.episodes, "stored": self.stored,
                           "reductions": self.reductions, "wall_time_s": self.wall_time()},
              "evals": self.evals, "warmup_rng": self.rng.bit_generator.state, "rng": run_io.rng_state(),
              "config": {"learner": _plain_cfg(config_to_dict(self.cfg)), "params": self.p.as_dict()}}
        if self.comcact and self.embedded is not None and self.embedded.qt_trainer is not None:
            st["qt_trainer"] = self.embedded.qt_trainer.state_dict()
        return st

    def wall_time(self) -> float:
        return self.wall_offset + (time.monotonic() - self.t_start)

    # ------------------------------------------------------------------------------ sim
    def _reset_env(self) -> np.ndarray:
        with self.ptimers("sim"):
            r = call(self.c_reset, Reset.Request(seed=-1), self.p.service_timeout_s)
        self.learner.reset_noise()
        self.ep_return, self.ep_len = 0.0, 0
        return np.array(array_to_numpy(r.observation), dtype=np.float32)

    def _end_episode(self, terminated: bool, truncated: bool) -> None:
        if self.ep_parts:
            t = self.ep_parts[0] if len(self.ep_parts) == 1 else Transitions.concatenate(self.ep_parts)
            self.ep_parts = []
            msg = transitions_to_batch(t)
            msg.header.stamp = self.get_clock().now().to_msg()
            self.transitions_pub.publish(msg)
        self.episodes += 1
        self.progress.episode(self.ep_return)
        msg = EpisodeSummary(run_id=self.run_id, env_id=self.p.env_id, source="train",
                             episode_id=self.episodes - 1, episode_return=float(self.ep_return),
                             length=int(self.ep_len), frames=int(self.ep_len), terminated=bool(terminated),
                             truncated=bool(truncated), global_step=int(self.step),
                             global_frames=int(self.step), wall_time_s=float(self.wall_time()))
        msg.header.stamp = self.get_clock().now().to_msg()
        self.episode_pub.publish(msg)
        self.metrics.write("episode", source="train", step=self.step, episode=self.episodes - 1,
                           ret=self.ep_return, length=self.ep_len, terminated=terminated, truncated=truncated,
                           wall_time_s=self.wall_time())
        self.scalars.scalar("train/episode_return", self.ep_return, self.step)
        self.ep_return, self.ep_len = 0.0, 0

    # ------------------------------------------------------------------------------ memory
    def _store(self, t: Transitions) -> None:
        if len(t) == 0:
            return
        if not self.comcact:
            with self.ptimers("learner"):
                self.replay.add(t)
            self.stored += len(t)
            self.ep_parts.append(t)
            return
        with self.ptimers("learner"):
            t.value_labels = self.learner.value_labels(t)
        req = Store.Request()
        transitions_to_batch(t, req.batch)
        with self.ptimers("memory"):
            call(self.c_store, req, self.p.service_timeout_s)
        self.stored += len(t)
        self.ep_parts.append(t)

    def _flush(self) -> None:
        if self.pending:
            cols = list(zip(*self.pending))
            self.pending = []
            n = len(cols[0])
            t = Transitions(states=np.stack(cols[0]), actions=np.stack(cols[1]).astype(np.float32),
                            rewards=np.asarray(cols[2], np.float32), next_states=np.stack(cols[3]),
                            terminated=np.asarray(cols[4], bool), truncated=np.asarray(cols[5], bool),
                            episode_ids=np.full(n, self.episodes, np.uint64),
                            steps=np.asarray(cols[6], np.uint64), run_id=self.run_id)
            self._store(t)

    def _sample(self) -> Transitions | None:
        k = self.cfg.batch_size
        source = Sample.Request.SOURCE_RTM
        if self.rtm_size <= 1:
            with self.ptimers("memory"):
                stats = call(self.c_stats, GetStats.Request(), self.p.service_timeout_s, check=False).stats
            self.rtm_size = int(stats.rtm_size)
            if self.rtm_size <= 1:
                source, avail = Sample.Request.SOURCE_TM, int(stats.tm_sets)
            else:
                avail = self.rtm_size
        else:
            avail = self.rtm_size
        k = min(k, avail)
        if k < 2:
            return None
        with self.ptimers("memory"):
            r = call(self.c_sample, Sample.Request(batch_size=k, source=source, seed=-1),
                     self.p.service_timeout_s, check=False)
        if not r.success:    # RTM shrank (evictions): refresh its size next time
            self.rtm_size = 0
            return None
        return batch_to_transitions(r.batch)

    def _reduce(self) -> None:
        p = self.p
        with self.ptimers("qt"):
            r = call(self.c_reduce, Reduce.Request(max_sets=int(p.reduce_batch), epochs=int(p.qt_epochs)),
                     p.service_timeout_s)
            self.ptimers.add("qt_server", r.duration_s, 0)
            self.rtm_size = int(r.rtm_size)
            self.since_reduce = 0
            self.reductions += 1
            self.last_reduce = {"sets": int(r.sets_reduced), "qt_version": int(r.qt_version),
                                "qt_loss": float(r.qt_loss), "duration_s": float(r.duration_s)}
            if p.qt_targets == "local" and r.qt_version > 0:
                deadline = time.monotonic() + p.qt_wait_s
                with self.qt_cond:
                    while (self.qt_local is None or self.qt_local.version < r.qt_version) \
                            and time.monotonic() < deadline:
                        self.qt_cond.wait(max(0.0, deadline - time.monotonic()))

    # ------------------------------------------------------------------------------ learning
    def _train_step(self) -> None:
        if self.comcact:
            batch = self._sample()
            if batch is None:
                return
            with self.ptimers("learner"):
                self.last_update = self.learner.update(batch)
            self.since_reduce += 1
            if self.since_reduce >= self.p.reduce_every or self.rtm_size == 0:
                self._reduce()
            targets = None
            if self.p.qt_targets == "rtm":
                if self.rtm_size > 0 and batch.value_labels.size == len(batch):
                    targets = batch.value_labels
            else:
                with self.qt_cond:
                    qt = self.qt_local
                if qt is not None:
                    from comper_memory.core import transition_keys
                    with self.ptimers("qt_predict"):
                        targets = qt.predict_transitions(batch, transition_keys)
            with self.ptimers("learner"):
                if targets is not None:
                    self.last_update.update(self.learner.qt_critic_step(batch, targets))
                self.learner.soft_update()
        else:
            with self.ptimers("learner"):
                batch = self.replay.sample(self.cfg.batch_size)
                self.last_update = self.learner.update(batch)
                self.learner.soft_update()
        self.update_count += 1
        if self.update_count % 250 == 0:
            self.scalars.scalars(self.last_update, self.step, prefix="train/")

    # ------------------------------------------------------------------------------ evaluation
    def evaluate(self) -> dict:
        p = self.p
        rets, lens = [], []
        with self.ptimers("eval"):
            for k in range(p.eval_episodes):
                obs, _ = self.eval_bridge.reset(self.eval_seed + k)
                ret, n = 0.0, 0
                while True:
                    a = self.learner.act(np.asarray(obs, np.float32), explore=False)
                    res = self.eval_bridge.step(a)
                    ret += float(res.reward)
                    n += 1
                    obs = res.observation
                    if res.episode_over:
                        break
                rets.append(ret)
                lens.append(n)
                ep = EpisodeSummary(run_id=self.run_id, env_id=p.env_id, source="eval", episode_id=k,
                                    episode_return=ret, length=n, frames=n, terminated=bool(res.terminated),
                                    truncated=bool(res.truncated), global_step=self.step,
                                    global_frames=self.step, wall_time_s=self.wall_time())
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
        self.csv.write(step=self.step, wall_time_s=round(self.wall_time(), 2), eval_mean_return=mean,
                       eval_std_return=std, episodes=self.episodes,
                       last_train_return=self.progress.last_episode_return,
                       steps_per_s=round(self.progress.overall_rate(self.step), 1),
                       rtm_size=self.rtm_size if self.comcact else self.stored,
                       critic_loss=self.last_update.get("critic_loss"))
        self.scalars.scalar("eval/mean_return", mean, self.step)
        self.scalars.scalar("eval/std_return", std, self.step)
        self.progress.evaluation(mean)
        self.log.info(f"evaluation at step {self.step}: return {mean:.1f} +- {std:.1f} over "
                      f"{len(rets)} episodes (lengths {min(lens)}-{max(lens)})")
        return rec

    # ------------------------------------------------------------------------------ checkpoints
    def save(self, final: bool = False) -> Path:
        with self.ptimers("io"):
            path = self.run_dir.save_checkpoint(self._state(), self.step, self.p.keep_checkpoints)
            self.metrics.flush()
        self.log.info(f"{'final ' if final else ''}checkpoint: {path}")
        return path

    # ------------------------------------------------------------------------------ main loop
    def run(self) -> int:
        p = self.p
        self._setup_learner()
        if self.resume_state is not None:
            self._restore(self.resume_state)
        rd = self.run_dir
        rd.write_config({"algorithm": p.algorithm, "params": p.as_dict(), "learner": config_to_dict(self.cfg),
                         "qt_trainer": (config_to_dict(self.embedded.qt_trainer.qt_config)
                                        if self.embedded is not None and self.embedded.qt_trainer else None),
                         "env": {"env_id": self.info.env_id, "observation_shape": list(self.obs_shape),
                                 "action_low": self.low.tolist(), "action_high": self.high.tolist(),
                                 "episode_end": self.episode_rule,
                                 "max_episode_steps": int(self.info.max_episode_steps)},
                         "resumed_from": str(self.resume_path) if self.resume_state is not None else None})
        self.metrics = run_io.MetricsLog(rd.file("metrics.jsonl"))
        self.csv = run_io.CsvLog(rd.file("progress.csv"),
                                 ["step", "wall_time_s", "eval_mean_return", "eval_std_return", "episodes",
                                  "last_train_return", "steps_per_s", "rtm_size", "critic_loss"])
        self.scalars = run_io.ScalarLog(rd.file("tb") if p.tensorboard else None)
        self.progress = run_io.Progress(p.total_steps, p.progress_period_s, start_step=self.step)
        self.t_start = time.monotonic()
        start_step = self.step
        what = ("COMCACT (memory + QT step)" if self.comcact else "DDPG baseline (uniform replay)")
        self.log.info(
            f"{what} on {p.env_id} (obs {list(self.obs_shape)}, actions {self.action_dim} in "
            f"[{self.low.min():g}, {self.high.max():g}]), {p.bringup} bring-up, "
            f"{'resuming at step ' + str(self.step) if self.step else 'fresh run'} to {p.total_steps} steps; "
            f"evaluation every {p.eval_every} steps x {p.eval_episodes} episodes"
            + (f"; reduce every {p.reduce_every} updates, reduce_batch {p.reduce_batch}" if self.comcact else "")
            + f"; run dir {rd.path}  (Ctrl-C stops and saves a checkpoint)")
        if not self.scalars.available and p.tensorboard:
            self.log.warning(f"TensorBoard scalars off: {self.scalars.error}")
        next_eval = (self.step // p.eval_every + 1) * p.eval_every if p.eval_every > 0 else None
        ck_every = p.checkpoint_every or p.eval_every or 0
        next_ck = (self.step // ck_every + 1) * ck_every if ck_every else None
        if p.eval_every > 0 and self.step == 0:
            self.evaluate()       # the untrained policy: the curve's first point
        self.pending: list = []
        rc = 0
        try:
            obs = self._reset_env()
            while self.step < p.total_steps and not self.stop_event.is_set():
                if self.step < p.warmup_steps:
                    obs = self._warmup_chunk(obs, min(p.warmup_steps, p.total_steps,
                                                      next_eval or p.total_steps) - self.step)
                else:
                    obs = self._agent_step(obs)
                if next_eval is not None and self.step >= next_eval:
                    self._flush()
                    self.evaluate()
                    next_eval += p.eval_every
                if next_ck is not None and self.step >= next_ck:
                    self.save()
                    next_ck += ck_every
                line = self.progress.tick(self.step)
                if line:
                    self._progress_line(line)
            self._flush()
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
            try:
                self.save(final=True)
            except Exception as exc:
                self.log.error(f"final checkpoint failed: {exc}")
            self._report_timers(elapsed, self.step - start_step)
            self.metrics.close()
            self.csv.close()
            self.scalars.close()
        if self.evals:
            e = self.evals[-1]
            self.log.info(f"done: {self.step} steps, {self.episodes} episodes, last evaluation "
                          f"{e['mean_return']:.1f} +- {e['std_return']:.1f} at step {e['step']}; outputs in {rd.path}")
        return rc

    def _progress_line(self, line: str) -> None:
        extra = ""
        if self.comcact:
            qv = self.qt_local.version if self.qt_local is not None else 0
            extra = f" | RTM {self.rtm_size} | QT v{qv}"
        self.log.info(line + extra)
        self.metrics.write("progress", step=self.step, steps_per_s=self.progress.rate, episodes=self.episodes,
                           wall_time_s=self.wall_time(), rtm_size=self.rtm_size, **{
                               k: v for k, v in self.last_update.items() if isinstance(v, float)})
        self.scalars.scalar("perf/steps_per_s", self.progress.rate, self.step)

    def _agent_step(self, obs: np.ndarray) -> np.ndarray:
        with self.ptimers("learner"):
            a = self.learner.act(obs, explore=True)
        req = Step.Request()
        numpy_to_array(a, req.action)
        with self.ptimers("sim"):
            r = call(self.c_step, req, self.p.service_timeout_s)
        nxt = np.array(array_to_numpy(r.observation), dtype=np.float32)
        self.ep_return += float(r.reward)
        self.ep_len += 1
        self.pending.append((obs, a, float(r.reward), nxt, bool(r.terminated), bool(r.truncated), self.step))
        self.step += 1
        over = _episode_over(self.episode_rule, r.terminated, r.truncated)
        if len(self.pending) >= self.p.store_every or over:
            self._flush()
        if self.stored >= max(self.cfg.learning_starts, 2):
            self._train_step()
        if over:
            self._end_episode(r.terminated, r.truncated)
            return self._reset_env()
        return nxt

    def _warmup_chunk(self, obs: np.ndarray, n: int) -> np.ndarray:
        n = max(1, min(int(n), 1000))
        acts = self.rng.uniform(self.low, self.high, size=(n, self.action_dim)).astype(np.float32)
        req = StepMany.Request(autoreset=True)
        numpy_to_array(acts, req.actions)
        with self.ptimers("sim"):
            r = call(self.c_step_many, req, self.p.service_timeout_s)
        t = batch_to_transitions(r.transitions)
        over = np.array([_episode_over(self.episode_rule, a, b) for a, b in zip(t.terminated, t.truncated)])
        ends_before = np.concatenate([[0], np.cumsum(over)[:-1]]).astype(np.uint64)
        t = Transitions(states=np.array(t.states, np.float32), actions=np.array(t.actions, np.float32),
                        rewards=np.array(t.rewards, np.float32), next_states=np.array(t.next_states, np.float32),
                        terminated=np.array(t.terminated), truncated=np.array(t.truncated),
                        episode_ids=self.episodes + ends_before,
                        steps=np.arange(self.step, self.step + len(t), dtype=np.uint64), run_id=self.run_id)
        seg = 0
        for i in range(len(t)):
            self.ep_return += float(t.rewards[i])
            self.ep_len += 1
            self.step += 1
            if over[i]:
                self._store(t.take(slice(seg, i + 1)))   # the episode's transitions go out with its summary
                seg = i + 1
                self._end_episode(bool(t.terminated[i]), bool(t.truncated[i]))
                self.learner.reset_noise()
        if seg < len(t):
            self._store(t.take(slice(seg, len(t))))
        return np.array(array_to_numpy(r.observation), dtype=np.float32)

    def _report_timers(self, elapsed: float, steps: int) -> None:
        """Log the time split; estimate ROS transport from small probe calls."""
        p = self.p
        probe_ms = float("nan")
        calls = sum(self.ptimers.calls.get(k, 0) for k in ("sim", "memory", "qt"))
        if p.transport_probe_calls > 0 and not self.stop_event.is_set():
            client = self.c_stats if self.comcact else self.c_info
            req = GetStats.Request() if self.comcact else EnvInfo.Request()
            try:
                t0 = time.perf_counter()
                for _ in range(p.transport_probe_calls):
                    call(client, req, 10.0, check=False)
                probe_ms = 1000.0 * (time.perf_counter() - t0) / p.transport_probe_calls
            except ServiceError:
                pass
        sim_compute = float("nan")
        try:   # simulation compute per step, measured on the learner's own (eval) env
            b = self.eval_bridge
            b.reset(0)
            t0 = time.perf_counter()
            n = 0
            for _ in range(500):
                res = b.step(self.rng.uniform(self.low, self.high).astype(np.float32))
                n += 1
                if res.episode_over:
                    b.reset(None)
            sim_compute = (time.perf_counter() - t0) / n
        except Exception:
            pass
        d = self.ptimers.as_dict()
        transport_s = probe_ms / 1000.0 * calls if math.isfinite(probe_ms) else float("nan")
        rate = steps / elapsed if elapsed > 0 else float("nan")
        self.log.info(f"time split over {elapsed:.1f} s, {steps} steps ({rate:.1f} steps/s): "
                      + self.ptimers.summary(elapsed))
        self.log.info(f"estimates: ROS round trip {probe_ms:.2f} ms/call x {calls} calls = {transport_s:.1f} s "
                      f"transport; simulation compute {1e6 * sim_compute:.0f} us/step "
                      f"(x {steps} = {sim_compute * steps:.1f} s of the 'sim' phase)")
        self.metrics.write("timers", elapsed_s=elapsed, steps=steps, steps_per_s=rate, phases=d,
                           ros_round_trip_ms=probe_ms, service_calls=calls, transport_estimate_s=transport_s,
                           sim_compute_us_per_step=1e6 * sim_compute)

    # ------------------------------------------------------------------------------ shutdown
    def shutdown(self) -> None:
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
        eb = getattr(self, "eval_bridge", None)
        if eb is not None:
            eb.close()
        self.destroy_node()


def _plain_cfg(d: dict) -> dict:
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in d.items()}


def main(args=None) -> int:
    """Entry point of ``ros2 run comper_agent comcact_node``: 0 done, 1 cannot start / failed, 130 aborted."""
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    logger = rclpy.logging.get_logger("comcact_node")
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
            node = ComcactNode()
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


if __name__ == "__main__":
    sys.exit(main())
