"""comper_node: the COMPER learner on Atari (thesis Algorithm 7; method.md sections 3-5), its
chapter-7 ablations COMPER-F and COMPER-M, and the DQN baseline (Table 35).

    ros2 run comper_agent comper_node                                   # COMPER on ALE/Freeway-v5, 100,000 frames
    ros2 run comper_agent comper_node --ros-args -p env_id:=ALE/Asterix-v5 -p seed:=1
    ros2 run comper_agent comper_node --ros-args -p algorithm:=comper_f   # or comper_m, dqn
    ros2 run comper_agent comper_node --ros-args -p frame_stack:=4        # 4 stacked frames
    ros2 run comper_agent comper_node --ros-args -p resume:=runs/<run_id>
    ros2 run comper_agent comper_node --ros-args --params-file src/comper_agent/config/comper.yaml

Bring-up (:mod:`comper_agent.bringup`): ``embedded`` (default) builds the simulation, memory and
QT trainer nodes in this process (separate node objects, one executor in a background thread);
``external`` uses nodes started with ``ros2 run`` by name. Outputs (:mod:`comper_agent.run_io`):
``<runs_root>/<run_id>/`` config.yaml, metrics.jsonl, progress.csv, tb/, checkpoints/, and
summary.json (the protocol's figures: mean of the last 10 training episodes, or 3 for runs
with fewer than 25 episodes, and the mean of the last 5 (or 3) episodes at the end of each
tercile of episodes).

One agent step (all variants): a = epsilon-greedy(Q(s)) with epsilon 1.0 -> 0.01 over 90,000
frames -> ``<sim>/step``. The value label of transition t (``qt_label`` next_value) is
max_a Q(s_{t+1}, a), read off the Q-values computed to act at t + 1 (0 when terminated; one extra
forward pass only for a truncated episode end); ``q_sa`` (thesis-literal) stores Q(s_t, a_t) from
the same forward pass. Every ``train_frequency`` (4) steps from ``learning_starts`` (100):

1. one ``<memory>/store`` call with the new labelled transitions **and** the previous update's
   batch re-stored with labels computed right after that update (Algorithm 7 / thesis 4.1.1);
2. reduce when RTM is empty or ``reduce_every`` (100) steps have passed: ``<qt_trainer>/reduce``
   (up to ``reduce_batch`` 1,000 sets; QT architecture comper, Table 37), then wait for the
   QTModel of that version on ``<qt_trainer>/qt_model``;
3. ``<memory>/sample`` 32 (RTM; TM for comper_m);
4. Huber loss on Q(s, a_taken) against r + gamma (1 - terminated) QT(tau), QT(tau) predicted
   by the local copy of the latest QTModel (comper, comper_m), or against the target network's
   max_a Q_target(s', a) (comper_f, dqn; copied every ``target_update_every`` 1,000 steps);
5. labels of the updated batch for its re-store: max_a Q(s', a) (0 when terminated).

comper_f reduces through ``<memory>/reduce`` (newest label as prediction; no QT is trained, the
variant does not use it). dqn uses an in-process frame-deduplicating replay (each frame stored
once: 100,000 x 4-frame transitions take ~0.8 GB instead of 5.6 GB), no memory or QT nodes.

The run stops at the first episode end after ``total_frames`` (100,000) frames counting skipped
ones (the episode in progress finishes), at ``max_steps`` if > 0 (stops mid-episode), or on
Ctrl-C (final checkpoint, summary, time split; a second Ctrl-C aborts).
"""
from __future__ import annotations

import json
import math
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

from comper_msgs.msg import EpisodeSummary, TransitionBatch
from comper_msgs.msg import QTModel as QTModelMsg
from comper_msgs.srv import EnvInfo, GetStats, Reduce, Reset, Sample, Step, Store
from comper_msgs_py.arrays import Transitions
from comper_msgs_py.convert import (array_to_numpy, batch_to_transitions, numpy_to_array,
                                    seq_to_numpy, transitions_to_batch)
from comper_msgs_py.params import config_to_dict
from comper_msgs_py.ros_params import declare_config

from . import run_io
from .bringup import (START_HINTS, ServiceError, Spinner, call, make_embedded_nodes,
                      wait_for_services)
from .core.config import ComperConfig, DQNConfig
from .qt_trainer_node import QT_MODEL_QOS, msg_to_qt

__all__ = ["ComperNode", "FrameReplay", "protocol_summary", "main", "SUMMARY_QOS", "TRANSITIONS_QOS",
           "ALGORITHMS"]

ALGORITHMS = ("comper", "comper_f", "comper_m", "dqn")

SUMMARY_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                         reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
TRANSITIONS_QOS = SUMMARY_QOS

# name, default, description (thesis value where there is one)
LEARNER_PARAMS = [
    ("algorithm", "comper", "comper (Algorithm 7: RTM sampling, QT target) | comper_f (RTM sampling, "
     "DQN loss with a target network; chapter 7) | comper_m (QT target, sampling from TM; chapter 7) | "
     "dqn (baseline, Table 35: in-process replay, target network, no memory / QT nodes)"),
    ("bringup", "embedded", "embedded: build sim, memory and QT trainer nodes in this process; external: "
     "use nodes started separately (names below)"),
    ("env_id", "ALE/Freeway-v5", "ALE game (ALE/<Game>-v5): Freeway, Asterix, Seaquest, SpaceInvaders, "
     "BeamRider, ... (embedded: given to the sim node; external: must match the running sim node)"),
    ("episode_end", "standard", "embedded sim node's episode end rule (method.md 6.3); an ALE game over "
     "always ends the episode"),
    ("total_frames", 100_000, "frame budget counting skipped frames; the episode in progress when it is "
     "reached finishes. Thesis: 100,000 (chapter 5)"),
    ("max_steps", 0, "if > 0, also stop after this many agent steps, even mid-episode (tests, smoke runs)"),
    ("reduce_every", 100, "agent steps between reductions + QT training (and whenever RTM is empty). "
     "Thesis: 100 (Table 34, UTF)"),
    ("reduce_batch", 1_000, "most similar-transition sets per reduction. Thesis: 1,000 (Table 34)"),
    ("qt_epochs", 0, "QT passes per reduction; 0 = the QT trainer's qt_epochs (1)"),
    ("qt_targets", "local", "QT(tau) for the loss: local = predicted by the latest QTModel received "
     "(Algorithm 7 line 16); rtm = the prediction stored in RTM at the entry's last reduction "
     "(comper only; comper_m samples TM and always predicts locally)"),
    ("qt_wait_s", 5.0, "after a reduction, seconds to wait for the QTModel of that version to arrive"),
    ("reducer", "auto", "who reduces TM into RTM: qt_trainer (<qt_trainer_node>/reduce, trains QT) | "
     "memory (<memory_node>/reduce, newest label as prediction, no QT) | auto = memory for comper_f "
     "(it does not use QT), qt_trainer otherwise"),
    ("qt_onednn", False, "let torch use oneDNN (mkldnn) for QT's LSTM while this node waits for a "
     "reduction and predicts QT targets; off = torch's native LSTM, measured 5x faster for the "
     "14114-input LSTM on this CPU (while oneDNN stays on for the CNN, where it is 2x faster). Affects "
     "the embedded QT trainer only (external: the trainer process's own setting). Speed only"),
    ("restore_batch", True, "re-store each updated batch with fresh labels (thesis 4.1.1; method.md 4)"),
    ("store_every", 4, "before learning starts / between updates: steps per store call (an update and an "
     "episode end always flush)"),
    ("stats_every", 1_000, "agent steps between memory statistics records (identities, TM, RTM, set sizes) "
     "in metrics.jsonl (0 = only at the end)"),
    ("publish_transitions", True, "publish each finished episode's stored transitions (with their labels) "
     "on ~/transitions when someone subscribes"),
    ("runs_root", "runs", "folder holding the run directories"),
    ("run_id", "", "run directory name; '' = <algorithm>-<env>-s<seed>-<timestamp>"),
    ("resume", "", "checkpoint file or run directory to continue from ('' = fresh run); the memory / "
     "replay contents are not in the checkpoint and refill from the resumed step, which starts a new "
     "episode"),
    ("checkpoint_every", 5_000, "agent steps between checkpoints (0 = only the final one)"),
    ("keep_checkpoints", 3, "step_<N>.pt files kept besides latest.pt"),
    ("progress_period_s", 10.0, "seconds between console progress lines"),
    ("tensorboard", True, "write TensorBoard scalars to <run dir>/tb"),
    ("sim_node", "sim_node", "name of the simulation node"),
    ("memory_node", "memory_node", "name of the memory node"),
    ("qt_trainer_node", "qt_trainer_node", "name of the QT trainer node"),
    ("service_timeout_s", 120.0, "seconds to wait for any one service answer"),
    ("startup_timeout_s", 30.0, "seconds to wait for the nodes' services at start"),
    ("transport_probe_calls", 200, "at the end, this many small service calls measure the ROS round "
     "trip for the time split (0 = skip)"),
]


def _as_bool(value) -> bool:
    if isinstance(value, str):
        if value.lower() in ("true", "1", "yes"):
            return True
        if value.lower() in ("false", "0", "no"):
            return False
        raise ValueError(value)
    return bool(value)


class LearnerParams:
    """The node's own (non-hyper-parameter) parameters as attributes."""

    def __init__(self, node: Node):
        for name, default, text in LEARNER_PARAMS:
            value = node.declare_parameter(name, default, ParameterDescriptor(
                description=text, read_only=True, dynamic_typing=True)).value
            try:
                value = _as_bool(value) if isinstance(default, bool) else type(default)(value)
            except (TypeError, ValueError):
                raise ValueError(f"parameter '{name}': cannot use {value!r} as {type(default).__name__} "
                                 f"({text})") from None
            setattr(self, name, value)

    def as_dict(self) -> dict:
        return {name: getattr(self, name) for name, _, _ in LEARNER_PARAMS}


def _episode_over(rule: str, terminated: bool, truncated: bool) -> bool:
    if rule == "truncation_only":
        return bool(truncated)
    if rule == "termination_only":
        return bool(terminated)
    return bool(terminated or truncated)


# ---------------------------------------------------------------------------------- protocol
def protocol_summary(returns: list[float], *, last: int = 10, last_few: int = 3, tercile_last: int = 5,
                     few_episodes: int = 25) -> dict:
    """The thesis's Atari figures for one run (chapter 5.3, Tables 23/25; method.md 5).

    last_mean: mean of the last `last` (10) training episodes, or the last `last_few` (3) when the
    run has fewer than `few_episodes` (25) episodes. terciles: the episodes are split into three
    equal parts by count; for each part, the mean of the last `tercile_last` (5, or 3 when fewer
    than 25 episodes) episodes preceding its end (episode boundaries round(j N / 3))."""
    r = [float(x) for x in returns]
    n = len(r)
    few = n < few_episodes
    k = last_few if few else last
    kt = last_few if few else tercile_last
    out = {"episodes": n, "last_k": min(k, n), "last_mean": float(np.mean(r[-k:])) if n else float("nan"),
           "last_std": float(np.std(r[-k:])) if n else float("nan"), "tercile_k": kt, "terciles": []}
    for j in (1, 2, 3):
        end = int(round(j * n / 3.0))
        part = r[max(0, end - kt):end]
        out["terciles"].append({"end_episode": end, "n": len(part),
                                "mean": float(np.mean(part)) if part else float("nan"),
                                "std": float(np.std(part)) if part else float("nan")})
    return out


# ---------------------------------------------------------------------------------- DQN replay
class FrameReplay:
    """Uniform replay for stacked uint8 frames that stores each frame once (DQN baseline).

    A transition keeps the ids of its state's and next state's frames; within an episode the next
    state's first C-1 frames are the state's last C-1 frames (the sim stacks oldest first), so each
    step adds one frame; an episode's first transition adds its state's C frames. Frame ids are
    global counters into a ring of `capacity + frame_margin` frames; a transition whose oldest frame
    was overwritten is no longer drawn. Reconstruction is exact (checked in the unit tests)."""

    def __init__(self, capacity: int, frame_shape: tuple, stack: int, seed: int | None = None,
                 frame_margin: int | None = None):
        self.capacity = int(capacity)
        self.stack = int(stack)
        self.frame_shape = tuple(frame_shape)          # one frame: (84, 84)
        self.n_frames = self.capacity + (frame_margin if frame_margin is not None
                                         else max(64, self.capacity // 8))
        self.frames = np.zeros((self.n_frames, *self.frame_shape), np.uint8)
        self.frames_written = 0
        c = self.capacity
        self.s_ids = np.zeros((c, self.stack), np.int64)
        self.ns_ids = np.zeros((c, self.stack), np.int64)
        self.actions = np.zeros(c, np.float32)
        self.rewards = np.zeros(c, np.float32)
        self.terminated = np.zeros(c, bool)
        self.truncated = np.zeros(c, bool)
        self.pos = 0
        self.size = 0
        self._last_ns: np.ndarray | None = None         # frame ids of the previous transition's s'
        self.rng = np.random.default_rng(seed)

    def __len__(self) -> int:
        return self.size

    @property
    def nbytes(self) -> int:
        return int(self.frames.nbytes + self.s_ids.nbytes + self.ns_ids.nbytes)

    def _push(self, frame: np.ndarray) -> int:
        i = self.frames_written
        self.frames[i % self.n_frames] = frame
        self.frames_written += 1
        return i

    def _stacked(self, obs: np.ndarray) -> np.ndarray:
        return obs.reshape(self.stack, *self.frame_shape)

    def add(self, state: np.ndarray, action: int, reward: float, next_state: np.ndarray,
            terminated: bool, truncated: bool, new_episode: bool) -> None:
        s = self._stacked(state)
        ns = self._stacked(next_state)
        if new_episode or self._last_ns is None:
            s_ids = np.array([self._push(f) for f in s], np.int64)
        else:
            s_ids = self._last_ns
        ns_ids = np.concatenate([s_ids[1:], [self._push(ns[-1])]]) if self.stack > 1 \
            else np.array([self._push(ns[-1])], np.int64)
        p = self.pos
        self.s_ids[p], self.ns_ids[p] = s_ids, ns_ids
        self.actions[p], self.rewards[p] = action, reward
        self.terminated[p], self.truncated[p] = terminated, truncated
        self._last_ns = ns_ids
        self.pos = (p + 1) % self.capacity
        self.size = min(self.capacity, self.size + 1)

    def end_episode(self) -> None:
        self._last_ns = None

    def _valid(self, idx: np.ndarray) -> np.ndarray:
        return self.s_ids[idx].min(axis=1) >= self.frames_written - self.n_frames

    def sample(self, k: int) -> Transitions:
        """k transitions drawn uniformly (with replacement) among those whose frames are all kept."""
        if self.size == 0:
            raise ValueError("cannot sample from an empty replay buffer")
        idx = self.rng.integers(0, self.size, size=int(k))
        for _ in range(100):
            bad = ~self._valid(idx)
            if not bad.any():
                break
            idx[bad] = self.rng.integers(0, self.size, size=int(bad.sum()))
        return self.take(idx)

    def take(self, idx) -> Transitions:
        idx = np.asarray(idx)
        squeeze = self.stack == 1
        st = self.frames[self.s_ids[idx] % self.n_frames]
        nst = self.frames[self.ns_ids[idx] % self.n_frames]
        if squeeze:
            st, nst = st[:, 0], nst[:, 0]
        return Transitions(states=st, actions=self.actions[idx], rewards=self.rewards[idx], next_states=nst,
                           terminated=self.terminated[idx], truncated=self.truncated[idx])


# ---------------------------------------------------------------------------------- the node
class ComperNode(Node):
    """The learner node. Construction declares parameters and brings up the other nodes; ``run()``
    trains (main thread) while a background executor serves ROS."""

    def __init__(self, node_name: str = "comper_node", **node_kwargs):
        super().__init__(node_name, **node_kwargs)
        self.p = p = LearnerParams(self)
        if p.algorithm not in ALGORITHMS:
            raise ValueError(f"algorithm must be one of {', '.join(ALGORITHMS)}, got {p.algorithm!r}")
        if p.bringup not in ("embedded", "external"):
            raise ValueError(f"bringup must be embedded or external, got {p.bringup!r}")
        if p.qt_targets not in ("local", "rtm"):
            raise ValueError(f"qt_targets must be local or rtm, got {p.qt_targets!r}")
        if p.reducer not in ("auto", "qt_trainer", "memory"):
            raise ValueError(f"reducer must be auto, qt_trainer or memory, got {p.reducer!r}")
        for name in ("total_frames", "reduce_every", "reduce_batch", "store_every"):
            if getattr(p, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(p, name)}")
        cls = DQNConfig if p.algorithm == "dqn" else ComperConfig
        # num_threads 1: measured faster on the 2-core machine with the embedded nodes (docs/comper.md)
        self.cfg = declare_config(self, cls, overrides={"variant": p.algorithm, "num_threads": 1})
        if self.cfg.variant != p.algorithm:
            raise ValueError(f"variant:={self.cfg.variant} contradicts algorithm:={p.algorithm}; set algorithm only")
        self.uses_memory = p.algorithm != "dqn"
        self.uses_qt = p.algorithm in ("comper", "comper_m")
        self.reducer = p.reducer if p.reducer != "auto" else ("memory" if p.algorithm == "comper_f" else "qt_trainer")
        if not self.uses_memory:
            self.reducer = "none"
        if self.uses_qt and self.reducer != "qt_trainer":
            raise ValueError(f"{p.algorithm} needs QT: use reducer:=qt_trainer (or auto)")
        self.sample_source = Sample.Request.SOURCE_TM if p.algorithm == "comper_m" else Sample.Request.SOURCE_RTM
        self.stop_event = threading.Event()
        self.ptimers = run_io.PhaseTimers()
        self.log = self.get_logger()

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

        self.episode_pub = self.create_publisher(EpisodeSummary, "~/episodes", SUMMARY_QOS)
        self.transitions_pub = self.create_publisher(TransitionBatch, "~/transitions", TRANSITIONS_QOS)
        self.qt_local = None
        self.qt_cond = threading.Condition()
        if self.uses_qt:
            self.create_subscription(QTModelMsg, f"/{p.qt_trainer_node.strip('/')}/qt_model",
                                     self._on_qt_model, QT_MODEL_QOS)

        self.embedded = None
        nodes: list[Node] = [self]
        if p.bringup == "embedded":
            self.embedded = make_embedded_nodes(
                self.context, sim_name=p.sim_node,
                sim_params={"env_id": p.env_id, "episode_end": p.episode_end, "run_id": run_id,
                            "seed": int(self.cfg.seed), "frame_stack": int(self.cfg.frame_stack)},
                memory_name=p.memory_node if self.uses_memory else None,
                memory_params={"reduce_batch": int(p.reduce_batch)},
                qt_name=p.qt_trainer_node if self.reducer == "qt_trainer" else None,
                qt_params={"memory_node": p.memory_node, "reduce_batch": int(p.reduce_batch),
                           "architecture": "comper"})
            nodes += self.embedded.all
        self.spinner = Spinner(nodes, self.context, num_threads=4).start()
        try:
            self._connect()
        except BaseException:
            self.shutdown()
            raise

    def _connect(self) -> None:
        p = self.p
        sim = p.sim_node.strip("/")
        self.c_reset = self.create_client(Reset, f"/{sim}/reset")
        self.c_step = self.create_client(Step, f"/{sim}/step")
        self.c_info = self.create_client(EnvInfo, f"/{sim}/info")
        clients = {"sim": self.c_step}
        if self.uses_memory:
            mem = p.memory_node.strip("/")
            self.c_store = self.create_client(Store, f"/{mem}/store")
            self.c_sample = self.create_client(Sample, f"/{mem}/sample")
            self.c_stats = self.create_client(GetStats, f"/{mem}/get_stats")
            clients["memory"] = self.c_store
            if self.reducer == "qt_trainer":
                self.c_reduce = self.create_client(Reduce, f"/{p.qt_trainer_node.strip('/')}/reduce")
                clients["qt_trainer"] = self.c_reduce
            else:
                self.c_reduce = self.create_client(Reduce, f"/{mem}/reduce")
        hints = {"sim": START_HINTS["sim"].format(name=sim),
                 "memory": START_HINTS["memory"].format(name=p.memory_node),
                 "qt_trainer": START_HINTS["qt_trainer"].format(name=p.qt_trainer_node)
                 + " -p architecture:=comper -p reduce_batch:=1000"}
        wait_for_services(clients, p.startup_timeout_s, hints, self.stop_event)
        info = call(self.c_info, EnvInfo.Request(), p.startup_timeout_s, check=False)
        if info.env_id != p.env_id:
            raise ValueError(f"the sim node /{sim} serves {info.env_id}, not env_id:={p.env_id}; "
                             f"set -p env_id:={info.env_id} or restart the sim node")
        if not info.discrete:
            raise ValueError(f"{info.env_id} has continuous actions; comper_node needs an ALE game "
                             "(use comcact_node for continuous control)")
        if int(info.num_actions) != self.cfg.n_actions:
            raise ValueError(f"{info.env_id} has {info.num_actions} actions but n_actions:={self.cfg.n_actions}")
        self.obs_shape = tuple(int(d) for d in info.observation_shape)
        want = (84, 84) if self.cfg.frame_stack == 1 else (self.cfg.frame_stack, 84, 84)
        if self.obs_shape != want:
            raise ValueError(f"the sim serves observations {list(self.obs_shape)} but frame_stack:="
                             f"{self.cfg.frame_stack} needs {list(want)}; start the sim with "
                             f"-p frame_stack:={self.cfg.frame_stack}")
        self.episode_rule = info.episode_end or "standard"
        self.frame_skip = max(1, int(info.frame_skip))
        self.info = info

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
            self.qt_cond.notify_all()

    # ------------------------------------------------------------------------------ setup / state
    def _setup_learner(self) -> None:
        from .core.comper import ComperLearner
        from .core.networks import configure_torch
        configure_torch(self.cfg.num_threads)
        self.learner = ComperLearner(self.cfg)
        self.replay = None
        if not self.uses_memory:
            self.replay = FrameReplay(self.cfg.replay_size, (84, 84), self.cfg.frame_stack, seed=self.cfg.seed)
        self.step = 0
        self.frames = 0              # emulator frames of the run, skipped ones included
        self.episodes = 0
        self.returns: list[float] = []
        self.stored = 0
        self.restored = 0
        self.updates = 0
        self.reductions = 0
        self.last_reduce_step = -(10 ** 9)
        self.rtm_size = 0
        self.tm_sets = 0
        self.wall_offset = 0.0
        self.last_update: dict = {}
        self.last_reduce: dict = {}
        self.restore: Transitions | None = None
        self.set_counts: list[np.ndarray] = []
        self.last_stats: dict = {}
        self.sample_calls = 0

    def _restore(self, state: dict) -> None:
        self.learner.load_state_dict(state["learner"])
        c = state["counters"]
        self.step, self.frames, self.episodes = int(c["step"]), int(c["frames"]), int(c["episodes"])
        self.updates, self.reductions = int(c.get("updates", 0)), int(c.get("reductions", 0))
        self.wall_offset = float(c.get("wall_time_s", 0.0))
        self.returns = [float(x) for x in state.get("returns", [])]
        run_io.set_rng_state(state["rng"])
        qt_state = state.get("qt_trainer")
        if qt_state and self.embedded is not None and self.embedded.qt_trainer is not None:
            self.embedded.qt_trainer.load_state_dict(qt_state)

    def _state(self) -> dict:
        st = {"run": {"run_id": self.run_id, "algorithm": self.p.algorithm, "env_id": self.p.env_id},
              "learner": self.learner.state_dict(),
              "counters": {"step": self.step, "frames": self.frames, "episodes": self.episodes,
                           "updates": self.updates, "reductions": self.reductions, "stored": self.stored,
                           "wall_time_s": self.wall_time()},
              "returns": list(self.returns), "rng": run_io.rng_state(),
              "config": {"learner": {k: (list(v) if isinstance(v, tuple) else v)
                                     for k, v in config_to_dict(self.cfg).items()},
                         "params": self.p.as_dict()}}
        if self.embedded is not None and self.embedded.qt_trainer is not None:
            st["qt_trainer"] = self.embedded.qt_trainer.state_dict()
        return st

    def wall_time(self) -> float:
        return self.wall_offset + (time.monotonic() - self.t_start)

    def save(self, final: bool = False) -> Path:
        with self.ptimers("io"):
            path = self.run_dir.save_checkpoint(self._state(), self.step, self.p.keep_checkpoints)
            self.metrics.flush()
        self.log.info(f"{'final ' if final else ''}checkpoint: {path}")
        return path

    # ------------------------------------------------------------------------------ episodes
    def _reset_env(self) -> np.ndarray:
        with self.ptimers("sim"):
            r = call(self.c_reset, Reset.Request(seed=-1), self.p.service_timeout_s)
        self.ep_return, self.ep_len, self.ep_frames0, self.ep_frames = 0.0, 0, self.frames, 0
        self.ep_stored: list[Transitions] = []
        self.new_episode = True
        if self.replay is not None:
            self.replay.end_episode()
        return np.array(array_to_numpy(r.observation), dtype=np.uint8)

    def _end_episode(self, terminated: bool, truncated: bool) -> None:
        self.episodes += 1
        self.returns.append(float(self.ep_return))
        self.progress.episode(self.ep_return)
        msg = EpisodeSummary(run_id=self.run_id, env_id=self.p.env_id, source="train",
                             episode_id=self.episodes - 1, episode_return=float(self.ep_return),
                             length=int(self.ep_len), frames=int(self.ep_frames), terminated=bool(terminated),
                             truncated=bool(truncated), global_step=int(self.step),
                             global_frames=int(self.frames), wall_time_s=float(self.wall_time()))
        msg.header.stamp = self.get_clock().now().to_msg()
        with self.ptimers("publish"):
            self.episode_pub.publish(msg)
            if self.p.publish_transitions and self.ep_stored and self.transitions_pub.get_subscription_count() > 0:
                t = Transitions.concatenate(self.ep_stored)
                bm = transitions_to_batch(t)
                bm.header.stamp = msg.header.stamp
                self.transitions_pub.publish(bm)
        self.ep_stored = []
        self.metrics.write("episode", source="train", step=self.step, frames=self.frames,
                           episode=self.episodes - 1, ret=self.ep_return, length=self.ep_len,
                           episode_frames=self.ep_frames, terminated=terminated, truncated=truncated,
                           epsilon=self.learner.epsilon(self.frames), wall_time_s=self.wall_time())
        self.scalars.scalar("train/episode_return", self.ep_return, self.frames)
        self.log.info(f"episode {self.episodes - 1}: return {self.ep_return:.1f}, {self.ep_len} steps, "
                      f"{self.ep_frames} frames; run {self.frames}/{self.p.total_frames} frames")

    # ------------------------------------------------------------------------------ stepping
    def _agent_step(self, obs: np.ndarray) -> tuple[np.ndarray, bool]:
        c = self.cfg
        with self.ptimers("learner"):
            a, q = self.learner.act(obs, frames=self.frames)
        if self.pending and self.pending[-1][6] is None:     # next_value label of the previous transition
            self.pending[-1][6] = float(q.max())
        req = Step.Request()
        numpy_to_array(np.asarray(a, np.float32), req.action)
        with self.ptimers("sim"):
            r = call(self.c_step, req, self.p.service_timeout_s)
        nxt = np.array(array_to_numpy(r.observation), dtype=np.uint8)
        term, trunc = bool(r.terminated), bool(r.truncated)
        self.ep_return += float(r.reward)
        self.ep_len += 1
        self.ep_frames = int(r.frames)
        self.frames = self.ep_frames0 + self.ep_frames
        over = _episode_over(self.episode_rule, term, trunc)
        if self.replay is not None:
            with self.ptimers("learner"):
                self.replay.add(obs, a, float(r.reward), nxt, term, trunc, self.new_episode)
            self.stored += 1
        else:
            if term:
                label = 0.0
            elif c.qt_label == "q_sa":
                label = float(q[a])
            elif over:      # truncated end: nobody acts on s', compute max_a Q(s', a) now
                with self.ptimers("learner"):
                    label = float(self.learner.act(nxt, epsilon=0.0)[1].max())
            else:
                label = None
            self.pending.append([obs, a, float(r.reward), nxt, term, trunc, label, self.step])
        self.new_episode = False
        self.step += 1
        if self.step % c.train_frequency == 0 and self.step >= c.learning_starts:
            self._train_step()
        elif self.uses_memory and (over or self._labelled() >= self.p.store_every):
            self._flush(with_restore=False)
        if over:
            if self.uses_memory:
                self._flush(with_restore=False)
            self._end_episode(term, trunc)
        return nxt, over

    def _labelled(self) -> int:
        n = len(self.pending)
        return n - 1 if n and self.pending[-1][6] is None else n

    def _flush(self, with_restore: bool) -> None:
        """One store call: the labelled new transitions (+ the previous update's batch re-stored)."""
        n = self._labelled()
        parts = []
        if n:
            rows, self.pending = self.pending[:n], self.pending[n:]
            cols = list(zip(*rows))
            t = Transitions(states=np.stack(cols[0]), actions=np.asarray(cols[1], np.float32),
                            rewards=np.asarray(cols[2], np.float32), next_states=np.stack(cols[3]),
                            terminated=np.asarray(cols[4], bool), truncated=np.asarray(cols[5], bool),
                            value_labels=np.asarray(cols[6], np.float32),
                            episode_ids=np.full(n, self.episodes, np.uint64),
                            steps=np.asarray(cols[7], np.uint64), run_id=self.run_id)
            parts.append(t)
            self.ep_stored.append(t)
            self.stored += n
        if with_restore and self.restore is not None:
            parts.append(self.restore)
            self.restored += len(self.restore)
            self.restore = None
        if not parts:
            return
        t = parts[0] if len(parts) == 1 else Transitions.concatenate(parts)
        with self.ptimers("convert"):
            req = Store.Request()
            transitions_to_batch(t, req.batch)
        with self.ptimers("memory"):
            call(self.c_store, req, self.p.service_timeout_s)

    # ------------------------------------------------------------------------------ memory
    def _lstm_backend(self):
        """Context for QT's LSTM work: oneDNN off unless qt_onednn (global torch flag; safe because the
        learner thread is blocked on the reduction meanwhile and no other node here runs torch)."""
        import contextlib

        import torch
        if self.p.qt_onednn:
            return contextlib.nullcontext()
        return torch.backends.mkldnn.flags(enabled=False)

    def _reduce(self) -> None:
        p = self.p
        with self.ptimers("qt" if self.reducer == "qt_trainer" else "memory_reduce"), self._lstm_backend():
            r = call(self.c_reduce, Reduce.Request(max_sets=int(p.reduce_batch), epochs=int(p.qt_epochs)),
                     p.service_timeout_s)
        self.ptimers.add("qt_server" if self.reducer == "qt_trainer" else "memory_reduce_server",
                         r.duration_s, 0)
        self.rtm_size = int(r.rtm_size)
        self.last_reduce_step = self.step
        self.reductions += 1
        self.last_reduce = {"sets": int(r.sets_reduced), "qt_version": int(r.qt_version),
                            "qt_loss": float(r.qt_loss), "duration_s": float(r.duration_s)}
        self.metrics.write("reduce", step=self.step, frames=self.frames, rtm_size=self.rtm_size,
                           **self.last_reduce)
        if self.uses_qt and r.qt_version > 0:
            with self.ptimers("qt_wait"), self._lstm_backend():
                deadline = time.monotonic() + p.qt_wait_s
                with self.qt_cond:
                    while (self.qt_local is None or self.qt_local.version < r.qt_version) \
                            and time.monotonic() < deadline:
                        self.qt_cond.wait(max(0.0, deadline - time.monotonic()))

    def _sample(self) -> tuple[Transitions, np.ndarray] | None:
        k = self.cfg.batch_size
        if self.sample_source == Sample.Request.SOURCE_RTM:
            k = min(k, self.rtm_size)
        if k < 1:
            return None
        with self.ptimers("memory"):
            r = call(self.c_sample, Sample.Request(batch_size=k, source=self.sample_source, seed=-1),
                     self.p.service_timeout_s, check=False)
            if not r.success:     # fewer entries than asked (TM drained by a reduction, RTM evictions)
                st = self._get_stats()
                avail = st["tm_sets"] if self.sample_source == Sample.Request.SOURCE_TM else st["rtm_size"]
                k = min(k, avail)
                if k < 1:
                    return None
                r = call(self.c_sample, Sample.Request(batch_size=k, source=self.sample_source, seed=-1),
                         self.p.service_timeout_s)
        self.sample_calls += 1
        with self.ptimers("convert"):
            batch = batch_to_transitions(r.batch, validate=False)
            counts = seq_to_numpy(r.counts, np.uint32).copy()
        return batch, counts

    def _get_stats(self) -> dict:
        s = call(self.c_stats, GetStats.Request(), self.p.service_timeout_s, check=False).stats
        d = {k: getattr(s, k) for k in ("identities", "tm_sets", "rtm_size", "transitions_stored",
                                         "similarity_hits", "hit_rate", "compaction_ratio", "reductions",
                                         "sets_reduced", "evictions", "bytes_used")}
        d = {k: (float(v) if isinstance(v, float) else int(v)) for k, v in d.items()}
        self.rtm_size, self.tm_sets = d["rtm_size"], d["tm_sets"]
        return d

    def _memory_record(self) -> None:
        if not self.uses_memory:
            rec = {"replay_size": len(self.replay), "replay_bytes": self.replay.nbytes}
        else:
            with self.ptimers("memory"):
                rec = self._get_stats()
            if self.set_counts:
                cnt = np.concatenate(self.set_counts)
                rec.update(sampled_set_size_mean=float(cnt.mean()), sampled_set_size_max=int(cnt.max()),
                           sampled_set_size_p90=float(np.percentile(cnt, 90)),
                           sampled_sets_with_similar=float((cnt > 1).mean()), sampled=int(cnt.size))
                self.set_counts = []
        self.last_stats = rec
        self.metrics.write("memory", step=self.step, frames=self.frames, wall_time_s=self.wall_time(), **rec)
        self.scalars.scalars({k: v for k, v in rec.items() if isinstance(v, (int, float))}, self.frames,
                             prefix="memory/")

    # ------------------------------------------------------------------------------ learning
    def _train_step(self) -> None:
        c, p = self.cfg, self.p
        if not self.uses_memory:
            if len(self.replay) < c.batch_size:     # a resumed run refills its replay first
                return
            with self.ptimers("learner"):
                batch = self.replay.sample(c.batch_size)
                self.last_update = self.learner.update(batch)
        else:
            self._flush(with_restore=True)
            if self.rtm_size == 0 or self.step - self.last_reduce_step >= p.reduce_every:
                self._reduce()
            got = self._sample()
            if got is None:
                return
            batch, counts = got
            self.set_counts.append(counts)
            targets = None
            if self.uses_qt:
                if p.qt_targets == "rtm" and self.sample_source == Sample.Request.SOURCE_RTM:
                    targets = batch.value_labels
                else:
                    with self.qt_cond:
                        qt = self.qt_local
                    if qt is None:
                        self.log.warning("no QTModel received yet: update skipped (is the QT trainer "
                                         "publishing on qt_model?)", throttle_duration_sec=10.0)
                        return
                    from comper_memory.core import transition_keys
                    with self.ptimers("qt_predict"), self._lstm_backend():
                        targets = qt.predict_transitions(batch, transition_keys)
            with self.ptimers("learner"):
                self.last_update = self.learner.update(batch, targets)
                if p.restore_batch:
                    batch.value_labels = self.learner.value_labels(batch)
                    self.restore = batch
        self.updates += 1
        if self.learner.uses_target_net and self.step % c.target_update_every < c.train_frequency:
            self.learner.sync_target()
        if self.updates % 250 == 0:
            self.scalars.scalars(self.last_update, self.frames, prefix="train/")

    # ------------------------------------------------------------------------------ main loop
    def run(self) -> int:
        p, c = self.p, self.cfg
        self._setup_learner()
        if self.resume_state is not None:
            self._restore(self.resume_state)
        rd = self.run_dir
        rd.write_config({"algorithm": p.algorithm, "params": p.as_dict(), "learner": config_to_dict(self.cfg),
                         "reducer": self.reducer,
                         "qt_trainer": (config_to_dict(self.embedded.qt_trainer.qt_config)
                                        if self.embedded is not None and self.embedded.qt_trainer else None),
                         "memory": (config_to_dict(self.embedded.memory.config)
                                    if self.embedded is not None and self.embedded.memory is not None
                                    and hasattr(self.embedded.memory, "config") else None),
                         "env": {"env_id": self.info.env_id, "observation_shape": list(self.obs_shape),
                                 "num_actions": int(self.info.num_actions), "frame_skip": self.frame_skip,
                                 "episode_end": self.episode_rule, "spec": json.loads(self.info.spec_json or "{}")},
                         "resumed_from": str(self.resume_path) if self.resume_state is not None else None})
        self.metrics = run_io.MetricsLog(rd.file("metrics.jsonl"))
        self.csv = run_io.CsvLog(rd.file("progress.csv"),
                                 ["step", "frames", "wall_time_s", "episodes", "last_train_return", "epsilon",
                                  "steps_per_s", "rtm_size", "tm_sets", "identities", "loss"])
        self.scalars = run_io.ScalarLog(rd.file("tb") if p.tensorboard else None)
        est_steps = int(math.ceil(p.total_frames / self.frame_skip))
        if p.max_steps > 0:
            est_steps = min(est_steps, p.max_steps)
        self.progress = run_io.Progress(est_steps, p.progress_period_s, start_step=self.step)
        self.t_start = time.monotonic()
        start_step, start_frames = self.step, self.frames
        names = {"comper": "COMPER (RTM sampling, QT target)", "comper_f": "COMPER-F (RTM sampling, DQN target network)",
                 "comper_m": "COMPER-M (TM sampling, QT target)", "dqn": "DQN baseline (replay + target network)"}
        self.log.info(
            f"{names[p.algorithm]} on {p.env_id} (obs {list(self.obs_shape)} uint8, {self.info.num_actions} actions, "
            f"frame skip {self.frame_skip}), {p.bringup} bring-up, "
            f"{'resuming at step ' + str(self.step) if self.step else 'fresh run'} to {p.total_frames} frames"
            + (f" (max {p.max_steps} steps)" if p.max_steps > 0 else "")
            + f"; update every {c.train_frequency} steps from step {c.learning_starts}, batch {c.batch_size}"
            + (f"; reduce every {p.reduce_every} steps x {p.reduce_batch} sets via {self.reducer}"
               if self.uses_memory else f"; replay {c.replay_size}")
            + (f"; target network every {c.target_update_every} steps" if self.learner.uses_target_net else "")
            + f"; torch threads {c.num_threads}; run dir {rd.path}  (Ctrl-C stops and saves a checkpoint)")
        if not self.scalars.available and p.tensorboard:
            self.log.warning(f"TensorBoard scalars off: {self.scalars.error}")
        ck_every = p.checkpoint_every
        next_ck = (self.step // ck_every + 1) * ck_every if ck_every > 0 else None
        next_stats = (self.step // p.stats_every + 1) * p.stats_every if p.stats_every > 0 else None
        self.pending: list = []
        rc = 0
        try:
            obs = self._reset_env()
            while not self.stop_event.is_set():
                obs, over = self._agent_step(obs)
                if over:
                    if self.frames >= p.total_frames:
                        break
                    obs = self._reset_env()
                if p.max_steps > 0 and self.step >= p.max_steps:
                    break
                if next_ck is not None and self.step >= next_ck:
                    self.save()
                    next_ck += ck_every
                if next_stats is not None and self.step >= next_stats:
                    self._memory_record()
                    next_stats += p.stats_every
                line = self.progress.tick(self.step)
                if line:
                    self._progress_line(line)
            if self.uses_memory and self.pending:
                if self.pending[-1][6] is None:    # stopped mid-episode: label the last one too
                    self.pending[-1][6] = float(self.learner.act(self.pending[-1][3], epsilon=0.0)[1].max()) \
                        * (0.0 if self.pending[-1][4] else 1.0)
                self._flush(with_restore=False)
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
                if rc != 130:
                    self._memory_record()
            except Exception as exc:
                self.log.warning(f"final memory statistics failed: {exc}")
            try:
                self.save(final=True)
            except Exception as exc:
                self.log.error(f"final checkpoint failed: {exc}")
            timers = self._report_timers(elapsed, self.step - start_step)
            self._write_summary(elapsed, self.step - start_step, self.frames - start_frames, timers)
            self.metrics.close()
            self.csv.close()
            self.scalars.close()
        return rc

    def _progress_line(self, line: str) -> None:
        eps = self.learner.epsilon(self.frames)
        extra = f" | frames {self.frames} | eps {eps:.3f}"
        if self.uses_memory:
            qv = self.qt_local.version if self.qt_local is not None else 0
            extra += f" | RTM {self.rtm_size}" + (f" | QT v{qv}" if self.uses_qt else "")
        else:
            extra += f" | replay {len(self.replay)}"
        if "loss" in self.last_update:
            extra += f" | loss {self.last_update['loss']:.4f}"
        self.log.info(line + extra)
        rate = self.progress.rate
        self.metrics.write("progress", step=self.step, frames=self.frames, steps_per_s=rate, episodes=self.episodes,
                           wall_time_s=self.wall_time(), epsilon=eps, rtm_size=self.rtm_size, updates=self.updates,
                           reductions=self.reductions,
                           **{k: v for k, v in self.last_update.items() if isinstance(v, float)})
        self.csv.write(step=self.step, frames=self.frames, wall_time_s=round(self.wall_time(), 2),
                       episodes=self.episodes, last_train_return=self.progress.last_episode_return, epsilon=eps,
                       steps_per_s=round(rate, 1) if math.isfinite(rate) else "", rtm_size=self.rtm_size,
                       tm_sets=self.last_stats.get("tm_sets"), identities=self.last_stats.get("identities"),
                       loss=self.last_update.get("loss"))
        self.scalars.scalar("perf/steps_per_s", rate, self.frames)

    def _report_timers(self, elapsed: float, steps: int) -> dict:
        """Log the time split; estimate the ROS transport share from small probe calls."""
        p = self.p
        probe_ms = float("nan")
        calls = sum(self.ptimers.calls.get(k, 0) for k in ("sim", "memory", "qt", "memory_reduce"))
        if p.transport_probe_calls > 0 and not self.stop_event.is_set():
            client, req = (self.c_stats, GetStats.Request()) if self.uses_memory else (self.c_info, EnvInfo.Request())
            try:
                t0 = time.perf_counter()
                for _ in range(p.transport_probe_calls):
                    call(client, req, 10.0, check=False)
                probe_ms = 1000.0 * (time.perf_counter() - t0) / p.transport_probe_calls
            except ServiceError:
                pass
        transport_s = probe_ms / 1000.0 * calls if math.isfinite(probe_ms) else float("nan")
        rate = steps / elapsed if elapsed > 0 else float("nan")
        d = self.ptimers.as_dict()
        accounted = sum(v["seconds"] for k, v in d.items() if not k.endswith("_server") and k != "qt_model_rebuild")
        self.log.info(f"time split over {elapsed:.1f} s, {steps} steps ({rate:.1f} steps/s): "
                      + self.ptimers.summary(elapsed) + f" | unaccounted (loop, logging) {elapsed - accounted:.1f} s")
        self.log.info(f"estimates: ROS round trip {probe_ms:.2f} ms/call x {calls} calls = {transport_s:.1f} s "
                      "transport (part of the sim / memory / qt phases); qt_server = time inside the QT "
                      "trainer's reductions (part of qt); qt_model_rebuild runs in the executor thread")
        rec = {"elapsed_s": elapsed, "steps": steps, "steps_per_s": rate, "phases": d,
               "ros_round_trip_ms": probe_ms, "service_calls": calls, "transport_estimate_s": transport_s,
               "unaccounted_s": elapsed - accounted}
        self.metrics.write("timers", **rec)
        return rec

    def _write_summary(self, elapsed: float, steps: int, frames: int, timers: dict) -> None:
        s = protocol_summary(self.returns)
        summary = {"run_id": self.run_id, "algorithm": self.p.algorithm, "env_id": self.p.env_id,
                   "seed": int(self.cfg.seed), "frame_stack": int(self.cfg.frame_stack),
                   "total_frames_budget": int(self.p.total_frames), "frames": int(self.frames), "steps": int(self.step),
                   "updates": int(self.updates), "reductions": int(self.reductions),
                   "complete": bool(self.frames >= self.p.total_frames and not self.stop_event.is_set()),
                   "episode_returns": self.returns, "protocol": s,
                   "wall_time_s": self.wall_time(), "session_elapsed_s": elapsed,
                   "session_steps_per_s": steps / elapsed if elapsed > 0 else None,
                   "session_frames": frames, "memory": self.last_stats, "timers": timers,
                   "sampling": {"source": ("replay" if not self.uses_memory else
                                           "tm" if self.sample_source == Sample.Request.SOURCE_TM else "rtm"),
                                "target": "qt" if self.uses_qt else "target_network",
                                "reducer": self.reducer, "sample_calls": int(self.sample_calls),
                                "restored": int(self.restored)}}
        run_io.write_text_atomic(self.run_dir.file("summary.json"), json.dumps(summary, indent=1, default=float))
        t = " | ".join(f"tercile {j + 1} (to episode {x['end_episode']}): {x['mean']:.1f} +- {x['std']:.1f}"
                       for j, x in enumerate(s["terciles"]))
        self.log.info(f"done: {self.step} steps, {self.frames} frames, {self.episodes} episodes; mean of the last "
                      f"{s['last_k']} episodes {s['last_mean']:.1f} +- {s['last_std']:.1f}; {t}; "
                      f"summary {self.run_dir.file('summary.json')}")

    # ------------------------------------------------------------------------------ shutdown
    def shutdown(self) -> None:
        try:
            self.spinner.stop()
        except Exception:
            pass
        if self.embedded is not None:
            self.embedded.destroy()
        self.destroy_node()


def main(args=None) -> int:
    """Entry point of ``ros2 run comper_agent comper_node``: 0 done, 1 cannot start / failed, 130 aborted."""
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    logger = rclpy.logging.get_logger("comper_node")
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
            node = ComperNode()
            if stop.is_set():
                node.stop_event.set()
        except Exception as exc:
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
