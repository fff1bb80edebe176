"""Python client of the LIBR+ intraoperative liver registration service (gRPC, ``librplus.v1``).

Units and frames are the service's: lengths in mm; measurements in the physical (tracker) frame;
the preoperative mesh in the image frame; both LPS (x left, y posterior, z superior). A
registration gives ``image_to_physical`` (4x4) and per-node displacements u (image frame): node i
is at ``image_to_physical(X_i + u_i)`` (:meth:`Registration.deformed_nodes`).

Example::

    from librplus_client import Client

    with Client("http://127.0.0.1:50051") as c:
        case = c.list_cases()[0].case_id
        with c.session(case, "libr") as s:
            r = s.add_surface(points)          # (N, 3) physical frame, mm
            print(r.quality, r.method_used, r.residual_rms_mm)

The generated protobuf modules are ``librplus_client.pb`` (messages) and
``librplus_client.pb_grpc`` (the service stub), for what this API does not cover.
"""

try:
    from ._pb.librplus.v1 import librplus_pb2 as pb
    from ._pb.librplus.v1 import librplus_pb2_grpc as pb_grpc
except ModuleNotFoundError as _e:  # pragma: no cover (an unbuilt source folder)
    if not (_e.name or "").startswith(__name__ + "._pb"):
        raise
    raise ImportError(
        "librplus_client: the generated stubs (librplus_client/_pb) are missing: this is the "
        "package's source folder, not built. Install it (pip install ./clients/python, which "
        "generates them from proto/librplus/v1/librplus.proto), or run from another folder."
    ) from None

from .client import MAX_MESSAGE_BYTES, Client, Session
from .errors import FieldViolation, LibrPlusError, RejectedError, RpcError, SessionClosedError
from .types import CaseDescription, CaseInfo, Registration, method_value, plane_pose

__version__ = "0.1.0"

__all__ = [
    "Client",
    "Session",
    "Registration",
    "CaseInfo",
    "CaseDescription",
    "LibrPlusError",
    "RpcError",
    "RejectedError",
    "SessionClosedError",
    "FieldViolation",
    "plane_pose",
    "method_value",
    "MAX_MESSAGE_BYTES",
    "pb",
    "pb_grpc",
]
