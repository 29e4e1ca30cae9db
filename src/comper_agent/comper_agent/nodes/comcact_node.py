"""comcact_node: the COMCACT learner (thesis Algorithm 8; method.md section 4) and the DDPG baseline.

    ros2 run comper_agent comcact_node                      # InvertedPendulum-v4, everything in-process
    ros2 run comper_agent comcact_node --ros-args -p env_id:=Hopper-v4 -p total_steps:=50000
    ros2 run comper_agent comcact_node --ros-args -p algorithm:=ddpg
    ros2 run comper_agent comcact_node --ros-args -p bringup:=external -p sim_node:=sim_node \\
        -p memory_node:=memory_node -p qt_trainer_node:=qt_trainer_node
    ros2 run comper_agent comcact_node --ros-args -p resume:=runs/<run_id>
    ros2 run comper_agent comcact_node --ros-args -p record:=true     # also bag the run (<run dir>/bag)
    ros2 run comper_agent comcact_node --ros-args --params-file src/comper_agent/config/comcact.yaml
    ros2 run comper_agent comcact_node --help                # every parameter

Bring-up. ``embedded`` (default) builds the simulation, memory and QT trainer nodes in this
process (separate node objects, each spun by its own executor in its own thread); the learner
loop runs in the main thread and talks to them only through ROS services and topics.
``external`` uses nodes started separately (``ros2 run comper_sim sim_node`` ...), by name.
Command-line parameters reach every embedded node that declares them (``-p delta:=1e-3`` sets the
memory's threshold; ``-p seed:=1`` seeds simulation and learner). The machinery shared with
comper_node (parameters, run directory, bring-up, recording, checkpoints, time split, Ctrl-C) is
:mod:`comper_agent.nodes.agent_node`.

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
``~/episodes`` (EpisodeSummary, source eval; training episodes have source train, each preceded
by its transitions on ``~/transitions``).

Outputs in ``<runs_root>/<run_id>/``: config.yaml, metrics.jsonl, progress.csv, tb/ (TensorBoard),
checkpoints/ (see :mod:`comper_agent.nodes.run_io`). Ctrl-C stops after the current step, saves a final
checkpoint and flushes the logs (a second Ctrl-C aborts).

Size: one node runs COMCACT and the DDPG baseline, each in lock step and in async mode; they share
the Algorithm 8 update (``_train_step``) and its memory side (``_store``, ``_sample``, ``_reduce``),
which read top to bottom here; splitting the modes or algorithms apart would repeat them.
"""
from __future__ import annotations

import sys
import time

import numpy as np

from comper_msgs_py.arrays import Transitions
from comper_msgs_py.convert import seq_to_numpy

from comper_agent.nodes.actor_node import ActorFleet, rate_limit_params
from comper_agent.nodes.agent_run import next_due, resume_text
from comper_agent.nodes.agent_node import SUMMARY_QOS, AgentNode, episode_over, run_main
from comper_agent.nodes.evaluation import Evaluation
from comper_agent.nodes.node_config import ComcactNodeConfig
from comper_agent.core.config import COMCACT_PROFILES, ComcactConfig, DDPGConfig, resolve_comcact_profile
from comper_agent.core.memory_schedule import Row, reduce_due, rows_to_transitions, updates_before_reduce
from comper_agent.nodes.policy_weights import PolicyPublisher

__all__ = ["ComcactNode", "ComcactNodeConfig", "main", "SUMMARY_QOS"]


class ComcactNode(AgentNode):
    """The COMCACT / DDPG learner node (see the module text); the shared machinery is AgentNode."""

    NODE_NAME = "comcact_node"
    CONFIG = ComcactNodeConfig
    LEARNER_CONFIGS = {"comcact": ComcactConfig, "ddpg": DDPGConfig}
    PROFILES = COMCACT_PROFILES
    RESOLVE_PROFILE = staticmethod(lambda name, values: resolve_comcact_profile(name, values["algorithm"]))
    # LEARNER_OVERRIDES num_threads 1 (AgentNode): the 400/300 nets at batch 64 gain nothing from a second
    # intra-op thread on the 2-core machine, and the ROS executor threads need the other core (docs/comcact.md)
    OBS_DTYPE = np.float32
    CSV_COLUMNS = ["step", "wall_time_s", "eval_mean_return", "eval_std_return", "episodes",
                   "last_train_return", "steps_per_s", "rtm_size", "critic_loss"]

    def _configure(self) -> None:
        p = self.p
        self.comcact = self.uses_qt = p.algorithm == "comcact"
        self.async_mode = p.mode == "async"
        # async: the actors store into the memory node, so DDPG samples it too (the memory node reduces)
        self.uses_memory = self.comcact or self.async_mode
        self.reducer = "qt_trainer" if self.comcact else ("memory" if self.async_mode else "none")
        self.policy_pub = (PolicyPublisher(f"{self.get_fully_qualified_name()}/policy", f"{self.get_name()}_policy")
                           if self.async_mode else None)
        self.fleet = None
        if self.async_mode:     # the embedded memory node's rate limiter holds replay_ratio
            self.embedded_params = ({}, rate_limit_params(p, self.cfg), {})
        self.progress_total = int(p.total_steps)

    def _check_env(self, info) -> None:
        if info.discrete:
            raise ValueError(f"{info.env_id} has discrete actions; COMCACT/DDPG need a continuous task "
                             "(use comper_node for Atari)")
        self.low = seq_to_numpy(info.action_low, np.float32).copy()
        self.high = seq_to_numpy(info.action_high, np.float32).copy()
        self.action_dim = int(self.low.size)
        self.env_description = {"env_id": info.env_id, "observation_shape": list(self.obs_shape),
                                "action_low": self.low.tolist(), "action_high": self.high.tolist(),
                                "episode_end": self.episode_rule, "max_episode_steps": int(info.max_episode_steps)}

    # ------------------------------------------------------------------------------ setup / state
    def _setup_learner(self) -> None:
        from comper_agent.core.comcact import ComcactLearner
        from comper_agent.core.networks import configure_torch
        from comper_agent.core.replay import ReplayBuffer
        configure_torch(self.cfg.num_threads)
        obs_dim = int(np.prod(self.obs_shape))
        self.learner = ComcactLearner(self.cfg, obs_dim, self.low, self.high)
        self.replay = None
        if not self.uses_memory:
            self.replay = ReplayBuffer(self.cfg.replay_size, self.obs_shape, (self.action_dim,),
                                       seed=self.cfg.seed)
        self.evaluation = Evaluation(self, self._eval_action, self._eval_recorded, action_out_of_range="clip")
        self.rng = np.random.default_rng(self.cfg.seed + 7)   # warm-up actions
        self.since_reduce = 0
        self.update_count = 0
        self.pending: list[Row] = []           # agent steps not yet stored (labelled when stored)
        self.experience.quiesce = self._flush   # before a memory snapshot: the steps not yet stored go out too

    def _restore(self, state: dict) -> None:
        super()._restore(state)
        self.rng.bit_generator.state = state["warmup_rng"]

    def _state(self) -> dict:
        st = super()._state()
        st.update(warmup_rng=self.rng.bit_generator.state)
        return st

    # ------------------------------------------------------------------------------ main loop
    def _start_line(self) -> str:
        p = self.p
        what = ("COMCACT (memory + QT step)" if self.comcact else "DDPG baseline (uniform replay)")
        return (f"{what} on {p.env_id} (obs {list(self.obs_shape)}, actions {self.action_dim} in "
                f"[{self.low.min():g}, {self.high.max():g}]), {p.bringup} bring-up, "
                f"{resume_text(self.step)} to {p.total_steps} steps; "
                f"evaluation every {p.eval_every} steps x {p.eval_episodes} episodes"
                + (f"; reduce every {p.reduce_every} updates, reduce_batch {p.reduce_batch}; profile {self.profile}"
                   if self.comcact else ""))

    def _before_loop(self) -> None:
        p = self.p
        self.next_eval = next_due(self.step, p.eval_every)
        self.outputs.schedule_checkpoints(p.checkpoint_every or p.eval_every, self.step)
        if p.eval_every > 0 and self.step == 0:
            self.evaluation.run(self.step)       # the untrained policy: the curve's first point

    def _loop(self) -> None:
        if self.async_mode:
            return self._loop_async()
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
                self.evaluation.run(self.step)
                self._memory_record()
                self.next_eval += p.eval_every
            self._after_step()
        self._flush()

    # ------------------------------------------------------------------------------ async mode
    def _loop_async(self) -> None:
        """mode:=async: publish the policy, start the actors (embedded), then update continuously; the
        memory's rate limiter holds the update-to-data ratio, this loop only counts steps and evaluates."""
        p = self.p

        def stored_by_actors() -> int:
            """Transitions in the memory's count that are not this learner's re-stores (restore_batch)."""
            with self.ptimers("memory"):
                return int(self.mem.stats()["transitions_stored"]) - self.mem.restored

        steps_base = stored_by_actors() - self.step

        def env_steps() -> int:
            """Environment steps so far: transitions the actors stored since this run started."""
            return stored_by_actors() - steps_base

        def publish_policy(final: bool = False) -> None:
            with self.ptimers("publish"):
                self.policy_pub.send(self.learner, env_steps=self.step, final=final)

        self.mem.relabel_apart = True   # restore_batch: re-stores are not environment steps for the rate limiter
        publish_policy()
        if p.bringup == "embedded" and p.num_actors > 0:
            left = p.total_steps - self.step
            self.fleet = ActorFleet(
                num_actors=p.num_actors, env_id=p.env_id, seed=int(self.cfg.seed), memory_node=p.memory_node,
                policy_topic=self.policy_pub.topic_name, steps_each=-(-left // p.num_actors),
                episode_end=self.episode_rule, log_dir=self.run_dir.path, startup_timeout_s=p.startup_timeout_s)
            self.log.info(f"async: {p.num_actors} actor processes started (logs {self.run_dir.path}/actor_*.log), "
                          f"rate limiter {self.embedded_params[1]}")
        last_policy = time.monotonic()
        since_count = 0
        while self.step < p.total_steps and not self.stop_event.is_set():
            failed = self.fleet.failed() if self.fleet is not None else []
            if failed:
                raise RuntimeError("an actor failed: " + " | ".join(failed))
            before = self.update_count
            self._train_step()
            since_count += 1
            if self.update_count == before:       # nothing to sample yet: the actors are filling the memory
                time.sleep(0.01)
            if since_count >= 20 or self.update_count == before:
                self.step = max(self.step, env_steps())
                since_count = 0
                self._flush()                 # restore_batch: the re-stores of these updates, marked relabel
            if time.monotonic() - last_policy >= p.policy_period_s:
                publish_policy()
                last_policy = time.monotonic()
            if self.next_eval is not None and self.step >= self.next_eval:
                self.evaluation.run(self.step)
                self._memory_record()
                self.next_eval = next_due(self.step, p.eval_every)
            self._after_step()
        # the updates still owed for the last steps (the rate limiter lets learning trail acting by up to
        # rate_buffer_steps): as in lock step, every step gets its replay_ratio updates
        owed = int(p.replay_ratio * max(0, self.step - self.cfg.learning_starts))
        while self.update_count < owed and not self.stop_event.is_set():
            self._train_step()
        self._flush()
        publish_policy(final=True)

    def shutdown(self) -> None:
        super().shutdown()
        if self.policy_pub is not None:
            self.policy_pub.close()
            self.policy_pub = None

    def _memory_record(self) -> None:
        """A 'memory' record in metrics.jsonl at each evaluation: the memory's statistics (identities, transitions
        stored, bytes held, evictions, ...) or, for DDPG, its replay's size."""
        if self.comcact:
            with self.ptimers("memory"):
                rec = self.mem.stats()
        else:
            rec = {"replay_size": len(self.replay), "replay_bytes": self.replay.nbytes}
        self.metrics.write("memory", step=self.step, wall_time_s=self.wall_time(), **rec)

    def _final_records(self, rc: int) -> None:
        if self.fleet is not None:
            codes = self.fleet.stop()
            self.log.info(f"async: actors exited with {codes}")
            self.metrics.write("actors", exit_codes=codes, policies_published=self.policy_pub.published,
                               updates=self.update_count, env_steps=self.step,
                               update_to_data=self.update_count / max(1, self.step), relabelled=int(self.mem.restored))

    def _finish(self, elapsed: float, steps: int, timers: dict) -> None:
        if self.evaluation.records:
            e = self.evaluation.records[-1]
            self.log.info(f"done: {self.step} steps, {self.env.count} episodes, last evaluation "
                          f"{e['mean_return']:.1f} +- {e['std_return']:.1f} at step {e['step']}; "
                          f"outputs in {self.run_dir.path}")

    def _progress_line(self, line: str) -> None:
        extra, counts = "", {}
        if self.comcact:
            extra = f" | RTM {self.rtm_size} | QT v{self.mem.qt_version}"
            # so far in the run: QT critic steps taken, and those qt_step_gate skipped
            counts = {"learner_updates": self.learner.updates, "qt_steps_taken": self.learner.qt_steps,
                      "qt_steps_gated": self.learner.qt_gated}
        self.log.info(line + extra)
        self.metrics.write("progress", step=self.step, steps_per_s=self.progress.rate, episodes=self.env.count,
                           wall_time_s=self.wall_time(), rtm_size=self.rtm_size, **{
                               k: v for k, v in self.last_update.items() if isinstance(v, float)}, **counts)
        self.scalars.scalar("perf/steps_per_s", self.progress.rate, self.step)

    # ------------------------------------------------------------------------------ stepping
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
        over = episode_over(self.episode_rule, r.terminated, r.truncated)
        if len(self.pending) >= self.p.store_every or over:
            self._flush()
        if self.stored >= max(self.cfg.learning_starts, 2):
            self._train_step()
        if over:
            self.env.end(r.terminated, r.truncated, step=self.step)
            return self._reset_env()
        return nxt

    def _warmup_chunk(self, obs: np.ndarray, n: int) -> np.ndarray:
        n = max(1, min(int(n), 1000))
        acts = self.rng.uniform(self.low, self.high, size=(n, self.action_dim)).astype(np.float32)
        with self.ptimers("sim"):
            r = self.sim.step_many(acts, autoreset=True, dtype=np.float32)
        t = r.transitions
        over = np.array([episode_over(self.episode_rule, a, b) for a, b in zip(t.terminated, t.truncated)])
        ends_before = np.concatenate([[0], np.cumsum(over)[:-1]]).astype(np.uint64)
        t = Transitions(states=np.array(t.states, np.float32), actions=np.array(t.actions, np.float32),
                        rewards=np.array(t.rewards, np.float32), next_states=np.array(t.next_states, np.float32),
                        terminated=np.array(t.terminated), truncated=np.array(t.truncated),
                        episode_ids=self.env.count + ends_before,
                        steps=np.arange(self.step, self.step + len(t), dtype=np.uint64), run_id=self.run_id)
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
        return r.observation

    # ------------------------------------------------------------------------------ memory
    def _store(self, t: Transitions) -> None:
        if len(t) == 0:
            return
        if not self.comcact:
            with self.ptimers("learner"):
                self.replay.add(t)
        else:
            with self.ptimers("learner"):
                t.value_labels = self.learner.value_labels(t)
            self.mem.store(t)           # with the re-stored batches waiting (restore_batch)
        self.stored += len(t)
        self.env.parts.append(t)

    def _flush(self) -> None:
        if self.pending:
            rows, self.pending = self.pending, []
            self._store(rows_to_transitions(rows, self.env.count, self.run_id))
        elif self.comcact:
            self.mem.store(None)        # only re-stored batches waiting, if any

    def _sample(self):
        """(batch, set sizes) for the next update: from RTM (prefetched up to the next reduction,
        MemoryLink.next_batch), from TM while RTM is empty (Algorithm 8 lines 14-17)."""
        k = self.cfg.batch_size
        source = "rtm"
        if self.rtm_size <= 1 and not self.mem.prefetched:
            with self.ptimers("memory"):
                stats = self.mem.stats()
            if self.rtm_size <= 1:
                source, avail = "tm", stats["tm_sets"]
            else:
                avail = self.rtm_size
        else:
            avail = self.rtm_size
        k = min(k, avail)
        if k < 2:
            return None
        got = self.mem.next_batch(k, source, updates_before_reduce(self.p.reduce_every - self.since_reduce))
        if got is None:      # RTM shrank (evictions): refresh its size next time
            self.mem.rtm_size = 0
            return None
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

    # ------------------------------------------------------------------------------ learning
    def _qt_targets(self, batch: Transitions) -> np.ndarray | None:
        """QT(tau) for the batch's rows (COMCACT; qt_targets rtm: the labels RTM sampled with them, local: the
        local QT copy), None for async DDPG, before the first reduction or while RTM is empty."""
        if not self.comcact:              # async DDPG: the memory is its replay, no QT step
            return None
        if self.p.qt_targets == "rtm":
            return batch.value_labels if self.rtm_size > 0 and batch.value_labels.size == len(batch) else None
        qt = self.mem.qt_model()
        if qt is None:
            return None
        from comper_memory.core import transition_keys
        with self.ptimers("qt_predict"):
            return qt.predict_transitions(batch, transition_keys)

    def _train_step(self) -> None:
        if self.uses_memory:
            self.mem.collect(wait=False)      # reduce_overlap: a reduction that has answered
            got = self._sample()
            if got is None:
                return
            batch, counts = got
            with self.ptimers("learner"):
                self.last_update = self.learner.update(batch)
            self.since_reduce += 1
            if reduce_due(self.since_reduce, self.p.reduce_every, self.rtm_size):
                self._reduce()
            targets = self._qt_targets(batch)
            p = self.p
            if targets is not None and self.diagnostics.due(self.update_count):
                # after the DDPG step on the batch, before the QT step
                self.diagnostics.record(self.learner, batch, counts, targets, step=self.step, update=self.update_count,
                                        x=self.step, qt_version=int(self.mem.qt_version), rtm_size=int(self.rtm_size),
                                        restored=int(self.mem.restored))
            with self.ptimers("learner"):
                if targets is not None:
                    self.last_update.update(self.learner.qt_critic_step(batch, targets))
                self.learner.soft_update()
                if p.restore_batch:       # fresh labels after this update's steps (and target update)
                    batch.value_labels = self.learner.value_labels(batch)
                    self.mem.queue_restore(batch)
        else:
            with self.ptimers("learner"):
                batch = self.replay.sample(self.cfg.batch_size)
                self.last_update = self.learner.update(batch)
                self.learner.soft_update()
        self.update_count += 1
        if self.update_count % 250 == 0:
            self.scalars.scalars(self.last_update, self.step, prefix="train/")

    # ------------------------------------------------------------------------------ evaluation
    def _eval_action(self, obs):
        return self.learner.act(np.asarray(obs, np.float32), explore=False)

    def _eval_recorded(self, rec: dict) -> None:
        self.csv.write(step=self.step, wall_time_s=round(self.wall_time(), 2), eval_mean_return=rec["mean_return"],
                       eval_std_return=rec["std_return"], episodes=self.env.count,
                       last_train_return=self.progress.last_episode_return,
                       steps_per_s=round(self.progress.overall_rate(self.step), 1),
                       rtm_size=self.rtm_size if self.comcact else self.stored,
                       critic_loss=self.last_update.get("critic_loss"))

    # ------------------------------------------------------------------------------ time split
    def _timer_notes(self, rec: dict, elapsed: float, steps: int) -> tuple[str, str]:
        # simulation compute per step, measured on the learner's own (eval) env
        sim_compute = self.evaluation.sim_seconds_per_step(
            lambda: self.rng.uniform(self.low, self.high).astype(np.float32))
        rec["sim_compute_us_per_step"] = 1e6 * sim_compute
        return "", (f"; simulation compute {1e6 * sim_compute:.0f} us/step "
                    f"(x {steps} = {sim_compute * steps:.1f} s of the 'sim' phase)")


def main(args=None) -> int:
    """Entry point of ``ros2 run comper_agent comcact_node``: 0 done, 1 cannot start / failed, 130 aborted."""
    return run_main(ComcactNode, "comcact_node", args)


if __name__ == "__main__":
    sys.exit(main())
