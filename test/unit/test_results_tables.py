"""Every figure of the results tables (docs/results.md, and the README's table of recommended configurations) must
follow from the per-run files committed under docs/results/, computed by the benchmarks' own report code: each run's
figure, the mean over seeds, the bootstrap 95% interval of that mean, the difference of two groups' means with its
interval and verdict, and the minutes a run took. A figure typed in by hand, or left behind when a sweep adds seeds,
fails here.

The dicts below name, for each cell, the per-run files and the variant key the figure comes from; the figures
themselves are recomputed. A cell with no per-run record is listed in NO_RUN_FILE with the reason.
``python test/unit/test_results_tables.py`` prints every table as the per-run files give it (to paste after a sweep).
"""
from __future__ import annotations

import json
import re
import sys
from functools import cache
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from scaffolding import load_benchmark  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "docs" / "results.md"
README = ROOT / "README.md"
LEARNING = ROOT / "docs" / "results" / "learning"
ATARI = ROOT / "docs" / "results" / "atari"
LEARNING_BENCH = load_benchmark("learning_bench")
ATARI_BENCH = load_benchmark("atari_bench")

# MuJoCo: (task, column) -> [(learning_bench results file, algorithm key), ...]; the runs of all files are joined by
# seed (a later file's seeds 3-4 extend an earlier file's 0-2).
MUJOCO = {
    ("Hopper-v4", "DDPG"): [("s12-hopper-base", "ddpg"), ("s27-hopper-s34", "ddpg")],
    ("Hopper-v4", "thesis"): [("s12-hopper-base", "comcact")],
    ("Hopper-v4", "fresh labels"): [("s12-hopper-restore", "comcact_restore")],
    ("Hopper-v4", "default"): [("s16-hopper-gate", "comcact_restore_gate"),
                               ("s27-hopper-s34", "comcact_restore_gate")],
    ("Walker2d-v4", "DDPG"): [("s15-walker", "ddpg"), ("s21-walker-s34", "ddpg")],
    ("Walker2d-v4", "thesis"): [("s15-walker", "comcact")],
    ("Walker2d-v4", "fresh labels"): [("s15-walker", "comcact_restore")],
    ("Walker2d-v4", "default"): [("s16-walker-gate", "comcact_restore_gate"),
                                 ("s21-walker-s34", "comcact_restore_gate")],
    ("HalfCheetah-v4", "DDPG"): [("s15-cheetah", "ddpg"), ("s16-cheetah-s34", "ddpg"), ("s27-cheetah-s59", "ddpg")],
    ("HalfCheetah-v4", "thesis"): [("s15-cheetah", "comcact")],
    ("HalfCheetah-v4", "fresh labels"): [("s15-cheetah", "comcact_restore"),
                                         ("s16-cheetah-fresh-s34", "comcact_restore")],
    ("HalfCheetah-v4", "default"): [("s16-cheetah-gate", "comcact_restore_gate"),
                                    ("s16-cheetah-s34", "comcact_restore_gate"),
                                    ("s27-cheetah-s59", "comcact_restore_gate")],
    ("InvertedDoublePendulum-v4", "DDPG"): [("s9-idp-restore", "ddpg")],
    ("InvertedDoublePendulum-v4", "thesis"): [("s9-idp-restore", "comcact")],
    ("InvertedDoublePendulum-v4", "fresh labels"): [("s9-idp-restore", "comcact_restore")],
    ("InvertedDoublePendulum-v4", "default"): [("s19-idp-gate", "comcact_restore_gate")],
    ("Hopper-v4", "SB3 DDPG"): [("s3-hopper50k", "sb3_ddpg")],
    ("Walker2d-v4", "SB3 DDPG"): [("s17-walker-sb3", "sb3_ddpg")],
    ("HalfCheetah-v4", "SB3 DDPG"): [("s18-cheetah-sb3", "sb3_ddpg")],
    ("InvertedDoublePendulum-v4", "SB3 DDPG"): [("s21-idp-sb3", "sb3_ddpg")],
}
MUJOCO_COLUMNS = ["DDPG", "SB3 DDPG", "thesis", "fresh labels", "default"]
MUJOCO_DIFF_COLUMNS = ["thesis", "fresh labels", "default"]          # each minus DDPG

# Classic control (comper_node, classic_control profile): (task, column) -> learning_bench files, as MUJOCO.
CLASSIC = {(task, col): [(tag, alg)]
           for task, tag in (("CartPole-v1", "s8-cartpole"), ("Acrobot-v1", "s8-acrobot"))
           for col, alg in (("COMPER", "comper"), ("COMPER-F", "comper_f"), ("COMPER-M", "comper_m"),
                            ("DQN", "dqn"))}
CLASSIC_COLUMNS = ["COMPER", "COMPER-F", "COMPER-M", "DQN"]

# Atari, data_efficient profile: column -> [(atari_bench runs file, variant)], joined the same way.
ATARI_RUNS = {
    "DQN": [("data-efficient-runs", "dqn")],
    "DQN, n_step:=10": [("data-efficient-runs", "dqn_n10")],
    "COMPER": [("data-efficient-runs", "comper")],
    "COMPER, n_step:=10": [("data-efficient-runs", "comper_n10")],
    "COMPER, n_step:=10, qt_target_gate:=true": [("qt-gate-runs", "comperg_n10")],
    "atari_100k": [("qt-gate-runs", "comperl_n10")],
    "COMPER, label_network:=target": [("label-network-target-runs", "comper_tl")],
}
ATARI_COLUMNS = ["random play", "best constant action", *ATARI_RUNS]
NO_RUN_FILE = {("Asterix", "COMPER, label_network:=target"):
               "seed 0's run folder was not kept (docs/studies, Value scale); only seeds 1 and 2 have run files"}
# Atari differences under data_efficient: column -> (variant column, baseline: a column of ATARI_RUNS or "random").
ATARI_DIFFS = {
    "atari_100k - random play": ("atari_100k", "random"),
    "atari_100k - DQN, n_step:=10": ("atari_100k", "DQN, n_step:=10"),
    "DQN - random play": ("DQN", "random"),
    "DQN, n_step:=10 - random play": ("DQN, n_step:=10", "random"),
}

# Atari, thesis profile.
ATARI_THESIS_RUNS = {
    "DQN": [("thesis-runs", "dqn")],
    "COMPER": [("thesis-runs", "comper")],
    "COMPER-F": [("comper-fm-runs", "comper_f")],
    "COMPER-M": [("comper-fm-runs", "comper_m")],
    "COMPER, label_network:=target": [("label-network-target-thesis-runs", "comper_tl")],
}
ATARI_THESIS_COLUMNS = ["random play", "best constant action", *ATARI_THESIS_RUNS]

# The README's recommended configurations: task -> (the configuration's runs, the baseline's name and runs); MuJoCo
# and classic control from learning_bench files, Atari from atari_bench files.
RECOMMENDED = {
    "Hopper-v4": (MUJOCO[("Hopper-v4", "default")], "DDPG", MUJOCO[("Hopper-v4", "DDPG")]),
    "Walker2d-v4": (MUJOCO[("Walker2d-v4", "default")], "DDPG", MUJOCO[("Walker2d-v4", "DDPG")]),
    "HalfCheetah-v4": (MUJOCO[("HalfCheetah-v4", "default")], "DDPG", MUJOCO[("HalfCheetah-v4", "DDPG")]),
    "InvertedDoublePendulum-v4": (MUJOCO[("InvertedDoublePendulum-v4", "default")], "DDPG",
                                  MUJOCO[("InvertedDoublePendulum-v4", "DDPG")]),
    "ALE/Asterix-v5": (ATARI_RUNS["atari_100k"], "10-step DQN", ATARI_RUNS["DQN, n_step:=10"]),
    "ALE/Seaquest-v5": (ATARI_RUNS["atari_100k"], "10-step DQN", ATARI_RUNS["DQN, n_step:=10"]),
    "ALE/Freeway-v5": (ATARI_RUNS["atari_100k"], "10-step DQN", ATARI_RUNS["DQN, n_step:=10"]),
    "CartPole-v1": (CLASSIC[("CartPole-v1", "COMPER")], "DQN", CLASSIC[("CartPole-v1", "DQN")]),
    "Acrobot-v1": (CLASSIC[("Acrobot-v1", "COMPER")], "DQN", CLASSIC[("Acrobot-v1", "DQN")]),
}

CELL = re.compile(r"^(-?[\d,.]+)(?: \[(-?[\d,.]+), (-?[\d,.]+)\])? \((\d+)\)$")
MINUTES = re.compile(r"^(\d+) \((\d+)-(\d+)\)$")


def _num(text: str) -> float:
    return float(text.replace(",", ""))


def _table(path: Path, heading: str) -> list[list[str]]:
    """The rows (cells stripped, bold marks removed) of the first Markdown table after the line starting with
    `heading`, or of the table whose header row that line is."""
    lines = path.read_text().splitlines()
    start = next((i for i, ln in enumerate(lines) if ln.startswith(heading)), None)
    assert start is not None, f"{path.name}: no line starts with {heading!r}"
    rows = []
    for ln in lines[start if heading.startswith("|") else start + 1:]:
        if ln.startswith("|"):
            rows.append([c.strip().replace("**", "") for c in ln.strip().strip("|").split("|")])
        elif rows:
            break
    return rows[2:]                                                  # without the header and the rule


def _rounds_to(text: str, value: float) -> bool:
    """Whether `text` is `value` rounded to the decimals `text` prints."""
    digits = len(text.partition(".")[2])
    return abs(_num(text) - value) <= 0.5 * 10 ** -digits + 1e-6


def _shown(cell: str, figure: tuple[float, float, float, int]) -> list[str]:
    """What is wrong with the cell as the figure 'mean [lo, hi] (n)' rounded to the decimals it prints."""
    m = CELL.match(cell)
    if not m:
        return [f"cell {cell!r} is not 'mean [lo, hi] (seeds)'"]
    mean, lo, hi, n = figure
    wrong = []
    if int(m.group(4)) != n:
        wrong.append(f"{cell}: {n} runs in the per-run files")
    if not _rounds_to(m.group(1), mean):
        wrong.append(f"{cell}: the runs give a mean of {mean:.2f}")
    if m.group(2) is None and n > 1:
        wrong.append(f"{cell}: {n} runs need an interval")
    if m.group(2) is not None and not (_rounds_to(m.group(2), lo) and _rounds_to(m.group(3), hi)):
        wrong.append(f"{cell}: the runs give [{lo:.2f}, {hi:.2f}]")
    return wrong


def _figure(values: list[float]) -> tuple[float, float, float, int]:
    lo, hi = LEARNING_BENCH.bootstrap_ci(values)
    return float(np.mean(values)), lo, hi, len(values)


def _difference(values: list[float], baseline: list[float]) -> str:
    """learning_bench's difference cell: '+12.3 [-4.5, +28.0] not separated'."""
    return LEARNING_BENCH.difference_cell(LEARNING_BENCH.difference(values, baseline))


@cache
def _read(path: Path):
    return json.loads(path.read_text())


def _learning_runs(sources) -> dict[int, dict]:
    """seed -> run record of learning_bench files (a later file's run of a seed replaces an earlier one's; a file's
    placeholder of a seed it did not run, without evaluations, does not)."""
    by_seed = {}
    for tag, alg in sources:
        res = _read(LEARNING / f"{tag}.json")
        for r in res["runs"].values():
            if r["algorithm"] == alg and r["evals"]:
                by_seed[r["seed"]] = dict(r, eval_every=res["eval_every"])
    return by_seed


def _return_at(evals, step: int, every: int) -> float | None:
    """learning_bench's return at `step` (the first evaluation logged at that grid point)."""
    return LEARNING_BENCH.return_at(evals, step, every)


def _learning_values(sources, step: int = 50_000) -> list[float]:
    by_seed = {s: _return_at(r["evals"], step, r["eval_every"]) for s, r in _learning_runs(sources).items()}
    return [by_seed[s] for s in sorted(by_seed) if by_seed[s] is not None]


def _atari_runs(game: str, sources) -> dict[int, dict]:
    by_seed = {}
    for name, variant in sources:
        for r in _read(ATARI / f"{name}.json"):
            if r["game"] == game and r["variant"] == variant:
                by_seed[r["seed"]] = r
    return by_seed


def _atari_values(game: str, sources, budget: int = 100_000) -> list[float]:
    runs = _atari_runs(game, sources)
    return [ATARI_BENCH.run_protocol(runs[s], budget)["last_mean"] for s in sorted(runs)]


def _reference(game: str) -> tuple[list[float], float, float]:
    """Random play's episodes, their mean, and the best constant action's mean (atari_constant_actions.py)."""
    ref = _read(ATARI / "constant-actions.json")[game]
    best_constant = max(float(np.mean(v)) for a, v in ref.items() if a != "random")
    return ref["random"], float(np.mean(ref["random"])), best_constant


def _minutes(task: str, sources) -> list[float]:
    """Wall-clock minutes of each run that recorded them: learning_bench's timers (elapsed_s of a run's sessions),
    atari_bench's wall_time_s."""
    if task.startswith("ALE/"):
        runs = _atari_runs(task[4:].removesuffix("-v5"), sources)
        return [r["wall_time_s"] / 60 for r in runs.values() if r.get("wall_time_s")]
    return [r["timers"]["elapsed_s"] / 60 for r in _learning_runs(sources).values() if r.get("timers")]


def _task_values(task: str, sources) -> list[float]:
    return _atari_values(task[4:].removesuffix("-v5"), sources) if task.startswith("ALE/") else \
        _learning_values(sources)


def _figure_table(path: Path, heading: str, keys: dict, columns: list[str]) -> list[str]:
    rows = _table(path, heading)
    assert {r[0] for r in rows} == {t for t, _ in keys}, f"{heading}: rows {[r[0] for r in rows]}"
    wrong = []
    for row in rows:
        assert len(row) == 1 + len(columns), row
        for col, cell in zip(columns, row[1:]):
            values = _learning_values(keys[(row[0], col)])
            assert values, f"{row[0]} / {col}: no run in the files named"
            wrong += [f"{row[0]} / {col}: {w}" for w in _shown(cell, _figure(values))]
    return wrong


def _atari_table(heading: str, runs: dict, columns: list[str]) -> list[str]:
    rows = _table(RESULTS, heading)
    assert {r[0] for r in rows} == {"Asterix", "Freeway", "Seaquest"}
    wrong = []
    for row in rows:
        game = row[0]
        assert len(row) == 1 + len(columns), row
        cells = dict(zip(columns, row[1:]))
        _, random_play, best_constant = _reference(game)
        if not _rounds_to(cells["random play"], random_play):
            wrong.append(f"{game}: random play is {random_play:.2f}")
        if not _rounds_to(cells["best constant action"], best_constant):
            wrong.append(f"{game}: the best constant action scores {best_constant:.2f}")
        for col, sources in runs.items():
            if (game, col) in NO_RUN_FILE:
                continue
            values = _atari_values(game, sources)
            assert values, f"{game} / {col}: no run in the files named"
            wrong += [f"{game} / {col}: {w}" for w in _shown(cells[col], _figure(values))]
    return wrong


def test_mujoco_table_follows_from_the_per_run_files():
    wrong = _figure_table(RESULTS, "**COMCACT against DDPG**", MUJOCO, MUJOCO_COLUMNS)
    assert not wrong, "\n".join(wrong)


def test_mujoco_differences_follow_from_the_per_run_files():
    rows = _table(RESULTS, "**COMCACT minus DDPG**")
    assert {r[0] for r in rows} == {t for t, _ in MUJOCO}
    wrong = []
    for row in rows:
        base = _learning_values(MUJOCO[(row[0], "DDPG")])
        for col, cell in zip(MUJOCO_DIFF_COLUMNS, row[1:]):
            want = _difference(_learning_values(MUJOCO[(row[0], col)]), base)
            if cell != want:
                wrong.append(f"{row[0]} / {col}: {cell!r}, the runs give {want!r}")
    assert not wrong, "\n".join(wrong)


def test_classic_control_table_follows_from_the_per_run_files():
    wrong = _figure_table(RESULTS, "**Classic control**", CLASSIC, CLASSIC_COLUMNS)
    assert not wrong, "\n".join(wrong)


def test_atari_data_efficient_table_follows_from_the_per_run_files():
    wrong = _atari_table("**COMPER and DQN under `data_efficient`**", ATARI_RUNS, ATARI_COLUMNS)
    assert not wrong, "\n".join(wrong)


def test_atari_thesis_table_follows_from_the_per_run_files():
    wrong = _atari_table("**COMPER and DQN under `thesis`**", ATARI_THESIS_RUNS, ATARI_THESIS_COLUMNS)
    assert not wrong, "\n".join(wrong)


def test_atari_differences_follow_from_the_per_run_files():
    rows = _table(RESULTS, "**Differences under `data_efficient`**")
    assert {r[0] for r in rows} == {"Asterix", "Freeway", "Seaquest"}
    wrong = []
    for row in rows:
        game = row[0]
        for (col, (variant, baseline)), cell in zip(ATARI_DIFFS.items(), row[1:]):
            base = _reference(game)[0] if baseline == "random" else _atari_values(game, ATARI_RUNS[baseline])
            want = _difference(_atari_values(game, ATARI_RUNS[variant]), base)
            if cell != want:
                wrong.append(f"{game} / {col}: {cell!r}, the runs give {want!r}")
    assert not wrong, "\n".join(wrong)


def test_cells_without_a_run_file_are_the_declared_ones():
    """What NO_RUN_FILE excuses must still show a figure with its seed count, and no more runs than stated
    are in the files (so the exemption ends when the missing run is added)."""
    rows = {r[0]: dict(zip(ATARI_COLUMNS, r[1:]))
            for r in _table(RESULTS, "**COMPER and DQN under `data_efficient`**")}
    for (game, col), why in NO_RUN_FILE.items():
        m = CELL.match(rows[game][col])
        assert m, (game, col, why)
        assert len(_atari_values(game, ATARI_RUNS[col])) < int(m.group(4)), f"{game} / {col}: drop the exemption"


def _recommended_wrong(path: Path, heading: str) -> list[str]:
    """Columns: task | command | return | baseline | baseline's return | minutes per run (median (min-max))."""
    rows = _table(path, heading)
    assert {r[0] for r in rows} == set(RECOMMENDED), f"{path.name}: rows {[r[0] for r in rows]}"
    wrong = []
    for task, command, ret, base_name, base_ret, minutes in rows:
        sources, want_name, base_sources = RECOMMENDED[task]
        wrong += [f"{task} / return: {w}" for w in _shown(ret, _figure(_task_values(task, sources)))]
        if base_name != want_name:
            wrong.append(f"{task}: the baseline is {want_name}")
        wrong += [f"{task} / baseline: {w}" for w in _shown(base_ret, _figure(_task_values(task, base_sources)))]
        mins = _minutes(task, sources)
        m = MINUTES.match(minutes)
        want = f"{np.median(mins):.0f} ({min(mins):.0f}-{max(mins):.0f})"
        if not m or minutes != want:
            wrong.append(f"{task} / minutes: {minutes!r}, the runs give {want!r}")
        if task not in command:
            wrong.append(f"{task}: the command does not name the task")
    return wrong


def test_recommended_configurations_follow_from_the_per_run_files():
    wrong = _recommended_wrong(README, "| task | command |") + _recommended_wrong(RESULTS, "| task | command |")
    assert not wrong, "\n".join(wrong)


# --- printing (python test/unit/test_results_tables.py) ---------------------------------------------------------

def _fmt(x: float) -> str:
    return f"{x:,.0f}" if abs(x) >= 100 else f"{x:.1f}" if abs(x) >= 0.95 else f"{x:.2f}"


def _cell(values: list[float]) -> str:
    mean, lo, hi, n = _figure(values)
    return f"{_fmt(mean)} [{_fmt(lo)}, {_fmt(hi)}] ({n})" if n > 1 else f"{_fmt(mean)} ({n})"


def tables() -> str:
    out = ["MuJoCo, return at 50,000 steps:"]
    for task in dict.fromkeys(t for t, _ in MUJOCO):
        out.append(f"| {task} | " + " | ".join(_cell(_learning_values(MUJOCO[(task, c)])) for c in MUJOCO_COLUMNS)
                   + " |")
    out.append("MuJoCo, minus DDPG:")
    for task in dict.fromkeys(t for t, _ in MUJOCO):
        base = _learning_values(MUJOCO[(task, "DDPG")])
        out.append(f"| {task} | " + " | ".join(_difference(_learning_values(MUJOCO[(task, c)]), base)
                                               for c in MUJOCO_DIFF_COLUMNS) + " |")
    out.append("Classic control:")
    for task in dict.fromkeys(t for t, _ in CLASSIC):
        out.append(f"| {task} | " + " | ".join(_cell(_learning_values(CLASSIC[(task, c)]))
                                               for c in CLASSIC_COLUMNS) + " |")
    for name, runs in (("data_efficient", ATARI_RUNS), ("thesis", ATARI_THESIS_RUNS)):
        out.append(f"Atari, {name}:")
        for game in ("Asterix", "Freeway", "Seaquest"):
            _, rnd, best = _reference(game)
            cells = [_fmt(rnd), _fmt(best)]
            for sources in runs.values():
                values = _atari_values(game, sources)
                cells.append(_cell(values) if values else "-")
            out.append(f"| {game} | " + " | ".join(cells) + " |")
    out.append("Atari, differences under data_efficient:")
    for game in ("Asterix", "Freeway", "Seaquest"):
        cells = []
        for variant, baseline in ATARI_DIFFS.values():
            base = _reference(game)[0] if baseline == "random" else _atari_values(game, ATARI_RUNS[baseline])
            cells.append(_difference(_atari_values(game, ATARI_RUNS[variant]), base))
        out.append(f"| {game} | " + " | ".join(cells) + " |")
    out.append("Recommended configurations (return | baseline | baseline's return | minutes):")
    for task, (sources, base_name, base_sources) in RECOMMENDED.items():
        mins = _minutes(task, sources)
        out.append(f"| {task} | {_cell(_task_values(task, sources))} | {base_name} | "
                   f"{_cell(_task_values(task, base_sources))} | "
                   f"{np.median(mins):.0f} ({min(mins):.0f}-{max(mins):.0f}) |")
    return "\n".join(out)


if __name__ == "__main__":
    print(tables())


def test_the_make_run_figure_follows_from_its_per_run_file():
    """The README's promise for `make run` (comcact_node's default on InvertedPendulum-v4, 20,000 steps): the return
    with its interval at 10,000 and 20,000 steps, the seeds and the minutes per run, from s31-ip-default.json."""
    text = " ".join(README.read_text().split())
    runs = _learning_runs([("s31-ip-default", "comcact")])
    every = next(iter(runs.values()))["eval_every"]
    for step in (10_000, 20_000):
        mean, lo, hi, n = _figure([_return_at(r["evals"], step, every) for r in runs.values()])
        cell = f"{mean:,.0f} [{lo:,.0f}, {hi:,.0f}] ({n} seeds)"
        assert cell in text, f"README: make run's figure at {step} steps should read {cell}"
    minutes = [r["timers"]["elapsed_s"] / 60 for r in runs.values()]
    shown = f"took {np.median(minutes):.0f} ({min(minutes):.0f}-{max(minutes):.0f}) minutes"
    assert shown in text, f"README: make run's time should read '{shown}'"
