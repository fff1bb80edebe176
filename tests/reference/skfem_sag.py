"""Independent scikit-fem reference for `librplus fem sag` (the project's reference gravity-sag problem).

Problem: the SOFA liver tet mesh (Gmsh v1 ASCII, coordinates in cm, scaled x10 to mm), linear elasticity
with P1 tetrahedra, E = 5 kPa, nu = 0.45 (Lame parameters from skfem.models.elasticity.lame_parameters),
body force f = (0, 0.0104, 0) mN/mm^3 assembled as the linear form int f.v dx, every node with
y > y_min + 0.8*(y_max - y_min) (strictly, y in mm) fixed in all 3 components. Units: mm, kPa, mN,
so displacements are mm and the strain energy 0.5 u^T K u is in mN*mm (= uJ).
Solved with skfem.condense + scipy.sparse.linalg.spsolve; the residual of the free system is checked.

Usage (from the repository root):
    python tests/reference/skfem_sag.py ../shared/data/sofa_liver.msh tests/reference/sofa_liver_sag_skfem.json
Needs scikit-fem, numpy, scipy (no meshio: the v1 format is parsed here)."""
import json
import os
import sys

import numpy as np
import scipy.sparse.linalg as sla
import skfem
from skfem.models.elasticity import lame_parameters, linear_elasticity

E_KPA, NU = 5.0, 0.45
BODY_FORCE = (0.0, 0.0104, 0.0)  # mN/mm^3, along +y
FIXED_FRACTION = 0.8
CM_TO_MM = 10.0


def read_gmsh_v1(path):
    """Nodes (N x 3, file units, in $NOD order) and type-4 tets (T x 4, 0-based indices) of a Gmsh v1 file.
    Node ids are mapped to indices; they are never used as indices directly."""
    lines = open(path).read().split('\n')
    i = next(k for k, l in enumerate(lines) if l.strip() == '$NOD')
    n = int(lines[i + 1])
    ids, pts = [], []
    for l in lines[i + 2:i + 2 + n]:
        f = l.split()
        ids.append(int(f[0])); pts.append([float(v) for v in f[1:4]])
    assert lines[i + 2 + n].strip() == '$ENDNOD'
    index = {nid: k for k, nid in enumerate(ids)}
    j = next(k for k, l in enumerate(lines) if l.strip() == '$ELM')
    m = int(lines[j + 1])
    tets = []
    for l in lines[j + 2:j + 2 + m]:
        f = [int(v) for v in l.split()]
        etype, nn = f[1], f[4]
        if etype == 4:
            assert nn == 4
            tets.append([index[v] for v in f[5:9]])
    assert lines[j + 2 + m].strip() == '$ENDELM'
    return np.array(pts, float), np.array(tets, int)


def signed_volumes(p, t):
    """det[x1-x0, x2-x0, x3-x0] / 6 per tet (p: N x 3, t: T x 4)."""
    x = p[t]
    return np.einsum('ij,ij->i', x[:, 1] - x[:, 0], np.cross(x[:, 2] - x[:, 0], x[:, 3] - x[:, 0])) / 6.0


def fixed_nodes(p):
    y = p[:, 1]
    return np.where(y > y.min() + FIXED_FRACTION * (y.max() - y.min()))[0]


def solve(p, t):
    """Returns (u as N x 3, K, f, fixed node indices, relative residual of the free system)."""
    mesh = skfem.MeshTet(p.T.copy(), t.T.copy())
    basis = skfem.Basis(mesh, skfem.ElementVector(skfem.ElementTetP1()))
    K = linear_elasticity(*lame_parameters(E_KPA, NU)).assemble(basis)

    @skfem.LinearForm
    def body(v, w):
        return BODY_FORCE[0] * v[0] + BODY_FORCE[1] * v[1] + BODY_FORCE[2] * v[2]

    f = body.assemble(basis)
    fixed = fixed_nodes(p)
    D = basis.nodal_dofs[:, fixed].ravel()
    Kc, fc, x, I = skfem.condense(K, f, D=D)
    uI = sla.spsolve(Kc.tocsc(), fc)
    x = x.copy(); x[I] = uI
    res = np.linalg.norm(Kc @ uI - fc) / np.linalg.norm(fc)
    u = x[basis.nodal_dofs].T  # nodal_dofs is 3 x N: row = component
    return u, K, f, x, fixed, res


def main(msh, out):
    p_cm, t = read_gmsh_v1(msh)
    p = p_cm * CM_TO_MM
    vol = signed_volumes(p, t)
    n_inverted = int((vol < 0).sum())
    u, K, f, x, fixed, res = solve(p, t)
    assert res < 1e-10, res
    mag = np.linalg.norm(u, axis=1)
    energy = 0.5 * float(x @ (K @ x))
    result = {
        "description": "scikit-fem reference for `fem sag`: P1 tets, linear elasticity, lengths mm, E kPa, "
                       "body force mN/mm^3, displacements mm, strain_energy = 0.5 u^T K u in mN*mm (uJ); "
                       "coordinates read in cm and scaled x10 to mm; tests/reference/skfem_sag.py",
        "mesh": os.path.basename(msh),
        "unit": "cm",
        "E_kPa": E_KPA,
        "nu": NU,
        "body_force_mN_per_mm3": list(BODY_FORCE),
        "fixed_rule": "y > y_min + 0.8*(y_max-y_min)",
        "nodes": int(len(p)),
        "tets": int(len(t)),
        "inverted_tets": n_inverted,
        "fixed_nodes": int(len(fixed)),
        "displacement_mm": [[float(c) for c in row] for row in u],
        "max_disp_mm": float(mag.max()),
        "mean_disp_mm": float(mag.mean()),
        "strain_energy": energy,
        "relative_residual": float(res),
        "skfem_version": skfem.__version__,
    }
    # json writes floats as repr (shortest round-trip, full precision); one displacement triple per line
    disp = result.pop("displacement_mm")
    text = json.dumps(result, indent=1)[:-2]
    text += ',\n "displacement_mm": [\n' + ',\n'.join('  ' + json.dumps(r) for r in disp) + '\n ]\n}\n'
    assert json.loads(text)["displacement_mm"] == disp
    with open(out, 'w') as fh:
        fh.write(text)
    print(f"{msh}: {len(p)} nodes, {len(t)} tets ({n_inverted} inverted, volume {vol.sum():.6g} mm^3), "
          f"{len(fixed)} fixed nodes")
    print(f"max |u| = {mag.max():.10g} mm, mean |u| = {mag.mean():.10g} mm, "
          f"strain energy = {energy:.10g} mN*mm, residual = {res:.2e}")
    print(f"wrote {out}")


if __name__ == '__main__':
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    main(sys.argv[1], sys.argv[2])
