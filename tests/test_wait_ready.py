"""A learner started before its servers: `Client(wait_ready_s=...)` waits until every server answers
SERVING (real servers, the real health service), or names the ones that did not in time."""

import socket
import threading
import time

import pytest

import radserve
from radserve._transport import _health_status


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def test_a_client_started_20_s_before_its_server_waits_and_works():
    address = f"127.0.0.1:{_free_port()}"
    outcome: dict = {}

    def learner():
        started = time.monotonic()
        try:
            outcome["client"] = radserve.Client(address, wait_ready_s=180)
        except Exception as error:  # reported below
            outcome["error"] = error
        outcome["waited"] = time.monotonic() - started

    thread = threading.Thread(target=learner)
    thread.start()
    time.sleep(20)
    assert thread.is_alive(), f"the client did not wait for a server that is not there: {outcome}"
    # From the main thread: LocalServer ties the server's life to the thread that starts it.
    with radserve.LocalServer(workers=1, address=address) as server:
        thread.join(180)
        assert "error" not in outcome, outcome.get("error")
        assert outcome["waited"] >= 20
        with outcome["client"] as client:
            # SERVING means the catalog is built: the first session needs no more waiting.
            envs = client.make_vec("gym/CartPole-v1", num_envs=2, seed=0)
            envs.reset(seed=0)
            envs.close()
        assert server.address == address


def test_servers_that_never_answer_are_named_with_what_they_last_said():
    addresses = [f"127.0.0.1:{_free_port()}", f"127.0.0.1:{_free_port()}"]
    started = time.monotonic()
    with pytest.raises(radserve.UnavailableError) as raised:
        radserve.Client(addresses, wait_ready_s=2)
    assert 2 <= time.monotonic() - started < 15
    message = str(raised.value)
    assert "2 of 2 radserve servers did not answer SERVING within 2" in message
    assert all(address in message for address in addresses), message


def test_the_health_answer_is_read_as_grpc_health_v1_writes_it():
    assert _health_status(b"") == 0  # UNKNOWN: the field absent
    assert _health_status(b"\x08\x01") == 1  # SERVING
    assert _health_status(b"\x08\x02") == 2  # NOT_SERVING
    assert _health_status(b"\x08\x83\x01") == 131  # a varint of two bytes
