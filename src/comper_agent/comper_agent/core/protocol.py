"""The Atari protocol's summaries of a run (thesis chapter 5.3; method.md 5), pure numpy.

* :func:`final_performance` - the mean of the last 10 training episodes (the last 3 when the run
  has fewer than 25 episodes).
* :func:`tercile_summaries` - the mean of the last 5 (3) episodes that ended by the end of each
  third of the **frame budget**. The thesis describes its checkpoints twice: "we divided the
  number of episodes obtained in each run to split the results into 3 checkpoints" (5.3 and 7.2),
  and, where it introduces the figures of Tables 25 and 26, "checkpoints at the end of every
  tercile on the total frames number". The suite takes the second: it is the sentence that defines
  the reported numbers, it matches Machado et al. (2018), whose frame checkpoints (10M ... 200M)
  the protocol follows, and it keeps the checkpoints where they are whatever the agent's episode
  lengths (a better agent ends fewer, longer episodes; equal episode counts would move them). The
  learner's summary.json and ``evaluate`` use this one definition.
* :func:`protocol_summary` - both, for comper_node's summary.json.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["last_n_rule", "final_performance", "tercile_summaries", "protocol_summary", "protocol_text"]


def last_n_rule(n_episodes: int, *, n: int = 10, n_small: int = 3, small_below: int = 25) -> int:
    """Episodes averaged for the final score: the last 10, or the last 3 for runs with under 25."""
    return n_small if n_episodes < small_below else n


def final_performance(returns, **kw) -> tuple[float, int]:
    """(mean of the last 10 training episode returns (last 3 with under 25 episodes), n used)."""
    r = np.asarray(returns, dtype=np.float64)
    if r.size == 0:
        return math.nan, 0
    k = min(last_n_rule(r.size, **kw), r.size)
    return float(np.mean(r[-k:])), k


def tercile_summaries(progress, returns, *, budget: float | None = None, n: int = 5,
                      n_small: int = 3, small_below: int = 25) -> list[dict]:
    """Mean (and std) of the last n (5; 3 for runs with under 25 episodes) episodes that ended by
    the end of each tercile of the budget, and how many had ended (end_episode). progress: frames
    (or steps) of the run when each episode ended; budget: the run's frame (or step) budget,
    default the last episode's progress."""
    p = np.asarray(progress, dtype=np.float64)
    r = np.asarray(returns, dtype=np.float64)
    if p.size == 0:
        return [{"tercile": k, "end": math.nan, "mean": math.nan, "std": math.nan, "n": 0, "end_episode": 0}
                for k in (1, 2, 3)]
    budget = float(budget if budget else p.max())
    k_use = n_small if p.size < small_below else n
    out = []
    for k in (1, 2, 3):
        end = budget * k / 3.0
        sel = r[p <= end + 1e-9] if k < 3 else r     # the episode in progress at the budget finishes
        m = sel[-k_use:]
        out.append({"tercile": k, "end": end, "mean": float(np.mean(m)) if m.size else math.nan,
                    "std": float(np.std(m)) if m.size else math.nan, "n": int(m.size),
                    "end_episode": int(sel.size)})
    return out


def protocol_text(s: dict) -> str:
    """One line of :func:`protocol_summary`'s figures, for a run's last log line."""
    t = " | ".join(f"tercile {j + 1} (to episode {x['end_episode']}): {x['mean']:.1f} +- {x['std']:.1f}"
                   for j, x in enumerate(s["terciles"]))
    return f"mean of the last {s['last_k']} episodes {s['last_mean']:.1f} +- {s['last_std']:.1f}; {t}"


def protocol_summary(returns, frames_at_end, budget: float | None = None) -> dict:
    """The protocol's figures for one run: returns of the training episodes, frames_at_end the run's
    frame count when each ended, budget the run's frame budget (default: the last episode's)."""
    r = np.asarray(returns, dtype=np.float64)
    n = int(r.size)
    last, k = final_performance(r)
    return {"episodes": n, "last_k": k, "last_mean": last,
            "last_std": float(np.std(r[-k:])) if k else math.nan, "tercile_k": last_n_rule(n, n=5),
            "terciles": tercile_summaries(frames_at_end, r, budget=budget)}
