"""The gRPC API's generated code, for callers who speak `radserve.v1` directly:
`radserve_pb2` (the messages) and `radserve_pb2_grpc` (the stubs), as `grpcio-tools` generates them
from `proto/radserve/v1/radserve.proto`; and the conversions the client itself uses between those
messages and numpy / gymnasium (`to_numpy`, `to_tensor`, `to_space`, `option_value`,
`from_option_value`).

    >>> from radserve.proto import radserve_pb2 as pb, radserve_pb2_grpc as pb_grpc, to_numpy
    >>> stub = pb_grpc.RadServeStub(grpc.insecure_channel("127.0.0.1:50051"))
    >>> stub.ServerInfo(pb.ServerInfoRequest()).version
"""

from ._convert import from_option_value, option_value, to_numpy, to_space, to_tensor
from ._proto import radserve_pb2, radserve_pb2_grpc

__all__ = ["radserve_pb2", "radserve_pb2_grpc", "to_numpy", "to_tensor", "to_space", "option_value",
           "from_option_value"]
