"""SHA-256 whose running state can be saved and resumed in another process.

``hashlib`` copies a hash's state only within one process. A stage's output starts with its
input's data section byte for byte, so the SHA-256 of the output continues the state its
input's hash had at the end of that section: with that state saved (see
:mod:`starlog.io.digest_cache`), the next stage knows its input's digest without reading it.

The state is OpenSSL's ``SHA256_CTX`` (eight 32-bit chaining words, the bit count, the pending
block, its fill), driven through libcrypto's ``SHA256_Init`` / ``SHA256_Update`` /
``SHA256_Final`` (the library ``hashlib`` itself uses). Where libcrypto cannot be loaded, or a
state saved and resumed does not give ``hashlib``'s digest on a test input, :func:`available`
is False and callers hash whole files with ``hashlib`` as before.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import hashlib
from functools import cache
from typing import Any

__all__ = ["ResumableSha256", "available", "STATE_SIZE"]

#: Bytes of a saved state: ``sizeof(SHA256_CTX)`` (28 32-bit words).
STATE_SIZE = 112
_BUFFER = 512  # room for a context larger than expected: the self-test then fails, nothing overflows


@cache
def _libcrypto() -> Any | None:
    name = ctypes.util.find_library("crypto")
    if name is None:
        return None
    try:
        lib = ctypes.CDLL(name)
        for fn in (lib.SHA256_Init, lib.SHA256_Update, lib.SHA256_Final):
            fn.restype = ctypes.c_int
        lib.SHA256_Update.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_size_t]
    except (OSError, AttributeError):
        return None
    return lib


class ResumableSha256:
    """A SHA-256 hash, started fresh or from a saved :meth:`state`."""

    def __init__(self, state: bytes | None = None) -> None:
        lib = _libcrypto()
        if lib is None:
            raise RuntimeError("libcrypto's SHA256 functions are not available")
        self._lib = lib
        self._ctx = ctypes.create_string_buffer(_BUFFER)
        if state is None:
            lib.SHA256_Init(self._ctx)
        else:
            if len(state) != STATE_SIZE:
                raise ValueError(f"a SHA-256 state has {STATE_SIZE} bytes, not {len(state)}")
            ctypes.memmove(self._ctx, state, STATE_SIZE)

    def update(self, data: bytes | bytearray | memoryview) -> None:
        """Hash ``data`` (libcrypto runs without the GIL)."""
        if not isinstance(data, bytes):
            try:
                data = (ctypes.c_char * len(data)).from_buffer(data)  # type: ignore[assignment]  # no copy
            except TypeError:  # a read-only buffer
                data = bytes(data)
        self._lib.SHA256_Update(self._ctx, data, len(data))

    def copy(self) -> ResumableSha256:
        """A hash that goes on from this one's state."""
        return ResumableSha256(self.state())

    def state(self) -> bytes:
        """The running state, to resume with ``ResumableSha256(state)``."""
        return self._ctx.raw[:STATE_SIZE]

    def hexdigest(self) -> str:
        """The digest of everything hashed so far (this hash can go on)."""
        ctx = ctypes.create_string_buffer(self._ctx.raw, _BUFFER)
        out = ctypes.create_string_buffer(32)
        self._lib.SHA256_Final(out, ctx)
        return out.raw.hex()


@cache
def available() -> bool:
    """Whether saved states resume correctly here (checked once against ``hashlib``)."""
    if _libcrypto() is None:
        return False
    data = bytes(range(256)) * 41 + b"starlog"  # not a whole number of 64-byte blocks: the pending block counts
    try:
        first = ResumableSha256()
        first.update(data[:1000])
        second = ResumableSha256(first.state())
        second.update(bytearray(data[1000:]))
        return second.hexdigest() == hashlib.sha256(data).hexdigest()
    except (OSError, ValueError, RuntimeError, ctypes.ArgumentError):
        return False
