"""The README's results tables are what users read first, so each figure in them must follow from the per-run
files committed under docs/results/ by the benchmarks' own report code (each run's figure, the mean over seeds and
the bootstrap 95% interval of that mean). A figure typed in by hand, or left behind when a sweep adds seeds, fails
here.

MUJOCO and ATARI_RUNS name, for each cell, the per-run files and the variant key the figure comes from; the figures
themselves are recomputed. A cell with no per-run record is listed in NO_RUN_FILE with the reason."""
from __future__ import annotations

import json
import re
from functools import cache
from pathlib import Path

import numpy as np

from scaffolding import load_benchmark

ROOT = Path(__file__).resolve().parents[2]
LEARNING = ROOT / "docs" / "results" / "learning"
ATARI = ROOT / "docs" / "results" / "atari"
LEARNING_BENCH = load_benchmark("learning_bench")
ATARI_BENCH = load_benchmark("atari_bench")

# MuJoCo table: (task, column) -> [(learning_bench results file, algorithm key), ...]; the runs of all files are
# joined by seed (a later file's seeds 3-4 extend an earlier file's 0-2).
MUJOCO = {
    ("Hopper-v4", "DDPG"): [("s12-hopper-base", "ddpg"), ("s27-hopper-s34", "ddpg")],
    ("Hopper-v4", "thesis"): [("s12-hopper-base", "comcact")],
    ("Hopper-v4", "fresh_labels"): [("s12-hopper-restore", "comcact_restore")],
    ("Hopper-v4", "fresh_labels_gate"): [("s16-hopper-gate", "comcact_restore_gate"),
                                         ("s27-hopper-s34", "comcact_restore_gate")],
    ("Walker2d-v4", "DDPG"): [("s15-walker", "ddpg"), ("s21-walker-s34", "ddpg")],
    ("Walker2d-v4", "thesis"): [("s15-walker", "comcact")],
    ("Walker2d-v4", "fresh_labels"): [("s15-walker", "comcact_restore")],
    ("Walker2d-v4", "fresh_labels_gate"): [("s16-walker-gate", "comcact_restore_gate"),
                                           ("s21-walker-s34", "comcact_restore_gate")],
    ("HalfCheetah-v4", "DDPG"): [("s15-cheetah", "ddpg"), ("s16-cheetah-s34", "ddpg"), ("s27-cheetah-s59", "ddpg")],
    ("HalfCheetah-v4", "thesis"): [("s15-cheetah", "comcact")],
    ("HalfCheetah-v4", "fresh_labels"): [("s15-cheetah", "comcact_restore"),
                                         ("s16-cheetah-fresh-s34", "comcact_restore")],
    ("HalfCheetah-v4", "fresh_labels_gate"): [("s16-cheetah-gate", "comcact_restore_gate"),
                                              ("s16-cheetah-s34", "comcact_restore_gate"),
                                              ("s27-cheetah-s59", "comcact_restore_gate")],
    ("InvertedDoublePendulum-v4", "DDPG"): [("s9-idp-restore", "ddpg")],
    ("InvertedDoublePendulum-v4", "thesis"): [("s9-idp-restore", "comcact")],
    ("InvertedDoublePendulum-v4", "fresh_labels"): [("s9-idp-restore", "comcact_restore")],
    ("InvertedDoublePendulum-v4", "fresh_labels_gate"): [("s19-idp-gate", "comcact_restore_gate")],
}
MUJOCO_COLUMNS = ["DDPG", "thesis", "fresh_labels", "fresh_labels_gate"]

# Atari table: (game, column) -> [(atari_bench runs file, variant)], joined the same way.
ATARI_RUNS = {
    "DQN": [("data-efficient-runs", "dqn")],
    "DQN, n_step:=10": [("data-efficient-runs", "dqn_n10")],
    "COMPER": [("data-efficient-runs", "comper")],
    "COMPER, n_step:=10": [("data-efficient-runs", "comper_n10")],
    "COMPER, n_step:=10, qt_target_gate:=true": [("qt-gate-runs", "comperg_n10")],
    "the same, qt_gate_reference:=label": [("qt-gate-runs", "comperl_n10")],
    "COMPER, label_network:=target": [("label-network-target-runs", "comper_tl")],
}
ATARI_COLUMNS = ["random play", "best constant action", *ATARI_RUNS]
NO_RUN_FILE = {("Asterix", "COMPER, label_network:=target"):
               "seed 0's run folder was not kept (docs/comper.md, Value scale); only seeds 1 and 2 have run files"}

CELL = re.compile(r"^\**(-?[\d,.]+)\**(?: \[(-?[\d,.]+), (-?[\d,.]+)\])? \((\d+)\)$")


def _num(text: str) -> float:
    return float(text.replace(",", ""))


def _table(heading: str) -> list[list[str]]:
    """The rows (cells stripped) of the first Markdown table after the line starting with `heading`."""
    lines = (ROOT / "README.md").read_text().splitlines()
    start = next(i for i, ln in enumerate(lines) if ln.startswith(heading))
    rows = []
    for ln in lines[start + 1:]:
        if ln.startswith("|"):
            rows.append([c.strip() for c in ln.strip().strip("|").split("|")])
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


@cache
def _read(path: Path):
    return json.loads(path.read_text())


def _mujoco_values(sources, step: int = 50_000) -> list[float]:
    by_seed = {}
    for tag, alg in sources:
        res = _read(LEARNING / f"{tag}.json")
        for r in res["runs"].values():
            v = LEARNING_BENCH.return_at(r["evals"], step, res["eval_every"])
            if r["algorithm"] == alg and v is not None:
                by_seed[r["seed"]] = v
    return [by_seed[s] for s in sorted(by_seed)]


def _atari_values(game: str, sources, budget: int = 100_000) -> list[float]:
    by_seed = {}
    for name, variant in sources:
        for r in _read(ATARI / f"{name}.json"):
            if r["game"] == game and r["variant"] == variant:
                by_seed[r["seed"]] = ATARI_BENCH.run_protocol(r, budget)["last_mean"]
    return [by_seed[s] for s in sorted(by_seed)]


def test_mujoco_table_follows_from_the_per_run_files():
    rows = _table("**COMCACT against DDPG**")
    assert {r[0] for r in rows} == {t for t, _ in MUJOCO}
    wrong = []
    for row in rows:
        assert len(row) == 1 + len(MUJOCO_COLUMNS), row
        for col, cell in zip(MUJOCO_COLUMNS, row[1:]):
            values = _mujoco_values(MUJOCO[(row[0], col)])
            assert values, f"{row[0]} / {col}: no run in the files named"
            wrong += [f"{row[0]} / {col}: {w}" for w in _shown(cell, _figure(values))]
    assert not wrong, "\n".join(wrong)


def test_atari_table_follows_from_the_per_run_files():
    rows = _table("Atari, `data_efficient` profile, 100,000 frames")
    ref = _read(ATARI / "constant-actions.json")
    assert {r[0] for r in rows} == {"Asterix", "Freeway", "Seaquest"}
    wrong = []
    for row in rows:
        game = row[0]
        assert len(row) == 1 + len(ATARI_COLUMNS), row
        cells = dict(zip(ATARI_COLUMNS, row[1:]))
        random_play = float(np.mean(ref[game]["random"]))
        best_constant = max(float(np.mean(v)) for a, v in ref[game].items() if a != "random")
        if not _rounds_to(cells["random play"], random_play):
            wrong.append(f"{game}: random play is {random_play:.2f}")
        if not _rounds_to(cells["best constant action"], best_constant):
            wrong.append(f"{game}: the best constant action scores {best_constant:.2f}")
        for col, sources in ATARI_RUNS.items():
            if (game, col) in NO_RUN_FILE:
                continue
            values = _atari_values(game, sources)
            if cells[col] == "not run":
                if values:
                    wrong.append(f"{game} / {col}: 'not run', but the files hold {len(values)} runs")
                continue
            assert values, f"{game} / {col}: no run in the files named"
            wrong += [f"{game} / {col}: {w}" for w in _shown(cells[col], _figure(values))]
    assert not wrong, "\n".join(wrong)


def test_cells_without_a_run_file_are_the_declared_ones():
    """What NO_RUN_FILE excuses must still show a figure with its seed count, and no more runs than stated
    are in the files (so the exemption ends when the missing run is added)."""
    rows = {r[0]: dict(zip(ATARI_COLUMNS, r[1:])) for r in _table("Atari, `data_efficient` profile, 100,000 frames")}
    for (game, col), why in NO_RUN_FILE.items():
        m = CELL.match(rows[game][col])
        assert m, (game, col, why)
        assert len(_atari_values(game, ATARI_RUNS[col])) < int(m.group(4)), f"{game} / {col}: drop the exemption"
