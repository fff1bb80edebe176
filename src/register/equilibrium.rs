//! Equilibrium of a free-floating organ model: lumped nodal volumes, the six rigid modes of a
//! node set (for inertia relief: projecting loads and responses onto what deforms), and a
//! statically determinate 3-2-1 support. Shared by LIBR's basis and the augmented models.

use crate::fem::Dirichlet;
use crate::mesh::TetMesh;
use crate::mesh::vec3::{cross, dist2, dot, sub, unit};
use crate::register::RegisterError;
use nalgebra::{Matrix6, Vector6};

/// Lumped nodal volumes (mm³): each node gets a quarter of each of its tets' volume.
pub fn lumped_volumes(mesh: &TetMesh) -> Vec<f64> {
    let mut m = vec![0.0; mesh.num_nodes()];
    for (t, tet) in mesh.tets().iter().enumerate() {
        let v = mesh.tet_volume(t).abs() / 4.0;
        for &i in tet {
            m[i as usize] += v;
        }
    }
    m
}

/// The six rigid modes of a node set (3 translations, 3 rotations about `center`) and their
/// mass matrix `RᵀMR`, for projections.
pub(crate) struct RigidModes {
    center: [f64; 3],
    mass: Vec<f64>,
    ginv: Matrix6<f64>,
}

impl RigidModes {
    pub(crate) fn new(nodes: &[[f64; 3]], mass: &[f64]) -> Result<Self, RegisterError> {
        let total: f64 = mass.iter().sum();
        let mut center = [0.0; 3];
        for (p, &w) in nodes.iter().zip(mass) {
            for a in 0..3 {
                center[a] += w * p[a] / total;
            }
        }
        let mut g = Matrix6::<f64>::zeros();
        for (i, p) in nodes.iter().enumerate() {
            let r = mode_rows(*p, center);
            for a in 0..3 {
                for k in 0..6 {
                    for l in 0..6 {
                        g[(k, l)] += mass[i] * r[a][k] * r[a][l];
                    }
                }
            }
        }
        let ginv = g.try_inverse().ok_or_else(|| {
            RegisterError::Model(
                "the mesh's rigid-mode mass matrix is singular (zero volume?)".into(),
            )
        })?;
        Ok(Self {
            center,
            mass: mass.to_vec(),
            ginv,
        })
    }

    /// The centre of mass the rotations are about.
    pub(crate) fn center(&self) -> [f64; 3] {
        self.center
    }

    /// `Rᵀ v` (6) for a node-major vector, optionally weighted by the lumped mass.
    fn project(&self, nodes: &[[f64; 3]], v: &[f64], weighted: bool) -> Vector6<f64> {
        let mut s = Vector6::zeros();
        for (i, p) in nodes.iter().enumerate() {
            let r = mode_rows(*p, self.center);
            let w = if weighted { self.mass[i] } else { 1.0 };
            for a in 0..3 {
                for k in 0..6 {
                    s[k] += w * r[a][k] * v[3 * i + a];
                }
            }
        }
        s
    }

    /// `f − M R G⁻¹ Rᵀ f`: the self-equilibrated part of a load (inertia relief).
    pub(crate) fn equilibrate(&self, nodes: &[[f64; 3]], f: &mut [f64]) {
        let c = self.ginv * self.project(nodes, f, false);
        for (i, p) in nodes.iter().enumerate() {
            let r = mode_rows(*p, self.center);
            for a in 0..3 {
                let acc: f64 = (0..6).map(|k| r[a][k] * c[k]).sum();
                f[3 * i + a] -= self.mass[i] * acc;
            }
        }
    }

    /// `u − R G⁻¹ RᵀM u`: removes the (mass-weighted) rigid part of a displacement.
    pub(crate) fn remove_rigid(&self, nodes: &[[f64; 3]], u: &mut [f64]) {
        let c = self.ginv * self.project(nodes, u, true);
        for (i, p) in nodes.iter().enumerate() {
            let r = mode_rows(*p, self.center);
            for a in 0..3 {
                let acc: f64 = (0..6).map(|k| r[a][k] * c[k]).sum();
                u[3 * i + a] -= acc;
            }
        }
    }
}

/// Rows (per axis) of the rigid modes at point p: translations e_a, rotations e_k × (p − c).
pub(crate) fn mode_rows(p: [f64; 3], c: [f64; 3]) -> [[f64; 6]; 3] {
    let d = sub(p, c);
    // e_k × d: k=0 → (0, −d_z, d_y); k=1 → (d_z, 0, −d_x); k=2 → (−d_y, d_x, 0)
    [
        [1.0, 0.0, 0.0, 0.0, d[2], -d[1]],
        [0.0, 1.0, 0.0, -d[2], 0.0, d[0]],
        [0.0, 0.0, 1.0, d[1], -d[0], 0.0],
    ]
}

/// A statically determinate 3-2-1 support on boundary nodes: node a fixed, node b fixed across
/// the a→b direction's dominant axis, node c fixed along the axis that best stops rotation
/// about a–b.
pub(crate) fn support_321(
    nodes: &[[f64; 3]],
    boundary: &[u32],
    center: [f64; 3],
) -> Result<Dirichlet, RegisterError> {
    let far = |from: [f64; 3]| -> u32 {
        let mut best = boundary[0];
        for &v in boundary {
            if dist2(nodes[v as usize], from) > dist2(nodes[best as usize], from) {
                best = v;
            }
        }
        best
    };
    let a = far(center);
    let pa = nodes[a as usize];
    let b = far(pa);
    let d = sub(nodes[b as usize], pa);
    let dn = unit(d);
    let mut c = boundary[0];
    let mut best = -1.0;
    for &v in boundary {
        let e = sub(nodes[v as usize], pa);
        let off = cross(dn, e);
        let l = dot(off, off);
        if l > best {
            best = l;
            c = v;
        }
    }
    let moment = cross(dn, sub(nodes[c as usize], pa));
    if dot(d, d) <= 0.0 || best <= 1e-12 * dot(d, d) {
        return Err(RegisterError::Model(
            "the boundary is degenerate (all nodes on a line): cannot support it".into(),
        ));
    }
    let free_b = argmax_abs(d);
    let fix_c = argmax_abs(moment);
    let mut bc = Dirichlet::new(nodes.len());
    bc.prescribe_node(a, [0.0; 3]);
    for axis in 0..3 {
        if axis != free_b {
            bc.prescribe_dof(b, axis, 0.0);
        }
    }
    bc.prescribe_dof(c, fix_c, 0.0);
    Ok(bc)
}

pub(super) fn argmax_abs(v: [f64; 3]) -> usize {
    let mut k = 0;
    for a in 1..3 {
        if v[a].abs() > v[k].abs() {
            k = a;
        }
    }
    k
}
