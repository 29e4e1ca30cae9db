"""benchmarks/learning_bench.py's report: evaluations an async learner logs just past each grid point count
for that point (they were read as the previous point's, one evaluation late); the last-k-evaluations column
averages each run's last k grid evaluations and leaves out a run that lacks one."""
import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _bench():
    spec = importlib.util.spec_from_file_location("learning_bench", ROOT / "benchmarks" / "learning_bench.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


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
