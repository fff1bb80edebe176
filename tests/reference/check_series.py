#!/usr/bin/env python3
"""Independent check of a ParaView time series (.pvd) written by `librplus-client replay --series`.

Usage: check_series.py FILE.pvd [EXPECTED_STEPS]
ParaView's own collection reader (vtkPVDReader) is not in the `vtk` wheel on PyPI, so this does
what it does with VTK's pieces: parses the collection with VTK's XML parser (vtkXMLDataParser,
the parser ParaView's reader is built on), checks the root (VTKFile type="Collection"), that
every DataSet has a file and a numeric timestep in non-decreasing order, opens every file with
VTK's vtkXMLUnstructuredGridReader (what ParaView uses for .vtu) and checks the tetrahedra, the
point arrays `displacement` (3 components) and `error_mm` (1, finite, >= 0). Prints one line per
step: time, points, mean error_mm (the caller compares it with its TRE). Exits non-zero on the
first problem.
"""
import sys
from pathlib import Path

import numpy as np
import vtk
from vtk.util.numpy_support import vtk_to_numpy


def fail(msg):
    print(f"check_series: FAIL: {msg}", file=sys.stderr)
    sys.exit(1)


def main():
    if len(sys.argv) not in (2, 3):
        fail("usage: check_series.py FILE.pvd [EXPECTED_STEPS]")
    pvd = Path(sys.argv[1])
    parser = vtk.vtkXMLDataParser()
    parser.SetFileName(str(pvd))
    if not parser.Parse():
        fail(f"{pvd}: VTK's XML parser could not parse it")
    root = parser.GetRootElement()
    if root.GetName() != "VTKFile" or root.GetAttribute("type") != "Collection":
        fail(f"{pvd}: root is <{root.GetName()} type={root.GetAttribute('type')}>, not a Collection")
    coll = root.FindNestedElementWithName("Collection")
    if coll is None:
        fail(f"{pvd}: no <Collection>")
    times = []
    for i in range(coll.GetNumberOfNestedElements()):
        ds = coll.GetNestedElement(i)
        if ds.GetName() != "DataSet":
            continue
        f, t = ds.GetAttribute("file"), ds.GetAttribute("timestep")
        if not f or t is None:
            fail(f"{pvd}: DataSet {i} lacks file or timestep")
        t = float(t)
        if times and t < times[-1]:
            fail(f"{pvd}: timestep {t} after {times[-1]}: not in time order")
        times.append(t)
        path = pvd.parent / f
        reader = vtk.vtkXMLUnstructuredGridReader()
        reader.SetFileName(str(path))
        reader.Update()
        if reader.GetErrorCode() != 0:
            fail(f"{path}: VTK reader error {reader.GetErrorCode()}")
        grid = reader.GetOutput()
        n, cells = grid.GetNumberOfPoints(), grid.GetNumberOfCells()
        if n == 0 or cells == 0:
            fail(f"{path}: {n} points, {cells} cells")
        if any(grid.GetCellType(c) != vtk.VTK_TETRA for c in range(cells)):
            fail(f"{path}: a cell is not a tetrahedron")
        pd = grid.GetPointData()
        disp, err = pd.GetArray("displacement"), pd.GetArray("error_mm")
        if disp is None or disp.GetNumberOfComponents() != 3 or disp.GetNumberOfTuples() != n:
            fail(f"{path}: no 3-component 'displacement' array with one tuple per point")
        if err is None or err.GetNumberOfComponents() != 1 or err.GetNumberOfTuples() != n:
            fail(f"{path}: no 'error_mm' array with one value per point")
        e = vtk_to_numpy(err)
        if not np.all(np.isfinite(e)) or np.any(e < 0):
            fail(f"{path}: error_mm has negative or non-finite values")
        print(f"step {len(times)} t={t!r} points={n} tets={cells} mean_error_mm={float(e.mean())!r}")
    if not times:
        fail(f"{pvd}: no DataSet")
    if len(sys.argv) == 3 and len(times) != int(sys.argv[2]):
        fail(f"{pvd}: {len(times)} steps, expected {sys.argv[2]}")
    print(f"check_series: OK, {len(times)} steps in {pvd}")


if __name__ == "__main__":
    main()
