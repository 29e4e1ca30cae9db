#!/usr/bin/env python3
"""Per-update time of the COMCACT / DDPG learner, eager against each optimisation, in one run
(docs/agent-core.md, "Learner step speed").

    python benchmarks/learner_step_bench.py                               # Hopper-v4 and IDP shapes, all variants
    python benchmarks/learner_step_bench.py --tasks Hopper-v4 --algorithms ddpg --variants off off@2   # threads

The learner is built for each task's shapes (no simulator: Hopper-v4 obs 11 / action 3, InvertedDoublePendulum-v4
obs 9 / action 1, bounds +-1) and fed fixed random batches of 64. One update is what the node does per agent step:
DDPG = update + soft_update; COMCACT = update + qt_critic_step (fixed random QT targets) + soft_update.

Variants (each its own learner, all from the same initial state):
  toggle   the eager step before the optimisations (requires_grad toggled off the critic for the actor step)
  off      the learner's eager step now (learner_compile off: actor loss through detached critic weights)
  default, max-autotune-no-cudagraphs   learner_compile with that torch.compile mode
  off@2    the eager step with 2 torch threads instead of --threads (set around each of its updates)

Timing is interleaved: update i of every variant runs before update i + 1 of any, so a load that comes and goes
on a shared machine hits every variant alike. Each row: median and p90 ms per update over --updates updates after
--warmup (the first call of a compiled variant, i.e. its compile time, is reported separately and amortised: the
number of updates its saving needs to repay it). The ratio is the reference's median over the variant's. Compiled
graphs are cached in the process, so a later case of the same mode reports ~0 s, and on disk (torch inductor's cache),
so a second run compiles faster than the first.

Equality: from the same state, --check-updates updates on the same batches; every parameter of actor, critic and
the target networks must agree with the reference's within the stated tolerance (compiled kernels round floats
in a different order; Adam divides by sqrt(v), so tiny gradients' rounding is amplified over steps).
"""
from __future__ import annotations

import argparse
import copy
import os
import statistics
import sys
import time
import warnings
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
for _p in ("comper_msgs", "comper_agent", "comper_memory"):
    if str(ROOT / "src" / _p) not in sys.path:
        sys.path.insert(0, str(ROOT / "src" / _p))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from comper_msgs_py.arrays import Transitions  # noqa: E402
from comper_msgs_py.params import config_from_dict  # noqa: E402
from comper_agent.core.comcact import ComcactLearner  # noqa: E402
from comper_agent.core.config import ComcactConfig  # noqa: E402

TASKS = {"Hopper-v4": (11, 3), "InvertedDoublePendulum-v4": (9, 1)}


def parse_args(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tasks", nargs="+", default=list(TASKS), choices=list(TASKS))
    ap.add_argument("--algorithms", nargs="+", default=["ddpg", "comcact"], choices=["ddpg", "comcact"])
    ap.add_argument("--qt-step-gate", action="store_true",
                    help="COMCACT's qt_step_gate on (its check reuses the update's DDPG targets, except in toggle)")
    ap.add_argument("--variants", nargs="+", default=["toggle", "off", "default"],
                    help="toggle, off, default, max-autotune-no-cudagraphs, off@2 (see above)")
    ap.add_argument("--reference", default="toggle", help="the variant the ratios and the equality check use")
    ap.add_argument("--threads", type=int, default=1, help="torch intra-op threads (the nodes' default: 1)")
    ap.add_argument("--updates", type=int, default=200, help="timed updates per variant")
    ap.add_argument("--warmup", type=int, default=30, help="untimed updates first (after the compiling call)")
    ap.add_argument("--check-updates", type=int, default=20, help="updates of the equality check")
    ap.add_argument("--atol", type=float, default=1e-5, help="equality tolerance (absolute) ...")
    ap.add_argument("--rtol", type=float, default=1e-4, help="... and relative, torch.allclose")
    ap.add_argument("--batch", type=int, default=64)
    return ap.parse_args(argv)


def batches(obs: int, act: int, n: int, size: int, seed: int = 0) -> list[tuple[Transitions, np.ndarray]]:
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        out.append((Transitions(
            states=rng.normal(size=(size, obs)).astype(np.float32),
            actions=rng.uniform(-1, 1, size=(size, act)).astype(np.float32),
            rewards=rng.normal(size=size).astype(np.float32),
            next_states=rng.normal(size=(size, obs)).astype(np.float32),
            terminated=rng.random(size) < 0.05, truncated=np.zeros(size, bool)),
            rng.normal(size=size).astype(np.float32)))
    return out


def toggle_update(lrn: ComcactLearner, batch: Transitions) -> None:
    """The eager DDPG update as it was before learner_compile: targets through td_targets, the actor step with
    requires_grad switched off on the critic's weights (same arithmetic as ComcactLearner.update)."""
    s, a, *_ = lrn._tensors(batch)
    y = lrn.td_targets(batch)
    lrn.critic.train()
    loss = torch.mean((lrn.critic(s, a) - y) ** 2)
    lrn.critic_opt.zero_grad(set_to_none=True)
    loss.backward()
    lrn.critic_opt.step()
    lrn.actor.train()
    params = list(lrn.critic.parameters())
    for p in params:
        p.requires_grad_(False)
    try:
        actor_loss = -lrn.critic(s, lrn.actor(s)).mean()
        lrn.actor_opt.zero_grad(set_to_none=True)
        actor_loss.backward()
    finally:
        for p in params:
            p.requires_grad_(True)
    lrn.actor_opt.step()
    lrn.actor.eval()
    lrn.critic.eval()
    lrn.updates += 1


class Variant:
    def __init__(self, name: str, base: ComcactLearner, algorithm: str, threads: int):
        self.name = name
        mode, _, t = name.partition("@")
        self.threads = int(t) if t else threads
        self.toggle = mode == "toggle"
        cfg = base.config if self.toggle else replace(base.config, learner_compile=mode)
        self.lrn = ComcactLearner(cfg, base.obs_dim, base.action_low, base.action_high)
        self.lrn.load_state_dict(copy.deepcopy(base.state_dict()))
        self.comcact = algorithm == "comcact"
        self.times: list[float] = []
        self.first_s = 0.0

    def step(self, batch: Transitions, qt: np.ndarray, base_threads: int) -> float:
        if self.threads != base_threads:
            torch.set_num_threads(self.threads)
        t0 = time.perf_counter()
        if self.toggle:
            toggle_update(self.lrn, batch)
        else:
            self.lrn.update(batch)
        if self.comcact:
            self.lrn.qt_critic_step(batch, qt)
        self.lrn.soft_update()
        dt = time.perf_counter() - t0
        if self.threads != base_threads:
            torch.set_num_threads(base_threads)
        return dt

    def compile_s(self) -> float:
        return sum(r["compile_s"] for r in self.lrn.compile_report().values())

    def fallbacks(self) -> list[str]:
        return [f"{k}: {r['fallback']}" for k, r in self.lrn.compile_report().items() if r["fallback"]]


def max_diff(a: ComcactLearner, b: ComcactLearner, atol: float, rtol: float) -> tuple[float, bool]:
    worst, ok = 0.0, True
    for net in ("actor", "critic", "actor_target", "critic_target"):
        for (k, p), (_, q) in zip(getattr(a, net).state_dict().items(), getattr(b, net).state_dict().items()):
            if not p.dtype.is_floating_point:
                ok &= bool(torch.equal(p, q))
                continue
            worst = max(worst, float((p - q).abs().max()))
            ok &= bool(torch.allclose(p, q, atol=atol, rtol=rtol))
    return worst, ok


def run_case(task: str, algorithm: str, args) -> list[dict]:
    obs, act = TASKS[task]
    cfg = config_from_dict(ComcactConfig, {"variant": algorithm, "seed": 0,
                                           "batch_size": args.batch, "qt_step_gate": args.qt_step_gate})
    base = ComcactLearner(cfg, obs, -np.ones(act, np.float32), np.ones(act, np.float32))
    data = batches(obs, act, 16, args.batch)
    names = list(dict.fromkeys([args.reference] + args.variants))

    # equality: same state, same batches, --check-updates updates (the compiling call included)
    variants = [Variant(n, base, algorithm, args.threads) for n in names]
    for i in range(args.check_updates):
        for v in variants:
            dt = v.step(*data[i % len(data)], args.threads)
            if i == 0:
                v.first_s = dt
    ref = variants[0]
    equal = {v.name: max_diff(ref.lrn, v.lrn, args.atol, args.rtol) for v in variants[1:]}

    # timing, interleaved (the check above was the warm-up's first part)
    for i in range(args.warmup + args.updates):
        for v in variants:
            dt = v.step(*data[i % len(data)], args.threads)
            if i >= args.warmup:
                v.times.append(dt)
    rows = []
    ref_med = statistics.median(ref.times)
    for v in variants:
        t = sorted(v.times)
        med, p90 = 1e3 * statistics.median(t), 1e3 * t[int(0.9 * (len(t) - 1))]
        comp = v.compile_s()
        saving = ref_med * 1e3 - med
        rows.append({"task": task, "algorithm": algorithm, "variant": v.name, "threads": v.threads,
                     "median_ms": med, "p90_ms": p90, "ratio": ref_med * 1e3 / med,
                     "compile_s": comp, "break_even_updates": (comp / (saving / 1e3)) if comp and saving > 0 else None,
                     "max_abs_diff": equal.get(v.name, (0.0, True))[0], "equal": equal.get(v.name, (0.0, True))[1],
                     "fallbacks": v.fallbacks()})
    return rows


def main(argv=None) -> int:
    args = parse_args(argv)
    torch.set_num_threads(args.threads)
    warnings.simplefilter("always", RuntimeWarning)
    print(f"[bench] torch {torch.__version__}, {args.threads} thread(s), batch {args.batch}, "
          f"qt_step_gate {args.qt_step_gate}, "
          f"{args.updates} timed updates after {args.warmup} warm-up, equality after {args.check_updates} updates "
          f"(torch.allclose atol {args.atol:g} rtol {args.rtol:g}), reference {args.reference}; "
          f"load average at start {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs", flush=True)
    rows = []
    t0 = time.monotonic()
    for task in args.tasks:
        for algorithm in args.algorithms:
            got = run_case(task, algorithm, args)
            rows += got
            for r in got:
                be = f"{r['break_even_updates']:.0f}" if r["break_even_updates"] else "-"
                print(f"[bench] {task} {algorithm} {r['variant']}: {r['median_ms']:.2f} ms median, {r['p90_ms']:.2f} p90, "
                      f"x{r['ratio']:.2f}; compile {r['compile_s']:.1f} s (break-even {be} updates); "
                      f"max |diff| {r['max_abs_diff']:.2e} {'EQUAL' if r['equal'] else 'DIFFERENT'}"
                      + (f"; fell back: {r['fallbacks']}" if r["fallbacks"] else ""), flush=True)
    print(f"\n| task | algorithm | variant | threads | median ms | p90 ms | x {args.reference} | compile s "
          f"| break-even updates | max abs diff after {args.check_updates} | equal |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        be = f"{r['break_even_updates']:,.0f}" if r["break_even_updates"] else "-"
        print(f"| {r['task']} | {r['algorithm']} | `{r['variant']}` | {r['threads']} | {r['median_ms']:.2f} "
              f"| {r['p90_ms']:.2f} | {r['ratio']:.2f} | {r['compile_s']:.1f} | {be} | {r['max_abs_diff']:.1e} "
              f"| {'yes' if r['equal'] else 'NO'} |")
    print(f"\n[bench] {time.monotonic() - t0:.0f} s; load average at end {os.getloadavg()[0]:.2f}")
    return 0 if all(r["equal"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
