"""A checkpoint's value estimates against what the logged episodes actually returned (offline, no
ROS): :func:`load_policy` (actor / critic or Q-network from a checkpoint), :func:`q_vs_mc` (critic
Q(s, a) against the discounted Monte Carlo return of each logged step), :func:`fitted_q_evaluation`
(a fresh critic fitted to the logged transitions). ``evaluate --checkpoint`` runs them.
"""
from __future__ import annotations

import copy
import math
import os
from dataclasses import dataclass

import numpy as np

from comper_msgs_py.arrays import Transitions

from comper_agent.offline.runs import discounted_returns, reconstruct_episodes

__all__ = ["Policy", "load_policy", "q_vs_mc", "fitted_q_evaluation"]


@dataclass
class Policy:
    kind: str                 # "ddpg" (actor + critic) or "dqn" (Q-network)
    actor: object = None
    critic: object = None
    q: object = None

    def q_values(self, states, actions):
        import torch
        with torch.no_grad():
            s = torch.as_tensor(states)
            if self.kind == "ddpg":
                return self.critic(s.float(), torch.as_tensor(actions, dtype=torch.float32).reshape(len(s), -1)
                                   ).reshape(-1).double().numpy()
            q = self.q(s)
            a = torch.as_tensor(np.asarray(actions).reshape(-1).astype(np.int64))
            return q.gather(1, a[:, None]).reshape(-1).double().numpy()

    def actions(self, states):
        import torch
        with torch.no_grad():
            s = torch.as_tensor(states)
            if self.kind == "ddpg":
                return self.actor(s.float()).numpy()
            return self.q(s).argmax(1).numpy()


def load_policy(path: str | os.PathLike) -> Policy:
    """Rebuild the networks of a comper_agent.core.checkpoint from the state-dict shapes.

    COMCACT / DDPG: {"learner": {"actor": ..., "critic": ...}} (or the learner dict itself);
    COMPER / DQN: {"learner": {"q": NatureCNN state}}.
    """
    from comper_agent.core.checkpoint import load_checkpoint
    from comper_agent.core.networks import Actor, Critic, NatureCNN

    state = load_checkpoint(path)
    learner = state.get("learner", state)
    if "actor" in learner and "critic" in learner:
        a, c = learner["actor"], learner["critic"]
        bn = "body.0.weight" in a         # batch_norm false: nn.Identity in the norms' places
        obs_dim = int(a["body.1.weight"].shape[1])
        hidden, i = [], 1
        while f"body.{i}.weight" in a:
            hidden.append(int(a[f"body.{i}.weight"].shape[0]))
            i += 3
        center, half = a["action_center"].numpy(), a["action_half_range"].numpy()
        actor = Actor(obs_dim, center - half, center + half, hidden, batch_norm=bn)
        actor.load_state_dict(a)
        h1, h2 = int(c["fc1.weight"].shape[0]), int(c["fc2.weight"].shape[0])
        mode = "second_hidden" if int(c["fc2.weight"].shape[1]) > h1 else "output"
        act_dim = (int(c["fc2.weight"].shape[1]) - h1) if mode == "second_hidden" else int(c["out.weight"].shape[1]) - h2
        critic = Critic(obs_dim, act_dim, (h1, h2), action_input=mode, batch_norm=bn)
        critic.load_state_dict(c)
        actor.eval()
        critic.eval()
        return Policy("ddpg", actor=actor, critic=critic)
    if "q" in learner:
        q = learner["q"]
        net = NatureCNN(int(q["features.0.weight"].shape[1]), int(q["head.2.weight"].shape[0]))
        net.load_state_dict(q)
        net.eval()
        return Policy("dqn", q=net)
    raise ValueError(f"{path}: no actor/critic or q state dict in the checkpoint (keys {sorted(learner)[:10]})")


def _batched(fn, *arrays, batch: int = 4096) -> np.ndarray:
    n = len(arrays[0])
    return np.concatenate([fn(*(a[i:i + batch] for a in arrays)) for i in range(0, n, batch)]) if n else np.zeros(0)


def q_vs_mc(policy: Policy, t: Transitions, gamma: float = 0.99) -> dict:
    """The policy's Q(s, a) on the logged (s, a) of complete episodes vs the discounted MC return
    the behaviour actually obtained from there (bias = mean(Q - G), RMSE, Pearson correlation)."""
    eps = [e for e in reconstruct_episodes(t) if e.complete]
    if not eps:
        return {"n": 0}
    idx = np.concatenate([e.index for e in eps])
    ends = np.zeros(idx.size, bool)
    ends[np.cumsum([e.length for e in eps]) - 1] = True
    g = discounted_returns(t.rewards[idx], ends, gamma)
    q = _batched(policy.q_values, t.states[idx], t.actions[idx])
    first = np.concatenate([[0], np.cumsum([e.length for e in eps])[:-1]])
    d = q - g
    corr = float(np.corrcoef(q, g)[0, 1]) if q.size > 1 and q.std() > 0 and g.std() > 0 else math.nan
    return {"n": int(idx.size), "episodes": len(eps), "gamma": gamma, "bias": float(d.mean()),
            "rmse": float(np.sqrt(np.mean(d ** 2))), "corr": corr,
            "mean_q": float(q.mean()), "mean_mc": float(g.mean()),
            "initial_mean_q": float(q[first].mean()), "initial_mean_mc": float(g[first].mean()),
            "_q": q, "_g": g}


def fitted_q_evaluation(policy: Policy, t: Transitions, *, gamma: float = 0.99, updates: int = 2000,
                        batch_size: int = 256, hidden: int = 256, lr: float = 1e-3,
                        target_every: int = 100, seed: int = 0) -> dict:
    """Fitted Q evaluation (Le et al. 2019; d3rlpy's FQE): learn Q_pi on the logged transitions
    with targets r + gamma (1 - terminated) Q'(s', pi(s')) (truncation does not mask), a small MLP,
    hard target copies every `target_every` updates; report V_pi = mean Q(s0, pi(s0)) over the
    initial states of the logged episodes. Vector observations only."""
    import torch
    from torch import nn

    if t.states.ndim != 2:
        return {"skipped": f"FQE supports vector observations only (got {t.states.shape[1:]})"}
    g = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    s = torch.as_tensor(t.states, dtype=torch.float32)
    s2 = torch.as_tensor(t.next_states, dtype=torch.float32)
    mu, sd = s.mean(0), s.std(0).clamp_min(1e-6)
    discrete = policy.kind == "dqn"
    a = torch.as_tensor(np.asarray(t.actions, dtype=np.float32).reshape(len(t), -1))
    pi2 = torch.as_tensor(_batched(policy.actions, t.next_states)
                          .astype(np.float32).reshape(len(t), -1))
    r = torch.as_tensor(t.rewards, dtype=torch.float32)
    notdone = torch.as_tensor(~t.terminated, dtype=torch.float32)
    in_dim = s.shape[1] + a.shape[1]
    net = nn.Sequential(nn.Linear(in_dim, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                        nn.Linear(hidden, 1))
    target = copy.deepcopy(net)
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    # scale returns so the MLP sees O(1) targets; results are reported in reward units
    scale = float(max(1e-6, r.abs().mean().item() / (1 - gamma)))

    def f(m, x, act):
        return m(torch.cat([(x - mu) / sd, act], 1)).squeeze(1)

    n = len(t)
    losses = []
    for u in range(updates):
        i = torch.randint(0, n, (min(batch_size, n),), generator=g)
        with torch.no_grad():
            y = r[i] / scale + gamma * notdone[i] * f(target, s2[i], pi2[i])
        loss = torch.nn.functional.mse_loss(f(net, s[i], a[i]), y)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
        if (u + 1) % target_every == 0:
            target.load_state_dict(net.state_dict())
    eps = [e for e in reconstruct_episodes(t) if e.complete] or reconstruct_episodes(t)
    first = np.array([e.index[0] for e in eps])
    with torch.no_grad():
        s0 = s[first]
        pi0 = torch.as_tensor(policy.actions(t.states[first]).astype(np.float32).reshape(len(first), -1))
        v = f(net, s0, pi0).double().numpy() * scale
        q_logged = _batched(lambda x, y: f(net, torch.as_tensor(x, dtype=torch.float32),
                                           torch.as_tensor(np.asarray(y, np.float32).reshape(len(x), -1))
                                           ).double().numpy() * scale, t.states, t.actions)
    critic_v0 = float(np.mean(policy.q_values(t.states[first], policy.actions(t.states[first]))))
    return {"updates": updates, "gamma": gamma, "discrete": discrete,
            "initial_states": int(first.size), "fqe_value": float(v.mean()), "fqe_value_std": float(v.std()),
            "critic_value": critic_v0, "final_loss": float(np.mean(losses[-50:])) if losses else None,
            "mean_q_logged": float(q_logged.mean())}
