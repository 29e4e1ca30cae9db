"""async_acting: the acting side of comcact_node's ``mode:=async`` (docs/comcact.md, Async mode).

:class:`AsyncActing` - the policy the learner publishes (``<learner>/policy``, PolicyWeights, from a DDS
participant of its own), the actor processes it starts in the embedded bring-up (:class:`ActorFleet`), the
memory node's rate limiter that holds the update-to-data ratio (:func:`rate_limit_params`), and the
environment steps, counted from what the actors stored. The learning loop itself is comcact_node's
``_loop_async``.
"""
from __future__ import annotations

import time

from comper_agent.nodes.actor_node import ActorFleet, rate_limit_params
from comper_agent.nodes.policy_weights import PolicyPublisher

__all__ = ["AsyncActing"]


class AsyncActing:
    """node: the learner's rclpy node (the policy topic is ``<node>/policy``); p, cfg: its parameters and
    learner hyper-parameters. ``rate_limits``: the embedded memory node's rate limiter parameters."""

    def __init__(self, node, p, cfg):
        self.p, self.cfg = p, cfg
        self.rate_limits = rate_limit_params(p, cfg)
        self.pub = PolicyPublisher(f"{node.get_fully_qualified_name()}/policy", f"{node.get_name()}_policy")
        self.fleet: ActorFleet | None = None
        self.h = None

    def start(self, h, learner, step: int) -> None:
        """Before the loop: the environment steps' base (the memory's count now), re-stores marked apart, the
        policy published, the actors started (embedded bring-up). h: the learner's harness."""
        p = self.p
        self.h = h
        self.base = self._stored_by_actors() - step
        h.mem.relabel_apart = True   # restore_batch: re-stores are not environment steps for the rate limiter
        self.publish(learner, step)
        if p.bringup == "embedded" and p.num_actors > 0:
            self.fleet = ActorFleet(
                num_actors=p.num_actors, env_id=p.env_id, seed=int(self.cfg.seed), memory_node=p.memory_node,
                policy_topic=self.pub.topic_name, steps_each=-(-(p.total_steps - step) // p.num_actors),
                episode_end=h.episode_rule, log_dir=h.run_dir.path, startup_timeout_s=p.startup_timeout_s)
            h.log.info(f"async: {p.num_actors} actor processes started (logs {h.run_dir.path}/actor_*.log), "
                       f"rate limiter {self.rate_limits}")
        self.last_policy = time.monotonic()

    def _stored_by_actors(self) -> int:
        """Transitions in the memory's count that are not the learner's re-stores (restore_batch)."""
        with self.h.ptimers("memory"):
            return int(self.h.mem.stats()["transitions_stored"]) - self.h.mem.restored

    def env_steps(self) -> int:
        """Environment steps so far: transitions the actors stored since this run started."""
        return self._stored_by_actors() - self.base

    def check(self) -> None:
        """RuntimeError when an actor process failed."""
        failed = self.fleet.failed() if self.fleet is not None else []
        if failed:
            raise RuntimeError("an actor failed: " + " | ".join(failed))

    def publish(self, learner, step: int, final: bool = False) -> None:
        with self.h.ptimers("publish"):
            self.pub.send(learner, env_steps=step, final=final)

    def publish_when_due(self, learner, step: int) -> None:
        """The policy again every ``policy_period_s``."""
        if time.monotonic() - self.last_policy >= self.p.policy_period_s:
            self.publish(learner, step)
            self.last_policy = time.monotonic()

    def stop(self, updates: int, env_steps: int) -> None:
        """At the end: the actors stopped, their exit codes and the update-to-data ratio in an 'actors' record."""
        if self.fleet is None:
            return
        h = self.h
        codes = self.fleet.stop()
        h.log.info(f"async: actors exited with {codes}")
        h.metrics.write("actors", exit_codes=codes, policies_published=self.pub.published, updates=updates,
                        env_steps=env_steps, update_to_data=updates / max(1, env_steps), relabelled=int(h.mem.restored))

    def close(self) -> None:
        if self.pub is not None:
            self.pub.close()
            self.pub = None
