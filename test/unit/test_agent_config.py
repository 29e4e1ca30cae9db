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


def test_doc_lists_every_parameter():
    text = DOC.read_text()
    for cls in ALL_CONFIGS:
        assert parameter_table_markdown(cls) in text, f"docs/agent-core.md is stale for {cls.__name__}"


@pytest.mark.parametrize("node", ["comper", "comcact"])
def test_node_doc_lists_every_profile_value(node):
    from comper_agent.core.config import profile_table_markdown
    from comper_agent.node_config import ComcactNodeConfig, ComperNodeConfig
    cls = {"comper": ComperNodeConfig, "comcact": ComcactNodeConfig}[node]
    text = (DOC.parent / f"{node}.md").read_text()
    assert profile_table_markdown(cls, node) in text, \
        f"docs/{node}.md's profile table is stale (paste profile_table_markdown({cls.__name__}, {node!r}))"


def test_comcact_profiles_name_existing_fields_with_a_source_and_thesis_is_the_default():
    from comper_agent.core.config import COMCACT_PROFILES
    from comper_agent.node_config import ComcactNodeConfig
    owner = {f.name for f in dataclasses.fields(ComcactConfig)} | {f.name for f in dataclasses.fields(ComcactNodeConfig)}
    assert COMCACT_PROFILES["thesis"] == {} and ComcactNodeConfig().profile == "thesis"
    for profile, values in COMCACT_PROFILES.items():
        for k, (v, source) in values.items():
            assert k in owner, (profile, k)
            assert isinstance(source, str) and ("docs/comcact.md" in source or "the same runs" in source), (profile, k)
    # each profile only adds to the one before it: fresh_labels_gate = fresh_labels + the gate
    assert COMCACT_PROFILES["fresh_labels"].items() <= COMCACT_PROFILES["fresh_labels_gate"].items()
