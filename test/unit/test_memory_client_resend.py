"""MemoryClient (and SimClient.info) re-send a request whose answer is lost (resend_s): a stats request unanswered
after resend_s is sent again and the second answer returned, where before one lost answer cost the whole timeout (a
test's first call to a freshly started memory node waited 20 s for it on a loaded machine). The futures are rclpy's
own; the node and client objects stand in for rclpy's only where the clients create and call their rclpy clients."""
import time

from rclpy.task import Future

from comper_memory.client import MemoryClient
from comper_msgs.srv import GetStats


class DroppingClient:
    """An rclpy client whose first ``drop`` requests are never answered (their answers lost on the way)."""

    def __init__(self, srv_type, name, drop=1):
        self.srv_type, self.srv_name, self.drop, self.calls = srv_type, name, drop, 0
        self.requests = []

    def call_async(self, request):
        self.calls += 1
        self.requests.append(request)
        f = Future()
        if self.calls > self.drop:
            resp = self.srv_type.Response()
            if hasattr(resp, "stats"):
                resp.stats.transitions_stored = 7
            if hasattr(resp, "success"):
                resp.success = True
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


def test_a_snapshot_save_or_restore_whose_answer_is_lost_is_sent_again_with_the_same_request_id():
    """The node carries out a request id once (test_memory_faults: ..._carried_out_once), so the re-send
    must repeat the first call's id; each new call gets a new one."""
    node = Node()
    memory = MemoryClient(node, "memory_node", timeout=10.0, resend_s=0.3)
    memory.snapshot("a")
    client = node.clients["memory_node/snapshot"]
    first, again = client.requests
    assert memory.resent == 1 and first.request_id != 0
    assert (again.op, again.path, again.request_id) == (first.op, first.path, first.request_id)
    client.drop = client.calls + 1
    memory.restore("a")
    lost, sent = client.requests[2:]
    assert lost.request_id == sent.request_id != first.request_id and sent.op == sent.OP_RESTORE


def test_the_sim_clients_info_is_sent_again_when_its_answer_is_lost():
    from comper_sim.client import SimClient
    node = Node()
    sim = SimClient(node, "sim_node", timeout=10.0)
    sim.INFO_RESEND_S = 0.3
    sim.info()
    assert node.clients["sim_node/info"].calls == 2 and sim.resent == 1
