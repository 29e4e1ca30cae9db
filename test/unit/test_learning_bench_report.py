"""benchmarks/learning_bench.py's report: evaluations an async learner logs just past each grid point count
for that point (they were read as the previous point's, one evaluation late)."""
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
