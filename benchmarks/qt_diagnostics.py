"""Plot the learners' QT diagnostics over runs: what the QT target pulls the value network towards,
against the bootstrap the learner's own networks give, and why (label age, set sizes).

Reads the 'qt_diagnostics' records comcact_node and comper_node write to <run dir>/metrics.jsonl every
`diagnostics_every` updates (docs/comcact.md, docs/comper.md) and draws, per run, against the agent step:
  1. qt_target_rmse (QT target vs the networks' own target on the update's batch: COMCACT's DDPG
     target, COMPER's max_a Q(s', a)) and the TD error on the same batch (critic_td_rmse, td_rmse);
  2. the mean age of the sampled entries (steps since their transition was first stored);
  3. the mean sampled set size and the fraction of sampled entries with more than one member;
  4. (comper_node runs) the share of the batch's states on its most common greedy action and the mean
     max-min Q gap: a policy collapsing onto one action shows here during the run.
It also prints, per run, the medians over the second half of the run (issue #15's target compares
qt_target_rmse with the TD error there), and for COMCACT, from the last 'progress' record, how many QT critic
steps the run took and how many `qt_step_gate` skipped. For comper_node runs with `qt_target_gate`, per half of
the run, the share of recorded batches the gate's test sent to the target network's bootstrap, and where that
test was the default target test, the share the label test would have sent, from the same records (gate_shares);
and per half, the share of all updates the gate sent there, from the progress records' cumulative
qt_gated_share (gated_update_halves).

    python benchmarks/qt_diagnostics.py runs/comcact-Hopper-v4-s0-* --out docs/results/comcact_diagnostics.png
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from comper_agent.nodes.run_io import MetricsLog
from learning_bench import went_on_with   # the benches' rule for a resumed run's records


def read(run: Path) -> tuple[list[dict], dict | None, list[dict]]:
    """One pass over the run's metrics.jsonl: its qt_diagnostics records on the run's final timeline (where a
    resumed run logged again steps its checkpoint had rolled back, the later records replace the earlier ones:
    learning_bench.went_on_with, the benches' rule for evaluations), its last record's learner_updates,
    qt_steps_taken and qt_steps_gated (None if no record has them), and its gated progress records
    (:func:`gated_progress`)."""
    recs = MetricsLog.read(run / "metrics.jsonl")
    diag = went_on_with([r for r in recs if r.get("kind") == "qt_diagnostics"], "step")
    last = next((r for r in reversed(recs) if "qt_steps_taken" in r), None)
    keys = ("learner_updates", "qt_steps_taken", "qt_steps_gated")
    counts = None if last is None else {k: int(last[k]) for k in keys}
    return diag, counts, gated_progress(recs)


def second_half_medians(recs: list[dict]) -> dict:
    if not recs:
        return {}
    last = recs[-1]["step"]
    half = [r for r in recs if r["step"] >= last / 2]
    keys = ("qt_target_rmse", "critic_td_rmse", "td_rmse", "qt_bias", "label_age_mean", "set_size_mean",
            "multi_member_fraction", "greedy_top_share", "q_gap_mean", "v_next_std", "qt_v_corr")
    return {k: float(np.nanmedian([r.get(k, np.nan) for r in half])) for k in keys if k in half[-1]}


def learner_config(run: Path):
    """The comper_node run's learner config (ComperConfig or DQNConfig) from its config.yaml."""
    import yaml
    from comper_agent.core.config import ComperConfig, DQNConfig
    from comper_msgs_py.params import config_from_dict
    learner = yaml.safe_load((run / "config.yaml").read_text())["learner"]
    # runs of earlier versions name parameters the learner no longer has (qt_gate_reference, label_network)
    return config_from_dict(DQNConfig if learner["variant"] == "dqn" else ComperConfig, learner, ignore_unknown=True)


def gate_reference(run: Path) -> str:
    """What the run's qt_target_gate tested QT against: label (V(s'), the only test now) or, for runs of earlier
    versions with qt_gate_reference target, the target network's bootstrap."""
    import yaml
    return yaml.safe_load((run / "config.yaml").read_text())["learner"].get("qt_gate_reference", "label")


def gate_discount(c) -> float:
    """The factor on a COMPER target's bootstrap under learner config `c`: gamma^n_step where the learner
    samples stored n-step windows (ComperConfig.window_rewards), gamma otherwise."""
    return c.gamma ** (c.n_step if c.window_rewards else 1)


def gate_shares(recs: list[dict], discount: float) -> list[dict]:
    """Per half of the run (agent steps before / from half the last record's step): `gated`, the share of the
    records whose batch `qt_target_gate` sent to the target network's bootstrap (qt_gate_on, the run's own
    test), and `label_test`, the share the label test would have sent: RMS of QT(tau) - V(s') > the spread of
    V(s'), estimated as qt_target_rmse / discount > v_next_std. qt_target_rmse is over every row, terminal rows
    counting as agreeing, so where a batch has terminal rows the estimate is a lower bound on that test's
    error. For a run whose own test was the label test (every run of this version) `gated` is that test."""
    recs = [r for r in recs if "qt_gate_on" in r]
    if not recs:
        return []
    half = recs[-1]["step"] / 2
    out = []
    for name, part in (("first half", [r for r in recs if r["step"] < half]),
                       ("second half", [r for r in recs if r["step"] >= half])):
        if part:
            out.append({"part": name, "records": len(part),
                        "gated": float(np.mean([r["qt_gate_on"] for r in part])),
                        "label_test": float(np.mean([r["qt_target_rmse"] / discount > r["v_next_std"]
                                                     for r in part]))})
    return out


def gated_progress(recs: list[dict]) -> list[dict]:
    """Of a run's metrics records, the progress records that carry qt_gated_share (comper_node with
    qt_target_gate), on the run's final timeline (a resumed run's later records replace the rolled-back ones)."""
    return went_on_with([r for r in recs if r.get("kind") == "progress" and "qt_gated_share" in r
                         and r.get("updates")], "step")


def gated_update_halves(progress: list[dict]) -> list[dict]:
    """Per half of the run, the share of all updates (not only the recorded batches) that qt_target_gate sent
    to the target network's bootstrap, from the cumulative counts in the progress records (updates x
    qt_gated_share): up to the record nearest half the last record's step, and from there to the end."""
    if len(progress) < 2:
        return []
    end = progress[-1]
    mid = min(progress[:-1], key=lambda r: abs(r["step"] - end["step"] / 2))
    g_mid, g_end = (round(r["updates"] * r["qt_gated_share"]) for r in (mid, end))   # whole updates
    out = [{"part": "first half", "to_step": mid["step"], "updates": mid["updates"], "gated": g_mid / mid["updates"]}]
    if end["updates"] > mid["updates"]:
        out.append({"part": "second half", "to_step": end["step"], "updates": end["updates"] - mid["updates"],
                    "gated": (g_end - g_mid) / (end["updates"] - mid["updates"])})
    return out


def td_error(rec: dict) -> float:
    """The TD error of the record's learner: COMCACT's critic, COMPER's Q-network."""
    return rec["critic_td_rmse"] if "critic_td_rmse" in rec else rec["td_rmse"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path, help="run directories of comcact_node or comper_node")
    ap.add_argument("--out", type=Path, default=Path("qt_diagnostics.png"), help="the figure to write")
    args = ap.parse_args(argv)
    runs = {r.name: r for r in args.runs}
    data = {r.name: read(r) for r in args.runs if (r / "metrics.jsonl").exists()}
    data = {k: v for k, v in data.items() if v[0]}
    if not data:
        print("no qt_diagnostics records in these runs (comcact_node or comper_node with a QT target and "
              "diagnostics_every > 0)", file=sys.stderr)
        return 1
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    policy = any("greedy_top_share" in recs[0] for recs, _, _ in data.values())
    fig, axes = plt.subplots(1, 4 if policy else 3, figsize=(20 if policy else 15, 4))
    for i, (name, (recs, counts, progress)) in enumerate(sorted(data.items())):
        col = f"C{i}"
        step = [r["step"] for r in recs]
        axes[0].plot(step, [r["qt_target_rmse"] for r in recs], color=col, label=f"{name}: QT vs own target")
        axes[0].plot(step, [td_error(r) for r in recs], color=col, ls="--", label=f"{name}: TD error")
        axes[1].plot(step, [r["label_age_mean"] for r in recs], color=col, label=name)
        axes[2].plot(step, [r["set_size_mean"] for r in recs], color=col, label=f"{name}: members per entry")
        axes[2].plot(step, [r["multi_member_fraction"] for r in recs], color=col, ls=":",
                     label=f"{name}: fraction with > 1 member")
        if "greedy_top_share" in recs[0]:
            axes[3].plot(step, [r["greedy_top_share"] for r in recs], color=col, label=f"{name}: top greedy share")
            axes[3].plot(step, [r["q_gap_mean"] for r in recs], color=col, ls=":", label=f"{name}: max-min Q")
        med = second_half_medians(recs)
        print(f"{name}: second half medians " + ", ".join(f"{k} {v:.3g}" for k, v in med.items()))
        if "qt_gate_on" in recs[-1]:
            c, ref = learner_config(runs[name]), gate_reference(runs[name])
            for g in gate_shares(recs, gate_discount(c)):
                other = f", the label test would have gated {g['label_test']:.0%}" if ref == "target" else ""
                print(f"{name}: {g['part']}, {g['records']} records: the {ref} test gated {g['gated']:.0%}{other}")
            for g in gated_update_halves(progress):
                print(f"{name}: {g['part']} (to step {g['to_step']}), {g['updates']} updates: the "
                      f"{ref} test gated {g['gated']:.0%} of the updates")
        if counts:
            print(f"{name}: {counts['qt_steps_taken']} QT steps in {counts['learner_updates']} updates, "
                  f"{counts['qt_steps_gated']} skipped by qt_step_gate")
    axes[0].set(title="RMS distance on the update's batch", xlabel="agent step", yscale="log")
    axes[1].set(title="age of the sampled entries (steps)", xlabel="agent step")
    axes[2].set(title="sampled set sizes", xlabel="agent step")
    if policy:
        axes[3].set(title="greedy actions on the batch (comper_node)", xlabel="agent step")
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
