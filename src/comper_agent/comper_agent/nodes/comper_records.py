"""comper_records: what comper_node writes about its run besides the harness's common records: the start line,
the progress line with its progress.csv row, and summary.json with the protocol's figures (last episodes, terciles
of the frame budget; :mod:`comper_agent.core.protocol`). Each function reads the node's counters (``step``,
``frames``, ``updates``, ``returns``, ...) and writes through its harness; none changes what the node learns.
"""
from __future__ import annotations

import math

import numpy as np

from comper_agent.core.protocol import protocol_summary, protocol_text
from comper_agent.nodes.agent_run import resume_text

__all__ = ["NAMES", "start_line", "progress", "write_summary"]

#: the start line's name of each variant
NAMES = {"comper": "COMPER (RTM sampling, QT target)", "comper_f": "COMPER-F (RTM sampling, DQN target network)",
         "comper_m": "COMPER-M (TM sampling, QT target)", "dqn": "DQN baseline (replay + target network)"}


def start_line(node) -> str:
    """The run's first log line: the variant, the task, the schedule of updates, reductions and evaluations."""
    p, c, mem = node.p, node.cfg, node.mem is not None
    return (f"{NAMES[p.algorithm]} on {p.env_id} (obs {list(node.h.obs_shape)} "
            f"{np.dtype(node.obs_dtype).name}, {node.n_actions} actions, frame skip {node.frame_skip}), "
            f"{p.bringup} bring-up, {resume_text(node.step)} to {p.total_frames} frames"
            + (f" (max {p.max_steps} steps)" if p.max_steps > 0 else "")
            + f"; update every {c.train_frequency} steps from step {c.learning_starts}, batch {c.batch_size}"
            + (f"; reduce every {p.reduce_every} steps x {p.reduce_batch} sets via {node.h.reducer}" if mem
               else f"; replay {c.replay_size}")
            + (f"; target network every {c.target_update_every} steps" if node.learner.uses_target_net else "")
            + ("; qt_target_gate: QT's or the target network's bootstrap per batch (QT tested against the "
               "labels' bootstrap)" if node.learner.gates_qt else "")
            + (f"; evaluation every {node.eval_every} steps x {p.eval_episodes} episodes"
               if node.eval_every else "")
            + f"; profile {node.profile}, {node.network} Q-network, {c.optimizer} (loss {c.loss_reduction}), "
              f"reward clip {c.reward_clip}; torch threads {c.num_threads}")


def progress(node, line: str) -> None:
    """The progress line (the harness's, with the frames, epsilon, memory or replay, loss) and its progress.csv row."""
    eps, rate = node.learner.epsilon(node.frames), node.h.progress.rate
    line += f" | frames {node.frames} | eps {eps:.3f}" + (
        (f" | RTM {node.h.rtm_size}" + (f" | QT v{node.mem.qt_version}" if node.uses_qt else ""))
        if node.mem is not None else f" | replay {len(node.replay)}")
    if "loss" in node.last_update:
        line += f" | loss {node.last_update['loss']:.4f}"
    node.h.progress_record(line, node.step, node.frames, node.last_update, frames=node.frames,
                           episodes=node.env.count, epsilon=eps, rtm_size=node.h.rtm_size, updates=node.updates,
                           reductions=node.h.reductions)
    node.h.csv.write(step=node.step, frames=node.frames, wall_time_s=round(node.h.wall_time(), 2),
                     episodes=node.env.count, last_train_return=node.h.progress.last_episode_return, epsilon=eps,
                     steps_per_s=round(rate, 1) if math.isfinite(rate) else "", rtm_size=node.h.rtm_size,
                     tm_sets=node.last_stats.get("tm_sets"), identities=node.last_stats.get("identities"),
                     loss=node.last_update.get("loss"))


def write_summary(node, timers: dict) -> None:
    """summary.json: the protocol's figures (last episodes, terciles) and the run's totals."""
    p, mem = node.p, node.mem
    s = protocol_summary(node.returns, node.return_frames, p.total_frames)
    path = node.h.write_summary(
        node.step, timers, frame_stack=int(node.cfg.frame_stack), total_frames_budget=int(p.total_frames),
        frames=int(node.frames), updates=int(node.updates), episode_returns=node.returns, protocol=s,
        complete=bool(node.frames >= p.total_frames and not node.stop_event.is_set()),
        session_frames=node.frames - node.start_frames, memory=node.last_stats,
        sampling={"source": "replay" if mem is None else node.sample_source,
                  "target": "qt" if node.uses_qt else "target_network",
                  # qt_target_gate: the updates whose batch took the target network's bootstrap
                  **({"qt_gated": int(node.learner.qt_gated)} if node.learner.gates_qt else {}),
                  "reducer": node.h.reducer, "sample_calls": int(mem.sample_calls if mem else 0),
                  "restored": int(mem.restored if mem else 0), "n_step": int(node.cfg.n_step),
                  # COMPER's n-step windows cut short by a truncation or the run's stop
                  "n_step_windows_dropped": int(node.windows.dropped if node.windows else 0)})
    node.log.info(f"done: {node.step} steps, {node.frames} frames, {node.env.count} episodes; {protocol_text(s)}; "
                  f"summary {path}")
