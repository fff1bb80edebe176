//! Post-processing: per-tet strain, stress and strain energy of a displacement field.

use super::assembly::LameField;
use super::element::{p1_gradients, strain, stress};
use crate::mesh::TetMesh;
use rayon::prelude::*;

/// Constant fields of one tet: symmetric tensors stored as `[xx, yy, zz, xy, yz, xz]`.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct TetField {
    /// Small strain ε (dimensionless).
    pub strain: [f64; 6],
    /// Cauchy stress σ (kPa).
    pub stress: [f64; 6],
    /// Strain energy `|V| σ:ε / 2` (mN·mm = µJ).
    pub energy: f64,
    /// Von Mises equivalent stress (kPa).
    pub von_mises_kpa: f64,
}

fn voigt(m: &[[f64; 3]; 3]) -> [f64; 6] {
    [m[0][0], m[1][1], m[2][2], m[0][1], m[1][2], m[0][2]]
}

/// Strain, stress and energy per tet for a node-major displacement `u` (mm).
pub fn tet_fields(mesh: &TetMesh, lame: &LameField, u: &[f64]) -> Vec<TetField> {
    (0..mesh.num_tets())
        .into_par_iter()
        .map(|t| {
            let p = mesh.tet_points(t);
            let Some((g, v)) = p1_gradients(&p) else {
                return TetField {
                    strain: [0.0; 6],
                    stress: [0.0; 6],
                    energy: 0.0,
                    von_mises_kpa: 0.0,
                };
            };
            let tet = mesh.tets()[t];
            let ue = tet.map(|n| {
                let n = n as usize;
                [u[3 * n], u[3 * n + 1], u[3 * n + 2]]
            });
            let (lambda, mu) = match lame {
                LameField::Uniform(l, m) => (*l, *m),
                LameField::PerTet(v) => v[t],
            };
            let eps = strain(&g, &ue);
            let sig = stress(&eps, lambda, mu);
            let mut se = 0.0;
            for a in 0..3 {
                for b in 0..3 {
                    se += sig[a][b] * eps[a][b];
                }
            }
            let s = voigt(&sig);
            let vm = (0.5
                * ((s[0] - s[1]).powi(2) + (s[1] - s[2]).powi(2) + (s[2] - s[0]).powi(2))
                + 3.0 * (s[3] * s[3] + s[4] * s[4] + s[5] * s[5]))
                .sqrt();
            TetField {
                strain: voigt(&eps),
                stress: s,
                energy: 0.5 * v.abs() * se,
                von_mises_kpa: vm,
            }
        })
        .collect()
}

/// Total strain energy over all tets (mN·mm).
pub fn strain_energy(mesh: &TetMesh, lame: &LameField, u: &[f64]) -> f64 {
    tet_fields(mesh, lame, u).iter().map(|f| f.energy).sum()
}
