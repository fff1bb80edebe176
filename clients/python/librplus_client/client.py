"""The LIBR+ gRPC client: :class:`Client` (cases, unary registration) and :class:`Session` (a
streamed intraoperative session, in lockstep: each message waits for the update answering it)."""

from __future__ import annotations

import os
import queue
import threading
import time
from typing import Any, Iterator, List, Optional, Tuple, Union

import grpc
import numpy as np

from ._pb.librplus.v1 import librplus_pb2 as pb
from ._pb.librplus.v1 import librplus_pb2_grpc as pb_grpc
from .errors import FieldViolation, RejectedError, RpcError, SessionClosedError
from .types import (
    CaseDescription,
    CaseInfo,
    Registration,
    RigidLike,
    TimeLike,
    feature_values,
    method_value,
    packed,
    points_array,
    rigid_message,
    seconds_of,
    timestamp,
)

#: Largest message the client sends or accepts (64 MiB, as the Rust clients).
MAX_MESSAGE_BYTES = 64 << 20

PathLike = Union[str, "os.PathLike[str]"]
"""A file path."""


def _read(path: Optional[PathLike], option: str) -> Optional[bytes]:
    if path is None:
        return None
    try:
        with open(path, "rb") as f:
            return f.read()
    except OSError as e:
        raise ValueError(f"{option} {path}: cannot read ({e.strerror or e})") from e


def _target(server: str) -> Tuple[str, bool]:
    """(host:port, whether the URL asks for TLS) of ``http://host:port``, ``https://host:port``
    or ``host:port``."""
    s = server.strip()
    https = s.startswith("https://")
    for scheme in ("http://", "https://"):
        if s.startswith(scheme):
            s = s[len(scheme) :]
    s = s.rstrip("/")
    if not s or "/" in s:
        raise ValueError(f"server {server!r}: expected host:port, http://host:port or https://host:port")
    return s, https


class Client:
    """A connection to a LIBR+ server (``librplus.v1.LibRPlus``).

    Args:
        server: ``http://host:port`` (plaintext), ``https://host:port`` (TLS) or ``host:port``.
        ca: CA certificate (PEM file) the server's certificate must chain to; it turns TLS on
            (an ``http://`` URL is then used over TLS, as the Rust client does). With an
            ``https://`` URL and no ``ca``, grpcio's default roots are used.
        cert, key: client certificate and private key (PEM files) for mutual TLS; both or
            neither.
        domain: the name the server's certificate must carry when it differs from the URL's
            host (e.g. ``localhost`` for the demo's certificates).
        token: bearer token, sent as ``authorization: Bearer TOKEN`` with every call (plaintext
            or TLS alike, as ``librplus-client --token``).
        timeout_s: deadline of each unary call, and the longest wait for a session's answer.

    A ``Client`` is a context manager (``with Client(...) as c:``) that closes its channel.
    """

    def __init__(
        self,
        server: str,
        *,
        ca: Optional[PathLike] = None,
        cert: Optional[PathLike] = None,
        key: Optional[PathLike] = None,
        domain: Optional[str] = None,
        token: Optional[str] = None,
        timeout_s: float = 120,
    ) -> None:
        target, https = _target(server)
        if (cert is None) != (key is None):
            missing = "key" if key is None else "cert"
            raise ValueError(f"{missing}: missing (mTLS needs both cert and key)")
        tls = ca is not None or https or cert is not None
        if token is not None:
            if not token or not all(0x20 < ord(c) < 0x7F for c in token):
                raise ValueError("token: must be non-empty printable ASCII without spaces")
            self._metadata: Tuple[Tuple[str, str], ...] = (("authorization", f"Bearer {token}"),)
        else:
            self._metadata = ()
        if not timeout_s > 0:
            raise ValueError(f"timeout_s: must be > 0, got {timeout_s}")
        self.server = server
        self.timeout_s = float(timeout_s)
        options: List[Tuple[str, Any]] = [
            ("grpc.max_receive_message_length", MAX_MESSAGE_BYTES),
            ("grpc.max_send_message_length", MAX_MESSAGE_BYTES),
        ]
        if tls:
            creds = grpc.ssl_channel_credentials(
                root_certificates=_read(ca, "ca"),
                private_key=_read(key, "key"),
                certificate_chain=_read(cert, "cert"),
            )
            if domain:
                options.append(("grpc.ssl_target_name_override", domain))
            self._channel = grpc.secure_channel(target, creds, options=options)
        else:
            self._channel = grpc.insecure_channel(target, options=options)
        self._stub = pb_grpc.LibRPlusStub(self._channel)

    # -- lifecycle --------------------------------------------------------------------------

    def close(self) -> None:
        """Closes the channel (open sessions end)."""
        self._channel.close()

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def _call(self, rpc: Any, request: Any) -> Any:
        try:
            return rpc(request, timeout=self.timeout_s, metadata=self._metadata)
        except grpc.RpcError as e:
            raise RpcError.from_grpc(e) from None

    # -- cases ------------------------------------------------------------------------------

    def list_cases(self) -> List[CaseInfo]:
        """The cases the server serves (with a token: those the caller may use)."""
        r = self._call(self._stub.ListCases, pb.ListCasesRequest())
        return [CaseInfo.from_message(c) for c in r.cases]

    def describe_case(self, case_id: str, *, include_mesh: bool = True) -> CaseDescription:
        """One case: its summary and, with ``include_mesh``, its preoperative mesh (nodes, image
        frame, mm; tets), node labels and vessel centrelines."""
        r = self._call(
            self._stub.DescribeCase,
            pb.DescribeCaseRequest(case_id=case_id, include_mesh=include_mesh),
        )
        return CaseDescription.from_message(r)

    def wait_ready(self, timeout_s: float = 120, poll_s: float = 0.5) -> List[CaseInfo]:
        """Waits until the server answers (it answers UNAVAILABLE while it preloads its cases or
        before it listens); returns :meth:`list_cases`. Raises the last :class:`RpcError` when
        ``timeout_s`` passes first; any other error at once."""
        end = time.monotonic() + timeout_s
        while True:
            try:
                return self.list_cases()
            except RpcError as e:
                if e.status_code != grpc.StatusCode.UNAVAILABLE or time.monotonic() >= end:
                    raise
            time.sleep(poll_s)

    # -- registration -----------------------------------------------------------------------

    def register(
        self,
        case_id: str,
        surface_points: Any,
        *,
        method: Union[str, int, None] = "libr",
        features: Any = None,
        contour_points: Any = None,
        vessel_points: Any = None,
        initial_alignment: Optional[RigidLike] = None,
        time_budget_ms: int = 0,
        omit_displacements: bool = False,
        trusted_alignment_mm: float = 0.0,
        held: bool = False,
    ) -> Registration:
        """One registration of a complete measurement set (unary ``Register``).

        Args:
            case_id: the case (:meth:`list_cases`).
            surface_points: (N, 3) anterior-surface points, physical frame, mm.
            method: ``rigid``, ``libr``, ``libr_plus``, ``v2s`` or ``default`` / None (the
                case's default).
            features: None, or one salient-feature designation per surface point (``none``,
                ``falciform``, ``inferior_ridge``, or the enum's names or values).
            contour_points: (M, 3) ultrasound posterior-contour points, physical frame, mm.
            vessel_points: (K, 3) ultrasound vessel-centreline points, physical frame, mm.
            initial_alignment: the navigation system's coarse image -> physical alignment
                (4x4 or (R, t)); None: the rigid stage starts from the centroids.
            time_budget_ms: the server's time budget (0: its default).
            omit_displacements: ask for the rigid transform and figures only.
            trusted_alignment_mm: > 0: trust the initial alignment to this RMS uncertainty.
            held: the organ is held in place and the start trusted (to 5 mm unless
                ``trusted_alignment_mm`` says otherwise): no pose search, and the surface the
                points do not come near is held where the start puts it.

        Raises:
            RpcError: the server refused the request (INVALID_ARGUMENT naming the field,
                NOT_FOUND, FAILED_PRECONDITION, ...) or the call failed.
        """
        parts = [("surface_points", surface_points, pb.POINT_KIND_SURFACE)]
        if contour_points is not None:
            parts.append(("contour_points", contour_points, pb.POINT_KIND_POSTERIOR_CONTOUR))
        if vessel_points is not None:
            parts.append(("vessel_points", vessel_points, pb.POINT_KIND_VESSEL))
        xyz: List[float] = []
        kind: List[Any] = []
        n_surface = 0
        for name, pts, k in parts:
            a = points_array(pts, name)
            xyz += packed(a)
            kind += [k] * len(a)
            if k == pb.POINT_KIND_SURFACE:
                n_surface = len(a)
        feature = feature_values(features, n_surface)
        if feature:
            # One designation per point when any: the ultrasound points carry none.
            feature += [pb.SALIENT_FEATURE_NONE] * (len(kind) - n_surface)
        m = pb.Measurements(xyz_mm=xyz, kind=kind, feature=feature)
        if initial_alignment is not None:
            m.initial_alignment.CopyFrom(rigid_message(initial_alignment, "initial_alignment"))
        req = pb.RegisterRequest(
            case_id=case_id,
            method=method_value(method),
            measurements=m,
            options=pb.RegisterOptions(
                time_budget_ms=int(time_budget_ms),
                omit_displacements=bool(omit_displacements),
                trusted_alignment_mm=float(trusted_alignment_mm),
                held=bool(held),
            ),
        )
        return Registration.from_message(self._call(self._stub.Register, req))

    def session(
        self,
        case_id: str,
        method: Union[str, int, None] = "libr",
        *,
        initial_alignment: Optional[RigidLike] = None,
        time_budget_ms: int = 0,
        omit_displacements: bool = False,
        trusted_alignment_mm: float = 0.0,
        held: bool = False,
        timeout_s: Optional[float] = None,
    ) -> "Session":
        """Opens a streamed session (``StreamRegister``) and sends its ``SessionStart``.

        Use it as a context manager::

            with client.session("g1", "libr", initial_alignment=T0) as s:
                r = s.add_surface(points)

        Arguments as in :meth:`register`; ``timeout_s`` (default: the client's) bounds the wait
        for each answer. A start the server refuses (an unknown case, a method the case cannot
        run) surfaces as an :class:`RpcError` from the first ``add_*`` call.
        """
        start = pb.SessionStart(
            case_id=case_id,
            method=method_value(method),
            options=pb.RegisterOptions(
                time_budget_ms=int(time_budget_ms),
                omit_displacements=bool(omit_displacements),
                trusted_alignment_mm=float(trusted_alignment_mm),
                held=bool(held),
            ),
        )
        if initial_alignment is not None:
            start.initial_alignment.CopyFrom(rigid_message(initial_alignment, "initial_alignment"))
        return Session(self, start, self.timeout_s if timeout_s is None else float(timeout_s))


_END = object()


class Session:
    """A streamed intraoperative session (``StreamRegister``), in lockstep: each ``add_*``
    sends one message and waits for the update that answers it (the first registration whose
    ``last_client_seq`` reaches the message's ``client_seq``, or the rejection of that message;
    for ``nonlinear``, the refined answer that follows the linear one, which stays in
    ``updates``).
    Made by :meth:`Client.session`; a context manager that closes the stream on exit (or
    cancels it when the block raised anything but a :class:`RejectedError`). Use a session from
    one thread at a time.

    ``client_seq`` runs 1 (the start), 2, 3, ...; ``acquired_at`` is the time given, else
    ``time.time()`` (never earlier than the previous message's).

    Attributes:
        session_id: the server's id of the session (after the first answer).
        last_update: the newest ``StreamUpdate`` received.
        updates: every ``StreamUpdate`` received, in order (discovery reports and stale ones
            included).
    """

    def __init__(self, client: Client, start: Any, timeout_s: float) -> None:
        self._timeout_s = timeout_s
        self._requests: "queue.Queue[Any]" = queue.Queue()
        self._updates: "queue.Queue[Any]" = queue.Queue()
        self._seq = 1
        self._last_time = float("-inf")
        self._closed = False
        self._broken: Optional[Exception] = None
        self.session_id: Optional[str] = None
        self.last_update: Optional[Any] = None
        self.updates: List[Any] = []
        self._requests.put(pb.StreamRegisterRequest(client_seq=1, start=start))
        self._call = client._stub.StreamRegister(
            self._request_iter(), metadata=client._metadata
        )
        self._reader = threading.Thread(
            target=self._read, name="librplus-session-reader", daemon=True
        )
        self._reader.start()

    # -- plumbing ---------------------------------------------------------------------------

    def _request_iter(self) -> Iterator[Any]:
        while True:
            m = self._requests.get()
            if m is None:
                return
            yield m

    def _read(self) -> None:
        try:
            for u in self._call:
                self._updates.put(u)
            self._updates.put(_END)
        except grpc.RpcError as e:
            self._updates.put(e)
        except Exception as e:  # noqa: BLE001 (the waiting thread reports it)
            self._updates.put(e)

    def _fail(self, e: Exception) -> Exception:
        self._broken = e
        self._call.cancel()
        self._requests.put(None)
        return e

    def _next(self, deadline: float, seq: int) -> Any:
        left = deadline - time.monotonic()
        try:
            item = self._updates.get(timeout=max(left, 0.0))
        except queue.Empty:
            raise self._fail(
                RpcError(
                    grpc.StatusCode.DEADLINE_EXCEEDED,
                    f"no answer to client_seq {seq} within {self._timeout_s:g} s",
                )
            ) from None
        if item is _END:
            raise self._fail(
                SessionClosedError(f"the server closed the stream before answering client_seq {seq}")
            )
        if isinstance(item, grpc.RpcError):
            raise self._fail(RpcError.from_grpc(item))
        if isinstance(item, Exception):
            raise self._fail(item)
        return item

    def _send(self, build: Any, acquired_at: Optional[TimeLike]) -> Registration:
        if self._closed:
            raise SessionClosedError("the session is closed")
        if self._broken is not None:
            raise SessionClosedError(f"the session's stream ended: {self._broken}")
        if acquired_at is None:
            t = max(time.time(), self._last_time)
        else:
            t = seconds_of(acquired_at)
        self._seq += 1
        seq = self._seq
        msg = build(seq, timestamp(acquired_at if acquired_at is not None else t))
        self._last_time = max(self._last_time, t)
        self._requests.put(msg)
        deadline = time.monotonic() + self._timeout_s
        while True:
            u = self._next(deadline, seq)
            self.updates.append(u)
            self.last_update = u
            if u.session_id:
                self.session_id = u.session_id
            kind = u.WhichOneof("update")
            if kind == "rejection" and u.rejection.client_seq == seq:
                rj = u.rejection
                raise RejectedError(
                    seq,
                    rj.code,
                    rj.message,
                    [FieldViolation(v.field, v.description) for v in rj.violations],
                    update=u,
                )
            if kind == "registration" and u.last_client_seq >= seq:
                r = u.registration
                if r.HasField("refinement") and r.refinement.follows:
                    # METHOD_NONLINEAR's linear answer (kept in ``updates``): its refinement
                    # follows for the same message and is the answer returned.
                    continue
                return Registration.from_message(r, u)
            # A discovery report, or an update answering an earlier message: not this answer.

    # -- messages ---------------------------------------------------------------------------

    def add_surface(
        self,
        points: Any,
        features: Any = None,
        *,
        acquired_at: Optional[TimeLike] = None,
    ) -> Registration:
        """Sends a batch of anterior-surface points and returns the registration of every
        point accepted so far.

        Args:
            points: (N, 3) points, physical frame, mm (sent point-major: x0, y0, z0, x1, ...).
            features: None, or one salient-feature designation per point (``none``,
                ``falciform``, ``inferior_ridge``, or the enum's names or values).
            acquired_at: when the batch was acquired (seconds since the epoch or a datetime;
                default now). Must not go back in time within the session.

        Raises:
            RejectedError: the server did not take the batch (the session goes on).
            RpcError: the stream ended with a status (e.g. the start was refused).
        """
        a = points_array(points, "points")
        feature = feature_values(features, len(a))
        xyz = packed(a)

        def build(seq: int, ts: Any) -> Any:
            return pb.StreamRegisterRequest(
                client_seq=seq,
                surface=pb.SurfaceBatch(acquired_at=ts, xyz_mm=xyz, feature=feature),
            )

        return self._send(build, acquired_at)

    def add_ultrasound(
        self,
        plane_to_physical: RigidLike,
        contour_uv: Any = None,
        vessel_uv: Any = None,
        *,
        acquired_at: Optional[TimeLike] = None,
    ) -> Registration:
        """Sends one tracked ultrasound frame and returns the registration of every point
        accepted so far.

        Args:
            plane_to_physical: the plane's pose, 4x4 or (R, t): plane point (u, v) (mm) is at
                ``R @ (u, v, 0) + t`` in the physical frame; R's columns are the u axis
                (lateral), the v axis (depth from the transducer) and u x v
                (:func:`librplus_client.plane_pose` builds it from the axes).
            contour_uv: (M, 2) posterior-surface contour points (u, v), mm; None: none.
            vessel_uv: (K, 2) vessel centreline crossings (u, v), mm; None: none.
            acquired_at: when the frame was acquired (default now).

        Raises:
            RejectedError, RpcError: as :meth:`add_surface`.
        """
        pose = rigid_message(plane_to_physical, "plane_to_physical")
        none = np.empty((0, 2))
        contour = packed(points_array(none if contour_uv is None else contour_uv, "contour_uv", 2))
        vessel = packed(points_array(none if vessel_uv is None else vessel_uv, "vessel_uv", 2))

        def build(seq: int, ts: Any) -> Any:
            return pb.StreamRegisterRequest(
                client_seq=seq,
                ultrasound=pb.UltrasoundPlane(
                    acquired_at=ts,
                    plane_to_physical=pose,
                    contour_uv_mm=contour,
                    vessel_uv_mm=vessel,
                ),
            )

        return self._send(build, acquired_at)

    # -- end --------------------------------------------------------------------------------

    def close(self) -> None:
        """Closes the client's side and reads the stream to its end (raises :class:`RpcError`
        when it ends with a non-OK status after all answers came)."""
        if self._closed:
            return
        self._closed = True
        self._requests.put(None)
        if self._broken is not None:
            return
        deadline = time.monotonic() + self._timeout_s
        while True:
            left = deadline - time.monotonic()
            try:
                item = self._updates.get(timeout=max(left, 0.0))
            except queue.Empty:
                self._call.cancel()
                return
            if item is _END:
                return
            if isinstance(item, grpc.RpcError):
                raise RpcError.from_grpc(item)
            if isinstance(item, Exception):
                raise item
            self.updates.append(item)
            self.last_update = item

    def cancel(self) -> None:
        """Ends the stream at once (the server sees the call cancelled)."""
        self._closed = True
        self._requests.put(None)
        self._call.cancel()

    def __enter__(self) -> "Session":
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        if exc_type is None or exc_type is RejectedError:
            self.close()
        else:
            self.cancel()

