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
