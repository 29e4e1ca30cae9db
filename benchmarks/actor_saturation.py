#!/usr/bin/env python3
"""How saturated the actor of finished comcact_node runs (ddpg, comcact) is at its last checkpoint, offline.

The actor ends in tanh. Where the output layer's value x is large (|x| > 2.65: within 1 % of the action
bound), tanh's slope is below 0.02, and at |x| ~ 20 it is 0 in float32: the critic's gradient no longer
reaches the actor, whatever the critic learns. A run whose actor saturates in every output for every state
holds one fixed action sequence for good (docs/comcact.md, "The actor's saturation").

For each run folder it rebuilds the actor from config.yaml and latest.pt (no ROS) and evaluates it on up to
--states states of the run's own replay at that checkpoint (the DDPG buffer's file, or COMCACT's memory
snapshot), then prints per run:
  saturation      share of (state, action dimension) outputs with |x| > 2.65
  all_saturated   share of states where every action dimension is saturated
  mean_abs_x      mean |x|
  action_spread   mean over action dimensions of the actions' standard deviation across states
                  (0: the same action in every state)

    python benchmarks/actor_saturation.py runs/ddpg-Hopper-v4-s0 runs/comcact-Hopper-v4-s0 --json sat.json
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from bench_args import last_checkpoint, offline_parser, rows_per_run

SATURATED = 2.65            # |x| past which tanh(x) is within 1 % of +-1


def replay_states(ckpt: Path, replay: dict) -> np.ndarray:
    """The states the run's replay held at the checkpoint (DDPG's buffer file, or the memory snapshot)."""
    if replay.get("kind") == "local":
        path = ckpt.parent / replay["file"]
    elif replay.get("kind") == "memory":
        snap = Path(replay["path"])
        path = (snap if snap.exists() else ckpt.parent / replay["request"]) / "state.npz"
    else:
        raise ValueError(f"{ckpt}: the checkpoint holds no replay (run with checkpoint_replay)")
    with np.load(path) as z:
        return np.asarray(z["states"], dtype=np.float32)


def saturation(run: Path, max_states: int, seed: int) -> dict:
    import torch
    from comper_agent.core.comcact import ComcactLearner
    from comper_agent.core.config import ComcactConfig
    from comper_msgs_py.params import config_from_dict

    cfg, ckpt, state = last_checkpoint(run, ("ddpg", "comcact"), "has no actor")
    env = cfg["env"]
    learner = ComcactLearner(config_from_dict(ComcactConfig, cfg["learner"]),
                             int(np.prod(env["observation_shape"])), env["action_low"], env["action_high"])
    learner.load_state_dict(state["learner"])
    states = replay_states(ckpt, state.get("replay") or {})
    if len(states) > max_states:
        states = states[np.random.default_rng(seed).choice(len(states), max_states, replace=False)]
    torch.set_num_threads(1)
    with torch.no_grad():
        x = learner.actor.pre_activation(torch.as_tensor(states.reshape(len(states), -1)))
        sat = x.abs() > SATURATED
        actions = torch.tanh(x)
    return {"run": run.name, "algorithm": cfg["algorithm"], "step": int(state["counters"]["step"]),
            "states": len(states), "saturation": float(sat.float().mean()),
            "all_saturated": float(sat.all(dim=1).float().mean()), "mean_abs_x": float(x.abs().mean()),
            "action_spread": float(actions.std(dim=0).mean())}


def main(argv=None) -> int:
    ap = offline_parser(__doc__, "comcact_node run folders (ddpg or comcact)")
    ap.add_argument("--states", type=int, default=20000, help="states drawn from the replay (default %(default)s)")
    args = ap.parse_args(argv)
    return rows_per_run(
        args.runs, lambda run: saturation(run, args.states, args.seed),
        lambda r: (f"{r['run']} ({r['algorithm']}, step {r['step']}, {r['states']} states): saturation "
                   f"{r['saturation']:.3f}, all_saturated {r['all_saturated']:.3f}, mean_abs_x {r['mean_abs_x']:.1f}, "
                   f"action_spread {r['action_spread']:.3f}"), args.json)


if __name__ == "__main__":
    sys.exit(main())
