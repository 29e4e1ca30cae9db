"""COMPER / COMPER-F / COMPER-M / DQN learner (thesis Algorithm 7, appendix A; method.md 4).

Q-network (``q_network``): :class:`~.networks.NatureCNN` for ALE frames (uint8 in, scaled to
[0, 1] once inside), :class:`~.networks.QMLP` for vector observations (classic control).
Optimiser (``optimizer``): :class:`DQNRMSprop`, the RMSProp of Mnih et al. 2015 / Machado et al.
2018 (Table 32): centred, the constant added inside the square root, no momentum term:

    g  <- rho_g g + (1 - rho_g) grad          (gradient momentum 0.95)
    n  <- rho_n n + (1 - rho_n) grad^2        (squared-gradient momentum 0.95)
    p  <- p - lr grad / sqrt(n - g^2 + min_sq_grad)      (min squared gradient 0.01)

torch.optim.RMSprop(centered=True) differs: one decay for both averages, eps added outside the
square root. Or torch's Adam (the data-efficient profile).

Loss: Huber (delta 1) on Q(s, a_taken) - y, **summed** over the batch (``loss_reduction`` sum:
Algorithm 7 accumulates the gradient over the k sampled transitions before one step, as
DeepMind's DQN, and Table 32's 0.01 is sized for that sum; with a batch mean every denominator
sits at sqrt(0.01) and the CNN barely moves). ``mean`` divides by the batch size and, with
rmsprop_dm, divides min_sq_grad by batch_size^2, which gives the identical step. Targets:

    comper, comper_m:  y = clip(r) + gamma (1 - terminated) QT(tau)       (qt_targets passed in)
                       (qt_target_gate: the batch takes comper_f's bootstrap B(s') instead when
                        RMS(QT(tau) - V(s')) > std(V(s')) over its non-terminal rows)
    comper_f, dqn:     y = clip(r) + gamma (1 - terminated) max_a Q_target(s', a)
                       (double_dqn: Q_target(s', argmax_a Q(s', a)))
    dqn, n_step n > 1: y = sum_j<m gamma^j clip(r_j) + gamma^m (1 - terminated_m) bootstrap(s_m)
                       (the replay's window of m <= n steps, :class:`~.replay.NStepRewards`)

clip(r) is ``reward_clip`` (default [-1, 1]); the memory and every report keep the raw reward.
Value labels (what QT learns for comper, comper_m): V(s') = max_a Q(s', a) of the network being trained,
x (1 - terminated). Target network (comper_f, dqn; comper, comper_m with ``qt_target_gate``): copied by
:meth:`ComperLearner.sync_target` every ``target_update_every`` agent steps. Epsilon counts frames (skipped too).
"""
from __future__ import annotations

import copy

import numpy as np
import torch
from torch import nn

from comper_msgs_py.arrays import Transitions

from .config import ComperConfig
from .networks import NatureCNN, QMLP, hard_update
from .replay import NStepRewards

__all__ = ["DQNRMSprop", "ComperLearner", "linear_epsilon", "clip_rewards", "resolve_q_network"]

ATARI_FRAME_SHAPE = (84, 84)
ATARI_ACTIONS = 18


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


def clip_rewards(r, mode: str):
    """The learning signal's reward (``reward_clip``): clip = clamp to [-1, 1], sign, none = raw.
    A torch tensor or a numpy array (COMPER's n-step windows clip before they are stored)."""
    if mode == "none":
        return r
    if isinstance(r, np.ndarray):
        return np.clip(r, -1.0, 1.0) if mode == "clip" else np.sign(r)
    return r.clamp(-1.0, 1.0) if mode == "clip" else torch.sign(r)


def resolve_q_network(choice: str, obs_shape: tuple) -> str:
    """``q_network`` auto -> nature_cnn for image observations ([H, W] or [C, H, W]), mlp for 1-D ones;
    an explicit choice that does not fit the observations is refused."""
    shape = tuple(int(d) for d in obs_shape)
    image = len(shape) in (2, 3)
    if choice == "auto":
        if len(shape) == 1:
            return "mlp"
        if image:
            return "nature_cnn"
        raise ValueError(f"observations of shape {list(shape)} are neither a vector nor frames; comper_node "
                         "supports 1-D vector observations (mlp) and ALE frames (nature_cnn)")
    if choice == "mlp" and len(shape) != 1:
        raise ValueError(f"q_network:=mlp needs 1-D observations, the task has {list(shape)}")
    if choice == "nature_cnn" and shape[-2:] != ATARI_FRAME_SHAPE:
        raise ValueError(f"q_network:=nature_cnn needs 84x84 frames, the task has {list(shape)}")
    return choice


class ComperLearner:
    """The Q-learner of every comper_node variant.

    obs_shape / n_actions: the task's (default: ALE single or stacked 84x84 frames per
    ``frame_stack``, and ``n_actions`` or 18)."""

    def __init__(self, config: ComperConfig, obs_shape: tuple | None = None, n_actions: int | None = None):
        self.config = c = config
        self.device = torch.device(c.device)
        if obs_shape is None:
            obs_shape = ATARI_FRAME_SHAPE if c.frame_stack == 1 else (c.frame_stack, *ATARI_FRAME_SHAPE)
        self.obs_shape = tuple(int(d) for d in obs_shape)
        self.n_actions = int(n_actions or c.n_actions or ATARI_ACTIONS)
        self.network = resolve_q_network(c.q_network, self.obs_shape)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(c.seed)
            if self.network == "mlp":
                self.q = QMLP(int(np.prod(self.obs_shape)), self.n_actions, c.mlp_hidden).to(self.device)
            else:
                self.q = NatureCNN(c.frame_stack, self.n_actions).to(self.device)
        self.q.eval()
        # comper_f and dqn bootstrap their TD targets from the target network; comper and comper_m with
        # qt_target_gate keep one for the batches the gate sends to it
        self.bootstraps_from_target = c.variant in ("comper_f", "dqn")
        self.gates_qt = c.qt_target_gate and not self.bootstraps_from_target
        self.uses_target_net = self.bootstraps_from_target or self.gates_qt
        self.q_target = copy.deepcopy(self.q) if self.uses_target_net else None
        if self.q_target is not None:
            for p in self.q_target.parameters():
                p.requires_grad_(False)
        if c.optimizer == "adam":
            self.optimizer = torch.optim.Adam(self.q.parameters(), lr=c.lr, eps=c.adam_eps)
        else:
            self.optimizer = DQNRMSprop(self.q.parameters(), lr=c.lr, grad_momentum=c.rms_grad_momentum,
                                        sq_grad_momentum=c.rms_sq_grad_momentum, min_sq_grad=c.rms_min_sq_grad)
        self.rng = np.random.default_rng(c.seed)
        self.updates = 0
        self.qt_gated = 0     # updates whose batch qt_target_gate sent to the target network's bootstrap

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
            return int(self.rng.integers(self.n_actions)), q
        return int(np.argmax(q)), q

    # ------------------------------------------------------------------ labels and targets
    def _target_bootstrap(self, next_states: torch.Tensor, q_online: torch.Tensor | None = None) -> torch.Tensor:
        """max_a Q_target(s', a), or with double_dqn Q_target(s', argmax_a Q(s', a)) (`q_online`: the
        online Q-values at s' when the caller has them already)."""
        q_next = self.q_target(next_states)
        if not self.config.double_dqn:
            return q_next.max(dim=1).values
        if q_online is None:
            q_online = self.q(next_states)
        return q_next.gather(1, q_online.argmax(dim=1, keepdim=True)).squeeze(1)

    def _label_bootstrap(self, next_states: torch.Tensor) -> torch.Tensor:
        """V(s'), the next_value label of s' before the terminal mask: max_a Q(s', a) of the network being
        trained."""
        return self.q(next_states).max(dim=1).values

    @torch.no_grad()
    def value_labels(self, batch: Transitions) -> np.ndarray:
        """next_value: V(s') = max_a Q(s', a) x (1 - terminated); q_sa: Q(s, a). float32 [N]."""
        if len(batch) == 0:
            return np.zeros(0, np.float32)
        if self.config.qt_label == "q_sa":
            q = self.q(self._t(batch.states))
            a = self._t(batch.actions, torch.int64).reshape(-1, 1)
            return q.gather(1, a).squeeze(1).cpu().numpy().astype(np.float32)
        v = self._label_bootstrap(self._t(batch.next_states))
        return (v * (1.0 - self._t(batch.terminated, torch.float32))).cpu().numpy().astype(np.float32)

    @staticmethod
    def next_value(next_obs: np.ndarray, q_online: np.ndarray) -> float:
        """The next_value label of one transition from the online Q-values at s' (those computed to act there):
        their max. The caller applies the terminal mask."""
        return float(np.max(q_online))

    @torch.no_grad()
    def qt_gate(self, batch: Transitions, qt_targets: np.ndarray) -> dict:
        """``qt_target_gate``'s test over the batch's non-terminal rows: error = RMS of QT(tau) - V(s'), spread =
        std of V(s') (the labels' bootstrap, what QT is fitted to); gated = error > spread (the batch then
        bootstraps from B, the target network's bootstrap). No such row: not gated."""
        live = self._t(batch.terminated, torch.float32) < 0.5
        if not bool(live.any()):
            return {"gated": False, "error": 0.0, "spread": 0.0, "bootstrap": None}
        next_states = self._t(batch.next_states)
        b = self._target_bootstrap(next_states)
        ref = self._label_bootstrap(next_states)
        qt = self._t(qt_targets, torch.float32).reshape(-1)
        error = float(torch.sqrt(torch.mean((qt[live] - ref[live]) ** 2)))
        spread = float(ref[live].std(unbiased=False))
        return {"gated": error > spread, "error": error, "spread": spread, "bootstrap": b}

    @torch.no_grad()
    def targets(self, batch: Transitions, qt_targets: np.ndarray | None = None,
                n_step: NStepRewards | None = None) -> torch.Tensor:
        """TD targets; with `n_step` (a replay's n-step windows, whose last transition `batch` ends at):
        sum_j gamma^j clip(r_j) over each window + gamma^length (1 - terminated) x bootstrap. A COMPER
        variant with ``n_step`` > 1 samples stored windows: r (their return) + gamma^n (1 - terminated)
        x bootstrap of s_{t+n}. ``qt_target_gate``: :meth:`qt_gate` picks QT's bootstrap or B's."""
        return self._targets(batch, qt_targets, n_step)[0]

    @torch.no_grad()
    def _targets(self, batch: Transitions, qt_targets: np.ndarray | None, n_step: NStepRewards | None,
                 gate: bool = True) -> tuple[torch.Tensor, bool | None]:
        """(targets, gated: whether qt_target_gate took the target network's bootstrap; None without it).
        gate=False: the targets with `qt_targets` as the bootstrap whatever the gate would decide (diagnostics
        that compare bootstraps)."""
        c = self.config
        if c.window_rewards:            # stored n-step windows
            if n_step is not None:
                raise ValueError("stored n-step windows take no replay windows")
            r = self._t(batch.rewards, torch.float32)
            discount = c.gamma ** c.n_step
        elif n_step is None:
            r = clip_rewards(self._t(batch.rewards, torch.float32), c.reward_clip)
            discount = c.gamma
        else:
            rw = clip_rewards(self._t(n_step.rewards, torch.float32), c.reward_clip)
            lengths = self._t(n_step.lengths, torch.int64)
            j = torch.arange(rw.shape[1], device=self.device)
            in_window = (j[None, :] < lengths[:, None]).to(rw.dtype)
            r = (rw * in_window * c.gamma ** j.to(rw.dtype)).sum(dim=1)
            discount = c.gamma ** lengths.to(rw.dtype)
        not_done = 1.0 - self._t(batch.terminated, torch.float32)
        gated = None
        if self.bootstraps_from_target:
            boot = self._target_bootstrap(self._t(batch.next_states))
        else:
            if qt_targets is None:
                raise ValueError(f"variant {c.variant} needs qt_targets")
            boot = self._t(qt_targets, torch.float32).reshape(-1)
            if gate and self.gates_qt:
                test = self.qt_gate(batch, qt_targets)
                gated = test["gated"]
                if gated:
                    boot = test["bootstrap"]
        return r + discount * not_done * boot, gated

    @torch.no_grad()
    def qt_diagnostics(self, batch: Transitions, qt_targets: np.ndarray) -> dict:
        """How QT's bootstrap compares on this batch (no parameter moves) with V(s'), the value label a
        re-store writes now (0 when terminated): max_a Q(s', a) of the network being trained. y_QT and y_V are
        :meth:`targets` with
        either bootstrap (``qt_target_gate`` not applied: they compare QT with V(s')).

        qt_target_rmse: RMS of y_QT - y_V; td_rmse: RMS of Q(s, a) - the target this update's loss sees (y_QT,
        or the target network's where ``qt_target_gate`` takes it); qt_bias: mean of QT(tau) - V(s') over
        non-terminal rows (positive: QT above the network); label_bias: the same for the value labels the
        sampled entries carry (RTM: QT's prediction from the entry's last reduction; TM: the set's newest label;
        NaN without labels); v_next_mean, v_next_std: mean and spread of V(s') over non-terminal rows (the
        state-dependent part that an RMS is to be read against); qt_v_corr: Pearson correlation of QT(tau) with
        V(s') over those rows (1: QT follows the network's state values; NaN with fewer than 2 rows or no
        spread); q_gap_mean: mean over the batch's states of max_a Q(s, a) - min_a Q(s, a); greedy_top_share:
        the share of the batch's states whose greedy action is the batch's most common one (1 = one action in
        every sampled state). With ``qt_target_gate`` also its test (:meth:`qt_gate`): qt_gate_error,
        qt_gate_spread and qt_gate_on (1.0 = this batch takes the target network's bootstrap)."""
        s = self._t(batch.states)
        live = self._t(batch.terminated, torch.float32) < 0.5
        v_next = self._label_bootstrap(self._t(batch.next_states)) * live
        qt = self._t(qt_targets, torch.float32).reshape(-1)
        y_qt = self._targets(batch, qt, None, gate=False)[0]
        y_v = self._targets(batch, v_next.cpu().numpy(), None, gate=False)[0]
        y_loss, gate = y_qt, {}
        if self.gates_qt:
            test = self.qt_gate(batch, qt_targets)
            gate = {"qt_gate_error": test["error"], "qt_gate_spread": test["spread"],
                    "qt_gate_on": float(test["gated"])}
            if test["gated"]:
                y_loss = self._targets(batch, test["bootstrap"].cpu().numpy(), None, gate=False)[0]
        q = self.q(s)
        q_sa = q.gather(1, self._t(batch.actions, torch.int64).reshape(-1, 1)).squeeze(1)
        greedy = q.argmax(dim=1)

        def bias(values: torch.Tensor) -> float:
            return float((values - v_next)[live].mean()) if bool(live.any()) else 0.0

        labelled = batch.value_labels.size == len(batch)
        v_live, qt_live = v_next[live], qt[live]
        spread = v_live.numel() > 1 and float(v_live.std()) > 0 and float(qt_live.std()) > 0
        corr = float(torch.corrcoef(torch.stack([qt_live, v_live]))[0, 1]) if spread else float("nan")
        return {"qt_target_rmse": float(torch.sqrt(torch.mean((y_qt - y_v) ** 2))),
                "td_rmse": float(torch.sqrt(torch.mean((q_sa - y_loss) ** 2))),
                "qt_bias": bias(qt),
                "label_bias": bias(self._t(batch.value_labels, torch.float32)) if labelled else float("nan"),
                "v_next_mean": float(v_live.mean()) if v_live.numel() else float("nan"),
                "v_next_std": float(v_live.std(unbiased=False)) if v_live.numel() else float("nan"),
                "qt_v_corr": corr,
                "q_gap_mean": float((q.max(dim=1).values - q.min(dim=1).values).mean()),
                "greedy_top_share": float(torch.bincount(greedy).max()) / max(len(batch), 1),
                **gate}

    def _loss(self, batch: Transitions, y: torch.Tensor) -> torch.Tensor:
        q = self.q(self._t(batch.states))
        a = self._t(batch.actions, torch.int64).reshape(-1, 1)
        q_sa = q.gather(1, a).squeeze(1)
        return nn.functional.huber_loss(q_sa, y, delta=self.config.huber_delta,
                                        reduction=self.config.loss_reduction)

    @torch.no_grad()
    def loss(self, batch: Transitions, qt_targets: np.ndarray | None = None) -> float:
        """The mean Huber loss per transition (whatever ``loss_reduction`` optimises)."""
        n = len(batch) if self.config.loss_reduction == "sum" else 1
        return float(self._loss(batch, self.targets(batch, qt_targets))) / n

    # ------------------------------------------------------------------ updates
    def update(self, batch: Transitions, qt_targets: np.ndarray | None = None,
               n_step: NStepRewards | None = None) -> dict:
        """One gradient step on `batch` (qt_targets required for comper / comper_m; n_step: the n-step
        windows of a replay draw, :meth:`targets`). Returns the mean Huber loss per transition (comparable
        across ``loss_reduction``) and the mean target."""
        y, gated = self._targets(batch, qt_targets, n_step)
        loss = self._loss(batch, y)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if isinstance(self.optimizer, DQNRMSprop):
            # loss_reduction mean scales the gradient by 1/B: min_sq_grad / B^2 keeps the sum's step (module
            # text); B is this batch's size (a batch can be smaller than batch_size while RTM fills)
            scale = float(len(batch)) ** 2 if self.config.loss_reduction == "mean" else 1.0
            for group in self.optimizer.param_groups:
                group["min_sq_grad"] = self.config.rms_min_sq_grad / scale
        self.optimizer.step()
        self.updates += 1
        info = {"loss": float(loss.detach()) / (len(batch) if self.config.loss_reduction == "sum" else 1),
                "target_mean": float(y.mean())}
        if gated is not None:
            self.qt_gated += int(gated)
            info["qt_gated"] = float(gated)
            info["qt_gated_share"] = self.qt_gated / self.updates
        return info

    def sync_target(self) -> None:
        if self.q_target is not None:
            hard_update(self.q_target, self.q)

    # ------------------------------------------------------------------ checkpointing
    def state_dict(self) -> dict:
        d = {"q": self.q.state_dict(), "optimizer": self.optimizer.state_dict(),
             "updates": self.updates, "rng": self.rng.bit_generator.state, "qt_gated": self.qt_gated}
        if self.q_target is not None:
            d["q_target"] = self.q_target.state_dict()
        return d

    def load_state_dict(self, d: dict) -> None:
        self.q.load_state_dict(d["q"])
        self.optimizer.load_state_dict(d["optimizer"])
        if self.q_target is not None and "q_target" in d:
            self.q_target.load_state_dict(d["q_target"])
        self.updates = int(d["updates"])
        self.qt_gated = int(d.get("qt_gated", 0))
        self.rng.bit_generator.state = d["rng"]
