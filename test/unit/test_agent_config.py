"""Agent hyper-parameters (comper_agent.core.config): documented, validated, thesis values."""
import dataclasses
import sys
from pathlib import Path

_SRC = Path(__file__).resolve().parents[2] / "src"
for _p in (_SRC / "comper_msgs", _SRC / "comper_agent"):
    if str(_p) not in sys.path:
        sys.path.insert(0, str(_p))

import pytest

from comper_msgs_py.params import ConfigError, config_from_dict, config_to_dict
from comper_agent.core.config import (ALL_CONFIGS, ComcactConfig, ComcactQTConfig, ComperConfig,
                                      DDPGConfig, DQNConfig, QTConfig, parameter_table_markdown,
                                      qt_config_for)

DOC = Path(__file__).resolve().parents[2] / "docs" / "agent-core.md"


@pytest.mark.parametrize("cls", ALL_CONFIGS)
def test_every_field_documented_and_defaults_valid(cls):
    for f in dataclasses.fields(cls):
        assert f.metadata.get("description"), f"{cls.__name__}.{f.name} has no description"
    cfg = config_from_dict(cls, {})
    assert config_from_dict(cls, config_to_dict(cfg)) == cfg


def test_thesis_values_and_deviations():
    assert ComcactConfig().critic_lr == 2e-3 and ComcactConfig().tau == 0.005
    assert DDPGConfig().variant == "ddpg" and DQNConfig().frame_stack == 4
    assert ComperConfig().epsilon_decay_frames == 90_000
    assert ComcactQTConfig().qt_lr == 1e-3 and QTConfig().qt_lr == 2.5e-4
    dev = {f.name: f.metadata["deviation"] for f in dataclasses.fields(ComcactQTConfig)}
    assert dev["qt_output_activation"]
    for cls in (ComcactConfig, ComperConfig):
        assert {f.name: f.metadata["deviation"] for f in dataclasses.fields(cls)}["qt_label"]
    assert qt_config_for("comcact", {"qt_sequence_length": "3"}).qt_sequence_length == 3
    with pytest.raises(ConfigError):
        config_from_dict(ComcactQTConfig, {"qt_output_activation": "sigmoid"})
    with pytest.raises(ConfigError):
        config_from_dict(ComperConfig, {"variant": "rainbow"})


def test_comcact_profiles_name_existing_fields_with_a_source_and_thesis_is_the_default():
    from comper_agent.core.config import COMCACT_PROFILES
    from comper_agent.nodes.node_config import ComcactNodeConfig
    owner = {f.name for f in dataclasses.fields(ComcactConfig)} | {f.name for f in dataclasses.fields(ComcactNodeConfig)}
    assert ComcactNodeConfig().profile == "auto"
    for profile, values in COMCACT_PROFILES.items():
        for k, (v, source) in values.items():
            assert k in owner, (profile, k)
            if profile == "thesis":         # its sources are the thesis's own
                assert source.startswith(("Algorithm 8", "appendix B")), (k, source)
                continue
            study = source.split(":")[0]
            assert study.startswith("docs/studies/") and (DOC.parents[1] / study).is_file(), (profile, k, source)


@pytest.mark.parametrize("name, algorithm, env_id, expected", [
    ("auto", "comcact", "", "fresh_labels_gate"), ("auto", "ddpg", "", "plain"), ("thesis", "comcact", "", "thesis"),
    ("thesis", "ddpg", "", "thesis"),
    ("auto", "comper", "ALE/Freeway-v5", "atari_100k"), ("auto", "dqn", "CartPole-v1", "classic_control"),
])
def test_auto_is_the_best_measured_profile_of_each_task_family(name, algorithm, env_id, expected):
    from comper_agent.core.config import resolve_comcact_profile, resolve_profile
    got = resolve_profile(name, env_id) if env_id else resolve_comcact_profile(name, algorithm)
    assert got == expected


def test_atari_100k_is_data_efficient_with_the_gated_10_step_targets():
    from comper_agent.core.config import COMPER_PROFILES
    de, best = COMPER_PROFILES["data_efficient"], COMPER_PROFILES["atari_100k"]
    assert de.items() <= best.items()
    assert {k: v for k, (v, _) in best.items() if k not in de} == {
        "n_step": 10, "qt_target_gate": True, "reduce_overlap": True}


def test_the_start_up_log_names_every_difference_from_the_thesis():
    from comper_agent.core.config import COMCACT_PROFILES, thesis_differences
    from comper_agent.nodes.node_config import ComcactNodeConfig
    thesis = COMCACT_PROFILES["thesis"]
    literal = {k: v for k, (v, _) in thesis.items()}
    node_keys = {f.name for f in dataclasses.fields(ComcactNodeConfig)}
    assert thesis_differences(ComcactNodeConfig(**{k: v for k, v in literal.items() if k in node_keys}),
                              ComcactConfig(**{k: v for k, v in literal.items() if k not in node_keys}),
                              thesis=thesis) == []
    best = thesis_differences(ComcactNodeConfig(restore_batch=True, runs_root="elsewhere"),
                              ComcactConfig(label_critic="target", qt_step_gate=True, seed=3), thesis=thesis)
    # the profile's three values and the three engineering settings every profile but thesis keeps; not paths or seeds
    assert {d.split("=")[0] for d in best} == set(COMCACT_PROFILES["fresh_labels_gate"]) | set(thesis)
    assert "label_critic='target' (thesis: 'online')" in best and "batch_norm=False (thesis: True)" in best
