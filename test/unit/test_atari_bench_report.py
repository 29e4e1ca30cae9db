"""benchmarks/atari_bench.py --report-only: --games and --variants select the table's rows and the curves, for the
runs of --out and the runs joined with --include alike (the docs' report commands name the variants they show
from per-run files that hold more)."""
import json

from scaffolding import load_benchmark


def _record(game: str, variant: str, seed: int, returns: list[float]) -> dict:
    frames = [1000 * (i + 1) for i in range(len(returns))]
    return {"run_id": f"{variant}-{game}-s{seed}", "game": game, "variant": variant, "seed": seed,
            "frames": frames[-1], "steps": frames[-1] // 4, "episodes": len(returns), "wall_time_s": 60.0,
            "complete": True, "episode_returns": returns, "episode_frames": frames}


def test_games_and_variants_select_the_rows_of_included_runs(tmp_path):
    bench = load_benchmark("atari_bench")
    include = tmp_path / "runs.json"
    include.write_text(json.dumps([_record(g, v, s, [float(10 * s + k) for k in range(12)])
                                   for g in ("Freeway", "Seaquest") for v in ("dqn", "comper", "dqn_n10")
                                   for s in (0, 1)]))
    out = tmp_path / "report"
    assert bench.main(["--out", str(out), "--report-only", "--games", "Seaquest", "--variants", "dqn", "dqn_n10",
                       "--variant", "dqn_n10=dqn:n_step=10", "--include", str(include)]) == 0
    rows = json.loads((out / "table.json").read_text())
    assert sorted((r["game"], r["variant"], tuple(r["seeds"])) for r in rows) == [
        ("Seaquest", "dqn", (0, 1)), ("Seaquest", "dqn_n10", (0, 1))]
    assert [p.name for p in out.glob("curve_*.png")] == ["curve_Seaquest.png"]
    # runs.json keeps every run it read, so a later report can select others from it
    assert len(json.loads((out / "runs.json").read_text())) == 12

    everything = tmp_path / "all"
    bench.main(["--out", str(everything), "--report-only", "--games", "Freeway", "Seaquest",
                "--variants", "comper", "dqn", "dqn_n10", "--variant", "dqn_n10=dqn:n_step=10",
                "--include", str(include)])
    assert len(json.loads((everything / "table.json").read_text())) == 6
