"""Unit tests of librplus_client against an in-process fake LIBR+ server (grpcio): what the
client sends (sequence numbers, timestamps, point packing, plane poses, options, the bearer
token) and how it reads the answers (the row-major rotation, displacements, rejections, errors).

Run: ``python -m unittest discover -s clients/python/tests`` (or ``python -m unittest`` in
clients/python) with the package installed. The example's test also needs
clients/python/examples/ (found relative to this file). The TLS test needs ``openssl``.
"""

from __future__ import annotations

import contextlib
import importlib.util
import io
import json
import math
import os
import shutil
import subprocess
import tempfile
import time
import unittest
from concurrent import futures
from typing import Any, Callable, List, Optional

os.environ.setdefault("GRPC_VERBOSITY", "ERROR")  # before grpc loads: no core info logs

import grpc  # noqa: E402
import numpy as np  # noqa: E402

import librplus_client as lc  # noqa: E402
from librplus_client import pb, pb_grpc  # noqa: E402

TOKEN = "s3cret-token"
SESSION_ID = "s-fake-000001"
# A rotation that is not symmetric (so that a transposed reading shows): 90 degrees about z,
# then the columns are (y, -x, z) ... written row-major as the proto says.
R0 = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
T0 = np.array([10.0, -20.0, 30.5])
NODES = 4
U0 = (np.arange(3 * NODES, dtype=np.float32) * 0.25 - 1.0).reshape(NODES, 3)
X0 = np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0], [-4.0, 5.0, 6.5], [7.0, -8.0, 9.0]])


# --- google.rpc.Status encoding, for the fake server's error details ---------------------------


def _varint(v: int) -> bytes:
    out = bytearray()
    while True:
        b = v & 0x7F
        v >>= 7
        if v:
            out.append(b | 0x80)
        else:
            out.append(b)
            return bytes(out)


def _ld(number: int, payload: bytes) -> bytes:
    return _varint(number << 3 | 2) + _varint(len(payload)) + payload


def bad_request_status(code: grpc.StatusCode, message: str, field: str, description: str) -> bytes:
    violation = _ld(1, field.encode()) + _ld(2, description.encode())
    bad_request = _ld(1, violation)
    any_ = _ld(1, b"type.googleapis.com/google.rpc.BadRequest") + _ld(2, bad_request)
    return (
        _varint(1 << 3 | 0) + _varint(code.value[0]) + _ld(2, message.encode()) + _ld(3, any_)
    )


class _Status(grpc.Status):
    def __init__(self, code: grpc.StatusCode, details: str, trailing_metadata: Any) -> None:
        self.code = code
        self.details = details
        self.trailing_metadata = trailing_metadata


def abort_with_field(context: Any, code: grpc.StatusCode, message: str, field: str) -> None:
    details = bad_request_status(code, message, field, "no such case")
    context.abort_with_status(
        _Status(code, message, (("grpc-status-details-bin", details),))
    )


# --- the fake server ----------------------------------------------------------------------------


def registration(method: int = pb.METHOD_LIBR, displacement: Optional[np.ndarray] = U0,
                 rigid: Any = (R0, T0), points: int = 0) -> Any:
    r, t = rigid
    return pb.Registration(
        image_to_physical=pb.Rigid(
            rotation=np.asarray(r).reshape(-1).tolist(), translation_mm=list(t)
        ),
        displacement_mm=[] if displacement is None else np.asarray(displacement).reshape(-1).tolist(),
        node_count=NODES if displacement is None else len(displacement),
        method_used=method,
        residual_rms_mm=1.25,
        points_used=points,
        points_matched=max(points - 1, 0),
        timings=pb.StageTimings(rigid_ms=2.0, libr_ms=7.5, total_ms=11.0, libr_iterations=12),
        quality=pb.QUALITY_NOT_CONVERGED,
        quality_reason="stopped at 20 iterations",
        effects=["gravity"],
    )


class FakeServer(pb_grpc.LibRPlusServicer):
    """Answers ListCases, DescribeCase, Register and StreamRegister enough to check a client.

    Sessions: case "nope" is refused NOT_FOUND (with a BadRequest naming start.case_id); case
    "slow" never answers; a surface batch with a non-finite coordinate is rejected; a surface
    batch of 7 points is answered by a discovery report, then its registration; ultrasound
    planes are answered METHOD_RIGID with no displacements (or by ``self.answer_ultrasound``);
    anything else by ``self.answer(points_so_far, message)``.
    """

    def __init__(self, token: Optional[str] = None) -> None:
        self.token = token
        self.sessions: List[List[Any]] = []  # received messages per session
        self.metadata: List[dict] = []
        self.register_requests: List[Any] = []
        self.answer: Callable[[int, Any], Any] = lambda n, m: registration(points=n)
        self.answer_ultrasound: Optional[Callable[[int, Any], Any]] = None

    def _auth(self, context: Any) -> None:
        md = dict(context.invocation_metadata())
        self.metadata.append(md)
        if self.token is not None and md.get("authorization") != f"Bearer {self.token}":
            context.abort(grpc.StatusCode.UNAUTHENTICATED, "missing or unknown credentials")

    def ListCases(self, request: Any, context: Any) -> Any:
        self._auth(context)
        return pb.ListCasesResponse(
            cases=[
                pb.CaseSummary(case_id="g1", node_count=NODES, tet_count=1, libr_ready=True,
                               default_method=pb.METHOD_LIBR, effects=["fixation"]),
                pb.CaseSummary(case_id="g2", node_count=9, tet_count=2, libr_plus_ready=True,
                               default_method=pb.METHOD_LIBR_PLUS),
            ]
        )

    def DescribeCase(self, request: Any, context: Any) -> Any:
        self._auth(context)
        if request.case_id != "g1":
            abort_with_field(context, grpc.StatusCode.NOT_FOUND, f"no case {request.case_id!r}",
                             "case_id")
        r = pb.DescribeCaseResponse(
            summary=pb.CaseSummary(case_id="g1", node_count=NODES, tet_count=1),
            length_unit="mm",
            frame="image (preoperative), LPS",
            status=pb.CaseStatus(case_id="g1", state=pb.CASE_STATE_READY),
        )
        if request.include_mesh:
            r.nodes_mm.extend(X0.reshape(-1).tolist())
            r.tets.extend([0, 1, 2, 3])
            r.node_labels.extend([1, 2, 5, 0])
            r.vessel_points_mm.extend([0, 0, 0, 1, 1, 1])
            r.vessel_segments.extend([0, 1])
        return r

    def Register(self, request: Any, context: Any) -> Any:
        self._auth(context)
        self.register_requests.append(request)
        if request.case_id != "g1":
            abort_with_field(context, grpc.StatusCode.NOT_FOUND, f"no case {request.case_id!r}",
                             "case_id")
        return registration(points=len(request.measurements.kind))

    def StreamRegister(self, request_iterator: Any, context: Any) -> Any:
        self._auth(context)
        got: List[Any] = []
        self.sessions.append(got)
        first = next(request_iterator)
        got.append(first)
        if first.WhichOneof("msg") != "start":
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, "the first message must be a start")
        if first.start.case_id == "nope":
            abort_with_field(context, grpc.StatusCode.NOT_FOUND, "no case 'nope'", "start.case_id")
        sequence = 0
        points = 0
        for m in request_iterator:
            got.append(m)
            if first.start.case_id == "slow":
                continue
            sequence += 1
            kind = m.WhichOneof("msg")
            u = pb.StreamUpdate(sequence=sequence, session_id=SESSION_ID,
                                last_client_seq=m.client_seq)
            if kind == "surface":
                xyz = list(m.surface.xyz_mm)
                bad = [i for i, v in enumerate(xyz) if not math.isfinite(v)]
                if bad:
                    u.rejection.CopyFrom(pb.Rejection(
                        client_seq=m.client_seq, code="INVALID_ARGUMENT",
                        message="a coordinate is not finite",
                        violations=[pb.FieldViolation(field=f"surface.xyz_mm[{bad[0]}]",
                                                      description="not finite")]))
                    u.points_total = points
                    yield u
                    continue
                points += len(xyz) // 3
                if len(xyz) == 21:
                    sequence += 1
                    yield pb.StreamUpdate(
                        sequence=sequence - 1, session_id=SESSION_ID,
                        last_client_seq=m.client_seq,
                        discovery=pb.DiscoveryReport(state=pb.DISCOVERY_STATE_RUNNING))
                    u.sequence = sequence
                if first.start.method == pb.METHOD_NONLINEAR:
                    # Two answers, as the server gives them: the linear fit, then its refinement.
                    linear = registration(method=pb.METHOD_ADAPTIVE, points=points)
                    linear.refinement.follows = True
                    sequence += 1
                    yield pb.StreamUpdate(
                        sequence=sequence - 1, session_id=SESSION_ID,
                        last_client_seq=m.client_seq, registration=linear, points_total=points)
                    u.sequence = sequence
                    refined = registration(method=pb.METHOD_NONLINEAR, points=points)
                    refined.refinement.refines = True
                    u.registration.CopyFrom(refined)
                else:
                    u.registration.CopyFrom(self.answer(points, m))
            elif kind == "ultrasound":
                points += (len(m.ultrasound.contour_uv_mm) + len(m.ultrasound.vessel_uv_mm)) // 2
                if self.answer_ultrasound is not None:
                    u.registration.CopyFrom(self.answer_ultrasound(points, m))
                else:
                    u.registration.CopyFrom(
                        registration(method=pb.METHOD_RIGID, displacement=None, points=points))
            else:
                u.rejection.CopyFrom(pb.Rejection(client_seq=m.client_seq, code="INVALID_ARGUMENT",
                                                  message="unexpected message"))
            u.points_total = points
            yield u


@contextlib.contextmanager
def serve(fake: FakeServer, credentials: Any = None):
    server = grpc.server(futures.ThreadPoolExecutor(max_workers=8))
    pb_grpc.add_LibRPlusServicer_to_server(fake, server)
    if credentials is None:
        port = server.add_insecure_port("127.0.0.1:0")
    else:
        port = server.add_secure_port("127.0.0.1:0", credentials)
    server.start()
    try:
        yield port
    finally:
        server.stop(grace=None)


class WithServer(unittest.TestCase):
    token: Optional[str] = None

    def setUp(self) -> None:
        self.fake = FakeServer(token=self.token)
        self._serving = serve(self.fake)
        self.port = self._serving.__enter__()
        self.url = f"http://127.0.0.1:{self.port}"
        self.client = lc.Client(self.url, token=self.token, timeout_s=20)

    def tearDown(self) -> None:
        self.client.close()
        self._serving.__exit__(None, None, None)


# --- the tests ----------------------------------------------------------------------------------


class CasesTest(WithServer):
    def test_list_cases(self) -> None:
        cases = self.client.list_cases()
        self.assertEqual([c.case_id for c in cases], ["g1", "g2"])
        self.assertEqual(cases[0].node_count, NODES)
        self.assertEqual(cases[0].default_method, "METHOD_LIBR")
        self.assertEqual(cases[1].default_method, "METHOD_LIBR_PLUS")
        self.assertTrue(cases[1].libr_plus_ready)
        self.assertEqual(cases[0].effects, ["fixation"])

    def test_describe_case_reshapes_point_major(self) -> None:
        d = self.client.describe_case("g1")
        np.testing.assert_array_equal(d.nodes, X0)
        self.assertEqual(d.tets.shape, (1, 4))
        np.testing.assert_array_equal(d.node_labels, [1, 2, 5, 0])
        np.testing.assert_array_equal(d.vessel_points, [[0, 0, 0], [1, 1, 1]])
        np.testing.assert_array_equal(d.vessel_segments, [[0, 1]])
        self.assertEqual(d.state, "CASE_STATE_READY")
        self.assertEqual(d.summary.case_id, "g1")

    def test_unknown_case_is_an_rpc_error_with_its_field(self) -> None:
        with self.assertRaises(lc.RpcError) as cm:
            self.client.describe_case("g9")
        e = cm.exception
        self.assertEqual(e.status_code, grpc.StatusCode.NOT_FOUND)
        self.assertEqual(e.code, "NOT_FOUND")
        self.assertIn("g9", e.message)
        self.assertEqual(e.violations, [lc.FieldViolation("case_id", "no such case")])


class RegisterTest(WithServer):
    def test_measurements_and_options(self) -> None:
        surface = np.asfortranarray([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
        contour = [[7.0, 8.0, 9.0]]
        vessel = np.array([[10.0, 11.0, 12.0], [13.0, 14.0, 15.0]])
        t = np.eye(4)
        t[:3, :3], t[:3, 3] = R0, T0
        r = self.client.register("g1", surface, method="rigid", features=["falciform", 0],
                                 contour_points=contour, vessel_points=vessel,
                                 initial_alignment=t, time_budget_ms=500,
                                 omit_displacements=True, trusted_alignment_mm=3.5,
                                 held=True)
        (req,) = self.fake.register_requests
        m = req.measurements
        self.assertEqual(req.case_id, "g1")
        self.assertEqual(req.method, pb.METHOD_RIGID)
        self.assertEqual(list(m.xyz_mm), [float(v) for v in range(1, 16)])
        self.assertEqual(list(m.kind), [1, 1, 2, 3, 3])
        self.assertEqual(list(m.feature), [pb.SALIENT_FEATURE_FALCIFORM, 0, 0, 0, 0])
        self.assertEqual(list(m.initial_alignment.rotation), R0.reshape(-1).tolist())
        self.assertEqual(list(m.initial_alignment.translation_mm), T0.tolist())
        self.assertEqual(req.options.time_budget_ms, 500)
        self.assertTrue(req.options.omit_displacements)
        self.assertEqual(req.options.trusted_alignment_mm, 3.5)
        self.assertTrue(req.options.held)
        self.assertEqual(r.points_used, 5)
        self.assertIsNone(r.session_id)

    def test_no_features_no_alignment(self) -> None:
        self.client.register("g1", [[0.0, 0.0, 0.0]])
        (req,) = self.fake.register_requests
        self.assertEqual(list(req.measurements.feature), [])
        self.assertFalse(req.measurements.HasField("initial_alignment"))
        self.assertEqual(req.method, pb.METHOD_LIBR)

    def test_bad_arguments_are_refused_before_sending(self) -> None:
        with self.assertRaisesRegex(ValueError, "surface_points"):
            self.client.register("g1", [1.0, 2.0, 3.0])
        with self.assertRaisesRegex(ValueError, "features"):
            self.client.register("g1", [[1.0, 2.0, 3.0]], features=[0, 0])
        with self.assertRaisesRegex(ValueError, "method"):
            self.client.register("g1", [[1.0, 2.0, 3.0]], method="magic")
        with self.assertRaisesRegex(ValueError, "initial_alignment"):
            self.client.register("g1", [[1.0, 2.0, 3.0]], initial_alignment=np.eye(3))
        self.assertEqual(self.fake.register_requests, [])


class RegistrationParsingTest(unittest.TestCase):
    def test_rotation_is_row_major_and_displacements_node_major(self) -> None:
        r = lc.Registration.from_message(registration(points=3))
        np.testing.assert_array_equal(r.image_to_physical[:3, :3], R0)
        self.assertEqual(r.image_to_physical[0, 1], -1.0)  # row 0, column 1: the 2nd value
        np.testing.assert_array_equal(r.image_to_physical[:3, 3], T0)
        np.testing.assert_array_equal(r.image_to_physical[3], [0, 0, 0, 1])
        np.testing.assert_array_equal(r.displacement_mm, U0.astype(np.float64))
        np.testing.assert_array_equal(r.displacement_mm[1], [-0.25, 0.0, 0.25])
        self.assertEqual(r.quality, "QUALITY_NOT_CONVERGED")
        self.assertEqual(r.quality_reason, "stopped at 20 iterations")
        self.assertEqual(r.method_used, "METHOD_LIBR")
        self.assertEqual(r.residual_rms_mm, 1.25)
        self.assertEqual((r.points_used, r.points_matched, r.node_count), (3, 2, NODES))
        self.assertEqual(r.timings["total_ms"], 11.0)
        self.assertEqual(r.timings["libr_iterations"], 12)
        self.assertEqual(r.effects, ["gravity"])
        self.assertIsInstance(r.raw, pb.Registration)

    def test_deformed_nodes(self) -> None:
        r = lc.Registration.from_message(registration())
        got = r.deformed_nodes(X0)
        for i in range(NODES):
            p = X0[i] + U0[i].astype(np.float64)
            np.testing.assert_allclose(got[i], R0 @ p + T0, rtol=0, atol=1e-12)
        # Node 1: X = (1, 2, 3), u = (-0.25, 0, 0.25): R0 @ (0.75, 2, 3.25) = (-2, 0.75, 3.25).
        np.testing.assert_allclose(got[1], [-2.0 + 10.0, 0.75 - 20.0, 3.25 + 30.5])
        with self.assertRaisesRegex(ValueError, "nodes"):
            r.deformed_nodes(X0[:2])

    def test_rigid_answer_without_displacements_is_zeros(self) -> None:
        r = lc.Registration.from_message(registration(method=pb.METHOD_RIGID, displacement=None))
        np.testing.assert_array_equal(r.displacement_mm, np.zeros((NODES, 3)))
        np.testing.assert_allclose(r.deformed_nodes(X0), X0 @ R0.T + T0)

    def test_omitted_displacements_are_none(self) -> None:
        r = lc.Registration.from_message(registration(method=pb.METHOD_LIBR, displacement=None))
        self.assertIsNone(r.displacement_mm)
        with self.assertRaisesRegex(ValueError, "omit_displacements"):
            r.deformed_nodes(X0)

    def test_error_estimate(self) -> None:
        r = lc.Registration.from_message(registration())
        self.assertIsNone(r.predicted_tre_mm)
        self.assertIsNone(r.node_uncertainty_mm)
        m = registration()
        m.error_estimate.predicted_tre_mm = 3.5
        m.error_estimate.level = 0.9
        m.error_estimate.node_uncertainty_mm.extend([0.5 + i for i in range(NODES)])
        r = lc.Registration.from_message(m)
        self.assertEqual(r.predicted_tre_mm, 3.5)
        self.assertEqual(r.uncertainty_level, 0.9)
        np.testing.assert_allclose(r.node_uncertainty_mm, [0.5 + i for i in range(NODES)])
        self.assertIsNone(r.failure_probability)
        self.assertIsNone(r.failure_threshold_mm)
        m.error_estimate.failure.probability = 0.25
        m.error_estimate.failure.threshold_mm = 20.0
        r = lc.Registration.from_message(m)
        self.assertEqual((r.failure_probability, r.failure_threshold_mm), (0.25, 20.0))
        m.error_estimate.node_uncertainty_mm.append(1.0)
        with self.assertRaisesRegex(ValueError, "node_uncertainty_mm"):
            lc.Registration.from_message(m)

    def test_auto_names_the_model_chosen(self) -> None:
        self.assertIsNone(lc.Registration.from_message(registration()).chosen_model)
        m = registration(method=pb.METHOD_AUTO)
        m.quality = pb.QUALITY_AMBIGUOUS_MODEL
        m.choice.chosen = "rigid"
        m.choice.runner_up = "libr"
        m.choice.candidates.add(name="rigid", held_out_mm2=1.5)
        r = lc.Registration.from_message(m)
        self.assertEqual((r.method_used, r.chosen_model), ("METHOD_AUTO", "rigid"))
        self.assertEqual(r.quality, "QUALITY_AMBIGUOUS_MODEL")
        self.assertEqual(r.raw.choice.candidates[0].held_out_mm2, 1.5)

    def test_wrong_lengths_name_the_field(self) -> None:
        bad = registration()
        del bad.image_to_physical.rotation[8]
        with self.assertRaisesRegex(ValueError, r"image_to_physical\.rotation has 8"):
            lc.Registration.from_message(bad)
        bad = registration()
        bad.displacement_mm.append(0.0)
        with self.assertRaisesRegex(ValueError, "displacement_mm"):
            lc.Registration.from_message(bad)


class SessionTest(WithServer):
    def test_messages_on_the_wire(self) -> None:
        t = np.eye(4)
        t[:3, :3], t[:3, 3] = R0, T0
        pts1 = np.asfortranarray(np.arange(15, dtype=np.float64).reshape(5, 3))
        pts2 = [[100.0, 101.0, 102.0]]
        # A plane whose u axis is +z, v axis +x (so u x v = +y), at (5, 6, 7).
        pose = lc.plane_pose([5.0, 6.0, 7.0], [0.0, 0.0, 2.0], [1.0, 0.0, 0.0])
        contour = np.array([[1.0, 2.0], [3.0, -4.0]])
        vessel = np.array([[0.5, 9.0]])
        before = time.time()
        with self.client.session("g1", "libr_plus", initial_alignment=t, time_budget_ms=300,
                                 trusted_alignment_mm=2.0, held=True) as s:
            r1 = s.add_surface(pts1, features=["none", "falciform", "inferior_ridge", 0, 1])
            r2 = s.add_surface(pts2, acquired_at=before + 1000.25)
            r3 = s.add_ultrasound(pose, contour, vessel)
            r4 = s.add_ultrasound((R0, T0))  # a frame with nothing found in it
        after = time.time()
        (msgs,) = self.fake.sessions
        self.assertEqual([m.client_seq for m in msgs], [1, 2, 3, 4, 5])
        self.assertEqual([m.WhichOneof("msg") for m in msgs],
                         ["start", "surface", "surface", "ultrasound", "ultrasound"])
        st = msgs[0].start
        self.assertEqual((st.case_id, st.method), ("g1", pb.METHOD_LIBR_PLUS))
        self.assertEqual(list(st.initial_alignment.rotation), R0.reshape(-1).tolist())
        self.assertEqual(st.options.time_budget_ms, 300)
        self.assertEqual(st.options.trusted_alignment_mm, 2.0)
        self.assertTrue(st.options.held)
        # Points point-major (x0, y0, z0, x1, ...) whatever the array's memory order.
        self.assertEqual(list(msgs[1].surface.xyz_mm), [float(v) for v in range(15)])
        self.assertEqual(list(msgs[1].surface.feature), [0, 1, 2, 0, 1])
        self.assertEqual(list(msgs[2].surface.feature), [])
        # acquired_at: set, from time.time() unless given, never going back.
        stamps = [m.surface.acquired_at if m.HasField("surface") else m.ultrasound.acquired_at
                  for m in msgs[1:]]
        secs = [ts.seconds + ts.nanos * 1e-9 for ts in stamps]
        self.assertTrue(all(m.HasField("surface") and m.surface.HasField("acquired_at")
                            or m.ultrasound.HasField("acquired_at") for m in msgs[1:]))
        self.assertTrue(before - 1 <= secs[0] <= after + 1, secs)
        self.assertAlmostEqual(secs[1], before + 1000.25, places=5)
        self.assertEqual(secs, sorted(secs))
        self.assertGreaterEqual(secs[2], secs[1])  # not earlier than the explicit one
        # The plane: rotation row-major with columns (u axis, v axis, u x v).
        us = msgs[3].ultrasound
        rot = np.array(us.plane_to_physical.rotation).reshape(3, 3)
        np.testing.assert_allclose(rot[:, 0], [0, 0, 1])
        np.testing.assert_allclose(rot[:, 1], [1, 0, 0])
        np.testing.assert_allclose(rot[:, 2], [0, 1, 0])
        self.assertAlmostEqual(np.linalg.det(rot), 1.0)
        self.assertEqual(list(us.plane_to_physical.translation_mm), [5.0, 6.0, 7.0])
        self.assertEqual(list(us.contour_uv_mm), [1.0, 2.0, 3.0, -4.0])
        self.assertEqual(list(us.vessel_uv_mm), [0.5, 9.0])
        # (u, v) = (1, 2) is at origin + 1 * z + 2 * x.
        p = rot @ np.array([1.0, 2.0, 0.0]) + np.array(us.plane_to_physical.translation_mm)
        np.testing.assert_allclose(p, [7.0, 6.0, 8.0])
        self.assertEqual(list(msgs[4].ultrasound.plane_to_physical.rotation),
                         R0.reshape(-1).tolist())
        self.assertEqual(len(msgs[4].ultrasound.contour_uv_mm), 0)
        # The answers.
        self.assertEqual([r.last_client_seq for r in (r1, r2, r3, r4)], [2, 3, 4, 5])
        self.assertEqual([r.points_total for r in (r1, r2, r3, r4)], [5, 6, 9, 9])
        self.assertEqual(r1.session_id, SESSION_ID)
        self.assertEqual(s.session_id, SESSION_ID)
        np.testing.assert_array_equal(r1.image_to_physical[:3, :3], R0)
        np.testing.assert_array_equal(r1.displacement_mm, U0)
        self.assertEqual(r3.method_used, "METHOD_RIGID")
        np.testing.assert_array_equal(r3.displacement_mm, np.zeros((NODES, 3)))
        self.assertEqual(self.fake.metadata[0].get("authorization"), None)

    def test_rejection_raises_and_the_session_goes_on(self) -> None:
        with self.client.session("g1") as s:
            s.add_surface([[1.0, 2.0, 3.0]])
            with self.assertRaises(lc.RejectedError) as cm:
                s.add_surface([[1.0, 2.0, 3.0], [4.0, float("nan"), 6.0]])
            e = cm.exception
            self.assertEqual((e.code, e.client_seq), ("INVALID_ARGUMENT", 3))
            self.assertIn("not finite", e.message)
            self.assertEqual(e.violations, [lc.FieldViolation("surface.xyz_mm[4]", "not finite")])
            self.assertEqual(e.update.rejection.client_seq, 3)
            r = s.add_surface([[7.0, 8.0, 9.0]])
            self.assertEqual((r.last_client_seq, r.points_total), (4, 2))
        self.assertEqual([m.client_seq for m in self.fake.sessions[0]], [1, 2, 3, 4])

    def test_rejection_inside_with_closes_cleanly(self) -> None:
        with self.assertRaises(lc.RejectedError):
            with self.client.session("g1") as s:
                s.add_surface([[float("inf"), 0.0, 0.0]])

    def test_a_refused_start_is_an_rpc_error(self) -> None:
        with self.assertRaises(lc.RpcError) as cm:
            with self.client.session("nope") as s:
                s.add_surface([[1.0, 2.0, 3.0]])
        e = cm.exception
        self.assertEqual(e.status_code, grpc.StatusCode.NOT_FOUND)
        self.assertEqual(e.violations, [lc.FieldViolation("start.case_id", "no such case")])
        with self.assertRaises(lc.SessionClosedError):
            s.add_surface([[1.0, 2.0, 3.0]])

    def test_updates_that_do_not_answer_are_skipped(self) -> None:
        with self.client.session("g1") as s:
            r = s.add_surface(np.zeros((7, 3)))
        self.assertEqual(r.last_client_seq, 2)
        self.assertEqual([u.WhichOneof("update") for u in s.updates],
                         ["discovery", "registration"])

    def test_nonlinear_answers_with_the_refinement_the_linear_answer_kept_in_updates(self) -> None:
        with self.client.session("g1", "nonlinear") as s:
            r = s.add_surface([[1.0, 2.0, 3.0]])
            self.assertEqual(r.method_used, "METHOD_NONLINEAR")
            self.assertEqual(r.last_client_seq, 2)
            first, last = s.updates
            self.assertTrue(first.registration.refinement.follows)
            self.assertEqual(first.registration.method_used, pb.METHOD_ADAPTIVE)
            self.assertTrue(last.registration.refinement.refines)
            # The next message is answered by its own refinement, not the previous one's.
            r = s.add_surface([[4.0, 5.0, 6.0]])
            self.assertEqual((r.last_client_seq, r.method_used), (3, "METHOD_NONLINEAR"))
            self.assertEqual(len(s.updates), 4)

    def test_no_answer_times_out(self) -> None:
        c = lc.Client(self.url, timeout_s=0.5)
        try:
            s = c.session("slow")
            t0 = time.monotonic()
            with self.assertRaises(lc.RpcError) as cm:
                s.add_surface([[1.0, 2.0, 3.0]])
            self.assertLess(time.monotonic() - t0, 10)
            self.assertEqual(cm.exception.status_code, grpc.StatusCode.DEADLINE_EXCEEDED)
            self.assertIn("client_seq 2", cm.exception.message)
            s.close()
        finally:
            c.close()

    def test_features_must_match_points(self) -> None:
        with self.client.session("g1") as s:
            with self.assertRaisesRegex(ValueError, "features"):
                s.add_surface([[1.0, 2.0, 3.0]], features=[1, 2])
            with self.assertRaisesRegex(ValueError, "contour_uv"):
                s.add_ultrasound(np.eye(4), contour_uv=[[1.0, 2.0, 3.0]])
            with self.assertRaisesRegex(ValueError, "plane_to_physical"):
                s.add_ultrasound(np.zeros((4, 4)))
            s.add_surface([[1.0, 2.0, 3.0]])
        self.assertEqual([m.client_seq for m in self.fake.sessions[0]], [1, 2])


class TokenTest(WithServer):
    token = TOKEN

    def test_bearer_token_on_every_call(self) -> None:
        self.client.list_cases()
        with self.client.session("g1") as s:
            s.add_surface([[1.0, 2.0, 3.0]])
        self.assertEqual([md.get("authorization") for md in self.fake.metadata],
                         [f"Bearer {TOKEN}"] * 2)

    def test_without_the_token_unauthenticated(self) -> None:
        with lc.Client(self.url) as c:
            with self.assertRaises(lc.RpcError) as cm:
                c.list_cases()
            self.assertEqual(cm.exception.code, "UNAUTHENTICATED")
            with self.assertRaises(lc.RpcError) as cm:
                with c.session("g1") as s:
                    s.add_surface([[1.0, 2.0, 3.0]])
            self.assertEqual(cm.exception.code, "UNAUTHENTICATED")

    def test_bad_options(self) -> None:
        with self.assertRaisesRegex(ValueError, "token"):
            lc.Client(self.url, token="two words")
        with self.assertRaisesRegex(ValueError, "key"):
            lc.Client(self.url, cert="c.pem")
        with self.assertRaisesRegex(ValueError, "server"):
            lc.Client("http://host:1/path")


@unittest.skipUnless(shutil.which("openssl"), "needs the openssl command")
class MutualTlsTest(unittest.TestCase):
    """A CA, a server certificate for ``localhost`` and a client certificate, made by openssl
    (EC P-256); the client connects to 127.0.0.1 and checks the name ``localhost``."""

    @classmethod
    def setUpClass(cls) -> None:
        cls.dir = tempfile.mkdtemp(prefix="librplus-client-tls-")
        d = cls.dir

        def run(*args: str) -> None:
            subprocess.run(["openssl", *args], cwd=d, check=True, capture_output=True)

        run("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes",
            "-keyout", "ca.key", "-out", "ca.pem", "-days", "2", "-subj", "/CN=test CA")
        with open(os.path.join(d, "ext.cnf"), "w") as f:
            f.write("subjectAltName=DNS:localhost\n")
        for name, cn in (("server", "localhost"), ("client", "nav")):
            run("req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes",
                "-keyout", f"{name}.key", "-out", f"{name}.csr", "-subj", f"/CN={cn}")
            run("x509", "-req", "-in", f"{name}.csr", "-CA", "ca.pem", "-CAkey", "ca.key",
                "-CAcreateserial", "-out", f"{name}.pem", "-days", "2", "-extfile", "ext.cnf")

    @classmethod
    def tearDownClass(cls) -> None:
        shutil.rmtree(cls.dir, ignore_errors=True)

    def path(self, name: str) -> str:
        return os.path.join(self.dir, name)

    def test_mtls(self) -> None:
        def read(name: str) -> bytes:
            with open(self.path(name), "rb") as f:
                return f.read()

        creds = grpc.ssl_server_credentials(
            [(read("server.key"), read("server.pem"))], root_certificates=read("ca.pem"),
            require_client_auth=True)
        fake = FakeServer()
        with serve(fake, creds) as port:
            url = f"http://127.0.0.1:{port}"  # http:// with a CA: TLS, as the Rust client
            with lc.Client(url, ca=self.path("ca.pem"), cert=self.path("client.pem"),
                           key=self.path("client.key"), domain="localhost", timeout_s=10) as c:
                self.assertEqual([x.case_id for x in c.list_cases()], ["g1", "g2"])
                with c.session("g1") as s:
                    self.assertEqual(s.add_surface([[1.0, 2.0, 3.0]]).last_client_seq, 2)
            # Without a client certificate, or plaintext: refused.
            with lc.Client(url, ca=self.path("ca.pem"), domain="localhost", timeout_s=10) as c:
                with self.assertRaises(lc.RpcError):
                    c.list_cases()
            with lc.Client(url, timeout_s=10) as c:
                with self.assertRaises(lc.RpcError):
                    c.list_cases()
        with self.assertRaisesRegex(ValueError, "ca"):
            lc.Client("https://127.0.0.1:1", ca=self.path("missing.pem"))


def load_example() -> Any:
    path = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "examples",
                        "replay_case.py")
    spec = importlib.util.spec_from_file_location("replay_case", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)  # type: ignore[union-attr]
    return module


def write_dataset(root: str) -> dict:
    """A tiny dataset in the `librplus generate` layout (manifest.json, scenarios.npz): one
    geometry g1 of NODES nodes, one deformation, two scenarios (the second with two planes whose
    points lie in them)."""
    rng = np.random.default_rng(7)
    a = 0.3
    true_t = np.eye(4)
    true_t[:3, :3] = [[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]]
    true_t[:3, 3] = [3.0, -2.0, 1.5]
    surface = [rng.normal(size=(6, 3)) * 10, rng.normal(size=(9, 3)) * 10]
    origins = np.array([[0.0, 0.0, 50.0], [5.0, 5.0, 40.0]])
    lateral = np.array([[1.0, 0.0, 0.0], [0.0, 0.6, 0.8]])
    depth = np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    normal = np.cross(depth, lateral)
    uv = [np.array([[1.0, 2.0], [-3.0, 4.0]]), np.array([[0.5, 7.0]])]
    vessel_uv = [np.array([[2.0, 2.0]]), np.empty((0, 2))]
    pts, kind, plane = list(surface[0]), [0] * 6, [-1] * 6
    pts += list(surface[1])
    kind += [0] * 9
    plane += [-1] * 9
    for q in range(2):
        for k, coords in ((1, uv[q]), (2, vessel_uv[q])):
            for u, v in coords:
                pts.append(origins[q] + u * lateral[q] + v * depth[q])
                kind.append(k)
                plane.append(q)
    pts = np.array(pts)
    os.makedirs(os.path.join(root, "deformations", "g1-L-00"))
    np.savez(
        os.path.join(root, "deformations", "g1-L-00", "scenarios.npz"),
        format_version=np.array([1], np.int32),
        nodes=X0, tets=np.array([[0, 1, 2, 3]], np.int32), displacement=U0.astype(np.float64) * 3,
        points=pts, kind=np.array(kind, np.uint8), plane=np.array(plane, np.int32),
        feature=np.zeros(len(pts), np.uint8), truth_image=pts,
        offsets=np.array([0, 6, len(pts)], np.int64), category=np.array([0, 2], np.uint8),
        seed=np.array([1, 2], np.uint64), coverage=np.array([0.3, 0.4]),
        image_to_physical=np.stack([true_t, true_t]),
        initial_alignment=np.stack([np.eye(4), np.eye(4)]),
        plane_offsets=np.array([0, 0, 2], np.int64), plane_origin=origins,
        plane_depth_dir=depth, plane_lateral_dir=lateral, plane_normal=normal,
    )
    manifest = {"format": "librplus-dataset", "version": 1, "units": "mm", "frame": "LPS",
                "geometries": [{"id": "g1", "nodes": NODES}],
                "deformations": [{"id": "g1-L-00", "geometry": "g1",
                                  "npz": "deformations/g1-L-00/scenarios.npz"}]}
    with open(os.path.join(root, "manifest.json"), "w") as f:
        json.dump(manifest, f)
    return {"true_t": true_t, "points": pts, "kind": np.array(kind), "plane": np.array(plane)}


class ExampleTest(WithServer):
    def test_replay_case_against_a_server_answering_the_truth(self) -> None:
        example = load_example()
        with tempfile.TemporaryDirectory() as root:
            truth = write_dataset(root)
            # The fake answers the dataset's truth: the example's TRE must then be ~0.
            rigid = (truth["true_t"][:3, :3], truth["true_t"][:3, 3])
            self.fake.answer = lambda n, m: registration(displacement=U0 * 3, rigid=rigid,
                                                         points=n)
            self.fake.answer_ultrasound = self.fake.answer
            out = io.StringIO()
            with contextlib.redirect_stdout(out):
                code = example.main(["--server", self.url, "--data", root, "--batches", "2",
                                     "--max-tre", "1e-4", "--wait", "5"])
            text = out.getvalue()
        self.assertEqual(code, 0, text)
        (msgs,) = self.fake.sessions
        # Scenario 1 (the first with planes): 2 surface batches, then its 2 planes.
        self.assertEqual([m.WhichOneof("msg") for m in msgs],
                         ["start", "surface", "surface", "ultrasound", "ultrasound"])
        self.assertEqual(msgs[0].start.case_id, "g1")
        sent = np.array(list(msgs[1].surface.xyz_mm) + list(msgs[2].surface.xyz_mm))
        scen = truth["points"][6:]
        np.testing.assert_array_equal(sent.reshape(-1, 3), scen[truth["kind"][6:] == 0])
        # Each plane's (u, v) points map back to the measured physical points.
        for q, m in enumerate(msgs[3:]):
            us = m.ultrasound
            rot = np.array(us.plane_to_physical.rotation).reshape(3, 3)
            o = np.array(us.plane_to_physical.translation_mm)
            self.assertAlmostEqual(np.linalg.det(rot), 1.0)
            back = [rot @ np.array([u, v, 0.0]) + o
                    for u, v in np.array(list(us.contour_uv_mm) + list(us.vessel_uv_mm))
                    .reshape(-1, 2)]
            sel = (truth["plane"][6:] == q) & (truth["kind"][6:] > 0)
            np.testing.assert_allclose(np.array(back), scen[sel], atol=1e-9)
        # Every update carries the truth: its TRE is 0; this fake sends no error estimate, so
        # the predicted TRE (last column) is "-".
        lines = [ln.split() for ln in text.splitlines() if ln.split() and ln.split()[0].isdigit()]
        self.assertEqual([ln[0] for ln in lines], ["2", "3", "4", "5"], text)
        self.assertEqual([ln[-2] for ln in lines], ["0.00"] * 4, text)
        self.assertEqual([ln[-1] for ln in lines], ["-"] * 4, text)

    def test_replay_case_fails_on_a_missing_case(self) -> None:
        example = load_example()
        with tempfile.TemporaryDirectory() as root:
            np.save(os.path.join(root, "p.npy"), np.zeros((3, 3)))
            err = io.StringIO()
            with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
                code = example.main(["--server", self.url, "--case", "g7", "--points",
                                     os.path.join(root, "p.npy"), "--wait", "5"])
        self.assertEqual(code, 1)
        self.assertIn("g7", err.getvalue())

    def test_replay_case_points_mode(self) -> None:
        example = load_example()
        with tempfile.TemporaryDirectory() as root:
            np.save(os.path.join(root, "p.npy"), np.arange(30.0).reshape(10, 3))
            with contextlib.redirect_stdout(io.StringIO()):
                code = example.main(["--server", self.url, "--points",
                                     os.path.join(root, "p.npy"), "--batches", "3"])
        self.assertEqual(code, 0)
        (msgs,) = self.fake.sessions
        self.assertEqual([len(m.surface.xyz_mm) // 3 for m in msgs[1:]], [3, 4, 3])
        self.assertEqual(msgs[0].start.case_id, "g1")


if __name__ == "__main__":
    unittest.main()
