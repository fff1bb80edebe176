//! `librplus fem sag`: the gravity-sag reference problem.

use crate::args::{Common, ModelArg};
use crate::mesh::{Volume, load_volume};
use crate::util::emit;
use anyhow::{Result, bail};
use librplus::fem::{self, LameField, sag};
use librplus::mesh::io::{self, DataArray, WriteOptions};
use serde_json::json;
use std::path::Path;
use std::time::Instant;

pub(crate) fn fem_sag(
    path: &Path,
    c: &Common,
    out: Option<&Path>,
    model: ModelArg,
    load_scale: f64,
) -> Result<()> {
    if !load_scale.is_finite() {
        bail!("--load-scale must be finite, got {load_scale}");
    }
    if let Some(out) = out
        && matches!(
            io::Format::from_path(out)?,
            io::Format::Obj | io::Format::Stl | io::Format::Vtp
        )
    {
        bail!(
            "{}: a surface format cannot hold the volume result; use .vtu, .vtk or .msh",
            out.display()
        );
    }
    let t0 = Instant::now();
    let Volume {
        mesh,
        flipped,
        removed_unused,
    } = load_volume(path, c.unit)?;
    let read_s = t0.elapsed().as_secs_f64();
    let mut params = sag::SagParams::default();
    params.body_force = params.body_force.map(|b| b * load_scale);
    let bar = indicatif::ProgressBar::new_spinner().with_message(match model {
        ModelArg::Linear => "solving linear sag",
        ModelArg::NeoHookean => "solving Neo-Hookean sag (Newton, load steps)",
    });
    bar.enable_steady_tick(std::time::Duration::from_millis(200));
    let r = match model {
        ModelArg::Linear => sag::solve(&mesh, &params)?,
        ModelArg::NeoHookean => {
            sag::solve_neo_hookean(&mesh, &params, &fem::hyperelastic::NewtonParams::default())?
        }
    };
    // The nonlinear result is reported together with its difference from the linear one.
    let vs_linear = if model == ModelArg::NeoHookean {
        let lin = sag::solve(&mesh, &params)?;
        let d: Vec<f64> = r
            .displacement
            .chunks_exact(3)
            .zip(lin.displacement.chunks_exact(3))
            .map(|(a, b)| {
                ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
            })
            .collect();
        Some(json!({
            "linear_max_disp_mm": lin.max_disp_mm,
            "linear_mean_disp_mm": lin.mean_disp_mm,
            "mean_node_difference_mm": d.iter().sum::<f64>() / d.len().max(1) as f64,
            "max_node_difference_mm": d.iter().copied().fold(0.0, f64::max),
        }))
    } else {
        None
    };
    bar.finish_and_clear();
    if let Some(out) = out {
        let fixed = sag::fixed_nodes(&mesh, params.fixed_fraction);
        let mut mask = vec![0.0; mesh.num_nodes()];
        for &n in &fixed {
            mask[n as usize] = 1.0;
        }
        let (l, m) = params.material.lame();
        // Small-strain fields (for Neo-Hookean results these are the linearized measures).
        let fields = fem::post::tet_fields(&mesh, &LameField::Uniform(l, m), &r.displacement);
        let mut file = mesh.to_file();
        file.point_data = vec![
            DataArray::new("displacement", 3, r.displacement.clone()),
            DataArray::new("fixed", 1, mask),
        ];
        if !file.tets.is_empty() {
            file.cell_data = vec![
                DataArray::new(
                    "von_mises_kpa",
                    1,
                    fields.iter().map(|f| f.von_mises_kpa).collect(),
                ),
                DataArray::new(
                    "strain_energy",
                    1,
                    fields.iter().map(|f| f.energy).collect(),
                ),
            ];
        }
        io::write(out, &file, WriteOptions::default())?;
    }
    let out_json = json!({
        "mesh": path.display().to_string(),
        "nodes": mesh.num_nodes(),
        "tets": mesh.num_tets(),
        "flipped_tets": flipped,
        "removed_unused_nodes": removed_unused,
        "fixed_nodes": r.fixed_nodes,
        "model": match model {
            ModelArg::Linear => "linear",
            ModelArg::NeoHookean => "neo-hookean",
        },
        "free_dofs": r.free_dofs,
        "E_kPa": params.material.youngs_modulus_kpa,
        "nu": params.material.poisson_ratio,
        "body_force_mN_per_mm3": params.body_force,
        "newton": r.newton,
        "vs_linear": vs_linear,
        "max_disp_mm": r.max_disp_mm,
        "mean_disp_mm": r.mean_disp_mm,
        "strain_energy": r.strain_energy,
        "applied_load_mN": r.applied_load_mn,
        "reaction_mN": r.reaction_mn,
        "strain_energy_unit": "mN·mm",
        "timings_s": {
            "read": read_s,
            "assemble": r.timings.assemble_s,
            "factor": r.timings.factor_s,
            "solve": r.timings.solve_s,
            "total": t0.elapsed().as_secs_f64(),
        },
        "out": out.map(|p| p.display().to_string()),
    });
    emit(c.json, &out_json);
    Ok(())
}
