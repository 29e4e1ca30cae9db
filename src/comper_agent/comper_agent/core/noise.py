"""Ornstein-Uhlenbeck exploration noise (Lillicrap et al. 2016; thesis section 4.2), numpy.

x_{t+1} = x_t + theta (mu - x_t) dt + sigma sqrt(dt) N(0, 1), one independent process per action
dimension, x_0 = mu. Call :meth:`reset` at the start of each episode.
"""
from __future__ import annotations

import numpy as np

__all__ = ["OUNoise"]


class OUNoise:
    def __init__(self, size: int, theta: float = 0.15, sigma: float = 0.2, mu: float = 0.0,
                 dt: float = 1.0, seed: int | None = None):
        self.size = int(size)
        self.theta, self.sigma, self.mu, self.dt = float(theta), float(sigma), float(mu), float(dt)
        self.rng = np.random.default_rng(seed)
        self.state = np.full(self.size, self.mu, dtype=np.float64)

    def reset(self) -> None:
        self.state = np.full(self.size, self.mu, dtype=np.float64)

    def sample(self) -> np.ndarray:
        """Advance one step; returns float32 [size]."""
        self.state = (self.state + self.theta * (self.mu - self.state) * self.dt
                      + self.sigma * np.sqrt(self.dt) * self.rng.standard_normal(self.size))
        return self.state.astype(np.float32)

    __call__ = sample

    def stationary_std(self) -> float:
        """Standard deviation of the process's stationary distribution (discrete-time exact)."""
        a = 1.0 - self.theta * self.dt
        return float(self.sigma * np.sqrt(self.dt / (1.0 - a * a)))

    def state_dict(self) -> dict:
        import torch
        return {"state": torch.from_numpy(self.state.copy()),
                "rng": self.rng.bit_generator.state}

    def load_state_dict(self, d: dict) -> None:
        self.state = d["state"].numpy().astype(np.float64)
        self.rng.bit_generator.state = d["rng"]
