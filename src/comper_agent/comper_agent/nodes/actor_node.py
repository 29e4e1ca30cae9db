"""actor_node: an environment and the learner's current policy, storing into the memory
(comcact_node mode:=async; docs/comcact.md, "Async mode").

    ros2 run comper_agent actor_node --ros-args -p env_id:=Hopper-v4 -p seed:=1 -p actor_id:=0 \\
        -p memory_node:=memory_node -p policy_topic:=/comcact_node/policy

It waits for the first PolicyWeights message on ``policy_topic`` (the learner publishes one at start
and then every policy_period_s; transient local, so a late actor gets the latest), builds the same
actor and critic from the message's config, and then, per step: mu(s) + OU noise (its own seed) ->
its own environment (comper_sim.core.SimBridge, in this process) -> every ``store_every`` steps and at
each episode end one ``<memory>/store`` call with the transitions labelled by the received critic
(the learner's label rule). A newer policy message is loaded between steps. The memory's rate
limiter may hold a store back while the learner catches up; the store then waits
(``rate_limit_timeout_s``). Each finished episode is published on ``~/episodes`` (source train).

It stops after ``total_steps`` (0 = no limit), on the learner's final policy message, or on
Ctrl-C / SIGTERM, storing what it holds first; exit 0. No learning happens here.
"""
from __future__ import annotations

import sys
import threading
import time

import numpy as np
from rclpy.node import Node

from comper_memory.client import MemoryClient, RateLimitTimeout, new_request_id
from comper_msgs.msg import EpisodeSummary, PolicyWeights
from comper_msgs_py.ros_params import declare_config, refuse_undeclared
from comper_msgs_py.qos import HAND_OVER_S, RECORDED_QOS as SUMMARY_QOS, wait_acknowledged
from comper_msgs_py.service_client import ServiceError, ServiceTimeout

from comper_agent.nodes.agent_main import run_main
from comper_agent.nodes.bringup import START_HINTS, Spinner
from comper_agent.core.memory_schedule import Row, rows_to_transitions
from comper_agent.nodes.node_config import ActorNodeConfig
from comper_agent.nodes.policy_weights import POLICY_QOS, config_of_policy, load_policy_msg

__all__ = ["ActorNode", "ActorNodeConfig", "ActorFleet", "rate_limit_params", "main"]

EPISODE_ID_STRIDE = 1_000_000_000   # episode ids of actor k: k x stride + its own episode count


class _RandomPolicy:
    """policy:=random: uniform actions within the bounds, label 0 (the memory's default label)."""

    def __init__(self, low, high, seed: int):
        self.low, self.high = np.asarray(low, np.float32), np.asarray(high, np.float32)
        self.rng = np.random.default_rng(seed)

    def act(self, obs, explore: bool = True) -> np.ndarray:
        return self.rng.uniform(self.low, self.high).astype(np.float32)

    def value_labels(self, t) -> np.ndarray:
        return np.zeros(len(t), np.float32)

    def reset_noise(self) -> None:
        pass


class ActorNode(Node):
    """See the module text. ``run()`` is the acting loop (main thread); the node itself is spun by
    a background executor (policy subscription, episode publisher, memory client)."""

    CONFIG = ActorNodeConfig
    HAND_OVER_S = HAND_OVER_S   # comper_msgs_py.qos: the longest wait for the last episodes to be acknowledged

    def __init__(self, node_name: str = "actor_node", **node_kwargs):
        super().__init__(node_name, **node_kwargs)
        self.p = p = declare_config(self, ActorNodeConfig)
        refuse_undeclared([self], "actor_node")
        self.stop_event = threading.Event()
        self.log = self.get_logger()
        self._latest: PolicyWeights | None = None
        self._lock = threading.Lock()
        self._have_policy = threading.Event()
        self.create_subscription(PolicyWeights, p.policy_topic, self._on_policy, POLICY_QOS)
        self.episode_pub = self.create_publisher(EpisodeSummary, "~/episodes", SUMMARY_QOS)
        self.spinner = Spinner([self], self.context).start()
        # short rate-limit waits, retried in _store: a held-back store still sees Ctrl-C and the final message
        self.memory = MemoryClient(self, p.memory_node, timeout=p.service_timeout_s, rate_limit_timeout=1.0)
        self.memory.stop = self.stop_event   # stopping: a store to a memory node that has gone ends at once
        self.final_seen = threading.Event()
        self.dropped = 0
        self.run_id = f"actor{p.actor_id}"
        self.steps = self.episodes = self.stored = 0
        self.policy_version = -1
        self.policy_loads = 0

    def _on_policy(self, msg: PolicyWeights) -> None:
        with self._lock:
            self._latest = msg
        if msg.final:
            self.final_seen.set()
        self._have_policy.set()

    def _take_policy(self) -> PolicyWeights | None:
        with self._lock:
            msg, self._latest = self._latest, None
        return msg

    # ------------------------------------------------------------------------------ set-up
    def _wait(self, what: str, ready, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while not ready():
            if self.stop_event.is_set():
                raise KeyboardInterrupt
            if time.monotonic() > deadline:
                raise RuntimeError(f"{what} did not come within {timeout:g} s")
            time.sleep(0.05)

    def _setup(self) -> None:
        from comper_sim.core import SimBridge, SimConfig
        from comper_agent.core.comcact import ComcactLearner
        from comper_agent.core.config import ComcactConfig, DDPGConfig
        from comper_agent.core.networks import configure_torch
        p = self.p
        self._wait(f"the memory node {p.memory_node!r} (start it with: "
                   f"{START_HINTS['memory'].format(name=p.memory_node)})",
                   lambda: self.memory.wait_for_service(0.5), p.startup_timeout_s)
        self.env = SimBridge(SimConfig(env_id=p.env_id, seed=p.seed, episode_end=p.episode_end,
                                       run_id=self.run_id, action_out_of_range="clip"))
        info = self.env.info()
        if info.discrete:
            raise ValueError(f"{p.env_id} has discrete actions; actor_node acts for COMCACT / DDPG")
        if p.policy == "random":
            self.policy = _RandomPolicy(info.action_low, info.action_high, p.seed)
            return
        self._wait(f"the first policy message on {p.policy_topic} (is the learner running, mode:=async?)",
                   self._have_policy.is_set, p.startup_timeout_s)
        msg = self._take_policy()
        cfg = config_of_policy(msg, ComcactConfig)
        if cfg.variant == "ddpg":
            cfg = config_of_policy(msg, DDPGConfig)
        configure_torch(1)
        from dataclasses import replace
        self.policy = ComcactLearner(replace(cfg, seed=p.seed, num_threads=1), int(np.prod(info.observation_shape)),
                                     info.action_low, info.action_high)
        self._load(msg)

    def _load(self, msg: PolicyWeights) -> bool:
        if msg.final:
            return False
        if int(msg.version) != self.policy_version:
            load_policy_msg(self.policy, msg)
            self.policy_version = int(msg.version)
            self.policy_loads += 1
        return True

    # ------------------------------------------------------------------------------ loop
    def run(self) -> int:
        p = self.p
        try:
            self._setup()
        except KeyboardInterrupt:
            return 0
        self.log.info(f"actor {p.actor_id} on {p.env_id} (seed {p.seed}): storing into {p.memory_node}, "
                      + (f"policy v{self.policy_version} from {p.policy_topic}" if p.policy == "learner"
                         else "random actions")
                      + (f", {p.total_steps} steps" if p.total_steps else ""))
        t0 = time.monotonic()
        rows: list[Row] = []
        obs, _ = self.env.reset(p.seed)
        self.policy.reset_noise()
        ep_return, ep_len = 0.0, 0
        rc = 0
        try:
            while not self.stop_event.is_set() and (p.total_steps == 0 or self.steps < p.total_steps):
                msg = self._take_policy() if p.policy == "learner" else None
                if msg is not None and not self._load(msg):
                    self.log.info(f"the learner finished (final policy message): stopping at step {self.steps}")
                    break
                a = self.policy.act(obs, explore=True)
                r = self.env.step(a)
                rows.append(Row(obs, a, r.reward, r.observation, r.terminated, r.truncated, self.steps))
                self.steps += 1
                ep_return += float(r.reward)
                ep_len += 1
                if r.episode_over or len(rows) >= p.store_every:
                    self._store(rows)
                    rows = []
                if r.episode_over:
                    self._episode_done(ep_return, ep_len, r.terminated, r.truncated, t0)
                    ep_return, ep_len = 0.0, 0
                    obs, _ = self.env.reset(None)
                    self.policy.reset_noise()
                else:
                    obs = r.observation
            if rows:
                self._store(rows)
        except ServiceError as exc:
            if not self.stop_event.is_set():
                err = self.spinner.error
                self.log.error(f"stopping: {exc}" + (f" (this node's executor stopped: {type(err).__name__}: {err})"
                                                     if err is not None else ""))
                rc = 1
        dt = time.monotonic() - t0
        self.log.info(f"done: {self.steps} steps ({self.steps / max(dt, 1e-9):.1f} steps/s), {self.episodes} "
                      f"episodes, {self.stored} transitions stored, {self.policy_loads} policies loaded "
                      f"(last v{self.policy_version}), {self.memory.rate_limited_s:.1f} s waiting for the learner"
                      + (f", {self.dropped} not stored (the learner had stopped)" if self.dropped else ""))
        return rc

    def _store(self, rows: list[Row]) -> None:
        t = rows_to_transitions(rows, self.p.actor_id * EPISODE_ID_STRIDE + self.episodes, self.run_id)
        t.value_labels = self.policy.value_labels(t)
        deadline = time.monotonic() + self.p.rate_limit_timeout_s
        lost, request_id = 0, new_request_id()
        while True:
            try:
                self.memory.store(t, request_id=request_id)
                break
            except RateLimitTimeout:
                if self.stop_event.is_set() or self.final_seen.is_set():
                    self.dropped += len(t)     # the learner no longer samples: nobody would learn from them
                    self.log.info(f"{len(t)} transitions not stored: the learner has stopped sampling")
                    return
                if time.monotonic() > deadline:
                    raise
            except ServiceTimeout:
                # no answer even after the client's own re-sends: try again with the same request id, so a
                # store that did arrive is answered from the memory's remembered answer, not applied twice
                lost += 1
                if lost > 3 or self.stop_event.is_set():
                    raise
                self.log.warning(f"store of {len(t)} transitions: no answer within {self.p.service_timeout_s:g} s; "
                                 f"sending it again ({lost}/3)")
        self.stored += len(t)

    def _episode_done(self, ret: float, length: int, terminated: bool, truncated: bool, t0: float) -> None:
        msg = EpisodeSummary(run_id=self.run_id, env_id=self.p.env_id, source="train",
                             episode_id=self.p.actor_id * EPISODE_ID_STRIDE + self.episodes,
                             episode_return=float(ret), length=int(length), frames=int(length),
                             terminated=bool(terminated), truncated=bool(truncated), global_step=int(self.steps),
                             global_frames=int(self.steps), wall_time_s=float(time.monotonic() - t0))
        msg.header.stamp = self.get_clock().now().to_msg()
        self.episode_pub.publish(msg)
        self.episodes += 1

    def shutdown(self) -> None:
        try:
            self.memory.close()
        except Exception:
            pass
        # the last EpisodeSummary usually goes out just before the actor ends (its budget spent, or the
        # learner's SIGINT): destroying the publisher first would drop it for a subscriber that had not
        # acknowledged it yet (as the learner's hand-over in harness.LearnerHarness.shutdown)
        if not wait_acknowledged((self.episode_pub,), self.HAND_OVER_S):
            self.log.warning(f"a subscriber of ~/episodes had not acknowledged this actor's last "
                             f"episodes after {self.HAND_OVER_S:g} s; it may miss them")
        self.spinner.stop()
        self.destroy_node()


def main(args=None) -> int:
    """Entry point of ``ros2 run comper_agent actor_node``: 0 done or stopped, 1 cannot start / failed."""
    return run_main(ActorNode, "actor_node", args)


if __name__ == "__main__":
    sys.exit(main())


class ActorFleet:
    """The actor_node processes a learner starts itself (comcact_node mode:=async, embedded bring-up):
    ``ros2 run comper_agent actor_node`` children with seeds seed + 1 + i, each killed with its
    parent (PR_SET_PDEATHSIG) and logged to ``<run dir>/actor_<i>.log``."""

    def __init__(self, *, num_actors: int, env_id: str, seed: int, memory_node: str, policy_topic: str,
                 steps_each: int, episode_end: str, log_dir, startup_timeout_s: float):
        import functools
        import os
        import shutil
        import subprocess
        from pathlib import Path

        from comper_agent.recording.recording_link import _die_with_parent
        self.procs, self.logs = [], []
        ros2 = shutil.which("ros2") or "ros2"
        for i in range(num_actors):
            log_path = Path(log_dir) / f"actor_{i}.log"
            log = open(log_path, "ab")
            cmd = [ros2, "run", "comper_agent", "actor_node", "--ros-args",
                   "-r", f"__node:=actor_{i}_{os.getpid()}", "-p", f"env_id:={env_id}", "-p", f"seed:={seed + 1 + i}",
                   "-p", f"actor_id:={i}", "-p", f"memory_node:={memory_node}", "-p", f"policy_topic:={policy_topic}",
                   "-p", f"total_steps:={steps_each}", "-p", f"episode_end:={episode_end}",
                   "-p", f"startup_timeout_s:={startup_timeout_s}"]
            # UDP between the actors and this process: over Fast DDS's shared memory, answers of the memory node
            # to an actor were lost now and then on the loaded 2-core machine (a store waited for ever); with UDP
            # only it was rarer (docs/comcact.md, Async mode; lost answers are re-sent with the same request id)
            env = {**os.environ}
            env.setdefault("FASTDDS_BUILTIN_TRANSPORTS", "UDPv4")
            self.procs.append(subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env,
                                               preexec_fn=functools.partial(_die_with_parent, os.getpid())))
            self.logs.append((log, log_path))

    def alive(self) -> int:
        return sum(p.poll() is None for p in self.procs)

    def failed(self) -> list[str]:
        """'actor i: exit n, <log tail>' for each actor that exited with an error."""
        out = []
        for i, (p, (_, path)) in enumerate(zip(self.procs, self.logs)):
            rc = p.poll()
            if rc not in (None, 0):
                out.append(f"actor {i}: exit {rc}; {path}: {path.read_text(errors='replace')[-800:]}")
        return out

    def stop(self, timeout: float = 30.0, grace: float = 60.0) -> list[int | None]:
        """Wait up to `grace` for the actors to end on their own (their step budgets are spent when the
        learner stops; tearing a node's DDS participant down took over 10 s on the loaded 2-core machine), then SIGINT (they store what they hold and exit 0), SIGKILL after `timeout`;
        exit codes."""
        import signal
        import subprocess
        import time as _t
        deadline = _t.monotonic() + grace
        while self.alive() and _t.monotonic() < deadline:
            _t.sleep(0.1)
        for p in self.procs:
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        deadline = _t.monotonic() + timeout
        codes = []
        for p in self.procs:
            try:
                codes.append(p.wait(max(0.1, deadline - _t.monotonic())))
            except subprocess.TimeoutExpired:
                p.kill()
                codes.append(p.wait())
        for log, _ in self.logs:
            log.close()
        return codes


def rate_limit_params(p, c) -> dict:
    """The memory node's rate limiter for an async learner (comcact_node parameters `p`, learner
    hyper-parameters `c`): replay_ratio updates of batch_size per environment step, with an error
    band of rate_buffer_steps steps (docs/comcact.md, Async mode)."""
    spi = float(p.replay_ratio * c.batch_size)
    # the band must hold the largest single call: an actor's store and a learner's prefetched sample
    widest = max(spi * 10, c.batch_size * max(1, min(p.prefetch_batches, p.reduce_every)))
    return {"samples_per_insert": spi, "rate_error_buffer": max(spi * p.rate_buffer_steps, widest, 1.0),
            "min_size_to_sample": int(max(c.learning_starts, c.batch_size))}
