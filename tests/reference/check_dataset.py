#!/usr/bin/env python3
"""Independent check of a LIBR+ dataset directory with Python's meshio, VTK and numpy.

Usage: check_dataset.py DIR
Reads manifest.json; opens every .vtu with meshio *and* VTK's own XML reader (what ParaView and
3D Slicer use), every .vtp (point sets; meshio has no .vtp reader) with VTK's XML PolyData reader,
loads every scenarios.npz with numpy.load alone, and checks that they agree with each other and
with the manifest (counts, shapes, values). Exits non-zero with a message on the first disagreement.
"""
import json
import sys
from pathlib import Path

import meshio
import numpy as np
import vtk
from vtk.util.numpy_support import vtk_to_numpy


def fail(msg):
    print(f"check_dataset: FAIL: {msg}", file=sys.stderr)
    sys.exit(1)


def read_vtk_xml(path):
    """Points and point-data arrays of a .vtu/.vtp through VTK's XML readers."""
    path = str(path)
    reader = vtk.vtkXMLPolyDataReader() if path.endswith(".vtp") else vtk.vtkXMLUnstructuredGridReader()
    reader.SetFileName(path)
    reader.Update()
    if reader.GetErrorCode() != 0:
        fail(f"{path}: VTK reader error {reader.GetErrorCode()}")
    out = reader.GetOutput()
    pts = out.GetPoints()
    points = vtk_to_numpy(pts.GetData()) if pts is not None else np.zeros((0, 3))
    pd = out.GetPointData()
    arrays = {pd.GetArrayName(i): vtk_to_numpy(pd.GetArray(i)) for i in range(pd.GetNumberOfArrays())}
    return points, arrays, out.GetNumberOfCells()


def main(root):
    root = Path(root)
    m = json.loads((root / "manifest.json").read_text())
    if m["format"] != "librplus-dataset" or m["version"] != 1:
        fail(f"unexpected format {m['format']} v{m['version']}")
    if not m["complete"]:
        fail(f"dataset incomplete, missing {m['missing']}")
    geos = {}
    for g in m["geometries"]:
        mesh = meshio.read(root / g["preop"])
        tets = mesh.cells_dict.get("tetra")
        if tets is None or len(tets) != g["tets"] or len(mesh.points) != g["nodes"]:
            fail(f"{g['preop']}: counts differ from the manifest")
        for name in ["region", "falciform", "inferior_ridge", "bare_area", "target", "tumour"]:
            if name not in mesh.point_data:
                fail(f"{g['preop']}: point array {name} missing")
        for name in ["tissue", "youngs_modulus_kpa"]:
            if name not in mesh.cell_data:
                fail(f"{g['preop']}: cell array {name} missing")
        p = mesh.points[tets]
        vol = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]) / 6
        if vol.min() <= 0:
            fail(f"{g['preop']}: a tet is not positively oriented")
        if abs(vol.sum() / 1000 - g["volume_ml"]) > 1e-6 * g["volume_ml"]:
            fail(f"{g['preop']}: volume {vol.sum() / 1000} mL, manifest {g['volume_ml']}")
        targets = np.flatnonzero(mesh.point_data["target"])
        if sorted(targets.tolist()) != sorted(g["targets"]):
            fail(f"{g['preop']}: targets differ from the manifest")
        vp, varrays, _ = read_vtk_xml(root / g["preop"])
        if not np.array_equal(vp, mesh.points) or not np.array_equal(varrays["region"], mesh.point_data["region"]):
            fail(f"{g['preop']}: VTK and meshio disagree")
        vpts, varrays, _ = read_vtk_xml(root / g["vessels"])
        if "radius_mm" not in varrays or len(varrays["radius_mm"]) != len(vpts):
            fail(f"{g['vessels']}: radius_mm missing")
        geos[g["id"]] = (mesh.points, tets)
    n_scen = 0
    for d in m["deformations"]:
        points, tets = geos[d["geometry"]]
        gt = meshio.read(root / d["gt"])
        u = gt.point_data["displacement"]
        if u.shape != points.shape or not np.array_equal(gt.points, points):
            fail(f"{d['gt']}: mesh differs from its geometry")
        mean = np.linalg.norm(u, axis=1).mean()
        if abs(mean - d["mean_displacement_mm"]) > 1e-9 * max(1.0, mean):
            fail(f"{d['gt']}: mean displacement {mean}, manifest {d['mean_displacement_mm']}")
        z = np.load(root / d["npz"])
        if not np.array_equal(z["nodes"], points) or not np.array_equal(z["tets"], tets):
            fail(f"{d['npz']}: mesh differs from preop.vtu")
        if not np.array_equal(z["displacement"], u):
            fail(f"{d['npz']}: displacement differs from gt.vtu")
        off = z["offsets"]
        if len(off) != len(d["scenarios"]) + 1 or off[-1] != len(z["points"]):
            fail(f"{d['npz']}: offsets inconsistent")
        for s in d["scenarios"]:
            k = s["index"]
            sl = slice(off[k], off[k + 1])
            vpts, varrays, ncells = read_vtk_xml(root / s["file"])
            if not np.array_equal(vpts, z["points"][sl]):
                fail(f"{s['file']}: points differ from the npz")
            if ncells != len(vpts):
                fail(f"{s['file']}: {ncells} vertex cells for {len(vpts)} points (ParaView shows only cells)")
            kind = z["kind"][sl]
            counts = [int((kind == c).sum()) for c in range(3)]
            if counts != [s["surface_points"], s["contour_points"], s["vessel_points"]]:
                fail(f"{s['file']}: point kinds {counts} differ from the manifest")
            if not np.array_equal(varrays["kind"], kind):
                fail(f"{s['file']}: kind differs from the npz")
            feat = z["feature"][sl]
            if not np.array_equal(varrays["feature"], feat) or int((feat > 0).sum()) != s["feature_points"]:
                fail(f"{s['file']}: feature differs from the npz or the manifest")
            if (feat[kind != 0] != 0).any():
                fail(f"{s['file']}: an ultrasound point is designated on a surface feature")
            t = z["image_to_physical"][k]
            r = t[:3, :3]
            if np.abs(r @ r.T - np.eye(3)).max() > 1e-9 or abs(np.linalg.det(r) - 1) > 1e-9:
                fail(f"{d['npz']}: scenario {k} transform is not a rotation")
            # Noise-free truth mapped by the true transform lies within noise of the measurements.
            truth = z["truth_image"][sl] @ r.T + t[:3, 3]
            err = np.linalg.norm(truth - z["points"][sl], axis=1)
            if len(err) and np.median(err) > 10.0:
                fail(f"{s['file']}: measurements far from the transformed truth ({np.median(err)} mm)")
            n_scen += 1
    print(f"check_dataset: OK: {len(m['geometries'])} geometries, {len(m['deformations'])} deformations, {n_scen} scenarios read with meshio {meshio.__version__}, VTK {vtk.vtkVersion.GetVTKVersion()} and numpy {np.__version__}")


if __name__ == "__main__":
    main(sys.argv[1])
