"""Second, independent check of the `fem sag` reference: the same problem as skfem_sag.py, assembled by hand
with numpy (P1 tets, B-matrix / Voigt formulation, K_e = V B^T C B, consistent load f V / 4 per node), solved
by eliminating the fixed dofs, and compared with the scikit-fem JSON. No scikit-fem code is used here.

Usage (from the repository root):
    python tests/reference/check_sag.py ../shared/data/sofa_liver.msh tests/reference/sofa_liver_sag_skfem.json
Prints the relative differences; exits non-zero if any exceeds 1e-10."""
import json
import sys

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla


def read_gmsh_v1(path):
    """Nodes (cm, $NOD order) and type-4 tets (0-based) of a Gmsh v1 file."""
    tok = open(path).read().split('\n')
    tok = [l.strip() for l in tok]
    i = tok.index('$NOD'); n = int(tok[i + 1])
    rows = [l.split() for l in tok[i + 2:i + 2 + n]]
    index = {int(r[0]): k for k, r in enumerate(rows)}
    p = np.array([[float(v) for v in r[1:4]] for r in rows])
    j = tok.index('$ELM'); m = int(tok[j + 1])
    t = [[index[int(v)] for v in l.split()[5:9]] for l in tok[j + 2:j + 2 + m] if l.split()[1] == '4']
    return p, np.array(t)


def main(msh, ref_json):
    ref = json.load(open(ref_json))
    p_cm, t = read_gmsh_v1(msh)
    p = 10.0 * p_cm  # cm -> mm
    E, nu = ref["E_kPa"], ref["nu"]
    fb = np.array(ref["body_force_mN_per_mm3"], float)
    lam = E * nu / ((1 + nu) * (1 - 2 * nu)); mu = E / (2 * (1 + nu))
    C = np.zeros((6, 6)); C[:3, :3] = lam; C[np.arange(3), np.arange(3)] += 2 * mu
    C[np.arange(3, 6), np.arange(3, 6)] = mu  # engineering shear strains (gamma = 2 eps)

    N = len(p); ndof = 3 * N
    rows, cols, vals = [], [], []
    f = np.zeros(ndof)
    for tet in t:
        X = p[tet]
        J = (X[1:] - X[0]).T  # columns x1-x0, x2-x0, x3-x0
        V = abs(np.linalg.det(J)) / 6.0
        # gradients of barycentric shape functions: grad(N1..N3) = rows of inv(J), grad N0 = -sum
        Ginv = np.linalg.inv(J)
        G = np.vstack([-Ginv.sum(axis=0), Ginv])  # 4 x 3, row a = grad N_a
        B = np.zeros((6, 12))
        for a in range(4):
            gx, gy, gz = G[a]
            B[:, 3 * a:3 * a + 3] = [[gx, 0, 0], [0, gy, 0], [0, 0, gz],
                                     [gy, gx, 0], [0, gz, gy], [gz, 0, gx]]
        Ke = V * B.T @ C @ B
        dofs = (3 * tet[:, None] + np.arange(3)).ravel()  # interleaved: node a, component c -> 3a+c
        rows.append(np.repeat(dofs, 12)); cols.append(np.tile(dofs, 12)); vals.append(Ke.ravel())
        for a in tet:
            f[3 * a:3 * a + 3] += fb * V / 4.0
    K = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(ndof, ndof))

    y = p[:, 1]
    fixed = np.where(y > y.min() + 0.8 * (y.max() - y.min()))[0]
    D = (3 * fixed[:, None] + np.arange(3)).ravel()
    I = np.setdiff1d(np.arange(ndof), D)
    u = np.zeros(ndof)
    u[I] = sla.splu(K[I][:, I].tocsc()).solve(f[I])
    U = u.reshape(N, 3)

    Uref = np.array(ref["displacement_mm"])
    mag = np.linalg.norm(U, axis=1)
    energy = 0.5 * u @ (K @ u)
    d_u = np.linalg.norm(U - Uref) / np.linalg.norm(Uref)
    d_max = abs(mag.max() - ref["max_disp_mm"]) / ref["max_disp_mm"]
    d_mean = abs(mag.mean() - ref["mean_disp_mm"]) / ref["mean_disp_mm"]
    d_e = abs(energy - ref["strain_energy"]) / ref["strain_energy"]
    # at equilibrium, 0.5 u^T K u == 0.5 f^T u (fixed dofs have u = 0)
    d_work = abs(energy - 0.5 * f @ u) / energy
    print(f"numpy: {N} nodes, {len(t)} tets, {len(fixed)} fixed; max |u| = {mag.max():.15g} mm, "
          f"mean |u| = {mag.mean():.15g} mm, energy = {energy:.15g} mN*mm")
    print(f"relative difference vs {ref_json}: displacements {d_u:.2e}, max {d_max:.2e}, mean {d_mean:.2e}, "
          f"energy {d_e:.2e}; energy vs 0.5 f.u {d_work:.2e}")
    ok = len(fixed) == ref["fixed_nodes"] and max(d_u, d_max, d_mean, d_e, d_work) < 1e-10
    print("OK" if ok else "MISMATCH")
    return 0 if ok else 1


if __name__ == '__main__':
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    sys.exit(main(sys.argv[1], sys.argv[2]))
