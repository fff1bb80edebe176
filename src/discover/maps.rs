//! Maps of a discovery on the preoperative mesh, for ParaView and 3D Slicer: where the held-out
//! misfit lies before and after, and what the named effects add (loads, supports, stiffer
//! tissue). Data only; the command line writes them as `.vtu`.
//!
//! Point data (one tuple per node):
//! - `heldout_before_mm`, `heldout_after_mm`: held-out RMS misfit of the spatial block whose
//!   centre is nearest the node (the blocks cross-validation holds out; NaN where a block was
//!   not scored);
//! - `mean_signed_mm`: that block's mean signed held-out residual before (outward, mm), and
//!   `t_across_sweeps`, how systematic it is across the sweeps;
//! - `block`: the block's index;
//! - per named effect `k` (in naming order) of a load kind: `effect<k>_<kind>_load_mn`, its
//!   nodal load (mN) at the fitted amplitude; of a support kind: `effect<k>_<kind>_stiffness`,
//!   the spring stiffness per area (kPa/mm) on the nodes it holds, 0 elsewhere.
//!
//! Cell data (one per tet), per named material kind (an inclusion): `effect<k>_<kind>_ratio`,
//! Young's modulus multiple (1 outside).
//!
//! Which map an effect gets is its kind's role in the table of kinds
//! ([`crate::register::physics::kinds::Role`]).

use super::CohortDiscovery;
use crate::mesh::TetMesh;
use crate::mesh::io::{DataArray, MeshFile};
use crate::mesh::vec3::dist2;
use crate::register::PreopModel;
use crate::register::RegisterError;
use crate::register::physics::Physics;
use crate::register::physics::kinds::Role;
use crate::register::physics::model::{BoundaryGeometry, Sites, effect_load};

/// The maps of one cohort's discovery on its preoperative mesh.
pub fn discovery_maps(
    model: &PreopModel,
    found: &CohortDiscovery,
) -> Result<MeshFile, RegisterError> {
    let mesh: &TetMesh = &model.mesh;
    let n = mesh.num_nodes();
    let mut file = mesh.to_file();
    let centers: Vec<[f64; 3]> = found.regions.iter().map(|r| r.center).collect();
    let block: Vec<usize> = mesh
        .nodes()
        .iter()
        .map(|&p| {
            (0..centers.len())
                .min_by(|&a, &b| dist2(centers[a], p).total_cmp(&dist2(centers[b], p)))
                .unwrap_or(0)
        })
        .collect();
    let per_block = |f: &dyn Fn(usize) -> f64| -> Vec<f64> {
        block
            .iter()
            .map(|&b| if centers.is_empty() { f64::NAN } else { f(b) })
            .collect()
    };
    let r = &found.regions;
    file.point_data.push(DataArray::new(
        "heldout_before_mm",
        1,
        per_block(&|b| r[b].before_mm),
    ));
    file.point_data.push(DataArray::new(
        "heldout_after_mm",
        1,
        per_block(&|b| r[b].after_mm),
    ));
    file.point_data.push(DataArray::new(
        "mean_signed_mm",
        1,
        per_block(&|b| r[b].mean_signed_mm),
    ));
    file.point_data.push(DataArray::new(
        "t_across_sweeps",
        1,
        per_block(&|b| r[b].t_across_sweeps),
    ));
    file.point_data.push(DataArray::new(
        "block",
        1,
        block.iter().map(|&b| b as f64).collect(),
    ));
    let geom = BoundaryGeometry::new(mesh)?;
    let sites = Sites {
        posterior: &model.posterior,
        falciform: &model.falciform,
    };
    for (k, named) in found.effects.iter().enumerate() {
        let e = &named.effect;
        let tag = format!("effect{k}_{}", e.kind.name());
        match e.kind.role() {
            Role::Load(_) => {
                let f = effect_load(
                    mesh,
                    &geom,
                    &Physics {
                        effects: vec![e.clone()],
                    },
                )?;
                file.point_data
                    .push(DataArray::new(format!("{tag}_load_mn"), 3, f));
            }
            Role::Support(s) => {
                let k = e.scalar(s.stiffness);
                let mut v = vec![0.0; n];
                for b in (s.held)(mesh, &geom, sites, e) {
                    v[b as usize] = k;
                }
                file.point_data
                    .push(DataArray::new(format!("{tag}_stiffness"), 1, v));
            }
            Role::Material(m) => {
                let p = mesh.nodes();
                let v: Vec<f64> = mesh
                    .tets()
                    .iter()
                    .map(|t| {
                        let c = [0, 1, 2]
                            .map(|a| t.iter().map(|&i| p[i as usize][a]).sum::<f64>() / 4.0);
                        (m.factor)(e, c)
                    })
                    .collect();
                file.cell_data
                    .push(DataArray::new(format!("{tag}_ratio"), 1, v));
            }
            Role::Uncarried => {}
        }
    }
    Ok(file)
}
