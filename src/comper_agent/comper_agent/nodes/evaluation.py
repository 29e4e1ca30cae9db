"""Evaluation of a learner's policy on a separate environment (the protocol's "separate
environment": a second environment of the task inside the learner's process).

:class:`Evaluation` plays ``eval_episodes`` full episodes of the evaluated (greedy) policy, episode
k reset from ``eval_seed + k``, and reports them: ``~/episodes`` (source eval) and
``~/evaluations`` (:class:`~comper_agent.nodes.episodes.LearnerTopics`), metrics.jsonl, TensorBoard, the
console and the node's own progress.csv row.
"""
from __future__ import annotations

import time
from typing import Callable

import numpy as np

__all__ = ["Evaluation"]


class Evaluation:
    """node: the learner node (its parameters ``p`` and ``cfg``, ``run_id``, ``topics``, ``outputs``,
    ``ptimers``, ``log``); policy(obs) -> action: the evaluated policy; on_record(rec): after an
    evaluation is logged (the node's progress.csv row); frame_skip: emulator frames per step (the
    summaries' frames); sim_params: extra SimConfig fields of the environment.

    ``records``: every evaluation of the run (checkpointed, so a resumed run keeps its curve)."""

    def __init__(self, node, policy: Callable[[np.ndarray], object], on_record: Callable[[dict], None],
                 frame_skip: int = 1, **sim_params):
        from comper_sim.core import SimBridge, SimConfig
        p = node.p
        self.p, self.topics, self.outputs, self.timers, self.log = p, node.topics, node.outputs, node.ptimers, node.log
        self.policy, self.on_record, self.frame_skip = policy, on_record, max(1, int(frame_skip))
        self.seed = p.eval_seed if p.eval_seed >= 0 else node.cfg.seed + 1000
        self.bridge = SimBridge(SimConfig(env_id=p.env_id, seed=self.seed, episode_end="standard",
                                          run_id=node.run_id, **sim_params))
        self.records: list[dict] = []

    def run(self, step: int, frames: int | None = None) -> dict:
        """eval_episodes episodes at the learner's `step` (`frames`: its emulator frames, default
        `step`); returns the record (step, mean_return, std_return, returns, lengths, wall_time_s)."""
        p, out = self.p, self.outputs
        rets, lens = [], []
        with self.timers("eval"):
            for k in range(p.eval_episodes):
                ret, n, res = self.bridge.play_episode(self.policy, self.seed + k)
                rets.append(ret)
                lens.append(n)
                self.topics.eval_episode(episode_id=k, episode_return=ret, length=n, frames=n * self.frame_skip,
                                         terminated=bool(res.terminated), truncated=bool(res.truncated),
                                         global_step=step, global_frames=int(step if frames is None else frames),
                                         wall_time_s=out.wall_time())
        mean, std = float(np.mean(rets)), float(np.std(rets))
        self.topics.evaluation(p.algorithm, global_step=step, episode_returns=[float(r) for r in rets],
                               episode_lengths=[int(n) for n in lens], mean_return=mean, std_return=std)
        rec = {"step": step, "mean_return": mean, "std_return": std, "returns": rets,
               "lengths": lens, "wall_time_s": out.wall_time()}
        self.records.append(rec)
        out.metrics.write("eval", **rec)
        self.on_record(rec)
        out.scalars.scalar("eval/mean_return", mean, step)
        out.scalars.scalar("eval/std_return", std, step)
        out.progress.evaluation(mean)
        self.log.info(f"evaluation at step {step}: return {mean:.1f} +- {std:.1f} over "
                      f"{len(rets)} episodes (lengths {min(lens)}-{max(lens)})")
        return rec

    def sim_seconds_per_step(self, action: Callable[[], np.ndarray], steps: int = 500) -> float:
        """The simulation's own compute per step, measured on this environment with `action()`'s
        actions (the time split's reference for the 'sim' phase); nan when it fails."""
        try:
            b = self.bridge
            b.reset(0)
            t0 = time.perf_counter()
            n = 0
            for _ in range(steps):
                res = b.step(action())
                n += 1
                if res.episode_over:
                    b.reset(None)
            return (time.perf_counter() - t0) / n
        except Exception:
            return float("nan")

    def sim_compute_notes(self, action: Callable[[], np.ndarray]):
        """The time split's notes (:meth:`AgentRun.report_time_split`): the simulation's compute per step,
        measured with `action()`'s actions (:meth:`sim_seconds_per_step`), against the 'sim' phase."""
        def notes(rec: dict, elapsed: float, steps: int) -> tuple[str, str]:
            sim_compute = self.sim_seconds_per_step(action)
            rec["sim_compute_us_per_step"] = 1e6 * sim_compute
            return "", (f"; simulation compute {1e6 * sim_compute:.0f} us/step "
                        f"(x {steps} = {sim_compute * steps:.1f} s of the 'sim' phase)")
        return notes

    def close(self) -> None:
        self.bridge.close()
