"""Blocking service calls for rclpy learners, and the base of the suite's service clients.

Every client of the suite (``comper_memory.client.MemoryClient`` and ``ReductionClient``,
``comper_sim.client.SimClient``) is a :class:`ServiceClient`: it makes its rclpy clients on a node
that an executor spins in *another* thread, and each call blocks the calling thread on a
``threading.Event`` until that executor delivers the answer (it never spins). The suite's own
learners and QT trainer use these clients, so they are the first users of the API other learners get.

Errors (all :class:`ServiceError`, a ``RuntimeError``):

* :class:`ServiceUnavailable` - the server did not appear within the start-up timeout;
* :class:`ServiceTimeout` - no answer within the call's timeout (also a ``TimeoutError``), or the
  call was cancelled / the context shut down under it;
* :class:`ServiceRefused` - the server answered ``success: false``; ``message`` is its reason, and by
  the suite's contract nothing was changed by the refused call.

A node that no executor spins raises ``RuntimeError`` at once instead of waiting for the timeout.
"""
from __future__ import annotations

import os
import threading
import time

from .qos import SERVICE_QOS

__all__ = ["ServiceError", "ServiceUnavailable", "ServiceTimeout", "NoAnswer", "ServiceRefused", "PendingCall",
           "abandon_future", "call", "resend_until_answered", "wait_for_services", "ServiceClient"]


class ServiceError(RuntimeError):
    """A service call failed: unavailable, timed out, refused (success false) or interrupted."""


class ServiceUnavailable(ServiceError):
    """The service's server is not (yet) on the graph."""


class ServiceTimeout(ServiceError, TimeoutError):
    """No answer within the timeout, or the call was cancelled (shutting down)."""


class NoAnswer(ServiceTimeout):
    """The answer did not come within the timeout (the server may be slow, gone, or its answer lost)."""


class ServiceRefused(ServiceError):
    """The server answered success=false; ``message`` is its reason, ``service`` the service name."""

    def __init__(self, service: str, message: str):
        super().__init__(f"{service} refused: {message}")
        self.service = service
        self.message = message


def _waker(event: threading.Event):
    def wake(_future) -> None:
        event.set()
        # runs in the executor thread: give the GIL up once so the woken caller runs now instead
        # of after the executor's next round of Python bookkeeping (up to the switch interval)
        time.sleep(0)
    return wake


class PendingCall:
    """A service call in flight, made from a thread that does not spin the node: ``done()`` polls,
    ``result(timeout)`` waits for the answer."""

    def __init__(self, client, request, what: str | None = None, *, refused: type = ServiceRefused,
                 woken: threading.Event | None = None):
        """woken: an event that this call's answer sets, shared by several sends of one request
        (``ServiceClient._call``); by default the call's own."""
        self.client = client
        self.name = what or client.srv_name
        self.refused = refused
        self._done = threading.Event() if woken is None else woken
        self.future = client.call_async(request)
        self.future.add_done_callback(_waker(self._done))

    def done(self) -> bool:
        return self.future.done()

    #: after a stop request, how long the server may be missing from the graph before the wait ends
    GONE_S = 1.0

    def result(self, timeout: float = 60.0, *, check: bool = True, stop: threading.Event | None = None):
        """The response. ServiceTimeout on timeout or cancellation, ServiceError when the call raised,
        ServiceRefused (check) when the response says success false. stop: once it is set, the wait ends
        with ServiceUnavailable as soon as the server has been gone from the graph for GONE_S (a node
        stopping on SIGTERM whose servers stop with it does not wait out a long timeout); while the
        server is there the wait goes on as before (a final checkpoint still gets its answers)."""
        name, future = self.name, self.future
        try:
            # an answered future may not have run its wake callback yet (the executor runs it as a task)
            if not future.done() and not self._wait(timeout, stop):
                raise NoAnswer(f"{name}: no answer within {timeout:g} s (is the node still running?)")
        except (NoAnswer, ServiceUnavailable):
            self.abandon()
            raise
        if future.cancelled():
            raise ServiceTimeout(f"{name}: the call was cancelled (shutting down?)")
        exc = future.exception()
        if exc is not None:
            raise ServiceError(f"{name}: {type(exc).__name__}: {exc}")
        response = future.result()
        if response is None:
            raise ServiceTimeout(f"{name}: no response (context shut down?)")
        if check and getattr(response, "success", True) is False:
            raise self.refused(name, response.message)
        return response

    def abandon(self) -> None:
        """Stop waiting for this call: its answer, should it still come, is dropped."""
        abandon_future(self.client, self.future)

    def _wait(self, timeout: float, stop: threading.Event | None, gone: list | None = None) -> bool:
        """Wait until the (shared) wake event is set, at most ``timeout`` s; see :meth:`result` for stop.
        gone: a one-item list holding since when the server has been missing (None: there), kept across the
        waits of several sends of one request (``ServiceClient._call``), so short waits still add up to GONE_S."""
        if stop is None:
            return self._done.wait(timeout)
        deadline, gone = time.monotonic() + timeout, [None] if gone is None else gone
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            if self._done.wait(min(left, 0.2)):
                return True
            if not stop.is_set() or self.client.service_is_ready():
                gone[0] = None
            elif gone[0] is None:
                gone[0] = time.monotonic()
            elif time.monotonic() - gone[0] >= self.GONE_S:
                raise ServiceUnavailable(f"{self.name}: the server left while this call waited for its answer, "
                                         "after a stop was requested")


def call(client, request, timeout: float = 60.0, *, what: str | None = None, check: bool = True):
    """Blocking call from a thread that does not spin the node (an executor spins it elsewhere).

    check: raise ServiceRefused when the response has ``success == False`` (with its message)."""
    return PendingCall(client, request, what).result(timeout, check=check)


def abandon_future(client, future) -> None:
    """Give up one ``client.call_async`` future: the client forgets it (a late answer is dropped, not kept in
    its pending table) and the future is cancelled."""
    client.remove_pending_request(future)
    future.cancel()


def resend_until_answered(send, wait, drop, timeout: float, resend_s: float) -> tuple:
    """Send a request, and send it again each time ``resend_s`` seconds pass without an answer to any send
    of it, until one is answered or ``timeout`` seconds are over. Every send's answer counts: a late answer
    to the first one ends the wait as well as an answer to the last.

    send() makes one call and returns it as anything with ``done()`` (an rclpy future, a PendingCall);
    wait(calls, seconds) returns once one of ``calls`` is done or ``seconds`` have passed (it may raise to end
    the wait); drop(call) gives one send up. Every send but the answered one is dropped before this returns,
    and every send when ``wait`` raises. resend_s <= 0 or >= timeout: one send. Returns (the answered call, or
    None when the timeout ran out; every call sent). Only for requests whose repetition is harmless (reads, or
    stores the server recognises by a request id)."""
    resend = 0 < resend_s < timeout
    deadline = time.monotonic() + timeout
    calls = [send()]
    answered = None
    try:
        while True:
            answered = next((c for c in calls if c.done()), None)
            left = deadline - time.monotonic()
            if answered is not None or left <= 0:
                break
            wait(calls, min(resend_s, left) if resend else left)
            if resend and not any(c.done() for c in calls) and deadline - time.monotonic() > 0:
                calls.append(send())
    except BaseException:
        for c in calls:
            drop(c)
        raise
    for c in calls:
        if c is not answered:
            drop(c)
    return answered, calls


def wait_for_services(clients: dict, timeout: float, hints: dict | None = None,
                      stop: threading.Event | None = None) -> None:
    """Wait until every client's service is available; ServiceUnavailable lists the missing ones.

    clients: label -> rclpy client; hints: label -> how to start the server; stop: give up early."""
    deadline = time.monotonic() + timeout
    pending = dict(clients)
    while pending:
        for label, c in list(pending.items()):
            if c.service_is_ready():
                del pending[label]
        if not pending:
            return
        if time.monotonic() > deadline or (stop is not None and stop.is_set()):
            lines = [f"  {c.srv_name}" + (f"   (start it: {hints[label]})" if hints and label in hints else "")
                     for label, c in pending.items()]
            raise ServiceUnavailable(f"services not available after {timeout:g} s:\n" + "\n".join(lines) +
                                     "\n(check node names, ROS_DOMAIN_ID and ROS_AUTOMATIC_DISCOVERY_RANGE, "
                                     "or use bringup:=embedded)")
        time.sleep(0.05)


class ServiceClient:
    """Base of a client of one server node: rclpy clients named ``<server>/<service>``.

    node: an rclpy node spun by an executor in another thread (or use :meth:`standalone`).
    server: the server node's name or fully qualified name ('/ns/name'); a relative name resolves
    in the node's namespace. timeout: default seconds per call (each method also takes ``timeout=``).
    Subclasses make their clients with :meth:`_make` and call with :meth:`_call`; a refusal raises
    their ``REFUSED`` class (a ServiceRefused).
    """

    REFUSED: type = ServiceRefused
    NODE_NAME = "service_client"   # standalone node names: <NODE_NAME>_<pid>_<n>

    def __init__(self, node, server: str, *, timeout: float = 30.0, callback_group=None):
        self.node = node
        self.server = server.rstrip("/")
        self.timeout = float(timeout)
        self._group = callback_group
        self._clients: list = []
        self.resent = 0      # requests sent again because their answer did not come (_call's resend_s)
        #: a node's stop request (e.g. its SIGTERM handler's event): once set, a call whose server has left
        #: the graph ends at once (PendingCall.result) instead of waiting out its timeout
        self.stop: threading.Event | None = None
        self._owned = None   # (own context or None, executor, thread) of a standalone client

    def _make(self, srv_type, name: str):
        c = self.node.create_client(srv_type, f"{self.server}/{name}", qos_profile=SERVICE_QOS,
                                    callback_group=self._group)
        self._clients.append(c)
        return c

    # --- construction -------------------------------------------------------------------------
    @classmethod
    def standalone(cls, server: str, context=None, *, node_name: str | None = None, timeout: float = 30.0,
                   **kwargs):
        """A client with its own node and a background executor thread; ``close()`` (or ``with``)
        tears them down. context=None: a private rclpy context is created and shut down by
        ``close()``; a given context must already be initialised and is left running."""
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node

        own_context = context is None
        if own_context:
            context = rclpy.Context()
            rclpy.init(context=context)
        try:
            name = node_name or f"{cls.NODE_NAME}_{os.getpid()}_{id(context) % 100000}"
            # a pure client: no parameter services, so each executor round has less to wait on
            node = Node(name, context=context, start_parameter_services=False)
            executor = SingleThreadedExecutor(context=context)
            executor.add_node(node)
        except Exception:
            if own_context:
                context.try_shutdown()
            raise
        thread = threading.Thread(target=_spin, args=(executor,), name=f"{name}_executor", daemon=True)
        thread.start()
        client = cls(node, server, timeout=timeout, **kwargs)
        client._owned = (context if own_context else None, executor, thread)
        return client

    def close(self) -> None:
        """Destroy the rclpy clients; a standalone client also stops its executor thread, destroys
        its node and shuts its private context down. Idempotent."""
        owned, self._owned = self._owned, None
        if owned is not None:
            context, executor, thread = owned
            executor.shutdown(timeout_sec=5.0)
            thread.join(timeout=5.0)
            self.node.destroy_node()
            if context is not None:
                context.try_shutdown()
        else:
            for c in self._clients:
                self.node.destroy_client(c)
        self._clients = []

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # --- plumbing -----------------------------------------------------------------------------
    def wait_for_service(self, timeout: float | None = None) -> bool:
        """True once every service of the server is available (False after `timeout` s)."""
        deadline = time.monotonic() + (self.timeout if timeout is None else float(timeout))
        for c in self._clients:
            if not c.wait_for_service(timeout_sec=max(0.0, deadline - time.monotonic())):
                return False
        return True

    def ready(self) -> bool:
        """Every service of the server is available now (no waiting)."""
        return all(c.service_is_ready() for c in self._clients)

    def _check_spun(self) -> None:
        if self.node.executor is None:
            raise RuntimeError(f"{type(self).__name__}: node {self.node.get_name()!r} is not spun by any "
                               f"executor; spin it in a background thread or use {type(self).__name__}.standalone()")

    def _send(self, client, request) -> PendingCall:
        self._check_spun()
        return PendingCall(client, request, refused=self.REFUSED)

    def _call(self, client, request, timeout: float | None = None, *, check: bool = True,
              resend_s: float = 0.0):
        """One call; resend_s > 0: a request without an answer after resend_s seconds is sent again (only for
        requests whose repetition is harmless: reads, or stores the server recognises by a request id), until
        one is answered or ``timeout`` is over (:func:`resend_until_answered`): the first answer to any of the
        sends is the call's, the others are dropped. ``self.resent`` counts the repetitions."""
        timeout = self.timeout if timeout is None else float(timeout)
        if not resend_s or resend_s <= 0 or resend_s >= timeout:
            return self._send(client, request).result(timeout, check=check, stop=self.stop)
        self._check_spun()
        woken = threading.Event()     # set by the answer to any of the sends
        gone: list = [None]           # since when the server has been missing after a stop (PendingCall._wait)
        answered, calls = resend_until_answered(
            lambda: PendingCall(client, request, refused=self.REFUSED, woken=woken),
            lambda calls, seconds: calls[0]._wait(seconds, self.stop, gone),
            PendingCall.abandon, timeout, resend_s)
        self.resent += len(calls) - 1
        if answered is None:
            raise NoAnswer(f"{client.srv_name}: no answer within {timeout:g} s (sent {len(calls)} times, "
                           f"every {resend_s:g} s; is the node still running?)")
        return answered.result(0.0, check=check)


def _spin(executor) -> None:
    from rclpy.executors import ExternalShutdownException
    try:
        executor.spin()
    except (ExternalShutdownException, KeyboardInterrupt):
        pass
