"""What the client returns (numpy arrays, mm, LPS), and the conversions between numpy and the
wire messages of ``librplus.v1``.

Frames (the proto's): "image" is the preoperative model's frame (the mesh of ``describe_case``),
"physical" the intraoperative tracker frame every measurement arrives in; both LPS (x left,
y posterior, z superior), lengths in mm.
"""

from __future__ import annotations

import datetime
import math
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Sequence, Tuple, Union, cast

import numpy as np

from ._pb.librplus.v1 import librplus_pb2 as pb

#: A rigid transform as a 4x4 homogeneous matrix, or as a (3x3 rotation, 3-vector translation)
#: pair.
RigidLike = Union[np.ndarray, Sequence[Sequence[float]], Tuple[Any, Any]]

#: A timestamp: seconds since the Unix epoch, or a datetime (naive datetimes are UTC).
TimeLike = Union[float, int, datetime.datetime]

_METHODS = {
    "default": pb.METHOD_UNSPECIFIED,
    "unspecified": pb.METHOD_UNSPECIFIED,
    "rigid": pb.METHOD_RIGID,
    "libr": pb.METHOD_LIBR,
    "libr_plus": pb.METHOD_LIBR_PLUS,
    "libr+": pb.METHOD_LIBR_PLUS,
    "libr-plus": pb.METHOD_LIBR_PLUS,
    "librplus": pb.METHOD_LIBR_PLUS,
    "v2s": pb.METHOD_V2S,
    "adaptive": pb.METHOD_ADAPTIVE,
    "auto": pb.METHOD_AUTO,
    "nonlinear": pb.METHOD_NONLINEAR,
}

_FEATURES = {
    "none": pb.SALIENT_FEATURE_NONE,
    "falciform": pb.SALIENT_FEATURE_FALCIFORM,
    "inferior_ridge": pb.SALIENT_FEATURE_INFERIOR_RIDGE,
    "inferior-ridge": pb.SALIENT_FEATURE_INFERIOR_RIDGE,
}


def method_value(method: Union[str, int, None]) -> "pb.Method":
    """The wire ``Method`` of a method: a short name (``rigid``, ``libr``, ``libr_plus`` or
    ``libr+``, ``v2s``, ``default``), an enum name (``METHOD_LIBR``), an enum value, or None
    (the case's default)."""
    if method is None:
        return pb.METHOD_UNSPECIFIED
    if isinstance(method, (int, np.integer)) and not isinstance(method, bool):
        if int(method) not in pb.Method.values():
            raise ValueError(f"method: unknown Method value {method}")
        return cast("pb.Method", int(method))
    if isinstance(method, str):
        key = method.strip()
        if key in pb.Method.keys():
            return cast("pb.Method", pb.Method.Value(key))
        if key.lower() in _METHODS:
            return cast("pb.Method", _METHODS[key.lower()])
    raise ValueError(
        f"method: unknown method {method!r}: expected rigid, libr, libr_plus, v2s or default"
    )


def _feature_value(f: Any, i: int) -> int:
    if isinstance(f, str):
        key = f.strip()
        if key in pb.SalientFeature.keys():
            return pb.SalientFeature.Value(key)
        if key.lower() in _FEATURES:
            return _FEATURES[key.lower()]
        raise ValueError(f"features[{i}]: unknown salient feature {f!r}")
    v = int(f)
    if v not in pb.SalientFeature.values():
        raise ValueError(f"features[{i}]: unknown SalientFeature value {v}")
    return v


def feature_values(features: Any, n: int) -> List["pb.SalientFeature"]:
    """The wire ``SalientFeature`` of each of ``n`` points (empty when ``features`` is None;
    a sequence or an array): names (``none``, ``falciform``, ``inferior_ridge``), enum names or values."""
    if features is None:
        return []
    items = features.reshape(-1).tolist() if isinstance(features, np.ndarray) else list(features)
    values = [_feature_value(f, i) for i, f in enumerate(items)]
    if len(values) != n:
        raise ValueError(f"features: {len(values)} values for {n} points (one per point)")
    return cast(List["pb.SalientFeature"], values)


def points_array(points: Any, name: str, dim: int = 3) -> np.ndarray:
    """``points`` as a C-ordered float64 (N, dim) array; an error names the argument."""
    a = np.asarray(points, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != dim:
        raise ValueError(f"{name}: expected an (N, {dim}) array, got shape {a.shape}")
    return np.ascontiguousarray(a)


def packed(points: np.ndarray) -> List[float]:
    """An (N, d) array as the wire's point-major packing: x0, y0, z0, x1, ..."""
    return np.ascontiguousarray(points, dtype=np.float64).reshape(-1).tolist()


def rigid_parts(t: RigidLike, name: str) -> Tuple[np.ndarray, np.ndarray]:
    """(R (3,3), t (3,)) of a 4x4 homogeneous matrix or an (R, t) pair."""
    if isinstance(t, tuple) and len(t) == 2:
        r = np.asarray(t[0], dtype=np.float64)
        tr = np.asarray(t[1], dtype=np.float64).reshape(-1)
        if r.shape != (3, 3) or tr.shape != (3,):
            raise ValueError(
                f"{name}: expected (R, t) with R 3x3 and t of 3 values, got {r.shape} and {tr.shape}"
            )
        return r, tr
    m = np.asarray(t, dtype=np.float64)
    if m.shape != (4, 4):
        raise ValueError(f"{name}: expected a 4x4 matrix or an (R, t) pair, got shape {m.shape}")
    if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
        raise ValueError(f"{name}: the last row of a homogeneous matrix must be 0 0 0 1, got {m[3]}")
    return m[:3, :3].copy(), m[:3, 3].copy()


def rigid_message(t: RigidLike, name: str) -> pb.Rigid:
    """A rigid transform as the wire's ``Rigid``: rotation row-major (R[0,0], R[0,1], R[0,2],
    R[1,0], ...), translation in mm."""
    r, tr = rigid_parts(t, name)
    return pb.Rigid(rotation=r.reshape(-1).tolist(), translation_mm=tr.tolist())


def matrix_of_rigid(r: pb.Rigid, name: str = "rigid") -> np.ndarray:
    """The 4x4 homogeneous matrix of a wire ``Rigid`` (its rotation is row-major)."""
    if len(r.rotation) != 9:
        raise ValueError(f"{name}.rotation has {len(r.rotation)} values, expected 9")
    if len(r.translation_mm) != 3:
        raise ValueError(f"{name}.translation_mm has {len(r.translation_mm)} values, expected 3")
    m = np.eye(4)
    m[:3, :3] = np.asarray(r.rotation, dtype=np.float64).reshape(3, 3)
    m[:3, 3] = np.asarray(r.translation_mm, dtype=np.float64)
    return m


def plane_pose(origin: Any, u_axis: Any, v_axis: Any) -> np.ndarray:
    """The ``plane_to_physical`` pose of an ultrasound plane as the proto defines it: a 4x4
    matrix whose rotation columns are the u axis (lateral), the v axis (depth from the
    transducer) and u x v, all unit vectors in the physical frame, and whose translation is the
    plane's origin (mm), so that plane point (u, v) is at ``origin + u * u_axis + v * v_axis``.

    ``v_axis`` is made orthogonal to ``u_axis`` (Gram-Schmidt); both are normalised.
    """
    o = np.asarray(origin, dtype=np.float64).reshape(3)
    u = np.asarray(u_axis, dtype=np.float64).reshape(3)
    v = np.asarray(v_axis, dtype=np.float64).reshape(3)
    nu = np.linalg.norm(u)
    if not nu > 0:
        raise ValueError("u_axis: zero vector")
    u = u / nu
    v = v - np.dot(v, u) * u
    nv = np.linalg.norm(v)
    if not nv > 1e-12:
        raise ValueError("v_axis: parallel to u_axis")
    v = v / nv
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = u, v, np.cross(u, v), o
    return m


def timestamp(t: TimeLike) -> Any:
    """A ``google.protobuf.Timestamp`` of seconds since the Unix epoch or of a datetime."""
    from google.protobuf.timestamp_pb2 import Timestamp

    ts = Timestamp()
    if isinstance(t, datetime.datetime):
        if t.tzinfo is None:
            t = t.replace(tzinfo=datetime.timezone.utc)
        ts.FromDatetime(t.astimezone(datetime.timezone.utc))
        return ts
    s = float(t)
    if not math.isfinite(s):
        raise ValueError(f"acquired_at: not a finite time: {t!r}")
    seconds = math.floor(s)
    nanos = min(int(round((s - seconds) * 1e9)), 999_999_999)
    ts.seconds, ts.nanos = int(seconds), nanos
    return ts


def seconds_of(t: TimeLike) -> float:
    """Seconds since the Unix epoch of a time."""
    if isinstance(t, datetime.datetime):
        if t.tzinfo is None:
            t = t.replace(tzinfo=datetime.timezone.utc)
        return t.timestamp()
    return float(t)


@dataclass(frozen=True, eq=False)
class Registration:
    """A registration result (``librplus.v1.Registration``).

    The intraoperative position of preoperative node i is
    ``image_to_physical @ (X_i + u_i)``: :meth:`deformed_nodes` computes it.

    Attributes:
        image_to_physical: 4x4 homogeneous rigid transform, image frame -> physical frame (mm).
        displacement_mm: (n, 3) float64 node displacements u, image frame, mm (float32 on the
            wire); zeros for a rigid answer that sent none; None when the request asked to omit
            them (``omit_displacements``) from a non-rigid answer.
        quality: ``QUALITY_OK``, ``QUALITY_NOT_CONVERGED``, ``QUALITY_DEGRADED``,
            ``QUALITY_DEGENERATE`` (do not navigate with it), ``QUALITY_AMBIGUOUS_POSE`` (two
            rigid poses explain the points about equally: the answer may be wrong) or
            ``QUALITY_LIKELY_FAILED`` (the error estimate gives a high chance that the answer's
            mean error exceeds its failure threshold: check the alignment) or
            ``QUALITY_AMBIGUOUS_MODEL`` (``METHOD_AUTO``: candidate models whose answers lie far
            apart predict the points equally well).
        quality_reason: why the quality is not OK (empty when it is).
        method_used: ``METHOD_RIGID``, ``METHOD_LIBR``, ``METHOD_LIBR_PLUS``, ``METHOD_V2S``,
            ``METHOD_ADAPTIVE`` or ``METHOD_AUTO``
            (may differ from the method asked when the server degraded it).
        chosen_model: for ``METHOD_AUTO``, the candidate chosen (``initial``, ``rigid``,
            ``libr``, ``adaptive``, ``libr-held``, ``adaptive-held``; the rest of the choice,
            runner-up, margin and every candidate's score, is ``raw.choice``); None otherwise.
        residual_rms_mm: RMS distance of the matched points to the registered model, mm.
        points_used: points in the registration.
        points_matched: points the fit kept after outlier trimming.
        node_count: the case's mesh node count.
        timings: per-stage wall-clock times (``StageTimings`` fields: ``queue_ms``,
            ``rigid_ms``, ``libr_ms``, ..., ``total_ms``, ``libr_iterations``, ...).
        effects: the named effects of the model that answered (empty: plain LIBR).
        rigid_ill_posed: the points could not fix the rigid motion (the start was trusted).
        predicted_tre_mm: the server's predicted mean TRE over the organ's nodes, mm (None
            when it sent no error estimate).
        uncertainty_level: the level of ``node_uncertainty_mm`` (e.g. 0.9; None without an
            estimate).
        node_uncertainty_mm: (n,) float64: per node, the registered position is within this
            distance of the true one with probability ``uncertainty_level``, mm (None without an
            estimate or with ``omit_displacements``).
        failure_probability: the probability that the registration failed, i.e. that its mean
            TRE exceeds ``failure_threshold_mm`` (a wrong pose; None when the server's error
            model has no failure part for the method).
        failure_threshold_mm: the mean TRE that counts as failed, mm (None with
            ``failure_probability``).
        raw: the ``Registration`` protobuf.
        session_id, sequence, last_client_seq, points_total: the carrying ``StreamUpdate``'s
            fields in a session (None for a unary ``register``).
    """

    image_to_physical: np.ndarray
    displacement_mm: Optional[np.ndarray]
    quality: str
    quality_reason: str
    method_used: str
    residual_rms_mm: float
    points_used: int
    points_matched: int
    node_count: int
    timings: Dict[str, float]
    effects: List[str]
    rigid_ill_posed: bool
    raw: Any = field(repr=False)
    predicted_tre_mm: Optional[float] = None
    uncertainty_level: Optional[float] = None
    node_uncertainty_mm: Optional[np.ndarray] = field(default=None, repr=False)
    failure_probability: Optional[float] = None
    failure_threshold_mm: Optional[float] = None
    session_id: Optional[str] = None
    sequence: Optional[int] = None
    last_client_seq: Optional[int] = None
    points_total: Optional[int] = None
    chosen_model: Optional[str] = None

    @classmethod
    def from_message(cls, r: Any, update: Any = None) -> "Registration":
        """A ``Registration`` protobuf (and, in a session, the ``StreamUpdate`` carrying it)."""
        t = matrix_of_rigid(r.image_to_physical, "registration.image_to_physical")
        n = int(r.node_count)
        if len(r.displacement_mm):
            if len(r.displacement_mm) != 3 * n:
                raise ValueError(
                    f"registration.displacement_mm has {len(r.displacement_mm)} values for "
                    f"{n} nodes (expected {3 * n})"
                )
            u: Optional[np.ndarray] = (
                np.asarray(r.displacement_mm, dtype=np.float32).astype(np.float64).reshape(n, 3)
            )
        elif r.method_used == pb.METHOD_RIGID:
            u = np.zeros((n, 3))
        else:
            u = None
        timings = {f.name: getattr(r.timings, f.name) for f in r.timings.DESCRIPTOR.fields}
        extra: Dict[str, Any] = {}
        if r.HasField("error_estimate"):
            e = r.error_estimate
            extra["predicted_tre_mm"] = float(e.predicted_tre_mm)
            extra["uncertainty_level"] = float(e.level)
            if e.HasField("failure"):
                extra["failure_probability"] = float(e.failure.probability)
                extra["failure_threshold_mm"] = float(e.failure.threshold_mm)
            if len(e.node_uncertainty_mm):
                if len(e.node_uncertainty_mm) != n:
                    raise ValueError(
                        f"registration.error_estimate.node_uncertainty_mm has "
                        f"{len(e.node_uncertainty_mm)} values for {n} nodes"
                    )
                extra["node_uncertainty_mm"] = np.asarray(
                    e.node_uncertainty_mm, dtype=np.float32
                ).astype(np.float64)
        if r.HasField("choice"):
            extra["chosen_model"] = r.choice.chosen
        if update is not None:
            extra.update(
                session_id=update.session_id,
                sequence=int(update.sequence),
                last_client_seq=int(update.last_client_seq),
                points_total=int(update.points_total),
            )
        return cls(
            image_to_physical=t,
            displacement_mm=u,
            quality=_enum_name(pb.Quality, r.quality),
            quality_reason=r.quality_reason,
            method_used=_enum_name(pb.Method, r.method_used),
            residual_rms_mm=float(r.residual_rms_mm),
            points_used=int(r.points_used),
            points_matched=int(r.points_matched),
            node_count=n,
            timings=timings,
            effects=list(r.effects),
            rigid_ill_posed=bool(r.rigid_ill_posed),
            raw=r,
            **extra,
        )

    @property
    def rotation(self) -> np.ndarray:
        """The 3x3 rotation of ``image_to_physical``."""
        return self.image_to_physical[:3, :3]

    @property
    def translation_mm(self) -> np.ndarray:
        """The translation of ``image_to_physical``, mm, physical frame."""
        return self.image_to_physical[:3, 3]

    def deformed_nodes(self, preop_nodes: Any) -> np.ndarray:
        """The registered (intraoperative) node positions, physical frame, mm:
        ``image_to_physical(X + u)`` for the preoperative nodes X ((n, 3), image frame, in the
        case's node order: ``Client.describe_case(case_id).nodes``).

        Raises:
            ValueError: X does not have one row per node, or the displacements were omitted.
        """
        x = points_array(preop_nodes, "preop_nodes")
        if self.displacement_mm is None:
            raise ValueError(
                "deformed_nodes: this registration carries no displacements "
                "(omit_displacements was set)"
            )
        if x.shape != self.displacement_mm.shape:
            raise ValueError(
                f"preop_nodes: shape {x.shape}, but the registration has "
                f"{self.displacement_mm.shape[0]} nodes"
            )
        p = x + self.displacement_mm
        return p @ self.rotation.T + self.translation_mm

    def to_physical(self, points_image: Any) -> np.ndarray:
        """Applies the rigid part only: image-frame points (N, 3) -> physical frame."""
        p = points_array(points_image, "points_image")
        return p @ self.rotation.T + self.translation_mm


@dataclass(frozen=True, eq=False)
class CaseInfo:
    """A case the server serves (``librplus.v1.CaseSummary``).

    Attributes:
        case_id: the id used in requests.
        source: where the server loaded it from.
        node_count, tet_count: mesh size.
        libr_ready, libr_plus_ready, v2s_ready: which methods it can answer.
        default_method: the method of a request that names none (``METHOD_LIBR``, ...).
        effects: the named effects its LIBR model carries.
        raw: the ``CaseSummary`` protobuf.
    """

    case_id: str
    source: str
    node_count: int
    tet_count: int
    libr_ready: bool
    libr_plus_ready: bool
    v2s_ready: bool
    default_method: str
    effects: List[str]
    raw: Any = field(repr=False)

    @classmethod
    def from_message(cls, s: Any) -> "CaseInfo":
        return cls(
            case_id=s.case_id,
            source=s.source,
            node_count=int(s.node_count),
            tet_count=int(s.tet_count),
            libr_ready=bool(s.libr_ready),
            libr_plus_ready=bool(s.libr_plus_ready),
            v2s_ready=bool(s.v2s_ready),
            default_method=_enum_name(pb.Method, s.default_method),
            effects=list(s.effects),
            raw=s,
        )


@dataclass(frozen=True, eq=False)
class CaseDescription:
    """One case (``librplus.v1.DescribeCaseResponse``); the mesh arrays are empty unless asked
    for (``include_mesh``).

    Attributes:
        summary: the case's summary (None while an uploaded case is not served yet).
        state: ``CASE_STATE_READY``, ``CASE_STATE_LOADING``, ``CASE_STATE_FAILED`` or
            ``CASE_STATE_STORED`` (an idle upload out of memory, loaded again when asked for)
            (``CASE_STATE_UNSPECIFIED`` from a server that does not say).
        nodes: (N, 3) preoperative node positions, image frame, mm.
        tets: (T, 4) node indices of the tetrahedra (int64).
        node_labels: (N,) OR of ``NodeLabel`` bits (1 anterior, 2 posterior, 4 falciform,
            8 inferior ridge).
        vessel_points: (V, 3) vessel centreline points, image frame, mm.
        vessel_segments: (S, 2) point index pairs.
        raw: the ``DescribeCaseResponse`` protobuf.
    """

    summary: Optional[CaseInfo]
    state: str
    nodes: np.ndarray
    tets: np.ndarray
    node_labels: np.ndarray
    vessel_points: np.ndarray
    vessel_segments: np.ndarray
    raw: Any = field(repr=False)

    @classmethod
    def from_message(cls, d: Any) -> "CaseDescription":
        return cls(
            summary=CaseInfo.from_message(d.summary) if d.HasField("summary") else None,
            state=_enum_name(pb.CaseState, d.status.state),
            nodes=np.asarray(d.nodes_mm, dtype=np.float64).reshape(-1, 3),
            tets=np.asarray(d.tets, dtype=np.int64).reshape(-1, 4),
            node_labels=np.asarray(d.node_labels, dtype=np.uint32),
            vessel_points=np.asarray(d.vessel_points_mm, dtype=np.float64).reshape(-1, 3),
            vessel_segments=np.asarray(d.vessel_segments, dtype=np.int64).reshape(-1, 2),
            raw=d,
        )


def _enum_name(enum: Any, value: int) -> str:
    try:
        return enum.Name(value)
    except ValueError:
        return str(value)
