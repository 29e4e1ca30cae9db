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


class LateClient(DroppingClient):
    """An rclpy client that answers nothing by itself: the test answers its futures (from another thread)."""

    def __init__(self, srv_type, name):
        super().__init__(srv_type, name, drop=10**9)
        self.futures, self.removed = [], []

    def call_async(self, request):
        f = super().call_async(request)
        self.futures.append(f)
        return f

    def remove_pending_request(self, future):
        self.removed.append(future)


def test_a_late_answer_to_the_first_send_ends_the_wait_and_the_other_sends_are_dropped():
    """Under load an answer can come after resend_s: it is the call's answer, not discarded for the re-send's
    (the re-send loop used to cancel each send before the next, so a server that always took longer than
    resend_s was never heard)."""
    import threading

    node = Node()
    node.create_client = lambda srv_type, name, qos_profile=None, callback_group=None: \
        node.clients.setdefault(name, LateClient(srv_type, name))
    memory = MemoryClient(node, "memory_node", timeout=10.0, resend_s=0.2)
    client = node.clients["memory_node/get_stats"]

    def answer_the_first_late():
        while len(client.futures) < 3:        # two re-sends went out without an answer
            time.sleep(0.01)
        resp = GetStats.Response()
        resp.stats.transitions_stored = 11
        client.futures[0].set_result(resp)

    t = threading.Thread(target=answer_the_first_late)
    t.start()
    t0 = time.monotonic()
    assert memory.stats()["transitions_stored"] == 11
    t.join()
    assert time.monotonic() - t0 < 3.0
    assert memory.resent == len(client.futures) - 1 >= 2
    assert client.futures[0] not in client.removed
    assert set(client.removed) == set(client.futures[1:]) and all(f.cancelled() for f in client.futures[1:])


def test_resend_until_answered_sends_every_resend_s_and_gives_up_at_the_timeout():
    from comper_msgs_py.service_client import resend_until_answered

    sent = []

    def send():
        sent.append(Future())
        return sent[-1]

    def nap(calls, seconds):
        time.sleep(seconds)

    answered, futures = resend_until_answered(send, nap, lambda f: None, timeout=0.55, resend_s=0.2)
    assert answered is None and futures == sent and len(sent) == 3      # at 0, 0.2 and 0.4 s
    sent.clear()
    answered, futures = resend_until_answered(send, nap, lambda f: None, timeout=0.3, resend_s=0.0)
    assert answered is None and len(sent) == 1                           # resend_s 0: one send

    def send_answered_on_the_second():
        f = send()
        if len(sent) == 2:
            f.set_result("ok")
        return f
    sent.clear()
    answered, futures = resend_until_answered(send_answered_on_the_second, nap, lambda f: None,
                                              timeout=5.0, resend_s=0.05)
    assert answered is sent[1] and len(futures) == 2 and answered.result() == "ok"


def test_a_stop_ends_a_re_sending_call_whose_server_left_and_drops_every_send():
    import threading

    import pytest

    from comper_msgs_py.service_client import ServiceUnavailable

    node = Node()
    node.create_client = lambda srv_type, name, qos_profile=None, callback_group=None: \
        node.clients.setdefault(name, LateClient(srv_type, name))
    memory = MemoryClient(node, "memory_node", timeout=30.0, resend_s=0.2)
    client = node.clients["memory_node/get_stats"]
    client.service_is_ready = lambda: False        # the memory node has left the graph
    memory.stop = threading.Event()
    memory.stop.set()
    t0 = time.monotonic()
    with pytest.raises(ServiceUnavailable):
        memory.stats()
    assert time.monotonic() - t0 < 5.0
    assert client.futures and set(client.removed) == set(client.futures)
