"""Mapping memory a radserve server shares with a client on its host (minibatches, acting)."""

import mmap
import os

from .errors import SharedMemoryError


def map_server_memory(path: str, size: int, magic: bytes, token: bytes, what: str, hint: str) -> mmap.mmap:
    """Maps `size` bytes of the server's memory file `path` (`/proc/<server pid>/fd/<n>`) and checks
    that it starts with `magic` and `token`, i.e. that it is the memory the server described."""
    try:
        fd = os.open(path, os.O_RDWR)
    except OSError as error:
        raise SharedMemoryError(f"cannot open the server's {what} {path}: {error}; {hint}") from None
    try:
        memory = mmap.mmap(fd, size, mmap.MAP_SHARED, mmap.PROT_READ | mmap.PROT_WRITE)
    except (OSError, ValueError) as error:
        raise SharedMemoryError(f"cannot map {size} bytes of {path}: {error}; {hint}") from None
    finally:
        os.close(fd)
    if memory[:16] != magic or memory[16:32] != token:
        memory.close()
        raise SharedMemoryError(f"{path} is not the {what} the server described (its token differs); {hint}")
    return memory
