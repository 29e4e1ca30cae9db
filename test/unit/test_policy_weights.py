"""The policy message (comper_agent.nodes.policy_weights) between an async learner and its actors: which
networks it carries and what an actor loads, with online and with target labels. The message is
built and read without a running ROS graph."""
import numpy as np
import torch

from comper_agent.core.comcact import ComcactLearner
from comper_agent.core.config import ComcactConfig
from comper_agent.nodes.policy_weights import config_of_policy, load_policy_msg, policy_to_msg
from test_agent_checkpoint import cont_batch as batch

torch.set_num_threads(1)


def trained(label_critic):
    """A learner whose online networks have moved away from their targets (tau 0.005, 20 updates)."""
    lrn = ComcactLearner(ComcactConfig(label_critic=label_critic, seed=1), 3, [-1.0], [1.0])
    for i in range(20):
        lrn.update(batch(seed=i))
        lrn.soft_update()
    return lrn


def actor_side(msg):
    """What an actor does: build the same networks from the message's config, then load it."""
    actor = ComcactLearner(config_of_policy(msg, ComcactConfig), 3, [-1.0], [1.0])
    load_policy_msg(actor, msg)
    return actor


def test_target_labels_travel_with_the_target_networks():
    lrn = trained("target")
    b = batch(seed=99)
    stale = ComcactLearner(ComcactConfig(label_critic="target"), 3, [-1.0], [1.0])
    for part in ("actor", "critic"):          # labels from the online networks in the targets' place
        getattr(stale, f"{part}_target").load_state_dict(getattr(lrn, part).state_dict())
    assert not np.allclose(stale.value_labels(b), lrn.value_labels(b), atol=1e-3)   # so the test can tell
    msg = policy_to_msg(lrn, version=20, env_steps=100)
    parts = {name.partition(".")[0] for name in msg.tensor_names}
    assert parts == {"actor", "critic", "actor_target", "critic_target"}
    actor = actor_side(msg)
    np.testing.assert_allclose(actor.value_labels(b), lrn.value_labels(b), rtol=1e-5, atol=1e-6)
    a_online = actor.act(b.states[:4], explore=False)
    np.testing.assert_allclose(a_online, lrn.act(b.states[:4], explore=False), rtol=1e-5, atol=1e-6)


def test_online_labels_send_only_the_online_networks():
    lrn = trained("online")
    msg = policy_to_msg(lrn, version=20, env_steps=100)
    assert {name.partition(".")[0] for name in msg.tensor_names} == {"actor", "critic"}
    actor = actor_side(msg)
    b = batch(seed=98)
    np.testing.assert_allclose(actor.value_labels(b), lrn.value_labels(b), rtol=1e-5, atol=1e-6)
    for part in ("actor", "critic"):           # targets copy the online networks (only labels would use them)
        own, tgt = getattr(actor, part).state_dict(), getattr(actor, f"{part}_target").state_dict()
        assert all(torch.equal(own[k], tgt[k]) for k in own)
