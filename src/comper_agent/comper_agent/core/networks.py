"""Networks: DDPG actor and critic (thesis appendix B), Nature-DQN CNN (Table 36).

Initialisation: hidden layers keep torch's default (U(+-1/sqrt(fan_in)) for weights and biases,
the fan-in initialisation of Lillicrap et al. 2016); output layers as the thesis gives them.

Batch normalisation (DDPG): ``nn.BatchNorm1d`` with torch defaults (momentum 0.1, eps 1e-5);
``batch_norm=False`` puts ``nn.Identity`` in its places (the plain MLP of most DDPG code).
Learners put a network in train mode (batch statistics, running stats updated) only inside an
update; acting, value labels and target computation run in eval mode (running statistics), so a
transition's action / value does not depend on the rest of its batch.
"""
from __future__ import annotations

import shutil
import time
import warnings

import torch
from torch import nn

__all__ = ["Actor", "Critic", "NatureCNN", "QMLP", "configure_torch", "compile_or_eager", "soft_update", "hard_update",
           "frames_to_nchw"]


def configure_torch(num_threads: int = 2, seed: int | None = None) -> None:
    """Call once from an entry point (never at import): thread count and optional global seed."""
    torch.set_num_threads(max(1, int(num_threads)))
    if seed is not None:
        torch.manual_seed(int(seed))


COMPILE_MODES = ("off", "default", "max-autotune-no-cudagraphs")


def cpp_compiler() -> str | None:
    """The C++ compiler torch.compile's CPU backend (inductor) would call, or None if there is none."""
    import os
    for name in (os.environ.get("CXX"), "g++", "c++", "clang++"):
        if name and shutil.which(name):
            return name
    return None


class CompiledOrEager:
    """`fn` run through torch.compile(mode), or `fn` itself when compiling is unavailable or fails.

    Compilation happens on the first call (its time is ``compile_s``, one call's run time included);
    if that call raises (no C++ compiler, an unsupported construct), the reason is kept in
    ``fallback``, one warning is issued and this and every later call run `fn` eagerly. `fn` must not
    have side effects before it fails: the learner's loss functions only read tensors (batch-norm
    running statistics are updated when the compiled graph runs, not while it is traced)."""

    def __init__(self, fn, mode: str, name: str):
        self.fn, self.mode, self.name = fn, mode, name
        self.compile_s = 0.0
        self.fallback: str | None = None
        self.calls = 0
        self.compiled = None
        if cpp_compiler() is None:
            self._fall_back("no C++ compiler found (CXX, g++, c++, clang++)")
        else:
            self.compiled = torch.compile(fn, mode=None if mode == "default" else mode)

    def _fall_back(self, why: str) -> None:
        self.fallback, self.compiled = why, None
        warnings.warn(f"torch.compile of {self.name} unavailable, running it eagerly: {why}", RuntimeWarning,
                      stacklevel=3)

    def __call__(self, *args):
        if self.compiled is None:
            return self.fn(*args)
        self.calls += 1
        if self.calls > 1:
            return self.compiled(*args)
        t0 = time.perf_counter()
        try:
            out = self.compiled(*args)
        except Exception as e:   # noqa: BLE001 - any compiler failure means: run eagerly
            self._fall_back(f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}")
            return self.fn(*args)
        self.compile_s = time.perf_counter() - t0
        return out

    def report(self) -> dict:
        return {"mode": self.mode, "compiled": self.compiled is not None, "compile_s": round(self.compile_s, 3),
                "fallback": self.fallback}


def compile_or_eager(fn, mode: str, name: str):
    """`fn` unchanged for mode "off"; otherwise a :class:`CompiledOrEager` (torch.compile with that
    mode, falling back to `fn`). Modes: :data:`COMPILE_MODES`."""
    if mode not in COMPILE_MODES:
        raise ValueError(f"compile mode must be one of {', '.join(COMPILE_MODES)}, got {mode!r}")
    return fn if mode == "off" else CompiledOrEager(fn, mode, name)


#: |x| of the actor's output before tanh past which the action is within 1 % of its bound (tanh(2.65) = 0.99),
#: where tanh's slope, and so the gradient the actor gets from the critic, is below 0.02
SATURATED_PREACT = 2.65


class Actor(nn.Module):
    """BN(obs) -> [Linear h -> ReLU -> BN] per hidden layer -> Linear (U(+-final_init)) -> tanh,
    scaled to [low, high] per action dimension."""

    def __init__(self, obs_dim: int, action_low, action_high, hidden=(400, 300),
                 final_init: float = 3e-3, batch_norm: bool = True):
        super().__init__()
        low = torch.as_tensor(action_low, dtype=torch.float32).reshape(-1)
        high = torch.as_tensor(action_high, dtype=torch.float32).reshape(-1)
        self.register_buffer("action_center", (high + low) / 2)
        self.register_buffer("action_half_range", (high - low) / 2)
        norm = nn.BatchNorm1d if batch_norm else (lambda n: nn.Identity())
        layers: list[nn.Module] = [norm(obs_dim)]
        d = obs_dim
        for h in hidden:
            layers += [nn.Linear(d, h), nn.ReLU(), norm(h)]
            d = h
        self.body = nn.Sequential(*layers)
        self.out = nn.Linear(d, low.numel())
        nn.init.uniform_(self.out.weight, -final_init, final_init)
        nn.init.uniform_(self.out.bias, -final_init, final_init)

    def pre_activation(self, obs: torch.Tensor) -> torch.Tensor:
        """The output layer's values before tanh (saturated past SATURATED_PREACT)."""
        return self.out(self.body(obs))

    def squash(self, pre: torch.Tensor) -> torch.Tensor:
        """tanh of pre_activation's values, scaled to [low, high]."""
        return self.action_center + self.action_half_range * torch.tanh(pre)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.squash(self.pre_activation(obs))


class Critic(nn.Module):
    """Q(s, a).

    action_input = "second_hidden" (default, Lillicrap et al.):
        BN(s) -> Linear h1 -> ReLU -> BN -> concat(a) -> Linear h2 -> ReLU -> Linear 1
    action_input = "output" (thesis-literal reading of appendix B):
        BN(s) -> Linear h1 -> ReLU -> BN -> Linear h2 -> ReLU -> BN -> concat(a) -> Linear 1
    Output layer weights and bias U(+-final_init). Batch norm never sees the action, so the
    critic's batch statistics depend on states only.
    """

    def __init__(self, obs_dim: int, action_dim: int, hidden=(400, 300), final_init: float = 3e-4,
                 action_input: str = "second_hidden", batch_norm: bool = True):
        super().__init__()
        h1, h2 = hidden
        self.action_input = action_input
        norm = nn.BatchNorm1d if batch_norm else (lambda n: nn.Identity())
        self.bn0 = norm(obs_dim)
        self.fc1 = nn.Linear(obs_dim, h1)
        self.bn1 = norm(h1)
        if action_input == "second_hidden":
            self.fc2 = nn.Linear(h1 + action_dim, h2)
            self.out = nn.Linear(h2, 1)
        elif action_input == "output":
            self.fc2 = nn.Linear(h1, h2)
            self.bn2 = norm(h2)
            self.out = nn.Linear(h2 + action_dim, 1)
        else:
            raise ValueError(f"unknown critic action_input {action_input!r}")
        nn.init.uniform_(self.out.weight, -final_init, final_init)
        nn.init.uniform_(self.out.bias, -final_init, final_init)

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        h = self.bn1(torch.relu(self.fc1(self.bn0(obs))))
        if self.action_input == "second_hidden":
            h = torch.relu(self.fc2(torch.cat([h, action], dim=-1)))
            return self.out(h).squeeze(-1)
        h = self.bn2(torch.relu(self.fc2(h)))
        return self.out(torch.cat([h, action], dim=-1)).squeeze(-1)


def frames_to_nchw(x: torch.Tensor, channels: int) -> torch.Tensor:
    """Atari observations to [N, C, 84, 84]: accepts [N, 84, 84] (C = 1), [N, C, 84, 84] and
    channel-last [N, 84, 84, C]."""
    if x.ndim == 3:
        return x.unsqueeze(1)
    if x.ndim == 4 and x.shape[1] != channels and x.shape[-1] == channels:
        return x.permute(0, 3, 1, 2)
    return x


class NatureCNN(nn.Module):
    """Mnih et al. 2015 / thesis Table 36: conv 32x8x8/4, 64x4x4/2, 64x3x3/1, dense 512, dense n.

    Takes uint8 frames (0..255) and scales them to [0, 1] once, inside; float input is assumed to
    be already in [0, 1].
    """

    def __init__(self, in_channels: int = 1, n_actions: int = 18):
        super().__init__()
        self.in_channels = in_channels
        self.features = nn.Sequential(
            nn.Conv2d(in_channels, 32, 8, stride=4), nn.ReLU(),
            nn.Conv2d(32, 64, 4, stride=2), nn.ReLU(),
            nn.Conv2d(64, 64, 3, stride=1), nn.ReLU(), nn.Flatten())
        self.head = nn.Sequential(nn.Linear(3136, 512), nn.ReLU(), nn.Linear(512, n_actions))

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        x = frames_to_nchw(frames, self.in_channels)
        x = x.float() / 255.0 if x.dtype == torch.uint8 else x.float()
        return self.head(self.features(x))


class QMLP(nn.Module):
    """Q-network for vector observations: [Linear -> ReLU] per hidden layer -> Linear n_actions
    (torch default initialisation). Input float32 [N, obs_dim] (any trailing shape is flattened)."""

    def __init__(self, obs_dim: int, n_actions: int, hidden=(256, 256)):
        super().__init__()
        layers: list[nn.Module] = [nn.Flatten()]
        d = int(obs_dim)
        for h in hidden:
            layers += [nn.Linear(d, int(h)), nn.ReLU()]
            d = int(h)
        layers.append(nn.Linear(d, int(n_actions)))
        self.net = nn.Sequential(*layers)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.net(obs.float())


@torch.no_grad()
def soft_update(target: nn.Module, source: nn.Module, tau: float) -> None:
    """target <- tau * source + (1 - tau) * target, for parameters and floating buffers
    (batch-norm running mean / var); integer buffers (num_batches_tracked) are copied."""
    for t, s in zip(target.parameters(), source.parameters()):
        t.lerp_(s, tau)
    for t, s in zip(target.buffers(), source.buffers()):
        if t.dtype.is_floating_point:
            t.lerp_(s, tau)
        else:
            t.copy_(s)


@torch.no_grad()
def hard_update(target: nn.Module, source: nn.Module) -> None:
    target.load_state_dict(source.state_dict())
