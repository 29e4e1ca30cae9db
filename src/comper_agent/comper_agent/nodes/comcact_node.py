"""comcact_node: the COMCACT learner (thesis Algorithm 8; method.md section 4) and the DDPG baseline.

    ros2 run comper_agent comcact_node                      # InvertedPendulum-v4, everything in-process
    ros2 run comper_agent comcact_node --ros-args -p env_id:=Hopper-v4 -p total_steps:=50000
    ros2 run comper_agent comcact_node --ros-args -p algorithm:=ddpg
    ros2 run comper_agent comcact_node --ros-args -p resume:=runs/<run_id>
    ros2 run comper_agent comcact_node --ros-args -p record:=true     # also bag the run (<run dir>/bag)
    ros2 run comper_agent comcact_node --help                # every parameter

One agent step (COMCACT): act with OU noise (per action dimension, reset each episode), clipped to the bounds
-> ``<sim>/step`` -> store the transition with its value label in the memory -> sample ``batch_size`` from RTM
(TM while RTM is empty, Algorithm 8 lines 14-17) -> DDPG critic and actor update -> reduce when due (every
``reduce_every`` updates and whenever RTM is empty: ``<qt_trainer>/reduce``) -> extra critic step towards
r + gamma (1 - terminated) QT(tau), QT being the local copy of the latest published QTModel -> soft target
updates. ``algorithm:=ddpg``: uniform replay in this process, no QT step, no memory or QT trainer.
``mode:=async``: actor processes store into the memory node, this node only learns. ``bringup:=embedded``
(default) builds the sim, memory and QT trainer nodes in this process, ``external`` uses running ones. Every
``eval_every`` steps ``eval_episodes`` deterministic episodes on a separate environment. Outputs in
``<runs_root>/<run_id>/``; Ctrl-C saves a final checkpoint (a second one aborts). docs/comcact.md.

Top to bottom: set-up, the loop (lock step or async, chosen once), one step (act, store, learn), the memory
(sample, reduce, QT targets), evaluation, checkpoints, the end. The update is ``core.comcact.ComcactLearner``;
the run plumbing (bring-up, run directory, logs, checkpoints, time split) is ``nodes.harness``, which it calls.
"""
from __future__ import annotations

import sys
import time

import numpy as np
from rclpy.node import Node

from comper_msgs_py.arrays import Transitions
from comper_msgs_py.convert import seq_to_numpy
from comper_sim.core import episode_over

from comper_agent.core.config import COMCACT_PROFILES, ComcactConfig, DDPGConfig, resolve_comcact_profile
from comper_agent.core.memory_schedule import Row, reduce_due, rows_to_transitions, updates_before_reduce
from comper_agent.nodes.agent_main import run_main
from comper_agent.nodes.agent_run import next_due, resume_text
from comper_agent.nodes.async_acting import AsyncActing
from comper_agent.nodes.episodes import SUMMARY_QOS
from comper_agent.nodes.harness import LearnerHarness, declare_learner_parameters
from comper_agent.nodes.node_config import ComcactNodeConfig

__all__ = ["ComcactNode", "ComcactNodeConfig", "main", "SUMMARY_QOS"]


class ComcactNode(Node):
    """The COMCACT / DDPG learner node (see the module text)."""

    NODE_NAME = "comcact_node"
    CONFIG = ComcactNodeConfig
    LEARNER_CONFIGS = {"comcact": ComcactConfig, "ddpg": DDPGConfig}
    # num_threads 1: the 400/300 nets at batch 64 gain nothing from a second intra-op thread on the 2-core
    # machine, and the ROS executor threads need the other core (docs/comcact.md)
    LEARNER_OVERRIDES = {"num_threads": 1}
    PROFILES = COMCACT_PROFILES
    RESOLVE_PROFILE = staticmethod(lambda name, values: resolve_comcact_profile(name, values["algorithm"]))
    CSV_COLUMNS = ["step", "wall_time_s", "eval_mean_return", "eval_std_return", "episodes",
                   "last_train_return", "steps_per_s", "rtm_size", "critic_loss"]

    # ------------------------------------------------------------------------------ set-up
    def __init__(self, **node_kwargs):
        super().__init__(self.NODE_NAME, **node_kwargs)
        self.p, self.cfg, self.profile = p, cfg, profile = declare_learner_parameters(self, ComcactNode)
        self.comcact = p.algorithm == "comcact"       # the memory and the QT step; ddpg: the baseline
        # mode async: actors store into the memory node (its rate limiter holds replay_ratio), DDPG samples it too
        self.acting = AsyncActing(self, p, cfg) if p.mode == "async" else None
        try:
            self.h = h = LearnerHarness(
                self, ComcactNode, p, cfg, profile, uses_memory=self.comcact or self.acting is not None, uses_qt=self.comcact,
                reducer="qt_trainer" if self.comcact else ("memory" if self.acting else "none"),
                check_env=self._check_env, obs_dtype=np.float32,
                embedded_params=({}, self.acting.rate_limits if self.acting else {}, {}))
        except BaseException:
            if self.acting is not None:
                self.acting.close()
            raise
        self.stop_event, self.log, self.ptimers = h.stop_event, h.log, h.ptimers
        self.env, self.mem = h.env, h.mem

    def _check_env(self, info) -> dict:
        """Refuses a discrete task; the action bounds; config.yaml's env."""
        if info.discrete:
            raise ValueError(f"{info.env_id} has discrete actions; COMCACT/DDPG need a continuous task "
                             "(use comper_node for Atari)")
        self.low = seq_to_numpy(info.action_low, np.float32).copy()
        self.high = seq_to_numpy(info.action_high, np.float32).copy()
        self.action_dim = int(self.low.size)
        return {"env_id": info.env_id, "observation_shape": [int(d) for d in info.observation_shape],
                "action_low": self.low.tolist(), "action_high": self.high.tolist(),
                "episode_end": info.episode_end or "standard", "max_episode_steps": int(info.max_episode_steps)}

    def run(self) -> int:
        """Set-up, the loop, the end: 0 done (or stopped and saved), 1 failed, 130 interrupted twice."""
        from comper_agent.core.comcact import ComcactLearner
        from comper_agent.core.networks import configure_torch
        from comper_agent.core.replay import ReplayBuffer
        h, p, cfg = self.h, self.p, self.cfg
        configure_torch(cfg.num_threads)
        self.learner = ComcactLearner(cfg, int(np.prod(h.obs_shape)), self.low, self.high)
        # the one choice of experience: the memory node (COMCACT; DDPG in async mode) or a local uniform replay
        self.replay = None if self.mem is not None else ReplayBuffer(cfg.replay_size, h.obs_shape, (self.action_dim,),
                                                                     seed=cfg.seed)
        self._learn = self._learn_from_memory if self.mem is not None else self._learn_from_replay
        self._store = self._store_in_memory if self.comcact else self._store_in_replay
        self.evaluation = h.open_evaluation(lambda obs: self.learner.act(np.asarray(obs, np.float32), explore=False),
                                            self._eval_recorded, action_out_of_range="clip")
        self.rng = np.random.default_rng(cfg.seed + 7)   # warm-up actions
        self.step = self.stored = self.update_count = self.since_reduce = 0
        self.pending: list[Row] = []           # agent steps not yet stored (labelled when stored)
        self.last_update: dict = {}
        h.experience.replay = self.replay
        h.experience.quiesce = self._flush      # before a memory snapshot: the steps not yet stored go out too
        if not h.resume(self._restore):
            return 1
        h.open_logs({}, self.CSV_COLUMNS, int(p.total_steps), self.step, self._start_line())
        self.next_eval = next_due(self.step, p.eval_every)
        h.outputs.schedule_checkpoints(p.checkpoint_every or p.eval_every, self.step)
        if p.eval_every > 0 and self.step == 0:
            self.evaluation.run(self.step)       # the untrained policy: the curve's first point
        rc = 0
        try:
            rc = h.guard(self._loop_async if self.acting else self._loop_lockstep)   # the loop, chosen once
        finally:
            h.settle(self.step)
            if self.acting is not None:
                self.acting.stop(self.update_count, self.step)
            h.finish(rc, self._state, self.step, self.evaluation.sim_compute_notes(
                lambda: self.rng.uniform(self.low, self.high).astype(np.float32)))
            if self.evaluation.records:
                e = self.evaluation.records[-1]
                self.log.info(f"done: {self.step} steps, {self.env.count} episodes, last evaluation "
                              f"{e['mean_return']:.1f} +- {e['std_return']:.1f} at step {e['step']}; "
                              f"outputs in {h.run_dir.path}")
        return rc

    def _start_line(self) -> str:
        p = self.p
        what = "COMCACT (memory + QT step)" if self.comcact else "DDPG baseline (uniform replay)"
        return (f"{what} on {p.env_id} (obs {list(self.h.obs_shape)}, actions {self.action_dim} in "
                f"[{self.low.min():g}, {self.high.max():g}]), {p.bringup} bring-up, "
                f"{resume_text(self.step)} to {p.total_steps} steps; "
                f"evaluation every {p.eval_every} steps x {p.eval_episodes} episodes"
                + (f"; reduce every {p.reduce_every} updates, reduce_batch {p.reduce_batch}; profile {self.profile}"
                   if self.comcact else ""))

    # ------------------------------------------------------------------------------ the loops
    def _loop_lockstep(self) -> None:
        """mode:=lockstep: act, store, learn, one step at a time (random actions in chunks while warming up)."""
        p = self.p
        obs = self._reset_env()
        while self.step < p.total_steps and not self.stop_event.is_set():
            if self.step < p.warmup_steps:
                obs = self._warmup_chunk(obs, min(p.warmup_steps, p.total_steps,
                                                  self.next_eval or p.total_steps) - self.step)
            else:
                obs = self._agent_step(obs)
            if self.next_eval is not None and self.step >= self.next_eval:
                self._flush()
                self._evaluate()
                self.next_eval += p.eval_every
            self._after_step()
        self._flush()

    def _loop_async(self) -> None:
        """mode:=async: actor processes act and store into the memory (AsyncActing); this loop only learns, held
        to replay_ratio by the memory's rate limiter, counts the environment steps and evaluates."""
        acting, p = self.acting, self.p
        acting.start(self.h, self.learner, self.step)
        since_count = 0
        while self.step < p.total_steps and not self.stop_event.is_set():
            acting.check()
            before = self.update_count
            self._learn()
            since_count += 1
            if self.update_count == before:       # nothing to sample yet: the actors are filling the memory
                time.sleep(0.01)
            if since_count >= 20 or self.update_count == before:
                self.step = max(self.step, acting.env_steps())
                since_count = 0
                self._flush()                 # restore_batch: the re-stores of these updates, marked relabel
            acting.publish_when_due(self.learner, self.step)
            if self.next_eval is not None and self.step >= self.next_eval:
                self._evaluate()
                self.next_eval = next_due(self.step, p.eval_every)
            self._after_step()
        # the updates still owed for the last steps (the rate limiter lets learning trail acting by up to
        # rate_buffer_steps): as in lock step, every step gets its replay_ratio updates
        owed = int(p.replay_ratio * max(0, self.step - self.cfg.learning_starts))
        while self.update_count < owed and not self.stop_event.is_set():
            self._learn()
        self._flush()
        acting.publish(self.learner, self.step, final=True)

    def _after_step(self) -> None:
        """A checkpoint and a progress line when due."""
        line = self.h.after_step(self.step, self._state)
        if not line:
            return
        extra, counts = "", {}
        if self.comcact:       # so far in the run: QT critic steps taken, and those qt_step_gate skipped
            extra = f" | RTM {self.h.rtm_size} | QT v{self.mem.qt_version}"
            counts = {"learner_updates": self.learner.updates, "qt_steps_taken": self.learner.qt_steps,
                      "qt_steps_gated": self.learner.qt_gated}
        self.h.progress_record(line + extra, self.step, self.step, self.last_update, episodes=self.env.count,
                               rtm_size=self.h.rtm_size, **counts)

    # ------------------------------------------------------------------------------ one step
    def _reset_env(self) -> np.ndarray:
        obs = self.env.reset()
        self.learner.reset_noise()
        return obs

    def _agent_step(self, obs: np.ndarray) -> np.ndarray:
        with self.ptimers("learner"):
            a = self.learner.act(obs, explore=True)
        r, nxt = self.env.step(a)
        self.pending.append(Row(obs, a, r.reward, nxt, r.terminated, r.truncated, self.step))
        self.step += 1
        over = episode_over(self.h.episode_rule, r.terminated, r.truncated)
        if len(self.pending) >= self.p.store_every or over:
            self._flush()
        if self.stored >= max(self.cfg.learning_starts, 2):
            self._learn()
        if over:
            self.env.end(r.terminated, r.truncated, step=self.step)
            return self._reset_env()
        return nxt

    def _warmup_chunk(self, obs: np.ndarray, n: int) -> np.ndarray:
        """Up to 1,000 uniformly random actions in one ``<sim>/step_many`` call; no learning."""
        n = max(1, min(int(n), 1000))
        acts = self.rng.uniform(self.low, self.high, size=(n, self.action_dim)).astype(np.float32)
        t, over, obs = self.env.step_many(acts, rule=self.h.episode_rule, step=self.step, run_id=self.h.run_id)
        seg = 0
        for i in range(len(t)):
            self.env.add(float(t.rewards[i]))
            self.step += 1
            if over[i]:
                self._store(t.take(slice(seg, i + 1)))   # the episode's transitions go out with its summary
                seg = i + 1
                self.env.end(bool(t.terminated[i]), bool(t.truncated[i]), step=self.step)
                self.env.begin()                         # step_many reset the environment itself
                self.learner.reset_noise()
        if seg < len(t):
            self._store(t.take(slice(seg, len(t))))
        return obs

    # ------------------------------------------------------------------------------ store
    def _flush(self) -> None:
        """The steps not yet stored go out (with the re-stored batches waiting, restore_batch)."""
        rows, self.pending = self.pending, []
        self._store(rows_to_transitions(rows, self.env.count, self.h.run_id) if rows else None)

    def _store_in_memory(self, t: Transitions | None) -> None:
        """COMCACT: `t` labelled (Q(s', mu(s'))) and the re-stores waiting in one ``<memory>/store``; None: those."""
        if t is not None:
            with self.ptimers("learner"):
                t.value_labels = self.learner.value_labels(t)
        self.mem.store(t)
        self._stored(t)

    def _store_in_replay(self, t: Transitions | None) -> None:
        """DDPG: the transitions into the local replay (async: the actors store, this stores nothing)."""
        if t is not None:
            with self.ptimers("learner"):
                self.replay.add(t)
        self._stored(t)

    def _stored(self, t: Transitions | None) -> None:
        if t is not None:
            self.stored += len(t)
            self.env.parts.append(t)     # ~/transitions with the episode's summary

    # ------------------------------------------------------------------------------ learn
    def _learn_from_replay(self) -> None:
        """DDPG: a uniform batch, critic and actor update, soft target updates."""
        with self.ptimers("learner"):
            batch = self.replay.sample(self.cfg.batch_size)
            self.last_update = self.learner.update(batch)
            self.learner.soft_update()
        self._updated()

    def _learn_from_memory(self) -> None:
        """Algorithm 8's update: a batch from the memory, the DDPG update, a reduction when due, the QT critic
        step (COMCACT), soft target updates; restore_batch: the batch goes back with fresh labels."""
        p = self.p
        self.mem.collect(wait=False)      # reduce_overlap: a reduction that has answered
        got = self._sample()
        if got is None:
            return
        batch, counts = got
        with self.ptimers("learner"):
            self.last_update = self.learner.update(batch)
        self.since_reduce += 1
        if reduce_due(self.since_reduce, p.reduce_every, self.h.rtm_size):
            self._reduce()
        targets = self._qt_targets(batch)
        if targets is not None and self.h.diagnostics.due(self.update_count):
            # after the DDPG step on the batch, before the QT step
            self.h.diagnostics.record(self.learner, batch, counts, targets, step=self.step, update=self.update_count,
                                      x=self.step, qt_version=int(self.mem.qt_version), rtm_size=int(self.h.rtm_size),
                                      restored=int(self.mem.restored))
        with self.ptimers("learner"):
            if targets is not None:
                self.last_update.update(self.learner.qt_critic_step(batch, targets))
            self.learner.soft_update()
            if p.restore_batch:       # fresh labels after this update's steps (and target update)
                batch.value_labels = self.learner.value_labels(batch)
                self.mem.queue_restore(batch)
        self._updated()

    def _updated(self) -> None:
        self.update_count += 1
        if self.update_count % 250 == 0:
            self.h.scalars.scalars(self.last_update, self.step, prefix="train/")

    # ------------------------------------------------------------------------------ the memory
    def _sample(self):
        """(batch, set sizes) for the next update: from RTM (prefetched up to the next reduction,
        MemoryLink.next_batch), from TM while RTM is empty (Algorithm 8 lines 14-17)."""
        k = self.cfg.batch_size
        source, avail = "rtm", self.h.rtm_size
        if self.h.rtm_size <= 1 and not self.mem.prefetched:
            with self.ptimers("memory"):
                stats = self.mem.stats()
            if self.h.rtm_size <= 1:
                source, avail = "tm", stats["tm_sets"]
            else:
                avail = self.h.rtm_size
        k = min(k, avail)
        if k < 2:
            return None
        got = self.mem.next_batch(k, source, updates_before_reduce(self.p.reduce_every - self.since_reduce))
        if got is None:      # RTM shrank (evictions): refresh its size next time
            self.mem.rtm_size = 0
        return got

    def _reduce(self) -> None:
        self._flush()               # every stored transition takes part in the reduction
        self.since_reduce = 0
        if self.mem.start_overlapped():   # reduce_overlap: learning goes on; mem.collect finishes it
            return
        with self.ptimers("qt"):
            r = self.mem.reduce()
            if self.comcact and self.p.qt_targets == "local" and r.qt_version > 0:
                self.mem.wait_qt_model(r.qt_version)

    def _qt_targets(self, batch: Transitions) -> np.ndarray | None:
        """QT(tau) for the batch's rows (COMCACT; qt_targets rtm: the labels RTM sampled with them, local: the
        local QT copy), None for async DDPG, before the first reduction or while RTM is empty."""
        if not self.comcact:              # async DDPG: the memory is its replay, no QT step
            return None
        if self.p.qt_targets == "rtm":
            return batch.value_labels if self.h.rtm_size > 0 and batch.value_labels.size == len(batch) else None
        return self.mem.qt_predictions(batch)

    # ------------------------------------------------------------------------------ evaluate
    def _evaluate(self) -> None:
        """The evaluation, then a 'memory' record: the memory's statistics (identities, transitions stored,
        bytes held, evictions, ...) or the local replay's size."""
        self.evaluation.run(self.step)
        self.h.memory_record(self.step, self.h.experience_stats(self.replay))

    def _eval_recorded(self, rec: dict) -> None:
        """The evaluation's progress.csv row."""
        self.h.csv.write(step=self.step, wall_time_s=round(self.h.wall_time(), 2), eval_mean_return=rec["mean_return"],
                         eval_std_return=rec["std_return"], episodes=self.env.count,
                         last_train_return=self.h.progress.last_episode_return,
                         steps_per_s=round(self.h.progress.overall_rate(self.step), 1),
                         rtm_size=self.h.rtm_size if self.comcact else self.stored,
                         critic_loss=self.last_update.get("critic_loss"))

    # ------------------------------------------------------------------------------ checkpoints
    def _state(self) -> dict:
        return {**self.h.state(self.learner, step=self.step, stored=self.stored),
                "warmup_rng": self.rng.bit_generator.state}

    def _restore(self, state: dict) -> None:
        c = self.h.restore(state, self.learner)
        self.step, self.stored = int(c["step"]), int(c.get("stored", 0))
        self.rng.bit_generator.state = state["warmup_rng"]

    # ------------------------------------------------------------------------------ the end
    def shutdown(self) -> None:
        self.h.shutdown()
        if self.acting is not None:
            self.acting.close()


def main(args=None) -> int:
    """Entry point of ``ros2 run comper_agent comcact_node``: 0 done, 1 cannot start / failed, 130 aborted."""
    return run_main(ComcactNode, "comcact_node", args)


if __name__ == "__main__":
    sys.exit(main())
