"""A large store through memory_node (issue 16): with ``store_chunk`` another client's calls are answered
between its chunks (each answer shows part of the batch applied), with ``store_chunk`` 0 never; a SIGKILL
in the middle leaves a storage the node starts from, holding the first chunks; the re-sent batch completes
it. Interleaving is asserted from what the answers contain, never from times."""
from __future__ import annotations

import signal
import threading

import numpy as np

from test_memory_node import client_of, start  # noqa: F401 - client_of is a fixture
from memory_worker import make_batch

N, CHUNK = 8192, 256
RID = 0x5EED_1234_5678   # the killed store's request id, re-sent to the restarted node


def store_while_polling(storer, poller, batch, stop_when=None, request_id=None):
    """Store `batch` in a thread while `poller` asks for stats; (reply or exception, transitions_stored
    seen by each stats answer that arrived while the store was unanswered). stop_when(seen): stop
    polling and return at once when it says so."""
    out, seen = {}, []

    def store():
        try:
            out["reply"] = storer.store(batch, timeout=120.0, request_id=request_id)
        except Exception as exc:  # noqa: BLE001 - reported by the caller
            out["reply"] = exc
    th = threading.Thread(target=store, daemon=True)
    before = poller.stats()["transitions_stored"]
    th.start()
    while th.is_alive():
        try:
            s = poller.stats(timeout=30.0)["transitions_stored"]
        except TimeoutError:
            break
        if th.is_alive():
            seen.append(s - before)
        if stop_when is not None and stop_when(s - before):
            return out.get("reply"), seen   # (the store's thread waits on; the test does not need it)
    th.join(timeout=120.0)
    return out.get("reply"), seen


def test_other_clients_are_answered_between_the_chunks_of_a_large_store(launch, client_of):  # noqa: F811
    proc, name = start(launch, "chunked", "-p", "key_size:=26", "-p", f"store_chunk:={CHUNK}")
    storer, poller = client_of(name), client_of(name)
    reply, seen = store_while_polling(storer, poller, make_batch(0, 0, N))
    assert reply.stored == N and reply.new_identities == N, reply
    np.testing.assert_array_equal(reply.identity_ids, np.arange(N, dtype=np.uint64))
    partial = [s for s in seen if 0 < s < N]
    assert partial, f"no stats answer arrived between chunks: {seen}"
    assert all(s % CHUNK == 0 for s in partial), seen      # whole chunks, in order
    assert seen == sorted(seen)
    assert poller.stats()["transitions_stored"] == N

    proc0, name0 = start(launch, "atomic", "-p", "key_size:=26", "-p", "store_chunk:=0")
    storer, poller = client_of(name0), client_of(name0)
    reply, seen = store_while_polling(storer, poller, make_batch(0, 0, N))
    assert reply.stored == N
    assert not [s for s in seen if 0 < s < N], seen        # one turn: nobody sees part of it
    assert proc.alive() and proc0.alive()


def test_sigkill_in_the_middle_of_a_large_store_leaves_a_state_the_node_starts_from(launch, client_of,  # noqa: F811
                                                                                     tmp_path):
    storage = tmp_path / "storage"
    params = ("-p", "key_size:=26", "-p", f"store_chunk:={CHUNK}", "-p", f"storage_dir:={storage}",
              "-p", "snapshot_every:=5")
    proc, name = start(launch, "kill", *params)
    storer, poller = client_of(name), client_of(name)
    batch = make_batch(1, 0, N)
    stored_before_kill = []

    def kill_when_partial(s):
        if 0 < s < N:
            stored_before_kill.append(s)
            proc.kill(signal.SIGKILL)
            return True
        return False
    reply, seen = store_while_polling(storer, poller, batch, stop_when=kill_when_partial, request_id=RID)
    assert stored_before_kill, f"the store ended before any answer between chunks: {seen}"
    assert not hasattr(reply, "stored"), "the killed node acknowledged the store"

    proc2, name2 = start(launch, "kill2", *params)
    memory = client_of(name2)
    s = memory.stats()
    # every chunk applied before the kill was logged first (flush); a torn last record is dropped
    assert stored_before_kill[0] <= s["transitions_stored"] < N and s["transitions_stored"] % CHUNK == 0
    assert s["identities"] == s["transitions_stored"]
    # the client re-sends the unanswered batch with its request id: the chunks left are applied, the
    # stored ones are not applied again, and the answer is the whole batch's
    r = memory.store(batch, request_id=RID)
    assert r.new_identities == N and r.stored == N
    np.testing.assert_array_equal(r.identity_ids, np.arange(N, dtype=np.uint64))
    assert memory.stats()["transitions_stored"] == N
    r = memory.store(batch)   # a new request id: the same transitions are stored again, joining their sets
    assert r.new_identities == 0 and memory.stats()["transitions_stored"] == 2 * N
    proc2.kill(signal.SIGTERM)
    assert proc2.proc.returncode == 0, proc2.log()


def test_a_store_sent_again_with_its_request_id_is_answered_once_and_not_applied_twice(launch, client_of):  # noqa: F811
    from comper_msgs.srv import Store
    from comper_msgs_py.convert import transitions_to_batch
    proc, name = start(launch, "resend", "-p", "key_size:=26", "-p", f"store_chunk:={CHUNK}")
    memory = client_of(name)
    req = Store.Request(request_id=12345)
    transitions_to_batch(make_batch(2, 0, 3 * CHUNK), req.batch)
    first = memory._call(memory._store, req)     # as if its answer were lost: the same request again
    again = memory._call(memory._store, req)
    assert not first.repeated and again.repeated
    assert list(again.identity_ids) == list(first.identity_ids) and again.stored == first.stored == 3 * CHUNK
    assert memory.stats()["transitions_stored"] == 3 * CHUNK
    # MemoryClient gives every store its own id: the same transitions stored again are applied again
    r = memory.store(make_batch(2, 0, 3 * CHUNK))
    assert r.new_identities == 0 and memory.stats()["transitions_stored"] == 6 * CHUNK
    assert proc.alive()
