"""COMPER / COMPER-F / COMPER-M / DQN learner (thesis Algorithm 7, appendix A; method.md 4).

Q-network: :class:`~.networks.NatureCNN` (uint8 frames in, scaled to [0, 1] once inside).
Optimiser: :class:`DQNRMSprop`, the RMSProp of Mnih et al. 2015 / Machado et al. 2018
(Table 32): centred, the constant added inside the square root, no momentum term:

    g  <- rho_g g + (1 - rho_g) grad          (gradient momentum 0.95)
    n  <- rho_n n + (1 - rho_n) grad^2        (squared-gradient momentum 0.95)
    p  <- p - lr grad / sqrt(n - g^2 + min_sq_grad)      (min squared gradient 0.01)

torch.optim.RMSprop(centered=True) differs: one decay for both averages, eps added outside the
square root. Loss: Huber (delta 1) on Q(s, a_taken) - y, with
    comper, comper_m:  y = r + gamma (1 - terminated) QT(tau)       (qt_targets passed in)
    comper_f, dqn:     y = r + gamma (1 - terminated) max_a Q_target(s', a)
The target network (comper_f, dqn) is copied by :meth:`ComperLearner.sync_target`, which the node
calls every ``target_update_every`` agent steps. Epsilon counts frames (skipped ones included).
"""
from __future__ import annotations

import copy

import numpy as np
import torch
from torch import nn

from comper_msgs_py.arrays import Transitions

from .config import ComperConfig
from .networks import NatureCNN, hard_update

__all__ = ["DQNRMSprop", "ComperLearner", "linear_epsilon"]


class DQNRMSprop(torch.optim.Optimizer):
    """DeepMind's RMSProp (see module docstring)."""

    def __init__(self, params, lr: float = 2.5e-4, grad_momentum: float = 0.95,
                 sq_grad_momentum: float = 0.95, min_sq_grad: float = 0.01):
        super().__init__(params, dict(lr=lr, grad_momentum=grad_momentum,
                                      sq_grad_momentum=sq_grad_momentum, min_sq_grad=min_sq_grad))

    @torch.no_grad()
    def step(self, closure=None):
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        for group in self.param_groups:
            for p in group["params"]:
                if p.grad is None:
                    continue
                st = self.state[p]
                if not st:
                    st["step"] = torch.zeros((), dtype=torch.float32)
                    st["g"] = torch.zeros_like(p)
                    st["n"] = torch.zeros_like(p)
                g, n, grad = st["g"], st["n"], p.grad
                g.mul_(group["grad_momentum"]).add_(grad, alpha=1 - group["grad_momentum"])
                n.mul_(group["sq_grad_momentum"]).addcmul_(grad, grad, value=1 - group["sq_grad_momentum"])
                denom = (n - g * g).add_(group["min_sq_grad"]).sqrt_()
                p.addcdiv_(grad, denom, value=-group["lr"])
                st["step"] += 1
        return loss


def linear_epsilon(frames: int, start: float = 1.0, end: float = 0.01, decay_frames: int = 90_000
                   ) -> float:
    """Linear decay from `start` to `end` over `decay_frames` frames, then constant."""
    frac = min(max(frames, 0) / float(decay_frames), 1.0)
    return float(start + frac * (end - start))


class ComperLearner:
    def __init__(self, config: ComperConfig):
        self.config = c = config
        self.device = torch.device(c.device)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(c.seed)
            self.q = NatureCNN(c.frame_stack, c.n_actions).to(self.device)
        self.q.eval()
        self.uses_target_net = c.variant in ("comper_f", "dqn")
        self.q_target = copy.deepcopy(self.q) if self.uses_target_net else None
        if self.q_target is not None:
            for p in self.q_target.parameters():
                p.requires_grad_(False)
        self.optimizer = DQNRMSprop(self.q.parameters(), lr=c.lr, grad_momentum=c.rms_grad_momentum,
                                    sq_grad_momentum=c.rms_sq_grad_momentum,
                                    min_sq_grad=c.rms_min_sq_grad)
        self.rng = np.random.default_rng(c.seed)
        self.updates = 0

    def _t(self, x, dtype=None) -> torch.Tensor:
        return torch.as_tensor(np.asarray(x), dtype=dtype, device=self.device)

    # ------------------------------------------------------------------ acting
    def epsilon(self, frames: int) -> float:
        c = self.config
        return linear_epsilon(frames, c.epsilon_start, c.epsilon_end, c.epsilon_decay_frames)

    @torch.no_grad()
    def act(self, obs: np.ndarray, frames: int | None = None, epsilon: float | None = None
            ) -> tuple[int, np.ndarray]:
        """Epsilon-greedy action for one observation; returns (action, Q(obs, .) float32 [A]).
        Pass `frames` (schedule) or an explicit `epsilon` (0 for greedy evaluation)."""
        eps = self.epsilon(frames or 0) if epsilon is None else float(epsilon)
        q = self.q(self._t(obs)[None]).squeeze(0).cpu().numpy()
        if self.rng.random() < eps:
            return int(self.rng.integers(self.config.n_actions)), q
        return int(np.argmax(q)), q

    # ------------------------------------------------------------------ labels and targets
    @torch.no_grad()
    def value_labels(self, batch: Transitions) -> np.ndarray:
        """next_value: max_a Q(s', a) * (1 - terminated); q_sa: Q(s, a). float32 [N]."""
        if len(batch) == 0:
            return np.zeros(0, np.float32)
        if self.config.qt_label == "q_sa":
            q = self.q(self._t(batch.states))
            a = self._t(batch.actions, torch.int64).reshape(-1, 1)
            return q.gather(1, a).squeeze(1).cpu().numpy().astype(np.float32)
        v = self.q(self._t(batch.next_states)).max(dim=1).values
        return (v * (1.0 - self._t(batch.terminated, torch.float32))).cpu().numpy().astype(np.float32)

    @torch.no_grad()
    def targets(self, batch: Transitions, qt_targets: np.ndarray | None = None) -> torch.Tensor:
        c = self.config
        r = self._t(batch.rewards, torch.float32)
        not_done = 1.0 - self._t(batch.terminated, torch.float32)
        if self.uses_target_net:
            boot = self.q_target(self._t(batch.next_states)).max(dim=1).values
        else:
            if qt_targets is None:
                raise ValueError(f"variant {c.variant} needs qt_targets")
            boot = self._t(qt_targets, torch.float32).reshape(-1)
        return r + c.gamma * not_done * boot

    def _loss(self, batch: Transitions, y: torch.Tensor) -> torch.Tensor:
        q = self.q(self._t(batch.states))
        a = self._t(batch.actions, torch.int64).reshape(-1, 1)
        q_sa = q.gather(1, a).squeeze(1)
        return nn.functional.huber_loss(q_sa, y, delta=self.config.huber_delta)

    @torch.no_grad()
    def loss(self, batch: Transitions, qt_targets: np.ndarray | None = None) -> float:
        return float(self._loss(batch, self.targets(batch, qt_targets)))

    # ------------------------------------------------------------------ updates
    def update(self, batch: Transitions, qt_targets: np.ndarray | None = None) -> dict:
        """One gradient step on `batch` (qt_targets required for comper / comper_m)."""
        y = self.targets(batch, qt_targets)
        loss = self._loss(batch, y)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        self.updates += 1
        return {"loss": float(loss.detach()), "target_mean": float(y.mean())}

    def sync_target(self) -> None:
        if self.q_target is not None:
            hard_update(self.q_target, self.q)

    # ------------------------------------------------------------------ checkpointing
    def state_dict(self) -> dict:
        d = {"q": self.q.state_dict(), "optimizer": self.optimizer.state_dict(),
             "updates": self.updates, "rng": self.rng.bit_generator.state}
        if self.q_target is not None:
            d["q_target"] = self.q_target.state_dict()
        return d

    def load_state_dict(self, d: dict) -> None:
        self.q.load_state_dict(d["q"])
        self.optimizer.load_state_dict(d["optimizer"])
        if self.q_target is not None and "q_target" in d:
            self.q_target.load_state_dict(d["q_target"])
        self.updates = int(d["updates"])
        self.rng.bit_generator.state = d["rng"]
