"""The gRPC byte stream's ceiling for batches of a given size, for benchmarks only: a stand-in server
that sends one batch's messages, recorded from a real radserve stream, again and again, and the
client's own decoding (`radserve.BatchStream`) reading them. Nothing is sampled or augmented, so what
is measured is the transport alone (gRPC framing, the socket, the client's parsing into numpy) for
the same message sizes; bench/replay_stream.py puts it beside radserve's served rate.

The stand-in runs in a process of its own (grpcio's C core, the messages pre-serialized once), so
that it takes the other core as the server would, not the learner's.
"""

from __future__ import annotations

import multiprocessing
from concurrent import futures

import grpc

import radserve
from radserve.proto import radserve_pb2 as pb

_METHOD = "/radserve.v1.RadServe/SampleBatches"
_OPTIONS = [("grpc.max_receive_message_length", -1), ("grpc.max_send_message_length", -1)]


def record_batch(client: "radserve.Client", request: "pb.SampleBatchesRequest") -> "list[bytes]":
    """The messages of the first batch the server sends for `request`, as the bytes it sent."""
    once = pb.SampleBatchesRequest()
    once.CopyFrom(request)
    once.max_batches = 1
    method = client.transports[0].channel.unary_stream(
        _METHOD, request_serializer=pb.SampleBatchesRequest.SerializeToString, response_deserializer=None)
    return list(method(once))


def _serve(messages: "list[bytes]", ports, stop) -> None:
    def sample_batches(request: "pb.SampleBatchesRequest", context):
        count = request.max_batches if request.HasField("max_batches") else None
        sent = 0
        while count is None or sent < count:
            yield from messages
            sent += 1

    handler = grpc.method_handlers_generic_handler("radserve.v1.RadServe", {
        "SampleBatches": grpc.unary_stream_rpc_method_handler(
            sample_batches, request_deserializer=pb.SampleBatchesRequest.FromString,
            response_serializer=lambda message: message),
    })
    server = grpc.server(futures.ThreadPoolExecutor(max_workers=2), handlers=[handler], options=_OPTIONS)
    ports.put(server.add_insecure_port("127.0.0.1:0"))
    server.start()
    stop.wait()
    server.stop(grace=None)


class RecordedServer:
    """The stand-in server for `messages` (one batch), while in a `with` block."""

    def __init__(self, messages: "list[bytes]"):
        context = multiprocessing.get_context("spawn")
        ports, self._stop = context.Queue(), context.Event()
        self._process = context.Process(target=_serve, args=(messages, ports, self._stop), daemon=True)
        self._process.start()
        self.address = f"127.0.0.1:{ports.get(timeout=60)}"
        self._channel = grpc.insecure_channel(self.address, options=_OPTIONS)

    def stream(self, max_batches: "int | None" = None) -> "radserve.BatchStream":
        """The recorded batch over and over (`max_batches` times, or until closed), decoded as radserve's
        client decodes a SampleBatches stream."""
        method = self._channel.unary_stream(
            _METHOD, request_serializer=pb.SampleBatchesRequest.SerializeToString, response_deserializer=None)
        request = pb.SampleBatchesRequest() if max_batches is None else pb.SampleBatchesRequest(max_batches=max_batches)
        return radserve.BatchStream(method(request))

    def __enter__(self) -> "RecordedServer":
        return self

    def __exit__(self, *exc_info) -> None:
        self._channel.close()
        self._stop.set()
        self._process.join(timeout=10)
