"""Hostile requests through grpcio, the client most learners use: malformed messages and oversized
fields get the status that names the client's mistake, in a message a client can read."""

import grpc
import pytest

import radserve
from radserve._proto import radserve_pb2 as pb


def _raw_call(server, method):
    channel = grpc.insecure_channel(server.address)
    call = channel.unary_unary(f"/radserve.v1.RadServe/{method}", request_serializer=None, response_deserializer=None)
    return channel, call


@pytest.mark.parametrize("payload", [b"\xff\xff\xff", b"\x0a\xff\x01", b"\x12\x05abc"], ids=["bad-tag", "truncated", "short-field"])
def test_malformed_protobuf_is_the_clients_fault(server, client, payload):
    channel, call = _raw_call(server, "CreateSession")
    with channel:
        with pytest.raises(grpc.RpcError) as raised:
            call(payload, timeout=10)
    assert raised.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert "not a valid CreateSessionRequest protobuf" in raised.value.details()
    assert client.list_envs("gym/CartPole")  # still serving


def test_huge_ids_come_back_as_the_real_error(client):
    # A 100 KB id used to be echoed whole: grpcio refused the trailer ("metadata size exceeds hard
    # limit", RESOURCE_EXHAUSTED) and the caller never saw why the call failed.
    with pytest.raises(radserve.NotFoundError, match=r"unknown session 'sss.*\(100000 bytes in all\)"):
        client.describe_session("s" * 100_000)
    with pytest.raises(radserve.InvalidArgumentError, match="env_id is 100000 bytes long; the most accepted is 256"):
        client.make_vec("e" * 100_000)
    with pytest.raises(radserve.InvalidArgumentError, match="a pipeline has at most 8 stages"):
        envs = client.make_vec("gym/CartPole-v1", replay_capacity=100)
        try:
            envs.reset()
            client.sample_batches(envs.session_id, batch_size=1, augment="|".join(["noise"] * 100))
        finally:
            envs.close()


def test_malformed_stream_messages_end_the_stream_cleanly(server, client):
    channel = grpc.insecure_channel(server.address)
    with channel:
        act = channel.stream_stream("/radserve.v1.RadServe/Act", request_serializer=None, response_deserializer=None)
        replies = act(iter([b"\xff\xff\xff"]), timeout=10)
        with pytest.raises(grpc.RpcError) as raised:
            list(replies)
    assert raised.value.code() == grpc.StatusCode.INVALID_ARGUMENT, raised.value
    assert "not a valid ActRequest protobuf" in raised.value.details()
    envs = client.make_vec("gym/CartPole-v1")  # still serving
    envs.close()


def test_typed_requests_with_wrong_enum_values_are_refused(server, client):
    envs = client.make_vec("gym/CartPole-v1", replay_capacity=100)
    try:
        envs.reset()
        request = pb.SampleBatchesRequest(session_id=envs.session_id, batch_size=1, sharing=77)
        with grpc.insecure_channel(server.address) as channel:
            sample = channel.unary_stream(
                "/radserve.v1.RadServe/SampleBatches",
                request_serializer=pb.SampleBatchesRequest.SerializeToString,
                response_deserializer=pb.BatchChunk.FromString,
            )
            with pytest.raises(grpc.RpcError) as raised:
                next(iter(sample(request, timeout=10)))
        assert raised.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert "unknown DrawSharing value 77" in raised.value.details()
    finally:
        envs.close()
