"""The stand-in's wait for discovery (comper_agent.tools.ros2_cli.wait_until_stable): a list is taken once the graph has
not changed for the quiet spell and every endpoint's node is known, within a bound. The graph here is a script
of what discovery shows over time, on a clock that the spins advance."""
from comper_agent.tools.ros2_cli import wait_until_stable


class Discovery:
    """What the graph shows from each time on: [(t, state, complete)], earliest first; spin(s) advances the clock."""

    def __init__(self, script):
        self.script, self.t, self.spins = script, 0.0, 0

    def clock(self):
        return self.t

    def spin(self, seconds):
        self.t += seconds
        self.spins += 1

    def snapshot(self):
        shown = [(state, complete) for t, state, complete in self.script if t <= self.t + 1e-9]
        return shown[-1]

    def wait(self, stable_s=3.0, max_s=15.0):
        return wait_until_stable(self.snapshot, self.spin, stable_s=stable_s, max_s=max_s, clock=self.clock)


def test_nodes_arriving_seconds_apart_are_all_waited_for():
    # a loaded machine: the third node arrives 2 s after the second, the fourth 2.5 s after that
    d = Discovery([(0.0, ("a",), True), (0.4, ("a", "b"), True), (2.4, ("a", "b", "c"), True),
                   (4.9, ("a", "b", "c", "d"), True)])
    assert d.wait() is True
    assert d.snapshot()[0] == ("a", "b", "c", "d")
    assert 4.9 + 3.0 <= d.t < 4.9 + 3.2          # it ended one quiet spell after the last arrival


def test_an_endpoint_of_an_unknown_node_keeps_the_wait_going():
    # the endpoints of a node are seen at 1 s, its name only at 5 s: the graph looks unchanged meanwhile
    d = Discovery([(0.0, ("a",), True), (1.0, ("a",), False), (5.0, ("a", "b"), True)])
    assert d.wait(stable_s=1.0) is True
    assert d.snapshot()[0] == ("a", "b") and d.t >= 6.0


def test_a_graph_that_keeps_changing_ends_at_the_bound():
    d = Discovery([(i * 0.5, (str(i),), True) for i in range(100)])
    assert d.wait(stable_s=3.0, max_s=10.0) is False
    assert 10.0 <= d.t < 10.2


def test_a_settled_graph_returns_after_the_quiet_spell_and_zero_waits_for_nothing():
    d = Discovery([(0.0, ("a", "b"), True)])
    assert d.wait(stable_s=3.0) is True and 3.0 <= d.t < 3.2
    d = Discovery([(0.0, ("a", "b"), True)])
    assert d.wait(stable_s=0.0) is True and d.spins == 0
