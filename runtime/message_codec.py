"""The wire codec under `runtime.messages`: framing, field readers/writers, validation helpers, the base class.

Why hand-rolled struct + raw numpy bytes: a 320x240 frame must encode/decode in microseconds (protobuf or
msgpack box every array), C++/Rust must be able to read it without Python, and a malformed or hostile
payload must never reach the policy or the arm (pickle executes code; here every field is validated).
All little-endian. Arrays are raw C-order bytes after an explicit dtype/shape; decoded arrays are read-only
views on the received buffer (no copy).

Header, 36 bytes, struct ``<4sHHQqQI``, on every message:

    =========  ====  ========================================================================
    magic      4s    b"SUDD"
    version    u16   SCHEMA_VERSION (1); any other value is rejected
    msg_type   u16   1 CameraFrame 2 RobotState 3 GripperStatus 4 ActionChunk 5 LanguageCommand
                     6 StatusEvent 7 Telemetry
    seq        u64   per-publisher sequence number (the bus finds gaps / reordering with it)
    stamp_ns   i64   source (publish) time, host CLOCK_MONOTONIC ns, >= 0
    source_id  u64   publisher id, random per publisher (a restart is a new source, not a reorder)
    body_len   u32   bytes after the header; must equal the rest of the payload exactly
    =========  ====  ========================================================================

Body fields: ``str`` = u16 byte length + UTF-8; ``arr`` = u8 dtype code (1 u8, 2 u16, 3 i64, 4 f64), u8
ndim, ndim x u32 dims, raw bytes; named items = u16 count, then per item a ``str`` name and a struct value.
The message bodies themselves are in `runtime.messages`.

Decoding raises only `DecodeError(reason, detail)`; `reason` is one of REASONS, a small fixed set, so the bus
can count errors per reason without unbounded labels. The `check_*` helpers raise it; `Message.encode`
turns it into a ValueError.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

MAGIC, SCHEMA_VERSION, HEADER = b"SUDD", 1, struct.Struct("<4sHHQqQI")
MAX_IMAGE_SIDE, MAX_CHUNK, MAX_TEXT, MAX_NAME = 4096, 256, 1000, 64
MAX_ITEMS = {"StatusEvent": 32, "Telemetry": 64}
MAX_BODY = MAX_IMAGE_SIDE * MAX_IMAGE_SIDE * 5 + 4096  # colour + depth at the largest size, + fields
REASONS = ("bad_magic", "bad_version", "bad_type", "truncated", "oversize", "bad_dtype", "bad_shape",
           "too_large", "non_finite", "bad_text", "bad_value", "non_monotonic", "wrong_type")
_DTYPES = {1: np.dtype("u1"), 2: np.dtype("<u2"), 3: np.dtype("<i8"), 4: np.dtype("<f8")}
_CODES = {v: k for k, v in _DTYPES.items()}


class DecodeError(ValueError):
    """A payload that is not a valid message. `reason` is one of REASONS; `detail` says what and where."""

    def __init__(self, reason: str, detail: str = ""):
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason, self.detail = reason, detail


def need(ok, reason: str, detail) -> None:
    """Raise DecodeError(reason, detail) unless `ok`; `detail` may be a lambda: formatted only on failure."""
    if not ok:
        raise DecodeError(reason, detail() if callable(detail) else detail)


def check_finite(name: str, a) -> None:
    need(bool(np.isfinite(a).all()), "non_finite", lambda: f"{name} has NaN/Inf")


def check_text(name: str, s, lo: int, hi: int) -> None:
    need(isinstance(s, str), "bad_text", lambda: f"{name} must be a str")
    need(len(s) <= hi, "too_large", lambda: f"{name} has {len(s)} chars > {hi}")
    need(len(s) >= lo, "bad_value", lambda: f"{name} must not be empty")


def check_time(name: str, t) -> None:
    need(0 <= int(t) < 2**63, "bad_value", lambda: f"{name} = {t} must be a time >= 0 ns")


class Writer:
    """Collects the body's parts (bytes and zero-copy array views) for one `b"".join`."""

    def __init__(self):
        self.parts: list = []

    def pack(self, fmt: str, *values) -> None:
        self.parts.append(struct.pack(fmt, *values))

    def text(self, s: str) -> None:
        raw = s.encode("utf-8")
        self.parts += [struct.pack("<H", len(raw)), raw]

    def array(self, a: np.ndarray) -> None:
        self.parts += [struct.pack(f"<BB{a.ndim}I", _CODES[a.dtype], a.ndim, *a.shape),
                       memoryview(np.ascontiguousarray(a)).cast("B")]

    def items(self, d: dict, fmt: str) -> None:
        self.pack("<H", len(d))
        for k, v in d.items():
            self.text(k)
            self.pack(fmt, v)


class Reader:
    """Reads body fields from `buf` at `pos`, bounds-checked: a short buffer is DecodeError("truncated")."""

    def __init__(self, buf: memoryview, pos: int):
        self.buf, self.pos = buf, pos

    def take(self, n: int, what: str) -> memoryview:
        need(self.pos + n <= len(self.buf), "truncated", lambda: f"{what} needs {n} bytes at offset {self.pos}")
        self.pos += n
        return self.buf[self.pos - n:self.pos]

    def unpack(self, fmt: str, what: str) -> tuple:
        n = struct.calcsize(fmt)
        need(self.pos + n <= len(self.buf), "truncated", lambda: f"{what} needs {n} bytes at offset {self.pos}")
        self.pos += n
        return struct.unpack_from(fmt, self.buf, self.pos - n)

    def text(self, what: str, lo: int, hi: int) -> str:
        (n,) = self.unpack("<H", what)
        need(n <= 4 * hi, "too_large", lambda: f"{what} is {n} bytes")
        try:
            s = str(self.take(n, what), "utf-8")
        except UnicodeDecodeError as exc:
            raise DecodeError("bad_text", f"{what} is not UTF-8 ({exc.reason})") from None
        check_text(what, s, lo, hi)
        return s

    def array(self, what: str, dtype: str, shape: tuple) -> np.ndarray:
        """A read-only view; its dtype and shape must be exactly `dtype` and `shape`."""
        code, ndim = self.unpack("<BB", what)
        dt = np.dtype(dtype)
        need(_DTYPES.get(code) == dt, "bad_dtype", lambda: f"{what}: dtype code {code}, want {dtype}")
        need(ndim == len(shape), "bad_shape", lambda: f"{what}: {ndim} dims, want {len(shape)}")
        dims = self.unpack(f"<{ndim}I", what)
        need(dims == shape, "bad_shape", lambda: f"{what}: shape {dims} != {shape}")
        return np.frombuffer(self.take(math.prod(dims) * dt.itemsize, what), dtype=dt).reshape(dims)

    def items(self, owner: str, fmt: str) -> dict:
        (n,) = self.unpack("<H", f"{owner} count")
        need(n <= MAX_ITEMS[owner], "too_large", lambda: f"{owner}: {n} entries > {MAX_ITEMS[owner]}")
        out = {}
        for _ in range(n):
            key = self.text(f"{owner} name", 1, MAX_NAME)
            need(key not in out, "bad_value", lambda: f"{owner}: duplicate name {key!r}")
            (out[key],) = self.unpack(fmt, f"{owner}[{key!r}]")
        return out


@dataclass(frozen=True, eq=False, kw_only=True)
class Message:
    """Base: the header fields. The bus sets seq/stamp_ns/source_id when it publishes (see `encode`).

    A subclass sets TYPE and implements `_check` (validation, raising DecodeError), `_write(w: Writer)` and
    the classmethod `_read(r: Reader, hdr: dict)`."""

    seq: int = 0
    stamp_ns: int = 0
    source_id: int = 0
    TYPE: ClassVar[int] = 0

    def encode(self, *, seq: int | None = None, stamp_ns: int | None = None, source_id: int | None = None) -> bytes:
        """Validate and serialise; header fields given here override the message's own. ValueError if invalid."""
        try:
            self._check()
            w = Writer()
            self._write(w)
            body_len = sum(p.nbytes if isinstance(p, memoryview) else len(p) for p in w.parts)
            head = HEADER.pack(MAGIC, SCHEMA_VERSION, self.TYPE, self.seq if seq is None else seq,
                               self.stamp_ns if stamp_ns is None else stamp_ns,
                               self.source_id if source_id is None else source_id, body_len)
        except (DecodeError, struct.error, TypeError) as exc:
            raise ValueError(f"cannot encode {type(self).__name__}: {exc}") from None
        return b"".join([head, *w.parts])

    def _check(self) -> None: ...

    def _write(self, w: Writer) -> None: ...
