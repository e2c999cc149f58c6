"""Mapping memory a radserve server shares with a client on its host (minibatches, shared stepping).

The server never names the memory: the client connects to the abstract Unix socket the server
described over gRPC, sends the 16-byte token it was given, and receives the memory's file
descriptor (SCM_RIGHTS). The server checks the client's user (SO_PEERCRED) before it reads the token.
"""

import mmap
import os
import socket

from .errors import SharedMemoryError

# How long the server may take to hand the descriptor over once the token is sent.
_HANDOFF_TIMEOUT_S = 10.0


def receive_server_memory(socket_name: str, token: bytes, size: int, magic: bytes, what: str, hint: str,
                          ) -> "tuple[mmap.mmap, socket.socket]":
    """Connects to the server's socket `socket_name`, presents `token`, maps the `size` bytes of
    memory it hands over and checks that they start with `magic` and `token`. Returns the mapping and
    the connection (a shared-stepping channel goes on using it; close it otherwise)."""
    connection = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    connection.settimeout(_HANDOFF_TIMEOUT_S)
    try:
        connection.connect("\0" + socket_name)
        connection.sendall(token)
        _, fds, _, _ = socket.recv_fds(connection, 1, 1)
    except OSError as error:
        connection.close()
        raise SharedMemoryError(f"cannot receive the server's {what} over {socket_name!r}: {error}; {hint}") from None
    connection.settimeout(None)
    if not fds:
        connection.close()
        raise SharedMemoryError(
            f"the server did not hand over its {what}: it refused this process (another user than the server's, "
            f"see server.shared_memory_uids) or the token; {hint}")
    try:
        memory = mmap.mmap(fds[0], size, mmap.MAP_SHARED, mmap.PROT_READ | mmap.PROT_WRITE)
    except (OSError, ValueError) as error:
        connection.close()
        raise SharedMemoryError(f"cannot map {size} bytes of the server's {what}: {error}; {hint}") from None
    finally:
        for fd in fds:
            os.close(fd)
    if memory[:16] != magic or memory[16:32] != token:
        memory.close()
        connection.close()
        raise SharedMemoryError(f"the memory handed over is not the {what} the server described (its token differs)")
    return memory, connection
