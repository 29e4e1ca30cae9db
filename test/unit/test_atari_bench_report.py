"""benchmarks/atari_bench.py --report-only: --games and --variants select the table's rows and the curves, for the
runs of --out and the runs joined with --include alike (the docs' report commands name the variants they show
from per-run files that hold more)."""
import json

import numpy as np

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

    # --report-seeds: the same seeds for every row (a variant run on fewer seeds against the others)
    same = tmp_path / "same"
    bench.main(["--out", str(same), "--report-only", "--games", "Freeway", "--variants", "dqn", "comper",
                "--include", str(include), "--report-seeds", "1"])
    assert sorted((r["variant"], tuple(r["seeds"])) for r in json.loads((same / "table.json").read_text())) == [
        ("comper", (1,)), ("dqn", (1,))]


def test_an_unfinished_runs_curve_stops_where_the_run_stopped_and_its_row_says_so(tmp_path):
    """A report made while a run is under way (a long run continued over sessions) drew the run's last episode
    as a flat line up to the whole budget, as if it had been played."""
    bench = load_benchmark("atari_bench")
    grid = np.linspace(0, 400_000, 101)
    y = bench.curve_on_grid(grid, [10_000, 100_000, 150_000], [50.0, 150.0, 250.0], reached=154_000)
    assert np.isnan(y[grid < 10_000]).all() and np.isnan(y[grid > 154_000]).all()
    assert y[grid == 100_000] == 150.0 and (y[(grid >= 150_000) & (grid <= 154_000)] == 250.0).all()
    # a complete run holds its last episode up to the frames it reached, the episode under way at the end
    done = bench.curve_on_grid(grid, [10_000, 396_000], [50.0, 300.0], reached=403_259)
    assert done[-1] == 300.0

    runs = [_record("Seaquest", "dqn_n10", 1, [float(k) for k in range(30)]),
            {**_record("Seaquest", "comper_n10", 1, [float(k) for k in range(12)]), "complete": False}]
    include = tmp_path / "runs.json"
    include.write_text(json.dumps(runs))
    out = tmp_path / "report"
    bench.main(["--out", str(out), "--report-only", "--games", "Seaquest", "--variants", "comper_n10", "dqn_n10",
                "--variant", "comper_n10=comper:n_step=10", "--variant", "dqn_n10=dqn:n_step=10",
                "--include", str(include)])
    table = (out / "table.md").read_text()
    assert "| Seaquest | comper_n10 | 1 (1 unfinished) |" in table and "| Seaquest | dqn_n10 | 1 |" in table


def test_episodes_of_steps_played_again_after_a_resume_are_dropped(tmp_path):
    """The 400,000-frame COMPER run: its checkpoint at step 7,500 held 13 episodes; the session stopped later had
    logged episodes 13 and 14 (ending at steps 7,613 and 7,987), and the resumed session played steps 7,500+ again
    and logged its own episodes 13 and 14 (ending at 8,221 and 8,755). Only the second pair is the run's."""
    bench = load_benchmark("atari_bench")
    run = tmp_path / "runs" / "comper_n10-Seaquest-s1"
    run.mkdir(parents=True)
    logged = [(k, 500 * (k + 1), float(k)) for k in range(13)]
    logged += [(13, 7613, 300.0), (14, 7987, 60.0), (13, 8221, 240.0), (14, 8755, 160.0), (15, 9000, 10.0)]
    with open(run / "metrics.jsonl", "w") as f:
        for k, step, ret in logged:
            f.write(json.dumps({"kind": "episode", "source": "train", "episode": k, "step": step,
                                "frames": 5 * step, "ret": ret}) + "\n")
        f.write(json.dumps({"kind": "progress", "step": 9000}) + "\n")
    (run / "summary.json").write_text(json.dumps({
        "env_id": "ALE/Seaquest-v5", "seed": 1, "protocol": {}, "frames": 45000, "steps": 9000,
        "wall_time_s": 100.0, "complete": False}))
    rec = bench.run_record(run / "summary.json")
    assert rec["episode_returns"] == [float(k) for k in range(13)] + [240.0, 160.0, 10.0]
    assert rec["episode_frames"][-3:] == [41105, 43775, 45000]


def test_the_baseline_table_gives_each_variants_difference_with_its_interval(tmp_path):
    """--baseline: per game, each variant's last-10 mean minus the baseline's, with learning_bench's independent
    two-group bootstrap interval of the difference; above / below only where the interval excludes 0."""
    bench = load_benchmark("atari_bench")
    learning = load_benchmark("learning_bench")
    last = {("comper_n10", "Asterix"): [330.0, 435.0, 395.0, 470.0, 355.0],
            ("dqn_n10", "Asterix"): [290.0, 425.0, 315.0, 245.0, 320.0],
            ("comper_n10", "Seaquest"): [210.0, 206.0, 162.0], ("dqn_n10", "Seaquest"): [122.0, 220.0, 178.0]}
    include = tmp_path / "runs.json"   # 30 episodes each, all at the run's value: its last 10 mean is that value
    include.write_text(json.dumps([_record(g, v, s, [x] * 30) for (v, g), xs in last.items()
                                   for s, x in enumerate(xs)]))
    out = tmp_path / "report"
    assert bench.main(["--out", str(out), "--report-only", "--games", "Asterix", "Seaquest", "--variants",
                       "comper_n10", "dqn_n10", "--variant", "comper_n10=comper:n_step=10", "--variant",
                       "dqn_n10=dqn:n_step=10", "--include", str(include), "--baseline", "dqn_n10"]) == 0
    diffs = {d["game"]: d for d in json.loads((out / "differences.json").read_text())}
    assert set(diffs) == {"Asterix", "Seaquest"} and all(d["variant"] == "comper_n10" for d in diffs.values())
    for game, d in diffs.items():
        want = learning.difference(last[("comper_n10", game)], last[("dqn_n10", game)])
        assert d["diff"] == want["diff"] and d["ci95"] == want["ci95"] and d["verdict"] == want["verdict"]
    assert diffs["Asterix"]["diff"] == 78.0 and diffs["Asterix"]["verdict"] == "above"
    assert diffs["Seaquest"]["verdict"] == "not separated"
    assert "| Asterix | comper_n10 | 5 / 5 | +78.0 [" in (out / "table.md").read_text()
    try:
        bench.main(["--out", str(out), "--report-only", "--variants", "comper", "--baseline", "dqn"])
    except SystemExit as exc:
        assert exc.code == 2
    else:
        raise AssertionError("a baseline outside --variants must be refused")


def test_runs_are_tested_against_random_plays_spread_not_its_point(tmp_path):
    """--reference: the random-play row shows its mean with the interval over its episodes, and each variant's
    difference to random play has learning_bench's two-group interval (the variant's seeds, random play's
    episodes): a mean above random play's mean is 'above' only where that interval excludes 0."""
    bench = load_benchmark("atari_bench")
    learning = load_benchmark("learning_bench")
    rng = np.random.default_rng(3)
    random_play = [float(x) for x in 50.0 * rng.integers(2, 10, size=200)]   # Asterix-like: multiples of 50
    reference = tmp_path / "constant-actions.json"
    reference.write_text(json.dumps({"Asterix": {"NOOP": [200.0] * 3, "UP": [650.0] * 3, "random": random_play}}))
    last = {"far": [400.0, 420.0, 440.0], "near": [250.0, 330.0, 390.0]}
    include = tmp_path / "runs.json"
    include.write_text(json.dumps([_record("Asterix", v, s, [x] * 30) for v, xs in last.items()
                                   for s, x in enumerate(xs)]))
    out = tmp_path / "report"
    assert bench.main(["--out", str(out), "--report-only", "--games", "Asterix", "--variants", "far", "near",
                       "--variant", "far=dqn:n_step=10", "--variant", "near=dqn:n_step=3", "--include", str(include),
                       "--reference", str(reference)]) == 0
    rows = {r["variant"]: r for r in json.loads((out / "table.json").read_text())}
    for variant, values in last.items():
        want = learning.difference(values, random_play)
        assert rows[variant]["vs_random"] == want
        assert rows[variant]["vs_random"]["n_baseline"] == 200
    assert rows["far"]["vs_random"]["verdict"] == "above"
    assert rows["near"]["vs_random"]["verdict"] == "not separated"   # its mean is above random play's, not its interval
    assert np.mean(last["near"]) > np.mean(random_play)
    table = (out / "table.md").read_text()
    lo, hi = learning.bootstrap_ci(random_play)
    assert f"| Asterix | random play (reference) | 200 episodes | {np.mean(random_play):.1f} [{lo:.1f}, {hi:.1f}] |" \
        in table
    assert "| Asterix | best constant action: UP (reference) | 3 episodes | 650.0 |" in table
    assert "| Asterix | far | 3 / 200 | +" in table and "above |" in table

    # without random episodes for a game there is no difference, rather than one against nothing
    reference.write_text(json.dumps({"Asterix": {"NOOP": [200.0] * 3}}))
    bench.main(["--out", str(out), "--report-only", "--games", "Asterix", "--variants", "far",
                "--variant", "far=dqn:n_step=10", "--include", str(include), "--reference", str(reference)])
    assert "vs_random" not in json.loads((out / "table.json").read_text())[0]
    assert "Difference to random play" not in (out / "table.md").read_text()
