"""benchmarks/qt_diagnostics.py's gate_shares: per half of a run, the share of recorded batches that
qt_target_gate sent to the target network (its records' qt_gate_on) and the share the label test
(qt_gate_reference label) would have sent, from qt_target_rmse / discount against v_next_std."""
from __future__ import annotations

import pytest

from scaffolding import load_benchmark


def test_gate_shares_split_the_run_in_halves_and_apply_the_label_test_to_each_record():
    diag = load_benchmark("qt_diagnostics")
    d = 0.99 ** 10
    recs = [  # step, qt_gate_on, qt_target_rmse, v_next_std
        {"step": 100, "qt_gate_on": 1.0, "qt_target_rmse": 0.02 * d, "v_next_std": 0.01},   # label test: on
        {"step": 200, "qt_gate_on": 1.0, "qt_target_rmse": 0.005 * d, "v_next_std": 0.01},  # off
        {"step": 300, "qt_gate_on": 0.0, "qt_target_rmse": 0.011 * d, "v_next_std": 0.01},  # on
        {"step": 400, "qt_gate_on": 1.0, "qt_target_rmse": 0.009 * d, "v_next_std": 0.01},  # off
    ]
    out = diag.gate_shares(recs, d)
    assert [g["part"] for g in out] == ["first half", "second half"]
    assert [g["records"] for g in out] == [1, 3]                  # half = step 200: 100 | 200, 300, 400
    assert out[0]["gated"] == 1.0 and out[0]["label_test"] == 1.0
    assert out[1]["gated"] == pytest.approx(2 / 3) and out[1]["label_test"] == pytest.approx(1 / 3)
    assert diag.gate_shares([{"step": 1, "qt_target_rmse": 0.1, "v_next_std": 0.0}], d) == []   # no gate


def test_gate_discount_is_gamma_to_the_windows_length_for_comper_variants(tmp_path):
    diag = load_benchmark("qt_diagnostics")
    for alg, n, want in (("comper", 10, 0.99 ** 10), ("comper", 1, 0.99), ("dqn", 10, 0.99)):
        (tmp_path / "config.yaml").write_text(f"algorithm: {alg}\nlearner:\n  gamma: 0.99\n  n_step: {n}\n"
                                              f"  variant: {alg}\n")
        assert diag.gate_discount(diag.learner_config(tmp_path)) == pytest.approx(want)


def test_gated_update_halves_split_the_cumulative_counts_on_the_runs_final_timeline(tmp_path):
    """Progress records carry the cumulative share; the halves come from updates x share at the record nearest
    half the last step and at the end. A resumed run's re-written steps replace the rolled-back records, the
    diagnostics records' as well as the progress records'."""
    import json
    diag = load_benchmark("qt_diagnostics")
    rows = [  # step, updates, cumulative share
        (100, 100, 0.9), (200, 200, 0.8), (300, 300, 0.6),
        (250, 250, 0.7),                                  # resumed from a checkpoint at step 240: 300 rolled back
        (400, 400, 0.5),
    ]
    lines = [json.dumps({"kind": "progress", "step": s, "updates": u, "qt_gated_share": g}) for s, u, g in rows]
    for at, step in ((4, 260), (3, 280), (1, 150)):   # 280 logged before the resume, rolled back by it
        lines.insert(at, json.dumps({"kind": "qt_diagnostics", "step": step, "qt_gate_on": 1.0}))
    (tmp_path / "metrics.jsonl").write_text("\n".join(lines) + "\n")
    diagnostics, counts, progress = diag.read(tmp_path)
    assert [r["step"] for r in progress] == [100, 200, 250, 400]
    assert [r["step"] for r in diagnostics] == [150, 260] and counts is None
    first, second = diag.gated_update_halves(progress)
    assert first["to_step"] == 200 and first["updates"] == 200 and first["gated"] == pytest.approx(0.8)
    # gated updates: 160 by step 200, 200 by step 400 -> 40 of the second half's 200
    assert second["updates"] == 200 and second["gated"] == pytest.approx(0.2)
    assert diag.gated_update_halves(progress[:1]) == []
