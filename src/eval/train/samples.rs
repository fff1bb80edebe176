//! Training samples: SR-GCN inputs built from LIBR's solutions, targets from the ground truth,
//! and the linearised LIBR refit the refit-aware loss differentiates through.

use super::*;
use crate::dataset::read::ScenarioData;
use crate::eval::EvalError;
use crate::gcn::GcnError;
use crate::gcn::model::{SrGcnConfig, Target};
use crate::gcn::sample::{CaseFrame, Registered, SampleData};
use crate::mesh::rigid::Rigid;
use crate::pipeline::PipelineError;
use crate::pipeline::PipelineParams;
use crate::register::libr;
use burn::tensor::{Device, Tensor, TensorData};
use rayon::prelude::*;
use std::collections::BTreeMap;

/// A prepared sample: its geometry and host data.
pub struct TrainingSample {
    /// Geometry id.
    pub geometry: String,
    /// Inputs and targets.
    pub data: SampleData,
    /// The linearised refit at LIBR's solution, when training through it.
    pub refit: Option<RefitLoss>,
}

/// LIBR+'s refit linearised at a sample's LIBR solution ([`libr::linearised_refit`]), for
/// training through it ([`TrainOptions::refit_loss`]): what the pipeline answers for a correction
/// `y` (output units) is, to first order, `y + step0 − G·K·Gᵀ·Dᵀ·D·y`, with `G` the geometry's
/// [`libr::LinearRefit::modes`] about its frame's centre.
pub struct RefitLoss {
    /// `D` (rows × 3V).
    pub d: crate::gcn::sparse::Csr,
    /// `K` (p × p, row-major).
    pub gain: Vec<f32>,
    /// The refit's move of LIBR's own shape, `[V, 3]` in output units.
    pub step0: Vec<f32>,
}

/// The [`RefitLoss`] of one LIBR solution: the refit's first step from it, with the matches the
/// refit would make there.
pub fn refit_loss_data(
    gc: &GeometryCase,
    meas: &crate::register::Checked,
    sol: &LibrSolution,
    params: &PipelineParams,
) -> Result<RefitLoss, EvalError> {
    let basis = gc.case.basis.as_ref().ok_or(PipelineError::NoBasis)?;
    let inv = sol.transform.inverse();
    let pts: Vec<[f64; 3]> = meas.points.iter().map(|&p| inv.apply(p)).collect();
    let (matches, _) =
        gc.case
            .correspondence
            .match_points(&pts, meas, Some(&sol.u), &final_cparams(params))?;
    let mesh = &gc.geo.model.mesh;
    let lin = libr::linearised_refit(
        basis,
        mesh,
        &matches,
        &pts,
        &sol.u,
        gc.frame.center,
        &params.libr,
    )?;
    let trip: Vec<(usize, usize, f32)> = lin.d.iter().map(|&(r, c, v)| (r, c, v as f32)).collect();
    let unit = gc.frame.unit_mm();
    Ok(RefitLoss {
        d: crate::gcn::sparse::Csr::from_triplets(lin.rows, 3 * mesh.num_nodes(), &trip)?,
        gain: lin.gain.iter().map(|&x| x as f32).collect(),
        step0: lin.step0.iter().map(|&x| (x / unit) as f32).collect(),
    })
}

/// The geometry's refit modes `G` (`[3V, p]`) on a device.
pub(super) fn refit_modes(gc: &GeometryCase, device: &Device) -> Result<Tensor<2>, EvalError> {
    let basis = gc.case.basis.as_ref().ok_or(PipelineError::NoBasis)?;
    let g = libr::LinearRefit::modes(basis, &gc.geo.model.mesh, gc.frame.center);
    let p = basis.columns() + 6;
    let rows = g.len() / p;
    Ok(Tensor::<2>::from_data(
        TensorData::new(
            g.into_iter().map(|x| x as f32).collect::<Vec<_>>(),
            [rows, p],
        ),
        device,
    ))
}

/// What the pipeline answers, to first order, for the correction `y` (`[V, 3]` row-major,
/// output units) of a sample of geometry `gc` with linearised refit `r`: the displacement from
/// LIBR's shape, in LIBR's image frame and output units.
pub fn answer_through_refit(
    gc: &GeometryCase,
    r: &RefitLoss,
    y: &[f32],
) -> Result<Vec<f32>, EvalError> {
    let device = crate::gcn::device::compute();
    let g = refit_modes(gc, &device)?;
    let v = y.len() / 3;
    through_refit(tensor2(y, v, &device), r, &g, &device)?
        .into_data()
        .convert::<f32>()
        .try_to_vec::<f32>()
        .map_err(|e| EvalError::Internal(format!("{e:?}")))
}

/// What the pipeline answers for the correction `y` (`[V, 3]`, output units) through the
/// linearised refit `r` with the geometry's modes `g`.
pub(super) fn through_refit(
    y: Tensor<2>,
    r: &RefitLoss,
    g: &Tensor<2>,
    device: &Device,
) -> Result<Tensor<2>, GcnError> {
    let [v, _] = y.dims();
    let p = g.dims()[1];
    if r.d.cols != 3 * v || g.dims()[0] != 3 * v || r.gain.len() != p * p || r.step0.len() != 3 * v
    {
        return Err(GcnError::Invalid(format!(
            "the linearised refit does not fit a {v}-node prediction"
        )));
    }
    let z = crate::gcn::sparse::SparseOp::new(r.d.clone()).apply(y.clone().reshape([3 * v, 1]))?;
    let w = crate::gcn::sparse::SparseOp::new(r.d.transpose()).apply(z)?;
    let gw = g.clone().transpose().matmul(w);
    let k = Tensor::<2>::from_data(TensorData::new(r.gain.clone(), [p, p]), device);
    let change = g.clone().matmul(k.matmul(gw)).reshape([v, 3]);
    Ok(y - change + tensor2(&r.step0, v, device))
}

/// Builds the SR-GCN samples of scenarios whose LIBR succeeded (with targets from the truth).
pub fn build_samples(
    cfg: &SrGcnConfig,
    cases: &BTreeMap<String, GeometryCase>,
    items: &[(&ScenarioData, &str, &Option<LibrSolution>)],
    params: &PipelineParams,
    with_truth: bool,
    refit_loss: bool,
) -> Result<Vec<Option<TrainingSample>>, EvalError> {
    let cparams = final_cparams(params);
    items
        .par_iter()
        .map(|(sc, g, sol)| {
            let Some(sol) = sol else { return Ok(None) };
            let gc = &cases[*g];
            let truth = with_truth.then(|| truth_positions(&gc.geo, sc));
            let libr = Registered {
                mesh: &gc.geo.model.mesh,
                correspondence: &gc.case.correspondence,
                cparams: &cparams,
                meas: &sc.measurements,
                u: &sol.u,
                transform: &sol.transform,
            };
            let mut data = SampleData::build_linking(cfg, &gc.frame, &libr, truth.as_deref())
                .map_err(|e| EvalError::within(sc.id.clone(), e))?;
            if let Some(t) = &truth {
                data.target = Some(training_target(
                    cfg,
                    &gc.frame,
                    &gc.geo.model.mesh,
                    &sol.u,
                    &sol.transform,
                    t,
                ));
            }
            let refit = if refit_loss {
                Some(
                    refit_loss_data(gc, &sc.measurements, sol, params).map_err(|e| {
                        EvalError::within(format!("{}: linearised refit", sc.id), e)
                    })?,
                )
            } else {
                None
            };
            Ok(Some(TrainingSample {
                geometry: g.to_string(),
                data,
                refit,
            }))
        })
        .collect()
}

/// The training target of a sample (`[n, 3]` row-major, in the frame's output units): the true
/// node positions `truth_physical` (physical frame) brought into the image frame by the inverse
/// of LIBR's `transform`, less LIBR's deformed node (residual target) or the preoperative node
/// (displacement target).
pub fn training_target(
    cfg: &SrGcnConfig,
    frame: &CaseFrame,
    mesh: &crate::mesh::TetMesh,
    u: &[f64],
    transform: &Rigid,
    truth_physical: &[[f64; 3]],
) -> Vec<f32> {
    let nodes = mesh.nodes();
    let unit = frame.unit_mm();
    let inv = transform.inverse();
    let mut out = Vec::with_capacity(3 * nodes.len());
    for (i, x) in nodes.iter().enumerate() {
        let q = inv.apply(truth_physical[i]);
        let base = match cfg.target {
            Target::Residual => [0, 1, 2].map(|a| x[a] + u[3 * i + a]),
            Target::Gt => *x,
        };
        out.extend((0..3).map(|a| ((q[a] - base[a]) / unit) as f32));
    }
    out
}
