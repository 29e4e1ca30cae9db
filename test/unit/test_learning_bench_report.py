"""benchmarks/learning_bench.py's report: evaluations an async learner logs just past each grid point count
for that point (they were read as the previous point's, one evaluation late); the last-k-evaluations column
averages each run's last k grid evaluations and leaves out a run that lacks one; a run resumed over several
sessions is read as its last session saw it."""
from scaffolding import load_benchmark


def _bench():
    return load_benchmark("learning_bench")


def test_async_evaluation_steps_land_on_their_grid_point():
    b = _bench()
    evals = [[0, 20.0, 1.0], [5004, 40.0, 1.0], [10019, 60.0, 1.0], [24990, 70.0, 1.0], [25024, 90.0, 1.0],
             [27000, 95.0, 1.0], [50000, 100.0, 1.0]]
    grid = b.on_grid(evals, 5000)
    assert grid == [(0, 20.0), (5000, 40.0), (10000, 60.0), (24990, 70.0), (25000, 90.0), (27000, 95.0),
                    (50000, 100.0)]
    at = lambda x: b.at_step([{"step": s, "mean_return": r} for s, r in grid], x)["mean_return"]
    assert (at(10000), at(25000), at(50000)) == (60.0, 90.0, 100.0)


def test_the_return_at_a_budget_is_the_evaluation_at_it_not_the_one_after_the_last_episode():
    """comper_node evaluates at its budget and once more when the episode in progress has finished (50,248 here):
    both land on the 50,000 grid point, and the return at 50,000 is the first (a CartPole run once read 70 for 500)."""
    lb = _bench()
    evals = [[45_000, 480.0], [50_000, 500.0], [50_248, 70.0]]
    assert lb.return_at(evals, 50_000, 5_000) == 500.0 and lb.return_at(evals, 45_000, 5_000) == 480.0


def test_final_mean_averages_the_last_grid_evaluations_and_needs_all_of_them():
    b = _bench()
    evals = [[st, float(st // 5000), 0.0] for st in range(0, 50001, 5000)]       # return = index of the evaluation
    assert b.final_mean(evals, 5000, 50000, 3) == 9.0                           # (8 + 9 + 10) / 3
    assert b.final_mean(evals, 5000, 50000, 1) == 10.0
    async_evals = [[0, 0.0, 0.0], [40012, 8.0, 0.0], [45003, 9.0, 0.0], [50000, 10.0, 0.0]]
    assert b.final_mean(async_evals, 5000, 50000, 3) == 9.0                     # just past a grid point counts
    assert b.final_mean(evals[:-1], 5000, 50000, 3) is None                     # ended at 45,000: no value
    assert b.final_mean(evals, 5000, 50000, 0) is None


def test_a_resumed_run_keeps_its_last_sessions_evaluations_and_sums_its_sessions_time():
    b = _bench()
    # killed after its evaluation at 15,000 with its last checkpoint at 10,000: the second session evaluates
    # 15,000 again from the checkpoint's weights, and that record is the one the run went on from
    logged = [{"step": st, "mean_return": r} for st, r in
              [(0, 1.0), (5000, 2.0), (10000, 3.0), (15000, 4.0), (15000, 40.0), (20000, 50.0)]]
    assert [(e["step"], e["mean_return"]) for e in b.resumed_evals(logged)] == \
        [(0, 1.0), (5000, 2.0), (10000, 3.0), (15000, 40.0), (20000, 50.0)]
    rewound = logged[:4] + [{"step": 10000, "mean_return": 30.0}]              # resumed from 5,000
    assert [e["mean_return"] for e in b.resumed_evals(rewound)] == [1.0, 2.0, 30.0]
    one = {"elapsed_s": 100.0, "steps": 1000, "steps_per_s": 10.0, "phases": {"learner": {"seconds": 60.0, "calls": 900}}}
    assert b.run_timers([one]) is one and b.run_timers([]) is None
    two = {"elapsed_s": 300.0, "steps": 2000, "steps_per_s": 6.7, "phases": {"learner": {"seconds": 200.0, "calls": 1900},
                                                                           "qt": {"seconds": 50.0, "calls": 4}}}
    merged = b.run_timers([one, two])
    assert (merged["elapsed_s"], merged["steps"], merged["steps_per_s"], merged["sessions"]) == (400.0, 3000, 7.5, 2)
    assert merged["phases"] == {"learner": {"seconds": 260.0, "calls": 2800}, "qt": {"seconds": 50.0, "calls": 4}}


def test_difference_to_a_baseline_resamples_each_algorithm_on_its_own_and_says_above_only_when_0_is_out():
    import numpy as np
    b = _bench()
    base = [100.0, 110.0, 90.0, 105.0, 95.0]
    far = [200.0, 210.0, 190.0]
    d = b.difference(far, base)
    assert d["diff"] == np.mean(far) - np.mean(base) == 100.0
    assert d["verdict"] == "above" and d["ci95"][0] <= 100.0 <= d["ci95"][1] and (d["n"], d["n_baseline"]) == (3, 5)
    assert b.difference(base, far)["verdict"] == "below"
    # overlapping groups: the interval straddles 0
    assert b.difference([90.0, 120.0, 95.0, 115.0], base)["verdict"] == "not separated"
    # a baseline of one run adds no spread: the interval is the other group's bootstrap interval shifted by it
    lo, hi = b.bootstrap_diff_ci(far, [150.0])
    blo, bhi = b.bootstrap_ci(far)
    assert abs(lo - (blo - 150.0)) < 5.0 and abs(hi - (bhi - 150.0)) < 5.0
    # identical constant groups: a zero-width interval at 0, not a difference
    assert b.difference([5.0, 5.0], [5.0, 5.0, 5.0]) == {"diff": 0.0, "ci95": [0.0, 0.0], "verdict": "not separated",
                                                         "n": 2, "n_baseline": 3}


def test_the_difference_table_reads_the_main_tables_per_seed_values_for_each_task_with_the_baseline():
    from types import SimpleNamespace
    b = _bench()
    args = SimpleNamespace(baseline="ddpg", final_evals=3, tasks=["T-v4", "U-v4"], algorithms=["ddpg", "comcact"])
    cell = lambda vals: {"values": vals}
    table = {"T-v4/ddpg": {"50000": cell([1.0, 2.0, 3.0]), "final": cell([1.0, 2.0, 3.0])},
             "T-v4/comcact": {"50000": cell([11.0, 12.0, 13.0]), "final": cell([0.0, 2.0, 4.0])},
             "U-v4/comcact": {"50000": cell([5.0])}}                     # no baseline on U-v4: no row
    lines, out = b.difference_table(args, table, [50000])
    assert list(out) == ["T-v4/comcact"]
    assert out["T-v4/comcact"]["50000"]["diff"] == 10.0 and out["T-v4/comcact"]["50000"]["verdict"] == "above"
    assert out["T-v4/comcact"]["final"]["diff"] == 0.0 and out["T-v4/comcact"]["final"]["verdict"] == "not separated"
    assert lines[-1].startswith("| T-v4 | comcact | 3 / 3 | +10.0 [") and "not separated" in lines[-1]
