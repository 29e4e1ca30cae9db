"""PendingCall.result with a stop event (comper_msgs_py.service_client): after a stop request, a call whose
server has left the graph ends within about GONE_S instead of waiting out its timeout; while the server is
there (or before any stop) it waits for the answer as before. The call's future is rclpy's own; the client
object stands in for an rclpy client only where the graph is asked (service_is_ready)."""
import threading
import time

import pytest
from rclpy.task import Future

from comper_msgs_py.service_client import NoAnswer, PendingCall, ServiceUnavailable


class Server:
    """What PendingCall uses of an rclpy client; ``ready`` says whether the server is on the graph."""
    srv_name = "/sim/step"

    def __init__(self):
        self.ready = True
        self.future = None
        self.removed = False

    def call_async(self, request):
        self.future = Future()
        return self.future

    def service_is_ready(self):
        return self.ready

    def remove_pending_request(self, future):
        self.removed = True


def test_a_stop_ends_a_wait_on_a_server_that_left_and_only_then():
    server, stop = Server(), threading.Event()
    call = PendingCall(server, object())
    stop.set()                                  # stop requested, but the server is still there: keep waiting
    threading.Timer(0.6, lambda: server.future.set_result("answer")).start()
    assert call.result(30.0, stop=stop) == "answer"

    call = PendingCall(server, object())        # the server leaves while the stopped node waits
    server.ready = False
    t0 = time.monotonic()
    with pytest.raises(ServiceUnavailable, match="left while this call waited"):
        call.result(60.0, stop=stop)
    assert time.monotonic() - t0 < PendingCall.GONE_S + 2.0 and server.removed and call.future.cancelled()


def test_without_a_stop_a_missing_server_is_waited_for_until_the_timeout():
    server, stop = Server(), threading.Event()
    server.ready = False
    call = PendingCall(server, object())
    t0 = time.monotonic()
    with pytest.raises(NoAnswer):
        call.result(1.5, stop=stop)             # no stop: the timeout decides, as without the event
    assert time.monotonic() - t0 >= 1.5
    call = PendingCall(server, object())
    threading.Timer(0.3, lambda: server.future.set_result("late")).start()
    assert call.result(5.0) == "late"


def test_an_answered_call_whose_wake_callback_has_not_run_yet_returns_its_answer():
    """rclpy runs a future's done callbacks as tasks of its executor, so a future can be done before the
    callback that wakes the waiting thread has run; result() takes the answer then instead of waiting."""
    class IdleExecutor:                   # holds the callbacks it is given and never runs them
        def __init__(self):
            self.tasks = []

        def create_task(self, callback, *args):
            self.tasks.append(callback)

    server, executor = Server(), IdleExecutor()
    call = PendingCall(server, object())
    server.future._set_executor(executor)
    server.future.set_result("answer")
    assert executor.tasks and not call._done.is_set()
    assert call.done() and call.result(0.0) == "answer"
