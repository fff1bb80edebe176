#!/usr/bin/env python3
"""Replays a recorded scenario through a LIBR+ server with librplus_client, as a navigation
system would: list the cases, open a session, stream the surface points in a few batches, then
a few tracked ultrasound planes, printing each update's quality, method and figures, the
server's predicted TRE (its error estimate) and, when the dataset's ground truth is at hand, the
true TRE.

Usage (a dataset written by ``librplus generate`` or ``librplus-server demo --only-data``, and a
server serving it: ``librplus-server serve --cases DIR``)::

    python replay_case.py --server http://127.0.0.1:50051 --data DIR [--deformation g1-L-00]
        [--scenario K] [--method libr] [--batches 4] [--planes 3]

or points of your own (physical frame, mm), with no ground truth::

    python replay_case.py --server URL --case g1 --points surface.npy [--batches 4]

TLS and tokens: ``--ca``, ``--cert``, ``--key``, ``--domain``, ``--token`` (as
``librplus-client``). Exit status: 0 when every message was answered with a registration (and
the last TRE is within ``--max-tre`` when given), 1 on an error or a rejection, 2 when the TRE
is over ``--max-tre``.

TRE is the dataset's: the mean over the mesh nodes of the distance between the registered node
position image_to_physical(X + u) and the true one T_true(X + u_true), physical frame, mm
(docs/dataset-and-models.md; the same definition as ``librplus-client replay``).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from typing import Any, List, Optional, Sequence, Tuple

import numpy as np

from librplus_client import Client, LibrPlusError, Registration, plane_pose

# Scenario categories in scenarios.npz (docs/dataset-and-models.md).
CATEGORIES = ["surface", "surface+1us", "surface+2us", "surface+3us", "surface+16us"]


class Scenario:
    """One dataset scenario: what surgery has, and the truth (evaluation only)."""

    def __init__(self, data: str, deformation: Optional[str], index: Optional[int]) -> None:
        with open(os.path.join(data, "manifest.json")) as f:
            manifest = json.load(f)
        deformations = manifest.get("deformations", [])
        if not deformations:
            raise SystemExit(f"{data}/manifest.json: no deformations")
        if deformation is None:
            d = deformations[0]
        else:
            found = [x for x in deformations if x["id"] == deformation]
            if not found:
                ids = ", ".join(x["id"] for x in deformations)
                raise SystemExit(f"--deformation {deformation}: not in {data} ({ids})")
            d = found[0]
        self.deformation = d["id"]
        self.case_id = d["geometry"]
        z = np.load(os.path.join(data, d["npz"]))
        offsets, plane_offsets = z["offsets"], z["plane_offsets"]
        count = len(offsets) - 1
        if index is None:
            # The first scenario with ultrasound planes, to show both kinds of message.
            index = next(
                (k for k in range(count) if plane_offsets[k + 1] > plane_offsets[k]), 0
            )
        if not 0 <= index < count:
            raise SystemExit(f"--scenario {index}: {self.deformation} has {count} scenarios")
        self.index = index
        lo, hi = offsets[index], offsets[index + 1]
        self.points = z["points"][lo:hi]
        self.kind = z["kind"][lo:hi]  # 0 surface, 1 posterior contour, 2 vessel
        self.plane = z["plane"][lo:hi]  # plane index within the scenario, -1 for surface
        self.feature = z["feature"][lo:hi]  # 0 none, 1 falciform, 2 inferior ridge
        self.category = CATEGORIES[int(z["category"][index])] if "category" in z else "?"
        self.initial_alignment = z["initial_alignment"][index]
        plo, phi = plane_offsets[index], plane_offsets[index + 1]
        self.plane_origin = z["plane_origin"][plo:phi]
        self.plane_lateral = z["plane_lateral_dir"][plo:phi]
        self.plane_depth = z["plane_depth_dir"][plo:phi]
        # Evaluation only: never sent to the server.
        self.nodes = z["nodes"]
        self.true_displacement = z["displacement"]
        self.true_image_to_physical = z["image_to_physical"][index]

    def surface(self) -> np.ndarray:
        return self.points[self.kind == 0]

    def surface_features(self) -> np.ndarray:
        return self.feature[self.kind == 0]

    def planes(self) -> List[tuple]:
        """(pose, contour (u, v), vessel (u, v)) per plane: the plane's points in its own
        coordinates (u lateral, v depth from the probe contact), as a tracked probe gives them."""
        out = []
        for q in range(len(self.plane_origin)):
            pose = plane_pose(self.plane_origin[q], self.plane_lateral[q], self.plane_depth[q])
            r, o = pose[:3, :3], pose[:3, 3]

            def uv(kind: int) -> np.ndarray:
                p = self.points[(self.plane == q) & (self.kind == kind)]
                return ((p - o) @ r)[:, :2]

            out.append((pose, uv(1), uv(2)))
        return out

    def tre_mm(self, r: Registration) -> float:
        """Mean node distance between the registered and the true positions, physical frame."""
        t = self.true_image_to_physical
        truth = (self.nodes + self.true_displacement) @ t[:3, :3].T + t[:3, 3]
        return float(np.linalg.norm(r.deformed_nodes(self.nodes) - truth, axis=1).mean())


def batches(n: int, count: int) -> List[slice]:
    count = max(1, min(count, n)) if n else 0
    edges = np.linspace(0, n, count + 1).round().astype(int)
    return [slice(a, b) for a, b in zip(edges[:-1], edges[1:]) if b > a]


def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--server", default=os.environ.get("LIBRPLUS_SERVER", "http://127.0.0.1:50051"))
    ap.add_argument("--ca")
    ap.add_argument("--cert")
    ap.add_argument("--key")
    ap.add_argument("--domain")
    ap.add_argument("--token", default=os.environ.get("LIBRPLUS_TOKEN"))
    ap.add_argument("--data", help="dataset directory (librplus generate / demo --only-data)")
    ap.add_argument("--deformation", help="deformation id (default: the manifest's first)")
    ap.add_argument("--scenario", type=int, help="scenario index (default: the first with planes)")
    ap.add_argument("--case", help="case id (default: the dataset's geometry, else the first)")
    ap.add_argument("--points", help="surface points (N, 3) .npy, physical frame, mm")
    ap.add_argument("--method", default="libr", help="rigid, libr, libr_plus, v2s or default")
    ap.add_argument("--batches", type=int, default=4, help="surface batches (default 4)")
    ap.add_argument("--planes", type=int, default=3, help="ultrasound planes at most (default 3)")
    ap.add_argument("--wait", type=float, default=120, help="seconds to wait for the server")
    ap.add_argument("--timeout", type=float, default=120, help="seconds per answer")
    ap.add_argument("--max-tre", type=float, help="fail (exit 2) when the last TRE is above this")
    a = ap.parse_args(argv)
    if (a.data is None) == (a.points is None):
        ap.error("give --data DIR (a dataset scenario) or --points FILE.npy")

    sc = Scenario(a.data, a.deformation, a.scenario) if a.data else None
    try:
        with Client(
            a.server, ca=a.ca, cert=a.cert, key=a.key, domain=a.domain, token=a.token,
            timeout_s=a.timeout,
        ) as client:
            cases = client.wait_ready(a.wait)
            ids = [c.case_id for c in cases]
            print(f"{a.server}: {len(cases)} case(s): " + ", ".join(
                f"{c.case_id} ({c.node_count} nodes, default {c.default_method})" for c in cases))
            case_id = a.case or (sc.case_id if sc else (ids[0] if ids else None))
            if case_id not in ids:
                print(f"case {case_id!r} is not served (cases: {ids})", file=sys.stderr)
                return 1
            features: Optional[np.ndarray]
            planes: List[tuple]
            alignment: Optional[np.ndarray]
            score = False  # whether the TRE can be computed
            if sc is not None:
                info = next(c for c in cases if c.case_id == case_id)
                score = info.node_count == len(sc.nodes)
                if not score:
                    print(f"note: case {case_id} has {info.node_count} nodes, the dataset's "
                          f"geometry {len(sc.nodes)}: no TRE", file=sys.stderr)
                surface, features = sc.surface(), sc.surface_features()
                planes = sc.planes()[: max(a.planes, 0)]
                alignment = sc.initial_alignment
                print(f"scenario {sc.deformation}/{sc.index} ({sc.category}): "
                      f"{len(surface)} surface points, {len(planes)} of "
                      f"{len(sc.plane_origin)} planes sent")
            else:
                surface = np.load(a.points)
                features, planes, alignment = None, [], None
            print(f"{'msg':>4} {'kind':<10} {'points':>6} {'quality':<22} {'method':<17} "
                  f"{'rms mm':>7} {'ms':>7} {'TRE mm':>7} {'pred mm':>7}")
            last: Optional[Registration] = None
            tre = float("nan")
            with client.session(case_id, a.method, initial_alignment=alignment) as s:
                msgs: List[Tuple[str, Any]] = [
                    ("surface", b) for b in batches(len(surface), a.batches)
                ]
                msgs += [("ultrasound", p) for p in planes]
                for i, (kind, what) in enumerate(msgs):
                    if kind == "surface":
                        feats = None if features is None else features[what]
                        r = s.add_surface(surface[what], feats)
                    else:
                        pose, contour, vessel = what
                        r = s.add_ultrasound(pose, contour, vessel)
                    if sc is not None and score:
                        tre = sc.tre_mm(r)
                    tre_text = f"{tre:.2f}" if tre == tre else "-"
                    # The server's own estimate of its error (None when it sent none).
                    pred = r.predicted_tre_mm
                    pred_text = "-" if pred is None else f"{pred:.2f}"
                    print(f"{i + 2:>4} {kind:<10} {r.points_total:>6} {r.quality:<22} "
                          f"{r.method_used:<17} {r.residual_rms_mm:>7.2f} "
                          f"{r.timings['total_ms']:>7.1f} {tre_text:>7} {pred_text:>7}")
                    if r.quality_reason:
                        print(f"     {r.quality_reason}")
                    last = r
            if last is None:
                print("nothing was sent (no points)", file=sys.stderr)
                return 1
            print(f"session {s.session_id}: {len(msgs)} updates, final {last.method_used} "
                  f"{last.quality}" + (f", TRE {tre:.2f} mm" if tre == tre else ""))
    except LibrPlusError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    if a.max_tre is not None:
        if tre != tre:
            print("--max-tre: no TRE (no ground truth, or the case's mesh is not the dataset's)",
                  file=sys.stderr)
            return 2
        if tre > a.max_tre:
            print(f"TRE {tre:.2f} mm is above --max-tre {a.max_tre}", file=sys.stderr)
            return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
