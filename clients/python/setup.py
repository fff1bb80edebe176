"""Build hook of librplus-client: the gRPC and protobuf stubs are generated from the repository's
proto at build time (never committed).

``build_py`` runs ``grpc_tools.protoc`` on ``../../proto/librplus/v1/librplus.proto`` (relative to
this file; pip >= 21.3 builds in the source tree, so the path resolves) into
``librplus_client/_pb/librplus/v1/`` (messages, their ``.pyi`` type stubs, and the service stub),
rewrites the service stub's absolute import ``from librplus.v1 import librplus_pb2`` into a
relative one, and adds the generated packages to the build. Everything else is in
pyproject.toml.
"""

import os
import re
import shutil
import sys

from setuptools import setup
from setuptools.command.build_py import build_py

HERE = os.path.dirname(os.path.abspath(__file__))
PROTO_ROOT = os.path.normpath(os.path.join(HERE, "..", "..", "proto"))
PROTO_FILE = os.path.join("librplus", "v1", "librplus.proto")
PB_DIR = os.path.join(HERE, "librplus_client", "_pb")
PB_PACKAGES = [
    "librplus_client._pb",
    "librplus_client._pb.librplus",
    "librplus_client._pb.librplus.v1",
]


def _tools_requirements():
    """The runtime requirements that match the grpcio-tools generating the stubs."""
    from importlib import metadata

    try:
        tools = metadata.version("grpcio-tools")
        requires = metadata.requires("grpcio-tools") or []
    except metadata.PackageNotFoundError:
        sys.exit(
            "librplus-client: grpcio-tools is not installed in the build environment "
            "(pyproject.toml's [build-system] requires it; build with pip, or install it first)"
        )
    # grpcio-tools names the protobuf its protoc writes for, e.g. "protobuf<8.0.0,>=7.35.1".
    protobuf = next(
        (
            r.split(";")[0].replace(" ", "")
            for r in requires
            if re.match(r"protobuf\s*[<>=!~]", r) and "extra ==" not in r
        ),
        "protobuf>=4.21",
    )
    return [f"grpcio>={tools}", protobuf, "numpy>=1.22"]


def generate_stubs():
    """Runs protoc on the proto into librplus_client/_pb; exits with a message naming the proto's
    path when it is missing."""
    proto = os.path.join(PROTO_ROOT, PROTO_FILE)
    if not os.path.isfile(proto):
        sys.exit(
            f"librplus-client: the service contract {proto} is missing. The stubs are generated "
            "from it at build time: build from a checkout of the LIBR+ repository "
            "(pip install ./clients/python, pip >= 21.3), where it is at "
            "proto/librplus/v1/librplus.proto."
        )
    import grpc_tools
    from grpc_tools import protoc

    # google/protobuf/timestamp.proto ships inside grpc_tools.
    well_known = os.path.join(os.path.dirname(grpc_tools.__file__), "_proto")
    if os.path.isdir(PB_DIR):
        shutil.rmtree(PB_DIR)
    os.makedirs(os.path.join(PB_DIR, "librplus", "v1"))
    args = [
        "grpc_tools.protoc",
        f"-I{PROTO_ROOT}",
        f"-I{well_known}",
        f"--python_out={PB_DIR}",
        f"--pyi_out={PB_DIR}",
        f"--grpc_python_out={PB_DIR}",
        PROTO_FILE,
    ]
    # protoc resolves PROTO_FILE against the include path; run from the proto root so that the
    # file name it records (and registers in the descriptor pool) is librplus/v1/librplus.proto.
    cwd = os.getcwd()
    os.chdir(PROTO_ROOT)
    try:
        code = protoc.main(args)
    finally:
        os.chdir(cwd)
    if code != 0:
        sys.exit(f"librplus-client: grpc_tools.protoc failed on {proto} (exit {code})")
    v1 = os.path.join(PB_DIR, "librplus", "v1")
    for d in (PB_DIR, os.path.join(PB_DIR, "librplus"), v1):
        with open(os.path.join(d, "__init__.py"), "w") as f:
            f.write(f'"""Generated from {PROTO_FILE} at build time by setup.py."""\n')
    grpc_stub = os.path.join(v1, "librplus_pb2_grpc.py")
    with open(grpc_stub) as f:
        text = f.read()
    fixed, n = re.subn(
        r"^from librplus\.v1 import librplus_pb2 ",
        "from . import librplus_pb2 ",
        text,
        flags=re.M,
    )
    if n != 1:
        sys.exit(
            f"librplus-client: {grpc_stub}: expected one 'from librplus.v1 import librplus_pb2' "
            f"to make relative, found {n} (grpcio-tools changed its output?)"
        )
    with open(grpc_stub, "w") as f:
        f.write(fixed)


class BuildPyWithStubs(build_py):
    """build_py that first generates the stubs and adds their packages."""

    def run(self):
        generate_stubs()
        packages = list(self.packages or [])
        packages += [p for p in PB_PACKAGES if p not in packages]
        self.packages = packages
        self.distribution.packages = packages
        # Data files (the .pyi stubs) are computed lazily from the packages: again, with these.
        self.__dict__.pop("data_files", None)
        super().run()


setup(cmdclass={"build_py": BuildPyWithStubs}, install_requires=_tools_requirements())
