"""export_dataset: recorded runs (bags and run directories) become Minari datasets that
``minari.load_dataset`` opens, episode by episode equal to the recorded transitions, with terminations
and truncations kept apart and the run's metadata carried (issue 19, item 3). No network: every
dataset goes into a temporary MINARI_DATASETS_PATH."""
from __future__ import annotations

import numpy as np
import pytest

minari = pytest.importorskip("minari")

from comper_agent.recording import bag_tools  # noqa: E402
from scaffolding import env_run, write_run_bag, write_run_dir  # noqa: E402


@pytest.fixture()
def datasets(tmp_path, monkeypatch):
    root = tmp_path / "minari"
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(root))
    return root


def _episodes_of(t, summaries):
    """(observations [T+1], actions, rewards, terminated, truncated) per recorded episode."""
    out, a = [], 0
    for s in summaries:
        b = a + s["length"]
        out.append((np.concatenate([t.states[a:b], t.next_states[b - 1:b]]), t.actions[a:b], t.rewards[a:b],
                    t.terminated[a:b], t.truncated[a:b]))
        a = b
    return out


def _assert_same_episodes(ds, t, summaries):
    want = _episodes_of(t, summaries)
    got = list(ds.iterate_episodes())
    assert len(got) == len(want) == ds.total_episodes and ds.total_steps == len(t)
    for e, (obs, act, rew, term, trunc) in zip(got, want):
        np.testing.assert_array_equal(e.observations, obs)
        np.testing.assert_array_equal(e.actions, act)
        np.testing.assert_array_equal(e.rewards, rew)
        np.testing.assert_array_equal(e.terminations, term)
        np.testing.assert_array_equal(e.truncations, trunc)


def test_bag_of_real_cartpole_episodes_loads_with_minari(tmp_path, datasets, capsys):
    # 20-step limit: random CartPole episodes both fail (terminated) and reach the limit (truncated)
    t, summ = env_run("CartPole-v1", 12, seed=3, max_episode_steps=20, run_id="cp-s3")
    kinds = {(s["terminated"], s["truncated"]) for s in summ}
    assert kinds == {(True, False), (False, True)}, kinds
    bag = write_run_bag(tmp_path / "bag", t, summ, env_id="CartPole-v1", algorithm="dqn")
    assert bag_tools.export_dataset_main([str(bag)]) == 0
    out = capsys.readouterr().out
    assert "comper/CartPole/cp-s3-v0" in out and f"{len(summ)} episodes, {len(t)} steps" in out, out
    ds = minari.load_dataset("comper/CartPole/cp-s3-v0")
    _assert_same_episodes(ds, t, summ)
    e = next(ds.iterate_episodes())
    assert e.actions.dtype == np.int64 and e.observations.dtype == np.float32
    assert ds.action_space.n == 2 and ds.observation_space.shape == (4,)
    assert ds.env_spec.id == "CartPole-v1"
    meta = ds.storage.metadata
    assert meta["algorithm_name"] == "dqn" and meta["data_format"] == "hdf5"
    c = meta["comper"]
    assert c["run_id"] == "cp-s3" and c["env_id"] == "CartPole-v1" and c["seed"] is None   # a bare bag: no seed
    assert "raw environment rewards" in c["rewards"] and c["suite_version"]
    em = list(ds.storage.get_episode_metadata(range(ds.total_episodes)))
    assert [m["episode_id"] for m in em] == [s["episode_id"] for s in summ]
    assert [m["return"] for m in em] == pytest.approx([s["episode_return"] for s in summ])


def test_run_directory_carries_seed_and_action_bounds(tmp_path, datasets):
    t, summ = env_run("Pendulum-v1", 3, seed=7, max_episode_steps=40, run_id="pend-s7")
    run = write_run_dir(tmp_path / "runs", t, summ, env_id="Pendulum-v1", seed=7,
                        env={"action_low": [-2.0], "action_high": [2.0]}, learner={"reward_clip": "none"})
    made = bag_tools.export_minari([run], dataset_id="test/pendulum-v2")
    assert [(d["dataset_id"], d["seed"], d["total_episodes"]) for d in made] == [("test/pendulum-v2", 7, 3)]
    ds = minari.load_dataset("test/pendulum-v2")
    _assert_same_episodes(ds, t, summ)
    assert all(e.truncations[-1] and not e.terminations.any() for e in ds.iterate_episodes())
    assert ds.action_space.low.tolist() == [-2.0] and ds.action_space.high.tolist() == [2.0]
    c = ds.storage.metadata["comper"]
    assert c["seed"] == 7 and c["algorithm"] == "comcact" and c["source_bags"] == [str(run / "bag")]
    assert c["reward_clip_in_learner"] == "none"


def test_refuses_an_existing_id_and_leaves_nothing_half_written(tmp_path, datasets, capsys):
    t, summ = env_run("CartPole-v1", 2, seed=0, max_episode_steps=15, run_id="dup")
    bag = write_run_bag(tmp_path / "bag", t, summ, env_id="CartPole-v1")
    assert bag_tools.export_dataset_main([str(bag), "--dataset-id", "tests/dup-v0"]) == 0
    capsys.readouterr()
    assert bag_tools.export_dataset_main([str(bag), "--dataset-id", "tests/dup-v0"]) == 1
    err = capsys.readouterr().err
    assert "exists already" in err and len(err.strip().splitlines()) == 1, err
    assert bag_tools.export_dataset_main([str(bag), "--dataset-id", "not a valid id"]) == 1
    assert "Malformed dataset ID" in capsys.readouterr().err
    # only the first export (and minari's namespace record)
    assert sorted(p.name for p in (datasets / "tests").iterdir()) == ["dup-v0", "namespace_metadata.json"]
    assert minari.load_dataset("tests/dup-v0").total_episodes == 2


def test_episodes_with_missing_steps_are_left_out_and_counted(tmp_path, datasets, capsys):
    t, summ = env_run("CartPole-v1", 4, seed=5, max_episode_steps=20, run_id="gap")
    a = summ[0]["length"]
    keep = np.ones(len(t), bool)
    keep[a + 2] = False                       # a step lost from the middle of episode 1
    bag = write_run_bag(tmp_path / "bag", t.take(np.flatnonzero(keep)), summ, env_id="CartPole-v1")
    assert bag_tools.export_dataset_main([str(bag), "--dataset-id", "tests/gap-v0"]) == 0
    assert "(1 episodes with missing steps left out)" in capsys.readouterr().out
    ds = minari.load_dataset("tests/gap-v0")
    _assert_same_episodes(ds, t.take(np.flatnonzero(~np.isin(t.episode_ids, [1]))), summ[:1] + summ[2:])
    assert ds.storage.metadata["comper"]["episodes_left_out_with_gaps"] == 1
