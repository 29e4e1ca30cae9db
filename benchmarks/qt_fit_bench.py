#!/usr/bin/env python3
"""Time of one QT training round (QTModel.fit + predict, what the QT trainer does per reduction) on
Atari-sized keys, the current implementation against the one before its two memory fixes, in one run
(docs/comper.md, "Speed").

    python benchmarks/qt_fit_bench.py                         # 1,784 sets of 4-frame keys (data_efficient profile)
    python benchmarks/qt_fit_bench.py --sets 1000 --frames 1  # the thesis profile's single frame

The keys are random 84x84 uint8 frames scaled by 1/255 (s and s', 4 frames each: 56,450 values) and the label
histories random; QT is the Table 37 network with its Table 33 RMSprop, 1 torch thread. Variants, alternated
round by round so that a load that comes and goes hits both alike:

  before        torch.optim.RMSprop (a new sqrt tensor per parameter per step: QT's 14.5M first-layer weights
                are re-allocated and page-faulted 112 times per round) and the scaler's moments taken on a
                float64 copy of all keys (800 MB with its temporaries)
  sqrt_buffer   QT's RMSprop with a kept sqrt buffer and the moments summed row by row (same values,
                unit-tested), the first layer's weight gradient a new tensor per backward pass
  now           also the first layer's weight gradient written into a kept buffer (NativeLSTM, _KeptWeightGrad;
                same values, unit-tested)
  compiled      now with qt_compile default: the first layer's RMSprop update through torch.compile, one fused
                pass (equal to the eager step up to float rounding, unit-tested; its predictions are compared
                to now's with a tolerance instead of bit for bit; its first round includes the compilation)

Each row: median seconds per round over --rounds rounds; the ratio is before over the variant. All variants start from
the same network and see the same data, and their predictions after the rounds must be equal.

``--from-transitions`` times the round as the QT trainer runs it instead (reduction_predictor on a lease of uint8
frames: the keys are built from the transitions inside the round), for two variants of the current code, eager:

  whole         the keys built by a cast, a scaled copy and a concatenation (three new arrays), the whole scaled input
                built at once for fit and a new one per prediction chunk (QTModel.kept_buffers False)
  kept          the keys written in place into a kept buffer, each mini-batch scaled when drawn, predictions scaled
                into a kept buffer (the default)

    python benchmarks/qt_fit_bench.py --from-transitions --sets 3300   # a 10-step data_efficient reduction
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time

import numpy as np
import torch

from comper_agent.core import qt as qt_mod
from comper_agent.core.config import QTConfig
from comper_agent.core.qt import QTModel


class _MomentsBefore(qt_mod._Moments):
    @staticmethod
    def batch_moments(x):
        x = np.asarray(x, np.float64)
        mb = x.mean(axis=0)
        return mb, ((x - mb) ** 2).sum(axis=0)


def build(variant: str, key_dim: int) -> QTModel:
    m = QTModel(QTConfig(qt_compile="default" if variant == "compiled" else "off"), key_dim=key_dim)
    if variant != "now":
        m.net.lstms[0].keep_grad_min_numel = float("inf")      # autograd's fresh gradient tensor
    if variant == "before":
        c = m.config
        m.optimizer = torch.optim.RMSprop(m.net.parameters(), lr=c.qt_lr, alpha=c.qt_rms_alpha, eps=c.qt_rms_eps,
                                          momentum=c.qt_rms_momentum)
        m._in, m._lab = _MomentsBefore(key_dim), _MomentsBefore(1)
    return m


def print_table(title: str, times: dict[str, list[float]], base: str) -> None:
    """Median seconds per round of each variant and the ratio base / variant, as a markdown table."""
    med = {v: statistics.median(t) for v, t in times.items()}
    print(f"\n{title}\n| variant | s per round (median) | {base} / variant |\n|---|---|---|")
    for v in times:
        print(f"| {v} | {med[v]:.2f} | {med[base] / med[v]:.2f}x |")


def _keys_before(t, frame_scale=1.0 / 255.0):
    """transition_keys as it was: each part cast (and scaled) into a new array, then concatenated."""
    def part(obs):
        flat = obs.reshape(len(t), -1)
        return flat.astype(np.float32) * np.float32(frame_scale) if flat.dtype == np.uint8 else flat
    a = np.asarray(t.actions).reshape(len(t), -1).astype(np.float32)
    return np.concatenate([part(t.states), a, np.asarray(t.rewards, np.float32)[:, None], part(t.next_states)], axis=1)


def from_transitions(args) -> int:
    from types import SimpleNamespace

    from comper_msgs_py.arrays import Transitions
    rng = np.random.default_rng(0)
    m, shape = args.sets, (args.sets, args.frames, 84, 84)
    reps = Transitions(rng.integers(0, 256, size=shape, dtype=np.uint8), rng.integers(0, 18, size=m),
                       np.sign(rng.normal(size=m)).astype(np.float32), rng.integers(0, 256, size=shape, dtype=np.uint8),
                       np.zeros(m, bool), np.zeros(m, bool))
    lengths = rng.integers(1, 12, size=m)
    lease = SimpleNamespace(representatives=reps, label_history=rng.normal(size=int(lengths.sum())).astype(np.float32),
                            history_lengths=lengths, counts=lengths.copy())
    key_dim = 2 * args.frames * 84 * 84 + 2
    models = {v: QTModel(QTConfig(), key_dim=key_dim) for v in ("whole", "kept")}
    models["whole"].kept_buffers = False
    key_fn = {"whole": _keys_before, "kept": qt_mod.default_key_fn}
    times: dict[str, list[float]] = {v: [] for v in models}
    preds = {}
    for r in range(args.rounds):
        for v, model in models.items():
            t = time.perf_counter()
            preds[v] = qt_mod.reduction_predictor(model, key_fn=key_fn[v])(lease)
            times[v].append(time.perf_counter() - t)
        print(f"round {r + 1}: " + ", ".join(f"{v} {times[v][-1]:.2f} s" for v in models), flush=True)
    same = np.array_equal(preds["whole"], preds["kept"])
    print_table(f"{m} sets of {args.frames}-frame transitions (key {key_dim} values), {args.rounds} rounds, 1 torch "
                "thread", times, "whole")
    print(f"predictions of the last round equal: {same}; kept buffers "
          f"{(models['kept'].key_rows.nbytes + models['kept']._input_rows.nbytes) / 1e6:.0f} MB")
    return 0 if same else 1


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sets", type=int, default=1784, help="sets per round (1,784: a data_efficient Freeway reduction)")
    ap.add_argument("--frames", type=int, default=4, help="frames per observation (key: 2 x frames x 7,056 + 2)")
    ap.add_argument("--rounds", type=int, default=3, help="training rounds per variant")
    ap.add_argument("--from-transitions", action="store_true",
                    help="time the trainer's round from uint8 transitions: whole inputs against kept buffers")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    if args.from_transitions:
        return from_transitions(args)
    key_dim = 2 * args.frames * 84 * 84 + 2
    rng = np.random.default_rng(0)
    keys = rng.integers(0, 256, size=(args.sets, key_dim), dtype=np.uint8).astype(np.float32) / 255.0
    lengths = rng.integers(1, 12, size=args.sets)
    hist = rng.normal(size=int(lengths.sum())).astype(np.float32)
    models = {v: build(v, key_dim) for v in ("before", "sqrt_buffer", "now", "compiled")}
    times: dict[str, list[float]] = {v: [] for v in models}
    for r in range(args.rounds):
        for v, m in models.items():
            t = time.perf_counter()
            m.fit(keys, hist, lengths)
            m.predict(keys, hist, lengths)
            times[v].append(time.perf_counter() - t)
        print(f"round {r + 1}: " + ", ".join(f"{v} {times[v][-1]:.2f} s" for v in models), flush=True)
    preds = {v: m.predict(keys, hist, lengths) for v, m in models.items()}
    same = all(np.array_equal(preds["before"], preds[v]) for v in ("sqrt_buffer", "now"))
    close = np.allclose(preds["compiled"], preds["now"], rtol=1e-3, atol=1e-3 * float(np.abs(preds["now"]).max()))
    print_table(f"{args.sets} sets, key {key_dim} values, {args.rounds} rounds, 1 torch thread", times, "before")
    print(f"predictions after the rounds equal (before, sqrt_buffer, now): {same}; compiled within 1e-3 of now: "
          f"{close} (max abs difference {float(np.abs(preds['compiled'] - preds['now']).max()):.2e}); "
          f"compile: {models['compiled'].optimizer.compile_report()}")
    return 0 if same and close else 1


if __name__ == "__main__":
    sys.exit(main())
