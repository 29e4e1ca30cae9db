"""Plot COMCACT's QT diagnostics over runs: what the QT step pulls the critic towards, against the DDPG
step's own target, and why (label age, set sizes).

Reads the 'qt_diagnostics' records comcact_node writes to <run dir>/metrics.jsonl every
`diagnostics_every` updates (docs/comcact.md) and draws, per run, against the agent step:
  1. qt_target_rmse (QT target vs DDPG target on the update's batch) and critic_td_rmse (the
     critic's own TD error on the same batch);
  2. the mean label age of the sampled RTM entries (steps since their representative was stored);
  3. the mean sampled set size and the fraction of sampled entries with more than one member.
It also prints, per run, the medians over the second half of the run (the issue's target compares
qt_target_rmse with critic_td_rmse there), and from the last 'progress' record how many QT critic steps the
run took and how many `qt_step_gate` skipped.

    python benchmarks/comcact_diagnostics.py runs/comcact-Hopper-v4-s0-* --out docs/results/comcact_diagnostics.png
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def read(run: Path) -> tuple[list[dict], dict | None]:
    """The run's qt_diagnostics records, and its last progress record's learner_updates, qt_steps_taken and
    qt_steps_gated (None if no progress record has them)."""
    out, last = [], None
    with open(run / "metrics.jsonl") as f:
        for line in f:
            if '"qt_diagnostics"' in line:
                rec = json.loads(line)
                if rec.get("kind") == "qt_diagnostics":
                    out.append(rec)
            elif '"qt_steps_taken"' in line:
                last = json.loads(line)
    keys = ("learner_updates", "qt_steps_taken", "qt_steps_gated")
    counts = None if last is None else {k: int(last[k]) for k in keys}
    return out, counts


def second_half_medians(recs: list[dict]) -> dict:
    if not recs:
        return {}
    last = recs[-1]["step"]
    half = [r for r in recs if r["step"] >= last / 2]
    keys = ("qt_target_rmse", "critic_td_rmse", "label_age_mean", "set_size_mean", "multi_member_fraction")
    return {k: float(np.median([r[k] for r in half])) for k in keys}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path, help="run directories of comcact_node")
    ap.add_argument("--out", type=Path, default=Path("comcact_diagnostics.png"), help="the figure to write")
    args = ap.parse_args(argv)
    data = {r.name: read(r) for r in args.runs if (r / "metrics.jsonl").exists()}
    data = {k: v for k, v in data.items() if v[0]}
    if not data:
        print("no qt_diagnostics records in these runs (comcact_node with diagnostics_every > 0)", file=sys.stderr)
        return 1
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    for i, (name, (recs, counts)) in enumerate(sorted(data.items())):
        col = f"C{i}"
        step = [r["step"] for r in recs]
        axes[0].plot(step, [r["qt_target_rmse"] for r in recs], color=col, label=f"{name}: QT vs DDPG target")
        axes[0].plot(step, [r["critic_td_rmse"] for r in recs], color=col, ls="--", label=f"{name}: critic TD error")
        axes[1].plot(step, [r["label_age_mean"] for r in recs], color=col, label=name)
        axes[2].plot(step, [r["set_size_mean"] for r in recs], color=col, label=f"{name}: members per entry")
        axes[2].plot(step, [r["multi_member_fraction"] for r in recs], color=col, ls=":",
                     label=f"{name}: fraction with > 1 member")
        med = second_half_medians(recs)
        print(f"{name}: second half medians " + ", ".join(f"{k} {v:.3g}" for k, v in med.items()))
        if counts:
            print(f"{name}: {counts['qt_steps_taken']} QT steps in {counts['learner_updates']} updates, "
                  f"{counts['qt_steps_gated']} skipped by qt_step_gate")
    axes[0].set(title="RMS distance on the update's batch", xlabel="agent step", yscale="log")
    axes[1].set(title="label age of sampled RTM entries (steps)", xlabel="agent step")
    axes[2].set(title="sampled set sizes", xlabel="agent step")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
