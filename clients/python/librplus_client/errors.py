"""Errors of the LIBR+ client: a gRPC status from the server (or a client-side deadline), and a
stream message the server rejected."""

from __future__ import annotations

from typing import List, NamedTuple, Optional, Sequence, Tuple

import grpc


class FieldViolation(NamedTuple):
    """A problem with one field of a request: the field as a path of proto field names (e.g.
    ``surface.points[7]``) and what is wrong with it."""

    field: str
    description: str


class LibrPlusError(Exception):
    """Base of the client's errors.

    Attributes:
        code: the gRPC status code name (``INVALID_ARGUMENT``, ``NOT_FOUND``, ...).
        message: the server's (or the client's) message.
        violations: the fields concerned, when the server named them.
    """

    def __init__(
        self, code: str, message: str, violations: Sequence[FieldViolation] = ()
    ) -> None:
        self.code = code
        self.message = message
        self.violations: List[FieldViolation] = list(violations)
        super().__init__(self._text())

    def _text(self) -> str:
        text = f"{self.code}: {self.message}"
        if self.violations:
            text += " (" + "; ".join(f"{v.field}: {v.description}" for v in self.violations) + ")"
        return text


class RpcError(LibrPlusError):
    """A call (or a session's stream) ended with a non-OK gRPC status: the server refused it
    (UNAUTHENTICATED, NOT_FOUND, INVALID_ARGUMENT, FAILED_PRECONDITION, UNAVAILABLE while the
    cases preload, ...), the connection failed, or no answer came within the client's timeout
    (DEADLINE_EXCEEDED).

    Attributes:
        status_code: the :class:`grpc.StatusCode`.
    """

    def __init__(
        self,
        status_code: grpc.StatusCode,
        message: str,
        violations: Sequence[FieldViolation] = (),
    ) -> None:
        self.status_code = status_code
        super().__init__(status_code.name, message, violations)

    @classmethod
    def from_grpc(cls, e: grpc.RpcError) -> "RpcError":
        """The error of a failed grpcio call, with the field violations of its
        ``google.rpc.Status`` details."""
        code = e.code() if hasattr(e, "code") else grpc.StatusCode.UNKNOWN
        message = e.details() if hasattr(e, "details") else str(e)
        trailers = e.trailing_metadata() if hasattr(e, "trailing_metadata") else None
        violations: List[FieldViolation] = []
        for key, value in trailers or ():
            if key == "grpc-status-details-bin" and isinstance(value, bytes):
                violations = status_violations(value)
        return cls(code or grpc.StatusCode.UNKNOWN, message or "", violations)


class RejectedError(LibrPlusError):
    """A session message the server did not take (a ``Rejection``): the session goes on without
    it.

    Attributes:
        client_seq: the rejected message's sequence number.
        update: the ``StreamUpdate`` that carried the rejection.
    """

    def __init__(
        self,
        client_seq: int,
        code: str,
        message: str,
        violations: Sequence[FieldViolation] = (),
        update: Optional[object] = None,
    ) -> None:
        self.client_seq = client_seq
        self.update = update
        super().__init__(code, message, violations)


class SessionClosedError(LibrPlusError):
    """The server ended the session's stream with OK before answering a message (code
    ``CLOSED``), or the session was used after it was closed or broken."""

    def __init__(self, message: str) -> None:
        super().__init__("CLOSED", message)


# --- google.rpc.Status details, decoded from the wire format (no googleapis dependency) --------


def _varint(buf: bytes, i: int) -> Tuple[int, int]:
    shift = result = 0
    while True:
        if i >= len(buf):
            raise ValueError("truncated varint")
        b = buf[i]
        i += 1
        result |= (b & 0x7F) << shift
        if not b & 0x80:
            return result, i
        shift += 7


def _fields(buf: bytes) -> List[Tuple[int, object]]:
    """(field number, value) pairs of a protobuf message: ints for varints, bytes for
    length-delimited fields; fixed-width fields are skipped."""
    out: List[Tuple[int, object]] = []
    i = 0
    while i < len(buf):
        key, i = _varint(buf, i)
        number, wire = key >> 3, key & 7
        if wire == 0:
            v, i = _varint(buf, i)
            out.append((number, v))
        elif wire == 2:
            n, i = _varint(buf, i)
            if i + n > len(buf):
                raise ValueError("truncated field")
            out.append((number, buf[i : i + n]))
            i += n
        elif wire == 1:
            i += 8
        elif wire == 5:
            i += 4
        else:
            raise ValueError(f"unsupported wire type {wire}")
    return out


def _strings(buf: bytes) -> dict:
    return {
        n: v.decode("utf-8", "replace") for n, v in _fields(buf) if isinstance(v, bytes)
    }


# type URL suffix -> (field number of the repeated violation, field numbers of (field, description))
_VIOLATIONS = {
    "google.rpc.BadRequest": (1, 1, 2),
    "google.rpc.PreconditionFailure": (1, 2, 3),
    "google.rpc.QuotaFailure": (1, 1, 2),
}


def status_violations(status_bin: bytes) -> List[FieldViolation]:
    """The field violations in a serialized ``google.rpc.Status`` (the
    ``grpc-status-details-bin`` trailer): BadRequest field violations, and the subjects of
    PreconditionFailure and QuotaFailure violations. Undecodable details give none."""
    out: List[FieldViolation] = []
    try:
        for number, detail in _fields(status_bin):
            if number != 3 or not isinstance(detail, bytes):
                continue
            any_fields = dict(_fields(detail))
            type_url = any_fields.get(1, b"")
            value = any_fields.get(2, b"")
            if not isinstance(type_url, bytes) or not isinstance(value, bytes):
                continue
            kind = _VIOLATIONS.get(type_url.decode("utf-8", "replace").rsplit("/", 1)[-1])
            if kind is None:
                continue
            repeated, f_field, f_desc = kind
            for n, v in _fields(value):
                if n == repeated and isinstance(v, bytes):
                    s = _strings(v)
                    out.append(FieldViolation(s.get(f_field, ""), s.get(f_desc, "")))
    except ValueError:
        return out
    return out
