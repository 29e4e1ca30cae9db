"""MemoryClient re-sends a read whose answer is lost (resend_s): a stats request unanswered after resend_s is sent
again and the second answer returned, where before one lost answer cost the whole timeout (a test's first call
to a freshly started memory node waited 20 s for it on a loaded machine). The futures are rclpy's own; the node
and client objects stand in for rclpy's only where MemoryClient creates and calls its clients."""
import time

from rclpy.task import Future

from comper_memory.client import MemoryClient
from comper_msgs.srv import GetStats


class DroppingClient:
    """An rclpy client whose first ``drop`` requests are never answered (their answers lost on the way)."""

    def __init__(self, srv_type, name, drop=1):
        self.srv_type, self.srv_name, self.drop, self.calls = srv_type, name, drop, 0

    def call_async(self, request):
        self.calls += 1
        f = Future()
        if self.calls > self.drop:
            resp = self.srv_type.Response()
            resp.stats.transitions_stored = 7
            f.set_result(resp)
        return f

    def service_is_ready(self):
        return True

    def remove_pending_request(self, future):
        pass


class Node:
    executor = object()          # "spun": MemoryClient only checks that an executor is there

    def __init__(self):
        self.clients = {}

    def create_client(self, srv_type, name, qos_profile=None, callback_group=None):
        self.clients[name] = DroppingClient(srv_type, name)
        return self.clients[name]


def test_a_stats_request_whose_answer_is_lost_is_sent_again_after_resend_s():
    node = Node()
    memory = MemoryClient(node, "memory_node", timeout=10.0, resend_s=0.3)
    t0 = time.monotonic()
    assert memory.stats()["transitions_stored"] == 7
    assert time.monotonic() - t0 < 3.0 and memory.resent == 1
    assert node.clients["memory_node/get_stats"].calls == 2
    assert node.clients["memory_node/get_stats"].srv_type is GetStats
