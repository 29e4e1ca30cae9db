"""COMCACT / DDPG learner (thesis Algorithm 8, appendix B; method.md section 4).

One COMCACT agent step, as the node drives it:
    a = learner.act(s, explore=True)                   # mu(s) + OU noise, clipped to the bounds
    ... env step, store transitions with learner.value_labels(batch) ...
    batch = sample(64) from RTM
    learner.update(batch)                              # DDPG critic step, then actor step
    ... reduce when due (QT trains on popped sets) ...
    learner.qt_critic_step(batch, qt_targets)          # only variant comcact
    learner.soft_update()
The DDPG baseline is the same learner with ``variant = ddpg`` (qt_critic_step refuses to run)
and a plain :class:`~.replay.ReplayBuffer`.

Batch norm: eval mode (running statistics) for acting, value labels and target computation;
train mode (batch statistics, running stats updated) inside update() and qt_critic_step().
Only ``terminated`` masks bootstrapping; ``truncated`` never does.
"""
from __future__ import annotations

import copy

import numpy as np
import torch
from torch import nn
from torch.func import functional_call

from comper_msgs_py.arrays import Transitions

from .config import ComcactConfig
from .networks import SATURATED_PREACT, Actor, Critic, compile_or_eager, soft_update
from .noise import OUNoise

__all__ = ["ComcactLearner"]


class ComcactLearner:
    def __init__(self, config: ComcactConfig, obs_dim: int, action_low, action_high):
        self.config = c = config
        self.device = torch.device(c.device)
        self.obs_dim = int(obs_dim)
        self.action_low = np.asarray(action_low, dtype=np.float32).reshape(-1)
        self.action_high = np.asarray(action_high, dtype=np.float32).reshape(-1)
        self.action_dim = int(self.action_low.size)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(c.seed)
            self.actor = Actor(obs_dim, self.action_low, self.action_high, c.actor_hidden,
                               c.actor_final_init, c.batch_norm).to(self.device)
            self.critic = Critic(obs_dim, self.action_dim, c.critic_hidden, c.critic_final_init,
                                     c.critic_action_input, c.batch_norm).to(self.device)
        self.actor_target = copy.deepcopy(self.actor)
        self.critic_target = copy.deepcopy(self.critic)
        for net in (self.actor, self.critic, self.actor_target, self.critic_target):
            net.eval()
        for p in list(self.actor_target.parameters()) + list(self.critic_target.parameters()):
            p.requires_grad_(False)
        # fused: one kernel per step instead of ~10 per parameter tensor (same arithmetic; measured
        # 12.1 -> 10.0 ms per DDPG update at batch 64 in one micro-benchmark run on the 2-core CPU)
        self._actor_params = list(self.actor.parameters())
        self._critic_params = list(self.critic.parameters())
        self.actor_opt = torch.optim.Adam(self._actor_params, lr=c.actor_lr, fused=True)
        self.critic_opt = torch.optim.Adam(self._critic_params, lr=c.critic_lr, fused=True)
        # the update's pure parts, compiled when learner_compile asks for it (eager if compiling fails)
        self._targets_fn = compile_or_eager(self._targets, c.learner_compile, "targets")
        self._critic_loss_fn = compile_or_eager(self._critic_loss, c.learner_compile, "critic_loss")
        self._actor_loss_fn = compile_or_eager(self._actor_loss, c.learner_compile, "actor_loss")
        self.noise = OUNoise(self.action_dim, c.ou_theta, c.ou_sigma, dt=c.ou_dt, seed=c.seed)
        self.updates = 0      # DDPG updates done
        self.qt_steps = 0     # extra critic steps towards QT targets done
        self.qt_gated = 0     # QT steps skipped by qt_step_gate
        # (batch, DDPG targets) of the last update: the target networks do not move before soft_update, so the QT
        # step's gate and qt_diagnostics on the same batch reuse them instead of two more forward passes
        self._last_targets: tuple[Transitions, torch.Tensor] | None = None

    # ------------------------------------------------------------------ helpers
    def _t(self, x, dtype=torch.float32) -> torch.Tensor:
        return torch.as_tensor(np.asarray(x), dtype=dtype, device=self.device)

    def _tensors(self, batch: Transitions):
        n = len(batch)
        s = self._t(batch.states).reshape(n, -1)
        a = self._t(batch.actions).reshape(n, -1)
        r = self._t(batch.rewards)
        s2 = self._t(batch.next_states).reshape(n, -1)
        not_done = 1.0 - self._t(batch.terminated)
        return s, a, r, s2, not_done

    def _step(self, loss: torch.Tensor, params: list, opt: torch.optim.Optimizer) -> None:
        """One optimiser step on `loss`: the gradients of `params` (what zero_grad(set_to_none) +
        backward() would leave in .grad, without the zeroing and accumulation passes), clipped
        if grad_clip > 0."""
        for p, g in zip(params, torch.autograd.grad(loss, params, allow_unused=True)):
            p.grad = g
        if self.config.grad_clip > 0:
            nn.utils.clip_grad_norm_(params, self.config.grad_clip)
        opt.step()

    # ------------------------------------------------------------------ acting
    def reset_noise(self) -> None:
        """Start of an episode: OU processes back to their mean."""
        self.noise.reset()

    @torch.no_grad()
    def act(self, obs: np.ndarray, explore: bool = True) -> np.ndarray:
        """mu(obs) (+ OU noise if explore), clipped to the action bounds. obs [obs_dim] -> [A];
        obs [N, obs_dim] -> [N, A] (one noise sample shared by the rows)."""
        obs = np.asarray(obs, dtype=np.float32)
        single = obs.ndim == 1
        x = self._t(obs.reshape(1 if single else obs.shape[0], -1))
        self.actor.eval()
        a = self.actor(x).cpu().numpy()
        if explore:
            n = self.noise.sample()
            if self.config.noise_relative_to_bounds:
                n = n * (self.action_high - self.action_low) / 2
            a = a + n
        a = np.clip(a, self.action_low, self.action_high).astype(np.float32)
        return a[0] if single else a

    # ------------------------------------------------------------------ labels and targets
    @torch.no_grad()
    def value_labels(self, batch: Transitions) -> np.ndarray:
        """Labels stored with transitions (eval mode), float32 [N].

        next_value: Q(s', mu(s')) * (1 - terminated); q_sa: Q(s, a) (thesis-literal); label_critic
        target: the target networks Q', mu' instead."""
        if len(batch) == 0:
            return np.zeros(0, np.float32)
        s, a, _, s2, not_done = self._tensors(batch)
        actor, critic = ((self.actor_target, self.critic_target) if self.config.label_critic == "target"
                         else (self.actor, self.critic))
        actor.eval()
        critic.eval()
        if self.config.qt_label == "q_sa":
            v = critic(s, a)
        else:
            v = critic(s2, actor(s2)) * not_done
        return v.cpu().numpy().astype(np.float32)

    @torch.no_grad()
    def td_targets(self, batch: Transitions) -> torch.Tensor:
        """DDPG target r + gamma (1 - terminated) Q'(s', mu'(s')) (target nets, eval mode)."""
        _, _, r, s2, not_done = self._tensors(batch)
        return self._targets_fn(r, s2, not_done)

    @torch.no_grad()
    def critic_loss(self, batch: Transitions, targets: torch.Tensor | np.ndarray | None = None
                    ) -> float:
        """MSE of Q(s, a) (eval mode) against `targets` (default: the DDPG targets)."""
        s, a, *_ = self._tensors(batch)
        y = self.td_targets(batch) if targets is None else self._t(targets)
        self.critic.eval()
        return float(torch.mean((self.critic(s, a) - y) ** 2))

    @torch.no_grad()
    def q_values(self, obs: np.ndarray, actions: np.ndarray | None = None) -> np.ndarray:
        """Q(s, a) in eval mode (a = mu(s) if actions is None), float32 [N]."""
        s = self._t(obs).reshape(len(obs), -1)
        self.actor.eval()
        self.critic.eval()
        a = self.actor(s) if actions is None else self._t(actions).reshape(len(obs), -1)
        return self.critic(s, a).cpu().numpy()

    # ------------------------------------------------------------------ updates
    def _targets(self, r: torch.Tensor, s2: torch.Tensor, not_done: torch.Tensor) -> torch.Tensor:
        """r + gamma (1 - terminated) Q'(s', mu'(s')) (pure; the caller holds no_grad and eval mode)."""
        return r + self.config.gamma * not_done * self.critic_target(s2, self.actor_target(s2))

    def _critic_loss(self, s: torch.Tensor, a: torch.Tensor, y: torch.Tensor):
        """(mean (Q(s, a) - y)^2, Q(s, a)) (pure up to batch-norm stats)."""
        q = self.critic(s, a)
        return torch.mean((q - y) ** 2), q

    def _actor_loss(self, s: torch.Tensor, critic_params: dict) -> tuple[torch.Tensor, torch.Tensor]:
        """(-mean Q(s, mu(s)), share of saturated outputs: |x| > SATURATED_PREACT, x = the actor's output before tanh (within 1 % of a bound). The critic's weights come as detached
        tensors: the backward pass reaches the actor's weights only (the critic is still differentiated with
        respect to its input), without toggling requires_grad on the critic, which a compiled graph would guard on."""
        pre = self.actor.pre_activation(s)
        loss = -functional_call(self.critic, critic_params, (s, self.actor.squash(pre))).mean()
        return loss, torch.mean((pre.detach().abs() > SATURATED_PREACT).float())

    def update(self, batch: Transitions) -> dict:
        """One DDPG update on `batch`: critic step towards r + gamma (1 - terminated)
        Q'(s', mu'(s')), then actor step maximising Q(s, mu(s)). No target update."""
        s, a, r, s2, not_done = self._tensors(batch)
        with torch.no_grad():
            y = self._targets_fn(r, s2, not_done)
        self._last_targets = (batch, y)
        self.critic.train()
        critic_loss, q = self._critic_loss_fn(s, a, y)
        self._step(critic_loss, self._critic_params, self.critic_opt)

        actor = self._actor_update(s)      # the critic still in train mode, as for its own step (batch norm)
        self.critic.eval()
        self.updates += 1
        out = {"critic_loss": float(critic_loss.detach()), **actor,
               "q_mean": float(q.detach().mean()), "target_mean": float(y.mean())}
        if self.config.learner_compile != "off":    # into the run's train/ scalars: what compiling cost
            out["compile_s"] = sum(r["compile_s"] for r in self.compile_report().values())
        return out

    def _actor_update(self, s: torch.Tensor) -> dict:
        """One actor step on states s against the critic as it is (its weights and its batch-norm mode)."""
        self.actor.train()
        loss, saturated = self._actor_loss_fn(s, {k: p.detach() for k, p in self.critic.named_parameters()})
        self._step(loss, self._actor_params, self.actor_opt)
        self.actor.eval()
        return {"actor_loss": float(loss.detach()), "actor_saturation": float(saturated)}

    def actor_step(self, states: np.ndarray) -> dict:
        """One actor step alone (update()'s second half) on these states: what the actor's gradient can still
        do with the critic it has (benchmarks/actor_saturation.py). Counts no update."""
        return self._actor_update(self._t(states).reshape(len(states), -1))

    def _qt_target(self, batch: Transitions, s: torch.Tensor, a: torch.Tensor, r: torch.Tensor,
                   not_done: torch.Tensor, qt_targets: np.ndarray) -> tuple[torch.Tensor | None, dict]:
        """(r + gamma (1 - terminated) QT(tau), or None when qt_step_gate finds it farther from the DDPG target
        than the critic's own TD error on this batch; the step's scalars). s, a, r, not_done: the batch's tensors,
        as the caller already made them."""
        if self.config.variant != "comcact":
            raise RuntimeError("the QT step is COMCACT's; the ddpg variant has it off")
        c = self.config
        qt = self._t(qt_targets).reshape(-1)
        if qt.shape[0] != r.shape[0]:
            raise ValueError(f"{qt.shape[0]} QT targets for {r.shape[0]} transitions")
        y = r + c.gamma * not_done * qt
        out = {"qt_target_mean": float(y.mean())}
        if c.qt_step_gate:
            d = self._qt_gap(batch, s, a, not_done, y)
            gated = d["qt_target_rmse"] > d["critic_td_rmse"]
            out["qt_gated"] = float(gated)
            if gated:
                self.qt_gated += 1
                return None, out
        return y, out

    def qt_critic_step(self, batch: Transitions, qt_targets: np.ndarray) -> dict:
        """COMCACT's extra critic step (Algorithm 8 lines 29-34): minimise
        (r + gamma (1 - terminated) QT(tau) - Q(s, a))^2 with the critic's optimiser. qt_step_gate: no step
        when the QT target is farther from the DDPG target than the critic's own TD error on this batch."""
        s, a, r, _, not_done = self._tensors(batch)
        y, out = self._qt_target(batch, s, a, r, not_done, qt_targets)
        if y is None:
            return out
        self.critic.train()
        loss, _ = self._critic_loss_fn(s, a, y)
        self._step(loss, self._critic_params, self.critic_opt)
        self.critic.eval()
        self.qt_steps += 1
        return {"qt_critic_loss": float(loss.detach()), **out}

    @torch.no_grad()
    def qt_diagnostics(self, batch: Transitions, qt_targets: np.ndarray) -> dict:
        """How far the QT step's target is from the DDPG step's on this batch (no update).

        qt_target_rmse: RMS of (r + gamma (1 - terminated) QT(tau)) - (r + gamma (1 - terminated)
        Q'(s', mu'(s'))), i.e. gamma (1 - terminated) |QT(tau) - Q'(s', mu'(s'))|;
        critic_td_rmse: RMS of Q(s, a) - the DDPG target (the critic's own TD error, before any
        update on the batch); qt_bias: mean of QT(tau) - Q'(s', mu'(s')) over non-terminal rows.
        After update(batch) and before soft_update() the DDPG targets are the update's own (same target networks)."""
        s, a, r, _, not_done = self._tensors(batch)
        qt = self._t(qt_targets).reshape(-1)
        return self._qt_gap(batch, s, a, not_done, r + self.config.gamma * not_done * qt)

    @torch.no_grad()
    def _qt_gap(self, batch: Transitions, s: torch.Tensor, a: torch.Tensor, not_done: torch.Tensor,
                y_qt: torch.Tensor) -> dict:
        """qt_diagnostics on the batch's tensors and its QT targets r + gamma (1 - terminated) QT(tau)."""
        c = self.config
        y = self._ddpg_targets(batch)
        self.critic.eval()
        q = self.critic(s, a)
        live = not_done > 0
        gap = (y_qt - y)[live] / c.gamma
        return {"qt_target_rmse": float(torch.sqrt(torch.mean((y_qt - y) ** 2))),
                "critic_td_rmse": float(torch.sqrt(torch.mean((q - y) ** 2))),
                "qt_bias": float(gap.mean()) if gap.numel() else 0.0}

    def _ddpg_targets(self, batch: Transitions) -> torch.Tensor:
        """The DDPG targets of `batch`: update()'s own when it was the last batch updated on (the target
        networks have not moved since, until soft_update), else computed now."""
        last = self._last_targets
        return last[1] if last is not None and last[0] is batch else self.td_targets(batch)

    def soft_update(self, tau: float | None = None) -> None:
        """Polyak update of both target networks (parameters and batch-norm running stats)."""
        tau = self.config.tau if tau is None else tau
        self._last_targets = None
        soft_update(self.actor_target, self.actor, tau)
        soft_update(self.critic_target, self.critic, tau)

    def compile_report(self) -> dict:
        """Per compiled function: whether it runs compiled, its first-call (compile) seconds, and why
        it fell back to eager, if it did. Empty with learner_compile off."""
        return {f.name: f.report() for f in (self._targets_fn, self._critic_loss_fn, self._actor_loss_fn)
                if hasattr(f, "report")}

    # ------------------------------------------------------------------ checkpointing
    def state_dict(self) -> dict:
        return {"actor": self.actor.state_dict(), "critic": self.critic.state_dict(),
                "actor_target": self.actor_target.state_dict(),
                "critic_target": self.critic_target.state_dict(),
                "actor_opt": self.actor_opt.state_dict(), "critic_opt": self.critic_opt.state_dict(),
                "noise": self.noise.state_dict(), "updates": self.updates, "qt_steps": self.qt_steps,
                "qt_gated": self.qt_gated}

    def load_state_dict(self, d: dict) -> None:
        self._last_targets = None
        self.actor.load_state_dict(d["actor"])
        self.critic.load_state_dict(d["critic"])
        self.actor_target.load_state_dict(d["actor_target"])
        self.critic_target.load_state_dict(d["critic_target"])
        self.actor_opt.load_state_dict(d["actor_opt"])
        self.critic_opt.load_state_dict(d["critic_opt"])
        self.noise.load_state_dict(d["noise"])
        self.updates, self.qt_steps = int(d["updates"]), int(d["qt_steps"])
        self.qt_gated = int(d.get("qt_gated", 0))
