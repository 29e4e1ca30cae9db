"""comper_node: the COMPER learner (thesis Algorithm 7; method.md sections 3-5), its chapter-7 ablations
COMPER-F and COMPER-M, and the DQN baseline (Table 35), on ALE games and vector tasks.

    ros2 run comper_agent comper_node                                   # COMPER on ALE/Freeway-v5, 100,000 frames
    ros2 run comper_agent comper_node --ros-args -p env_id:=ALE/Asterix-v5 -p seed:=1
    ros2 run comper_agent comper_node --ros-args -p algorithm:=comper_f   # or comper_m, dqn
    ros2 run comper_agent comper_node --ros-args -p env_id:=CartPole-v1   # a vector task (profile classic_control)
    ros2 run comper_agent comper_node --ros-args -p resume:=runs/<run_id>
    ros2 run comper_agent comper_node --help                            # every parameter

One agent step: a = epsilon-greedy(Q(s)) -> ``<sim>/step``; the label of transition t (next_value) is
max_a Q(s_{t+1}, a), from the Q-values computed to act at t + 1. Every ``train_frequency`` steps: one
``<memory>/store`` with the new labelled transitions and the last update's batch re-stored (Algorithm 7 /
thesis 4.1.1), a reduction when due (``<qt_trainer>/reduce``; comper_f: ``<memory>/reduce``), ``<memory>/sample``
(RTM; TM for comper_m), the Huber update towards r + gamma (1 - terminated) QT(tau) (comper, comper_m) or the
target network (comper_f, dqn). dqn: a local replay, no memory or QT nodes. The run stops at the first
episode end after ``total_frames`` frames, at ``max_steps`` if > 0, or on Ctrl-C (final checkpoint,
summary.json; a second Ctrl-C aborts). Outputs in ``<runs_root>/<run_id>/``; docs/comper.md.

Top to bottom: set-up (the experience chosen once: the memory node or a local replay), the loop, one step,
learning (store, reduce, sample, update), checkpoints, the end. The update is ``core.comper.ComperLearner``; the
run plumbing ``nodes.harness``; the start line, progress rows and summary.json ``nodes.comper_records``.
"""
from __future__ import annotations

import json
import math
import sys

import numpy as np
from rclpy.node import Node

from comper_msgs_py.arrays import Transitions
from comper_sim.core import episode_over

from comper_agent.core.config import COMPER_PROFILES, ComperConfig, DQNConfig, resolve_profile
from comper_agent.core.memory_schedule import (NStepWindows, PendingRows, Row, reduce_due, rows_to_transitions,
                                               updates_before_reduce)
from comper_agent.nodes import comper_records
from comper_agent.nodes.agent_main import run_main
from comper_agent.nodes.agent_run import next_due, unaccounted_notes
from comper_agent.nodes.episodes import SUMMARY_QOS
from comper_agent.nodes.harness import LearnerHarness, declare_learner_parameters
from comper_agent.nodes.qt_diagnostics import sampled_set_sizes
from comper_agent.nodes.node_config import ComperNodeConfig, check_frames, comper_reducer, reduce_pace_warning

__all__ = ["ComperNode", "ComperNodeConfig", "main", "SUMMARY_QOS", "TRANSITIONS_QOS"]

TRANSITIONS_QOS = SUMMARY_QOS


class ComperNode(Node):
    """The COMPER / COMPER-F / COMPER-M / DQN learner node (see the module text)."""

    NODE_NAME = "comper_node"
    CONFIG = ComperNodeConfig
    LEARNER_CONFIGS = {"comper": ComperConfig, "comper_f": ComperConfig, "comper_m": ComperConfig, "dqn": DQNConfig}
    LEARNER_OVERRIDES = {"num_threads": 1}   # measured faster on the 2-core machine with the embedded nodes
    PROFILES = COMPER_PROFILES
    RESOLVE_PROFILE = staticmethod(lambda name, values: resolve_profile(name, values["env_id"]))
    CSV_COLUMNS = ["step", "frames", "wall_time_s", "episodes", "last_train_return", "epsilon",
                   "steps_per_s", "rtm_size", "tm_sets", "identities", "loss", "eval_mean_return"]
    QT_START_HINT = " -p architecture:=comper -p reduce_batch:=1000"

    # ------------------------------------------------------------------------------ set-up
    def __init__(self, **node_kwargs):
        super().__init__(self.NODE_NAME, **node_kwargs)
        self.p, self.cfg, self.profile = p, cfg, profile = declare_learner_parameters(self, ComperNode)
        reducer = comper_reducer(p, cfg)           # refuses parameters that do not go together
        self.is_atari = p.env_id.startswith("ALE/")
        self.obs_dtype = np.uint8 if self.is_atari else np.float32
        self.eval_every = p.eval_every if p.eval_every >= 0 else (0 if self.is_atari else 5_000)
        self.uses_qt = p.algorithm in ("comper", "comper_m")      # QT targets; comper_f, dqn: the target network
        self.sample_source = "tm" if p.algorithm == "comper_m" else "rtm"
        # the sim parameters the learner's settings fix (ALE: frames per observation, frame pooling)
        self.sim_protocol = ({"frame_stack": int(cfg.frame_stack), "frame_pooling": cfg.frame_pooling}
                             if self.is_atari else {})
        self.h = h = LearnerHarness(
            self, ComperNode, p, cfg, profile, uses_memory=reducer != "none", uses_qt=self.uses_qt, reducer=reducer,
            check_env=self._check_env, obs_dtype=self.obs_dtype,
            embedded_params=(self.sim_protocol, {"reduce_batch": int(p.reduce_batch)}, {"architecture": "comper"}))
        self.stop_event, self.log, self.ptimers = h.stop_event, h.log, h.ptimers
        self.env, self.mem = h.env, h.mem

    def _check_env(self, info) -> dict:
        """Refuses a continuous task or observations that do not fit the frame stack; config.yaml's env."""
        from comper_agent.core.comper import resolve_q_network
        c, obs_shape = self.cfg, tuple(int(d) for d in info.observation_shape)
        if not info.discrete:
            raise ValueError(f"{info.env_id} has continuous actions; comper_node needs discrete actions (an ALE "
                             "game or a task such as CartPole-v1; use comcact_node for continuous control)")
        self.n_actions = int(info.num_actions)
        if c.n_actions and c.n_actions != self.n_actions:
            raise ValueError(f"{info.env_id} has {info.num_actions} actions but n_actions:={c.n_actions} "
                             "(0 = take the environment's)")
        spec = json.loads(info.spec_json or "{}")
        if self.is_atari and (note := check_frames(obs_shape, spec, c)):     # a wrong frame stack raises
            self.get_logger().warning(note)
        self.network = resolve_q_network(c.q_network, obs_shape)
        self.frame_skip = max(1, int(info.frame_skip))
        return {"env_id": info.env_id, "observation_shape": list(obs_shape), "num_actions": self.n_actions,
                "frame_skip": self.frame_skip, "episode_end": info.episode_end or "standard", "spec": spec}

    def run(self) -> int:
        """Set-up, the loop, the end: 0 done (or stopped and saved), 1 failed, 130 interrupted twice."""
        from comper_agent.core.comper import ComperLearner, clip_rewards
        from comper_agent.core.networks import configure_torch
        from comper_agent.core.replay import FrameReplay, ReplayBuffer
        h, p, c = self.h, self.p, self.cfg
        configure_torch(c.num_threads)
        self.learner = ComperLearner(c, h.obs_shape, self.n_actions)
        # the one choice of experience: the memory node (COMPER variants: labelled rows stored in batches, sampled
        # from RTM or TM, reduced) or a local replay (DQN: each step added, uniform batches)
        self.replay = None
        if self.mem is not None:
            self._keep, self._store_due = self._keep_for_memory, self._store_when_due
            self._learn = self._learn_from_memory
            self.mem.on_reduced = self._after_reduce
        else:
            self.replay = (FrameReplay(c.replay_size, (84, 84), c.frame_stack, seed=c.seed) if self.is_atari
                           else ReplayBuffer(c.replay_size, h.obs_shape, seed=c.seed))
            self._keep, self._store_due = self._keep_in_replay, lambda learned, over: None
            self._learn = self._learn_from_replay
        self.evaluation = None if self.eval_every <= 0 else h.open_evaluation(
            lambda obs: self.learner.act(np.asarray(obs, self.obs_dtype), epsilon=p.eval_epsilon)[0],
            lambda rec: h.csv.write(step=self.step, frames=self.frames, wall_time_s=round(h.wall_time(), 2),
                                    episodes=self.env.count, eval_mean_return=rec["mean_return"]),   # progress.csv
            self.frame_skip, **self.sim_protocol)
        self.step = self.frames = self.stored = self.updates = 0    # frames: the emulator's, skipped ones included
        self.returns, self.return_frames = [], []    # each training episode's return and the run's frames at its end
        self.last_reduce_step = -(10 ** 9)
        self.pending = PendingRows()            # agent steps not yet stored (the newest may wait for its label)
        self.windows = None                     # n_step > 1: the memory stores n-step windows of those steps
        if self.mem is not None and c.n_step > 1:
            self.windows = NStepWindows(c.n_step, c.gamma, lambda r: clip_rewards(r, c.reward_clip))
        self.set_counts, self.last_stats, self.last_update = [], {}, {}
        h.experience.replay = self.replay
        if not h.resume(self._restore):
            return 1
        steps = int(math.ceil(p.total_frames / self.frame_skip))       # what the progress line counts towards
        h.open_logs({"q_network": self.network, "eval_every": self.eval_every}, self.CSV_COLUMNS,
                    min(steps, p.max_steps) if p.max_steps > 0 else steps, self.step, comper_records.start_line(self))
        if self.mem is not None and (note := reduce_pace_warning(p, c)):
            self.log.warning(note)
        self.start_frames = self.frames
        h.outputs.schedule_checkpoints(p.checkpoint_every, self.step)
        self.next_stats, self.next_eval = next_due(self.step, p.stats_every), next_due(self.step, self.eval_every)
        if self.eval_every > 0 and self.step == 0:
            self.evaluation.run(self.step, self.frames)       # the untrained policy: the curve's first point
        rc = 0
        try:
            rc = h.guard(self._loop)
        finally:
            h.settle(self.step)
            try:
                if rc != 130:
                    self._memory_record()
            except Exception as exc:
                self.log.warning(f"final memory statistics failed: {exc}")
            comper_records.write_summary(self, h.finish(rc, self._state, self.step, unaccounted_notes))
        return rc

    # ------------------------------------------------------------------------------ the loop
    def _loop(self) -> None:
        p = self.p
        obs = self._reset_env()
        while not self.stop_event.is_set():
            obs, over = self._agent_step(obs)
            if over:
                if self.frames >= p.total_frames:
                    break
                obs = self._reset_env()
            if p.max_steps > 0 and self.step >= p.max_steps:
                break
            if self.next_stats is not None and self.step >= self.next_stats:
                self._memory_record()
                self.next_stats += p.stats_every
            if self.next_eval is not None and self.step >= self.next_eval:
                self.evaluation.run(self.step, self.frames)
                self.next_eval += self.eval_every
            if line := self.h.after_step(self.step, self._state):     # a checkpoint when due; the progress line
                comper_records.progress(self, line)
        evals = self.evaluation.records if self.eval_every > 0 else []
        if self.eval_every > 0 and not self.stop_event.is_set() and (evals[-1]["step"] if evals else None) != self.step:
            self.evaluation.run(self.step, self.frames)       # the final policy
        last = self.pending.newest_unlabelled()
        if last is not None:    # stopped mid-episode: label the last one too
            q_last = self.learner.act(last.next_state, epsilon=0.0)[1]
            last.label = self.learner.next_value(last.next_state, q_last) * (0.0 if last.terminated else 1.0)
        if self.pending:
            self._flush(with_restore=False)
        if self.windows is not None:
            self.windows.reset()          # the windows still open at the stop are dropped (and counted)

    # ------------------------------------------------------------------------------ one step
    def _reset_env(self) -> np.ndarray:
        obs = self.env.reset()
        self.ep_frames0, self.ep_frames = self.frames, 0
        self.new_episode = True
        if self.windows is not None:
            self.windows.reset()
        return obs

    def _agent_step(self, obs: np.ndarray) -> tuple[np.ndarray, bool]:
        c = self.cfg
        with self.ptimers("learner"):
            a, q = self.learner.act(obs, frames=self.frames)
        waiting = self.pending.newest_unlabelled()
        if waiting is not None:     # next_value label of the previous transition
            with self.ptimers("learner"):
                waiting.label = self.learner.next_value(obs, q)
        r, nxt = self.env.step(a)
        term, trunc = bool(r.terminated), bool(r.truncated)
        self.ep_frames = int(r.frames)
        self.frames = self.ep_frames0 + self.ep_frames
        over = episode_over(self.h.episode_rule, term, trunc)
        self._keep(Row(obs, a, r.reward, nxt, term, trunc, self.step), q, over)
        self.new_episode = False
        self.step += 1
        learned = self.step % c.train_frequency == 0 and self.step >= c.learning_starts
        if learned:
            self._learn()
        self._store_due(learned, over)
        if over:
            self._end_episode(term, trunc)
        return nxt, over

    def _keep_in_replay(self, row: Row, q: np.ndarray, over: bool) -> None:
        """DQN: the step into the local replay (ALE: its frames, each once)."""
        with self.ptimers("learner"):
            self.replay.add_step(row.state, row.action, float(row.reward), row.next_state, row.terminated,
                                 row.truncated, self.new_episode)
        self.stored += 1
        self.env.add_row(row)            # ~/transitions, while someone records

    def _keep_for_memory(self, row: Row, q: np.ndarray, over: bool) -> None:
        """COMPER: the step waits for its label (next_value: the next step's Q-values; q_sa: Q(s, a) now)."""
        if row.terminated:
            row.label = 0.0
        elif self.cfg.qt_label == "q_sa":
            row.label = float(q[row.action])
        elif over:      # truncated end: nobody acts on s', compute max_a Q(s', a) now
            with self.ptimers("learner"):
                row.label = self.learner.next_value(row.next_state, self.learner.act(row.next_state, epsilon=0.0)[1])
        self.pending.append(row)

    def _end_episode(self, terminated: bool, truncated: bool) -> None:
        ep = self.env
        self.returns.append(float(ep.ret))
        self.return_frames.append(int(self.frames))
        ep.end(terminated, truncated, step=self.step, ep_frames=self.ep_frames, global_frames=self.frames,
               x=self.frames, frames=self.frames, episode_frames=self.ep_frames,
               epsilon=self.learner.epsilon(self.frames))
        self.log.info(f"episode {ep.count - 1}: return {ep.ret:.1f}, {ep.length} steps, "
                      f"{self.ep_frames} frames; run {self.frames}/{self.p.total_frames} frames")

    # ------------------------------------------------------------------------------ learn
    def _learn_from_replay(self) -> None:
        """DQN: a uniform batch (n-step windows with n_step > 1), the update against the target network."""
        c = self.cfg
        if len(self.replay) < c.batch_size:     # a resumed run refills its replay first
            return
        with self.ptimers("learner"):
            if c.n_step > 1:
                batch, windows = self.replay.sample(c.batch_size, c.n_step)
                self.last_update = self.learner.update(batch, n_step=windows)
            else:
                self.last_update = self.learner.update(self.replay.sample(c.batch_size))
        self._updated()

    def _learn_from_memory(self) -> None:
        """Algorithm 7's update: store (with the last batch re-stored), reduce when due, sample, the update
        against QT(tau) or the target network, the batch relabelled for its re-store."""
        p = self.p
        self._flush(with_restore=True)
        self.mem.collect(wait=False)      # reduce_overlap: a reduction that has answered
        if reduce_due(self.step - self.last_reduce_step, p.reduce_every, self.h.rtm_size):
            self._reduce()
        got = self._sample()
        if got is None:
            return
        batch, counts = got
        self.set_counts.append(counts)
        targets = None
        if self.uses_qt:
            if p.qt_targets == "rtm" and self.sample_source == "rtm":
                targets = batch.value_labels
            else:
                targets = self.mem.qt_predictions(batch)
                if targets is None:
                    self.log.warning("no QTModel received yet: update skipped (is the QT trainer "
                                     "publishing on qt_model?)", throttle_duration_sec=10.0)
                    return
            if self.h.diagnostics.due(self.updates):     # before the update on the batch
                self.h.diagnostics.record(self.learner, batch, counts, targets, step=self.step, update=self.updates,
                                          x=self.frames, frames=self.frames, qt_version=int(self.mem.qt_version),
                                          rtm_size=int(self.h.rtm_size))
        with self.ptimers("learner"):
            self.last_update = self.learner.update(batch, targets)
            if p.restore_batch:
                batch.value_labels = self.learner.value_labels(batch)
                self.mem.queue_restore(batch)
        self._updated()

    def _updated(self) -> None:
        c = self.cfg
        self.updates += 1
        if self.learner.uses_target_net and self.step % c.target_update_every < c.train_frequency:
            self.learner.sync_target()
        if self.updates % 250 == 0:
            self.h.scalars.scalars(self.last_update, self.frames, prefix="train/")

    # ------------------------------------------------------------------------------ the memory
    def _store_when_due(self, learned: bool, over: bool) -> None:
        """Between updates, the labelled steps go out every ``store_every`` and at an episode end."""
        if over or (not learned and self.pending.labelled() >= self.p.store_every):
            self._flush(with_restore=False)

    def _flush(self, with_restore: bool) -> None:
        """One store call: the labelled new transitions (+ the previous update's batch re-stored)."""
        rows = self.pending.take_labelled()
        t = None
        if rows:
            t = rows_to_transitions(rows, self.env.count, self.h.run_id)
            self.env.parts.append(t)         # ~/transitions and bags: the one-step transitions, raw rewards
            if self.windows is not None:
                rows = self.windows.push(rows)
                t = rows_to_transitions(rows, self.env.count, self.h.run_id) if rows else None
            self.stored += len(rows)
        self.mem.store(t, with_restore=with_restore)

    def _reduce(self) -> None:
        self.last_reduce_step = self.step
        if self.mem.start_overlapped():   # reduce_overlap: learning goes on; mem.collect finishes it
            return
        with self.ptimers("qt" if self.h.reducer == "qt_trainer" else "memory_reduce"):
            r = self.mem.reduce()
        self._after_reduce(r)
        if self.uses_qt and r.qt_version > 0:
            with self.ptimers("qt_wait"):
                self.mem.wait_qt_model(r.qt_version)

    def _after_reduce(self, r) -> None:
        self.h.metrics.write("reduce", step=self.step, frames=self.frames, rtm_size=self.h.rtm_size,
                             **self.mem.last_reduce)

    def _sample(self) -> tuple[Transitions, np.ndarray] | None:
        """(batch, set sizes) for the next update: from RTM prefetched up to the next reduction
        (MemoryLink.next_batch), from TM (COMPER-M) one call per update."""
        k = self.cfg.batch_size
        if self.sample_source == "rtm":
            k = min(k, self.h.rtm_size)
        if k < 1:
            return None
        steps_left = self.p.reduce_every - (self.step - self.last_reduce_step)
        got = self.mem.next_batch(k, self.sample_source, updates_before_reduce(steps_left, self.cfg.train_frequency))
        if got is None:     # fewer entries than asked (TM drained by a reduction, RTM evictions)
            with self.ptimers("memory"):
                st = self.mem.stats()
            k = min(k, st["tm_sets"] if self.sample_source == "tm" else st["rtm_size"])
            got = self.mem.next_batch(k, self.sample_source, 1) if k >= 1 else None
        return got

    # ------------------------------------------------------------------------------ records
    def _memory_record(self) -> None:
        """A 'memory' record: the memory's statistics with the sizes of the sets sampled since the last one,
        or the replay's size."""
        rec = self.h.experience_stats(self.replay)
        if self.set_counts:
            rec.update(sampled_set_sizes(np.concatenate(self.set_counts)))
            self.set_counts = []
        self.last_stats = rec
        self.h.memory_record(self.step, rec, x=self.frames, frames=self.frames)

    # ------------------------------------------------------------------------------ checkpoints
    def _state(self) -> dict:
        st = self.h.state(self.learner, step=self.step, stored=self.stored, frames=self.frames, updates=self.updates)
        return {**st, "returns": list(self.returns), "return_frames": list(self.return_frames)}

    def _restore(self, state: dict) -> None:
        c = self.h.restore(state, self.learner)
        self.step, self.stored = int(c["step"]), int(c.get("stored", 0))
        self.frames, self.updates = int(c["frames"]), int(c.get("updates", 0))
        self.returns = [float(x) for x in state.get("returns", [])]
        self.return_frames = [int(x) for x in state.get("return_frames", [])]
        if len(self.return_frames) != len(self.returns):   # a checkpoint from before they were kept
            self.return_frames = [-1] * (len(self.returns) - 1) + [self.frames] if self.returns else []

    # ------------------------------------------------------------------------------ the end
    def shutdown(self) -> None:
        self.h.shutdown()


def main(args=None) -> int:
    """Entry point of ``ros2 run comper_agent comper_node``: 0 done, 1 cannot start / failed, 130 aborted."""
    return run_main(ComperNode, "comper_node", args)


if __name__ == "__main__":
    sys.exit(main())
