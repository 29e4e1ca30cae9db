#!/usr/bin/env python3
"""How saturated the actor of finished comcact_node runs (ddpg, comcact) is at its last checkpoint, offline.

The actor ends in tanh. Where the output layer's value x is large (|x| > 2.65: within 1 % of the action
bound), tanh's slope is below 0.02, and at |x| ~ 20 it is 0 in float32: the critic's gradient no longer
reaches the actor, whatever the critic learns. A run whose actor saturates in every output for every state
holds one fixed action sequence for good (docs/studies/comcact-actor-saturation.md). The actor penalty that study
measured (actor_preact_l2) is no longer in the learner: check out the study's commit to rerun it.

For each run folder it rebuilds the actor from config.yaml and latest.pt (no ROS) and evaluates it on up to
--states states of the run's own replay at that checkpoint (the DDPG buffer's file, or COMCACT's memory
snapshot), then prints per run:
  saturation      share of (state, action dimension) outputs with |x| > 2.65
  all_saturated   share of states where every action dimension is saturated
  mean_abs_x      mean |x|
  action_spread   mean over action dimensions of the actions' standard deviation across states
                  (0: the same action in every state)

With --actor-steps N it then takes N actor steps alone (the learner's own actor step and Adam state, the
critic held as it is, batches of the run's batch size drawn from those states) and prints the same figures
after them, with the critic's mean value of
the actor's actions before and after (q_before, q_after): whether the actor's gradient can still move it.

    python benchmarks/actor_saturation.py runs/ddpg-Hopper-v4-s0 runs/comcact-Hopper-v4-s0 --json sat.json
    python benchmarks/actor_saturation.py runs/comcact-Hopper-v4-s1 --actor-steps 500
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from bench_args import checkpoint_replay, last_checkpoint, offline_parser, rows_per_run

def replay_states(ckpt: Path, state: dict) -> np.ndarray:
    """The states the run's replay held at the checkpoint (DDPG's buffer file, or the memory snapshot)."""
    kind, path = checkpoint_replay(ckpt, state)
    with np.load(path if kind == "local" else path / "state.npz") as z:
        return np.asarray(z["states"], dtype=np.float32)


def figures(learner, states) -> dict:
    """The saturation figures of learner's actor on these states, and the critic's mean value of its actions."""
    import torch
    from comper_agent.core.networks import SATURATED_PREACT
    with torch.no_grad():
        s = torch.as_tensor(states.reshape(len(states), -1))
        x = learner.actor.pre_activation(s)
        sat = x.abs() > SATURATED_PREACT
        q = learner.critic(s, learner.actor.squash(x))
    return {"saturation": float(sat.float().mean()), "all_saturated": float(sat.all(dim=1).float().mean()),
            "mean_abs_x": float(x.abs().mean()), "action_spread": float(torch.tanh(x).std(dim=0).mean()),
            "q": float(q.mean())}


def saturation(run: Path, max_states: int, seed: int, actor_steps: int = 0) -> dict:
    import torch
    from comper_agent.core.comcact import ComcactLearner
    from comper_agent.core.config import ComcactConfig
    from comper_msgs_py.params import config_from_dict

    cfg, ckpt, state = last_checkpoint(run, ("ddpg", "comcact"), "has no actor")
    env = cfg["env"]
    # runs of earlier versions may name parameters the learner no longer has (the studies' ablations)
    learner = ComcactLearner(config_from_dict(ComcactConfig, cfg["learner"], ignore_unknown=True),
                             int(np.prod(env["observation_shape"])), env["action_low"], env["action_high"])
    learner.load_state_dict(state["learner"])
    states = replay_states(ckpt, state)
    rng = np.random.default_rng(seed)
    if len(states) > max_states:
        states = states[rng.choice(len(states), max_states, replace=False)]
    torch.set_num_threads(1)
    before = figures(learner, states)
    row = {"run": run.name, "algorithm": cfg["algorithm"], "step": int(state["counters"]["step"]),
           "states": len(states), **{k: v for k, v in before.items() if k != "q"}}
    if actor_steps > 0:
        for _ in range(actor_steps):
            learner.actor_step(states[rng.integers(0, len(states), learner.config.batch_size)])
        after = figures(learner, states)
        row.update({"actor_steps": actor_steps, "q_before": before["q"], "q_after": after["q"],
                    **{f"after_{k}": v for k, v in after.items() if k != "q"}})
    return row


def line(r: dict) -> str:
    text = (f"{r['run']} ({r['algorithm']}, step {r['step']}, {r['states']} states): saturation {r['saturation']:.3f}, "
            f"all_saturated {r['all_saturated']:.3f}, mean_abs_x {r['mean_abs_x']:.1f}, "
            f"action_spread {r['action_spread']:.3f}")
    if "actor_steps" in r:
        text += (f"; after {r['actor_steps']} actor steps: saturation "
                 f"{r['after_saturation']:.3f}, all_saturated {r['after_all_saturated']:.3f}, mean_abs_x "
                 f"{r['after_mean_abs_x']:.1f}, action_spread {r['after_action_spread']:.3f}, critic's Q of the "
                 f"actions {r['q_before']:.2f} -> {r['q_after']:.2f}")
    return text


def main(argv=None) -> int:
    ap = offline_parser(__doc__, "comcact_node run folders (ddpg or comcact)")
    ap.add_argument("--states", type=int, default=20000, help="states drawn from the replay (default %(default)s)")
    ap.add_argument("--actor-steps", type=int, default=0,
                    help="then take this many actor steps alone and measure again (default %(default)s: none)")
    args = ap.parse_args(argv)
    return rows_per_run(args.runs, lambda run: saturation(run, args.states, args.seed, args.actor_steps), line,
                        args.json)


if __name__ == "__main__":
    sys.exit(main())
