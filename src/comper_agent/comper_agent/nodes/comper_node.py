"""comper_node: the COMPER learner on Atari (thesis Algorithm 7; method.md sections 3-5), its
chapter-7 ablations COMPER-F and COMPER-M, and the DQN baseline (Table 35).

    ros2 run comper_agent comper_node                                   # COMPER on ALE/Freeway-v5, 100,000 frames
    ros2 run comper_agent comper_node --ros-args -p env_id:=ALE/Asterix-v5 -p seed:=1
    ros2 run comper_agent comper_node --ros-args -p algorithm:=comper_f   # or comper_m, dqn
    ros2 run comper_agent comper_node --ros-args -p frame_stack:=4        # 4 stacked frames
    ros2 run comper_agent comper_node --ros-args -p resume:=runs/<run_id>
    ros2 run comper_agent comper_node --ros-args -p record:=true         # also bag the run (<run dir>/bag)
    ros2 run comper_agent comper_node --ros-args --params-file src/comper_agent/config/comper.yaml
    ros2 run comper_agent comper_node --help                            # every parameter

Bring-up (:mod:`comper_agent.nodes.bringup`): ``embedded`` (default) builds the simulation, memory and
QT trainer nodes in this process (separate node objects, each on its own executor thread);
``external`` uses nodes started with ``ros2 run`` by name. Outputs (:mod:`comper_agent.nodes.run_io`):
``<runs_root>/<run_id>/`` config.yaml, metrics.jsonl, progress.csv, tb/, checkpoints/, and
summary.json (the protocol's figures, :mod:`comper_agent.core.protocol`: mean of the last 10
training episodes, or 3 for runs with fewer than 25 episodes, and the mean of the last 5 (or 3)
episodes by the end of each third of the frame budget). The machinery shared with comcact_node
(run directory, bring-up, memory and recording links, checkpoints, time split, Ctrl-C) is
:mod:`comper_agent.nodes.agent_node` and the modules it names.

Size: one node runs four variants (comper, comper_f, comper_m, dqn) on two kinds of tasks (ALE
frames with a frame replay, vector observations with an MLP); splitting them would repeat the
Algorithm 7 loop that they share, which reads top to bottom in ``_agent_step`` / ``_train_step``.

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

Topics: ``~/episodes`` per training episode, preceded by its transitions on ``~/transitions``
(with the labels stored; dqn: without labels) while someone subscribes. The run stops at the
first episode end after ``total_frames`` (100,000) frames counting skipped ones (the episode in
progress finishes), at ``max_steps`` if > 0 (stops mid-episode), or on Ctrl-C (final checkpoint,
summary, time split; a second Ctrl-C aborts).
"""
from __future__ import annotations

import json
import math
import sys

import numpy as np

from comper_msgs_py.arrays import Transitions

from comper_agent.nodes import run_io
from comper_agent.nodes.agent_run import next_due, resume_text
from comper_agent.nodes.agent_node import SUMMARY_QOS, AgentNode, episode_over, run_main
from comper_agent.nodes.evaluation import Evaluation
from comper_agent.nodes.node_config import COMPER_ALGORITHMS, ComperNodeConfig
from comper_agent.core.memory_schedule import (NStepWindows, PendingRows, Row, reduce_due, rows_to_transitions,
                                   sets_touched_per_reduction, updates_before_reduce)
from comper_agent.core.protocol import protocol_summary
from comper_agent.core.replay import FrameReplay
from comper_agent.core.config import COMPER_PROFILES, ComperConfig, DQNConfig, resolve_profile

__all__ = ["ComperNode", "ComperNodeConfig", "FrameReplay", "protocol_summary", "main", "SUMMARY_QOS",
           "TRANSITIONS_QOS", "ALGORITHMS"]

ALGORITHMS = COMPER_ALGORITHMS

TRANSITIONS_QOS = SUMMARY_QOS


# ---------------------------------------------------------------------------------- the node
class ComperNode(AgentNode):
    """The COMPER / COMPER-F / COMPER-M / DQN learner node (see the module text); the shared
    machinery is AgentNode."""

    NODE_NAME = "comper_node"
    CONFIG = ComperNodeConfig
    LEARNER_CONFIGS = {"comper": ComperConfig, "comper_f": ComperConfig, "comper_m": ComperConfig,
                       "dqn": DQNConfig}
    # LEARNER_OVERRIDES num_threads 1 (AgentNode): measured faster on the 2-core machine with the
    # embedded nodes (docs/comper.md)
    OBS_DTYPE = np.uint8
    CSV_COLUMNS = ["step", "frames", "wall_time_s", "episodes", "last_train_return", "epsilon",
                   "steps_per_s", "rtm_size", "tm_sets", "identities", "loss", "eval_mean_return"]
    QT_START_HINT = " -p architecture:=comper -p reduce_batch:=1000"
    NAMES = {"comper": "COMPER (RTM sampling, QT target)", "comper_f": "COMPER-F (RTM sampling, DQN target network)",
             "comper_m": "COMPER-M (TM sampling, QT target)", "dqn": "DQN baseline (replay + target network)"}

    PROFILES = COMPER_PROFILES
    RESOLVE_PROFILE = staticmethod(lambda name, values: resolve_profile(name, values["env_id"]))


    def _configure(self) -> None:
        p = self.p
        self.is_atari = p.env_id.startswith("ALE/")
        if not self.is_atari:
            self.OBS_DTYPE = np.float32
            if self.cfg.frame_stack != 1:
                raise ValueError(f"frame_stack:={self.cfg.frame_stack} applies to ALE games; {p.env_id} has vector "
                                 "observations (use frame_stack:=1, or profile:=classic_control)")
        self.eval_every = p.eval_every if p.eval_every >= 0 else (0 if self.is_atari else 5_000)
        self.uses_memory = p.algorithm != "dqn"
        if self.cfg.n_step > 1 and self.uses_memory and self.cfg.qt_label == "q_sa":
            raise ValueError(f"n_step:={self.cfg.n_step} needs qt_label:=next_value: a q_sa label (Q(s_t, a_t)) "
                             "is not the bootstrap of s_(t+n)")
        self.uses_qt = p.algorithm in ("comper", "comper_m")
        self.reducer = p.reducer if p.reducer != "auto" else ("memory" if p.algorithm == "comper_f" else "qt_trainer")
        if not self.uses_memory:
            self.reducer = "none"
        if self.uses_qt and self.reducer != "qt_trainer":
            raise ValueError(f"{p.algorithm} needs QT: use reducer:=qt_trainer (or auto)")
        self.sample_source = "tm" if p.algorithm == "comper_m" else "rtm"
        # the sim parameters the learner's settings fix (ALE: frames per observation, frame pooling)
        self.sim_protocol = ({"frame_stack": int(self.cfg.frame_stack), "frame_pooling": self.cfg.frame_pooling}
                             if self.is_atari else {})
        self.embedded_params = (self.sim_protocol, {"reduce_batch": int(p.reduce_batch)}, {"architecture": "comper"})

    def _check_env(self, info) -> None:
        from comper_agent.core.comper import resolve_q_network
        if not info.discrete:
            raise ValueError(f"{info.env_id} has continuous actions; comper_node needs discrete actions (an ALE "
                             "game or a task such as CartPole-v1; use comcact_node for continuous control)")
        self.n_actions = int(info.num_actions)
        if self.cfg.n_actions and self.cfg.n_actions != self.n_actions:
            raise ValueError(f"{info.env_id} has {info.num_actions} actions but n_actions:={self.cfg.n_actions} "
                             "(0 = take the environment's)")
        if self.is_atari:
            want = (84, 84) if self.cfg.frame_stack == 1 else (self.cfg.frame_stack, 84, 84)
            if self.obs_shape != want:
                raise ValueError(f"the sim serves observations {list(self.obs_shape)} but frame_stack:="
                                 f"{self.cfg.frame_stack} needs {list(want)}; start the sim with "
                                 f"-p frame_stack:={self.cfg.frame_stack}")
            spec = json.loads(info.spec_json or "{}")
            pooling = spec.get("frame_pooling", "average")
            if pooling in ("average", "max") and pooling != self.cfg.frame_pooling:
                self.log.warning(f"the sim pools frames by {pooling} but frame_pooling:={self.cfg.frame_pooling} "
                                 f"(start the sim with -p frame_pooling:={self.cfg.frame_pooling})")
        self.network = resolve_q_network(self.cfg.q_network, self.obs_shape)
        self.frame_skip = max(1, int(info.frame_skip))
        est_steps = int(math.ceil(self.p.total_frames / self.frame_skip))
        self.progress_total = min(est_steps, self.p.max_steps) if self.p.max_steps > 0 else est_steps
        self.env_description = {"env_id": info.env_id, "observation_shape": list(self.obs_shape),
                                "num_actions": int(info.num_actions), "frame_skip": self.frame_skip,
                                "episode_end": self.episode_rule, "spec": json.loads(info.spec_json or "{}")}

    # ------------------------------------------------------------------------------ setup / state
    def _setup_learner(self) -> None:
        from comper_agent.core.comper import ComperLearner
        from comper_agent.core.networks import configure_torch
        configure_torch(self.cfg.num_threads)
        self.learner = ComperLearner(self.cfg, self.obs_shape, self.n_actions)
        self.replay = None
        if not self.uses_memory:
            if self.is_atari:
                self.replay = FrameReplay(self.cfg.replay_size, (84, 84), self.cfg.frame_stack, seed=self.cfg.seed)
            else:
                from comper_agent.core.replay import ReplayBuffer
                self.replay = ReplayBuffer(self.cfg.replay_size, self.obs_shape, seed=self.cfg.seed)
        if self.eval_every > 0:
            self.evaluation = Evaluation(self, self._eval_action, self._eval_recorded, self.frame_skip,
                                         **self.sim_protocol)
        if self.mem is not None:
            self.mem.on_reduced = self._after_reduce
        self.frames = 0              # emulator frames of the run, skipped ones included
        self.returns: list[float] = []
        self.return_frames: list[int] = []      # the run's frames when each training episode ended
        self.updates = 0
        self.last_reduce_step = -(10 ** 9)
        self.pending = PendingRows()            # agent steps not yet stored (the newest may wait for its label)
        self.windows = None                     # n_step > 1: the memory stores n-step windows of those steps
        if self.uses_memory and self.cfg.n_step > 1:
            from comper_agent.core.comper import clip_rewards
            mode = self.cfg.reward_clip
            self.windows = NStepWindows(self.cfg.n_step, self.cfg.gamma, lambda r: clip_rewards(r, mode))
        self.set_counts: list[np.ndarray] = []
        self.last_stats: dict = {}

    def _restore(self, state: dict) -> None:
        super()._restore(state)
        c = state["counters"]
        self.frames, self.updates = int(c["frames"]), int(c.get("updates", 0))
        self.returns = [float(x) for x in state.get("returns", [])]
        self.return_frames = [int(x) for x in state.get("return_frames", [])]
        if len(self.return_frames) != len(self.returns):   # a checkpoint from before they were kept
            self.return_frames = [-1] * (len(self.returns) - 1) + [self.frames] if self.returns else []

    def _state(self) -> dict:
        st = super()._state()
        st["counters"].update(frames=self.frames, updates=self.updates)
        st["returns"] = list(self.returns)
        st["return_frames"] = list(self.return_frames)
        return st

    def _run_config(self) -> dict:
        return {**super()._run_config(), "q_network": self.network, "eval_every": self.eval_every}

    # ------------------------------------------------------------------------------ main loop
    def _start_line(self) -> str:
        p, c = self.p, self.cfg
        return (f"{self.NAMES[p.algorithm]} on {p.env_id} (obs {list(self.obs_shape)} {np.dtype(self.OBS_DTYPE).name}, "
                f"{self.info.num_actions} actions, frame skip {self.frame_skip}), {p.bringup} bring-up, "
                f"{resume_text(self.step)} to {p.total_frames} frames"
                + (f" (max {p.max_steps} steps)" if p.max_steps > 0 else "")
                + f"; update every {c.train_frequency} steps from step {c.learning_starts}, batch {c.batch_size}"
                + (f"; reduce every {p.reduce_every} steps x {p.reduce_batch} sets via {self.reducer}"
                   if self.uses_memory else f"; replay {c.replay_size}")
                + (f"; target network every {c.target_update_every} steps" if self.learner.uses_target_net else "")
                + ("; qt_target_gate: QT's or the target network's bootstrap per batch (QT tested against the "
                   "labels' bootstrap)" if self.learner.gates_qt else "")
                + (f"; evaluation every {self.eval_every} steps x {p.eval_episodes} episodes" if self.eval_every else "")
                + f"; profile {self.profile}, {self.network} Q-network, {c.optimizer} (loss {c.loss_reduction}), "
                  f"reward clip {c.reward_clip}; torch threads {c.num_threads}")

    def _before_loop(self) -> None:
        p = self.p
        touched = sets_touched_per_reduction(p.reduce_every, self.cfg.batch_size, self.cfg.train_frequency,
                                             p.restore_batch)
        if self.uses_memory and p.reduce_batch < touched:
            self.log.warning(f"reduce_batch {p.reduce_batch} < up to {touched} sets stored into between two "
                             f"reductions (reduce_every {p.reduce_every} x (1 + batch {self.cfg.batch_size} / "
                             f"train_frequency {self.cfg.train_frequency})): TM may fall behind and QT's targets "
                             f"go stale; -p reduce_batch:={touched} or more keeps pace (docs/comper.md)")
        self.start_frames = self.frames
        self.outputs.schedule_checkpoints(p.checkpoint_every, self.step)
        self.next_stats = next_due(self.step, p.stats_every)
        self.next_eval = next_due(self.step, self.eval_every)
        if self.eval_every > 0 and self.step == 0:
            self.evaluation.run(self.step, self.frames)       # the untrained policy: the curve's first point

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
            self._after_step()
        evals = self.evaluation.records if self.evaluation is not None else []
        last_eval = evals[-1]["step"] if self.eval_every > 0 and evals else None
        if self.eval_every > 0 and not self.stop_event.is_set() and last_eval != self.step:
            self.evaluation.run(self.step, self.frames)       # the final policy
        if self.uses_memory and self.pending:
            last = self.pending.newest_unlabelled()
            if last is not None:    # stopped mid-episode: label the last one too
                q_last = self.learner.act(last.next_state, epsilon=0.0)[1]
                last.label = self.learner.next_value(last.next_state, q_last) * (0.0 if last.terminated else 1.0)
            self._flush(with_restore=False)
        if self.windows is not None:
            self.windows.reset()          # the windows still open at the stop are dropped (and counted)

    def _final_records(self, rc: int) -> None:
        try:
            if rc != 130:
                self._memory_record()
        except Exception as exc:
            self.log.warning(f"final memory statistics failed: {exc}")

    def _progress_line(self, line: str) -> None:
        eps = self.learner.epsilon(self.frames)
        extra = f" | frames {self.frames} | eps {eps:.3f}"
        if self.uses_memory:
            extra += f" | RTM {self.rtm_size}" + (f" | QT v{self.mem.qt_version}" if self.uses_qt else "")
        else:
            extra += f" | replay {len(self.replay)}"
        if "loss" in self.last_update:
            extra += f" | loss {self.last_update['loss']:.4f}"
        self.log.info(line + extra)
        rate = self.progress.rate
        self.metrics.write("progress", step=self.step, frames=self.frames, steps_per_s=rate, episodes=self.env.count,
                           wall_time_s=self.wall_time(), epsilon=eps, rtm_size=self.rtm_size, updates=self.updates,
                           reductions=self.reductions,
                           **{k: v for k, v in self.last_update.items() if isinstance(v, float)})
        self.csv.write(step=self.step, frames=self.frames, wall_time_s=round(self.wall_time(), 2),
                       episodes=self.env.count, last_train_return=self.progress.last_episode_return, epsilon=eps,
                       steps_per_s=round(rate, 1) if math.isfinite(rate) else "", rtm_size=self.rtm_size,
                       tm_sets=self.last_stats.get("tm_sets"), identities=self.last_stats.get("identities"),
                       loss=self.last_update.get("loss"))
        self.scalars.scalar("perf/steps_per_s", rate, self.frames)

    # ------------------------------------------------------------------------------ episodes
    def _reset_env(self) -> np.ndarray:
        obs = self.env.reset()
        self.ep_frames0, self.ep_frames = self.frames, 0
        self.new_episode = True
        self.ep_rows: list | None = None
        if self.windows is not None:
            self.windows.reset()
        if self.replay is not None:
            if isinstance(self.replay, FrameReplay):
                self.replay.end_episode()
            if self.topics.transitions_wanted():
                self.ep_rows = []     # dqn stores nothing per episode: keep the rows for ~/transitions
        return obs

    def _end_episode(self, terminated: bool, truncated: bool) -> None:
        ep = self.env
        self.returns.append(float(ep.ret))
        self.return_frames.append(int(self.frames))
        if self.ep_rows:
            ep.parts.append(rows_to_transitions(self.ep_rows, ep.count, self.run_id))
            self.ep_rows = []
        ep.end(terminated, truncated, step=self.step, ep_frames=self.ep_frames, global_frames=self.frames,
               x=self.frames, frames=self.frames, episode_frames=self.ep_frames,
               epsilon=self.learner.epsilon(self.frames))
        self.log.info(f"episode {ep.count - 1}: return {ep.ret:.1f}, {ep.length} steps, "
                      f"{self.ep_frames} frames; run {self.frames}/{self.p.total_frames} frames")

    # ------------------------------------------------------------------------------ stepping
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
        over = episode_over(self.episode_rule, term, trunc)
        if self.replay is not None:
            with self.ptimers("learner"):
                if self.is_atari:
                    self.replay.add(obs, a, float(r.reward), nxt, term, trunc, self.new_episode)
                else:
                    self.replay.add(Transitions(states=obs[None], actions=np.array([a], np.float32),
                                                rewards=np.array([r.reward], np.float32), next_states=nxt[None],
                                                terminated=np.array([term]), truncated=np.array([trunc])))
            self.stored += 1
            if self.ep_rows is not None:
                self.ep_rows.append(Row(obs, a, r.reward, nxt, term, trunc, self.step))
        else:
            if term:
                label = 0.0
            elif c.qt_label == "q_sa":
                label = float(q[a])
            elif over:      # truncated end: nobody acts on s', compute max_a Q(s', a) now
                with self.ptimers("learner"):
                    label = self.learner.next_value(nxt, self.learner.act(nxt, epsilon=0.0)[1])
            else:
                label = None
            self.pending.append(Row(obs, a, r.reward, nxt, term, trunc, self.step, label))
        self.new_episode = False
        self.step += 1
        if self.step % c.train_frequency == 0 and self.step >= c.learning_starts:
            self._train_step()
        elif self.uses_memory and (over or self.pending.labelled() >= self.p.store_every):
            self._flush(with_restore=False)
        if over:
            if self.uses_memory:
                self._flush(with_restore=False)
            self._end_episode(term, trunc)
        return nxt, over

    def _flush(self, with_restore: bool) -> None:
        """One store call: the labelled new transitions (+ the previous update's batch re-stored)."""
        rows = self.pending.take_labelled()
        t = None
        if rows:
            t = rows_to_transitions(rows, self.env.count, self.run_id)
            self.env.parts.append(t)         # ~/transitions and bags: the one-step transitions, raw rewards
            if self.windows is not None:
                rows = self.windows.push(rows)
                t = rows_to_transitions(rows, self.env.count, self.run_id) if rows else None
            self.stored += len(rows)
        self.mem.store(t, with_restore=with_restore)

    # ------------------------------------------------------------------------------ memory
    def _reduce(self) -> None:
        self.last_reduce_step = self.step
        if self.mem.start_overlapped():   # reduce_overlap: learning goes on; mem.collect finishes it
            return
        with self.ptimers("qt" if self.reducer == "qt_trainer" else "memory_reduce"):
            r = self.mem.reduce()
        self._after_reduce(r)
        if self.uses_qt and r.qt_version > 0:
            with self.ptimers("qt_wait"):
                self.mem.wait_qt_model(r.qt_version)

    def _after_reduce(self, r) -> None:
        self.metrics.write("reduce", step=self.step, frames=self.frames, rtm_size=self.rtm_size,
                           **self.mem.last_reduce)

    def _sample(self) -> tuple[Transitions, np.ndarray] | None:
        """(batch, set sizes) for the next update: from RTM prefetched up to the next reduction
        (MemoryLink.next_batch), from TM (COMPER-M) one call per update."""
        k = self.cfg.batch_size
        if self.sample_source == "rtm":
            k = min(k, self.rtm_size)
        if k < 1:
            return None
        steps_left = self.p.reduce_every - (self.step - self.last_reduce_step)
        got = self.mem.next_batch(k, self.sample_source, updates_before_reduce(steps_left, self.cfg.train_frequency))
        if got is None:     # fewer entries than asked (TM drained by a reduction, RTM evictions)
            with self.ptimers("memory"):
                st = self.mem.stats()
            avail = st["tm_sets"] if self.sample_source == "tm" else st["rtm_size"]
            k = min(k, avail)
            if k < 1:
                return None
            got = self.mem.next_batch(k, self.sample_source, 1)
            if got is None:
                return None
        return got

    def _memory_record(self) -> None:
        if not self.uses_memory:
            rec = {"replay_size": len(self.replay), "replay_bytes": self.replay.nbytes}
        else:
            with self.ptimers("memory"):
                rec = self.mem.stats()
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
                if c.n_step > 1:
                    batch, windows = self.replay.sample(c.batch_size, c.n_step)
                    self.last_update = self.learner.update(batch, n_step=windows)
                else:
                    self.last_update = self.learner.update(self.replay.sample(c.batch_size))
        else:
            self._flush(with_restore=True)
            self.mem.collect(wait=False)      # reduce_overlap: a reduction that has answered
            if reduce_due(self.step - self.last_reduce_step, p.reduce_every, self.rtm_size):
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
                    qt = self.mem.qt_model()
                    if qt is None:
                        self.log.warning("no QTModel received yet: update skipped (is the QT trainer "
                                         "publishing on qt_model?)", throttle_duration_sec=10.0)
                        return
                    from comper_memory.core import transition_keys
                    with self.ptimers("qt_predict"):
                        targets = qt.predict_transitions(batch, transition_keys)
                if self.diagnostics.due(self.updates):     # before the update on the batch
                    self.diagnostics.record(self.learner, batch, counts, targets, step=self.step, update=self.updates,
                                            x=self.frames, frames=self.frames, qt_version=int(self.mem.qt_version),
                                            rtm_size=int(self.rtm_size))
            with self.ptimers("learner"):
                self.last_update = self.learner.update(batch, targets)
                if p.restore_batch:
                    batch.value_labels = self.learner.value_labels(batch)
                    self.mem.queue_restore(batch)
        self.updates += 1
        if self.learner.uses_target_net and self.step % c.target_update_every < c.train_frequency:
            self.learner.sync_target()
        if self.updates % 250 == 0:
            self.scalars.scalars(self.last_update, self.frames, prefix="train/")


    # ------------------------------------------------------------------------------ evaluation
    def _eval_action(self, obs):
        return self.learner.act(np.asarray(obs, self.OBS_DTYPE), epsilon=self.p.eval_epsilon)[0]

    def _eval_recorded(self, rec: dict) -> None:
        self.csv.write(step=self.step, frames=self.frames, wall_time_s=round(self.wall_time(), 2),
                       episodes=self.env.count, eval_mean_return=rec["mean_return"])

    # ------------------------------------------------------------------------------ time split / summary
    def _timer_notes(self, rec: dict, elapsed: float, steps: int) -> tuple[str, str]:
        accounted = sum(v["seconds"] for k, v in rec["phases"].items()
                        if not k.endswith("_server") and k != "qt_model_rebuild")
        rec["unaccounted_s"] = elapsed - accounted
        return (f" | unaccounted (loop, logging) {elapsed - accounted:.1f} s",
                " (part of the sim / memory / qt phases); qt_server = time inside the QT trainer's reductions "
                "(part of qt); qt_model_rebuild runs in the executor thread")

    def _finish(self, elapsed: float, steps: int, timers: dict) -> None:
        """summary.json: the protocol's figures (last episodes, terciles) and the run's totals."""
        frames = self.frames - self.start_frames
        s = protocol_summary(self.returns, self.return_frames, self.p.total_frames)
        summary = {"run_id": self.run_id, "algorithm": self.p.algorithm, "env_id": self.p.env_id, "profile": self.profile,
                   "seed": int(self.cfg.seed), "frame_stack": int(self.cfg.frame_stack),
                   "total_frames_budget": int(self.p.total_frames), "frames": int(self.frames), "steps": int(self.step),
                   "updates": int(self.updates), "reductions": int(self.reductions),
                   "complete": bool(self.frames >= self.p.total_frames and not self.stop_event.is_set()),
                   "episode_returns": self.returns, "protocol": s,
                   "evaluations": [{k: e[k] for k in ("step", "mean_return", "std_return")}
                                   for e in (self.evaluation.records if self.evaluation is not None else [])],
                   "wall_time_s": self.wall_time(), "session_elapsed_s": elapsed,
                   "session_steps_per_s": steps / elapsed if elapsed > 0 else None,
                   "session_frames": frames, "memory": self.last_stats, "timers": timers,
                   "sampling": {"source": ("replay" if not self.uses_memory else
                                           self.sample_source),
                                "target": "qt" if self.uses_qt else "target_network",
                                # qt_target_gate: the updates whose batch took the target network's bootstrap
                                **({"qt_gated": int(self.learner.qt_gated)} if self.learner.gates_qt else {}),
                                "reducer": self.reducer, "sample_calls": int(self.mem.sample_calls if self.mem else 0),
                                "restored": int(self.mem.restored if self.mem else 0),
                                "n_step": int(self.cfg.n_step),
                                # COMPER's n-step windows cut short by a truncation or the run's stop
                                "n_step_windows_dropped": int(self.windows.dropped if self.windows else 0)}}
        run_io.write_text_atomic(self.run_dir.file("summary.json"), json.dumps(summary, indent=1, default=float))
        t = " | ".join(f"tercile {j + 1} (to episode {x['end_episode']}): {x['mean']:.1f} +- {x['std']:.1f}"
                       for j, x in enumerate(s["terciles"]))
        self.log.info(f"done: {self.step} steps, {self.frames} frames, {self.env.count} episodes; mean of the last "
                      f"{s['last_k']} episodes {s['last_mean']:.1f} +- {s['last_std']:.1f}; {t}; "
                      f"summary {self.run_dir.file('summary.json')}")


def main(args=None) -> int:
    """Entry point of ``ros2 run comper_agent comper_node``: 0 done, 1 cannot start / failed, 130 aborted."""
    return run_main(ComperNode, "comper_node", args)


if __name__ == "__main__":
    sys.exit(main())
