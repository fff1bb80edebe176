//! The losses and error measures of training on tensors.

use super::*;
use crate::gcn::GcnError;
use crate::gcn::model::{Loss, MeshGraphs, SrGcn, SrGcnConfig};
use crate::gcn::sample::SampleData;
use burn::tensor::{Device, Tensor, TensorData};

pub(super) fn tensor2(v: &[f32], rows: usize, device: &Device) -> Tensor<2> {
    Tensor::<2>::from_data(TensorData::new(v.to_vec(), [rows, 3]), device)
}

/// Mean penalty of per-row error vectors `e` `[n, 3]`.
pub(super) fn penalty(kind: Loss, e: Tensor<2>) -> Tensor<1> {
    match kind {
        Loss::Squared => e.powi_scalar(2).mean(),
        Loss::Distance => {
            let eps = 0.01f32;
            let d = (e.powi_scalar(2).sum_dim(1) + eps * eps).sqrt() - eps;
            d.mean()
        }
    }
}

/// Stage-2 loss of one sample: the mean penalty ([`Loss`]) of the correction error over nodes, plus
/// λ times the same at the matched measured points. Also returns the answer: the prediction, or
/// with `refit` (the sample's linearised refit and its geometry's modes) what the pipeline's
/// refit makes of it, to first order, which the node loss then scores.
///
/// Stage 2 keeps the bipartite branch fixed: it runs as `frozen` (a copy of the network without
/// autodiff, on `plain`) and its features are copied onto `device`. Running it on the autodiff
/// device and detaching its output would leave its recorded graph, unreachable from the loss,
/// behind at every step (memory grew to 24 GB in one epoch).
#[allow(clippy::too_many_arguments)]
pub(super) fn mesh_loss(
    net: &SrGcn,
    frozen: &SrGcn,
    cfg: &SrGcnConfig,
    s: &SampleData,
    graph: &MeshGraphs,
    refit: Option<(&RefitLoss, &Tensor<2>)>,
    plain: &Device,
    device: &Device,
) -> Result<(Tensor<1>, Tensor<2>), GcnError> {
    let x = s.tensors_mesh(device);
    let (bip, out) = match s.tensors(cfg, plain)?.1 {
        Some(b) => {
            let o = frozen.forward_bipartite(&b)?;
            let to = |t: Tensor<2>| Tensor::<2>::from_data(t.into_data(), device);
            let o = o.map(|o| crate::gcn::model::BipartiteOutput {
                features: o.features.into_iter().map(to).collect(),
                reconstruction: to(o.reconstruction),
            });
            let b = crate::gcn::model::BipartiteInput {
                mask: to(b.mask),
                features: to(b.features),
                ..b
            };
            (Some(b), o)
        }
        None => (None, None),
    };
    let y = net.forward_mesh(x, graph, bip.as_ref().zip(out.as_ref()))?;
    let target = s
        .target
        .as_ref()
        .ok_or_else(|| GcnError::Invalid("sample has no target".into()))?;
    let t = tensor2(target, s.num_nodes, device);
    let answer = match refit {
        Some((r, g)) => through_refit(y.clone(), r, g, device)?,
        None => y.clone(),
    };
    let mut loss = penalty(cfg.loss, answer.clone() - t);
    if cfg.sparse_weight > 0.0 && s.sparse_rows.rows > 0 {
        let op = crate::gcn::sparse::SparseOp::new(s.sparse_rows.clone());
        let at = op.apply(y.clone())?;
        let ts = tensor2(&s.sparse_target, s.sparse_rows.rows, device);
        loss = loss + penalty(cfg.loss, at - ts) * cfg.sparse_weight;
    }
    Ok((loss, answer))
}

/// Mean node error (mm) of the corrected prediction against the target (both in output units).
pub(super) fn node_error_mm(y: &Tensor<2>, target: &[f32], unit: f64) -> f64 {
    scaled_errors_mm(y, target, unit, &[1.0])[0]
}

/// Mean node error (mm) of the correction `y` scaled by each factor of `grid`.
pub(super) fn scaled_errors_mm(y: &Tensor<2>, target: &[f32], unit: f64, grid: &[f64]) -> Vec<f64> {
    let p = y
        .clone()
        .into_data()
        .convert::<f32>()
        .try_to_vec::<f32>()
        .unwrap_or_default();
    let n = target.len() / 3;
    if n == 0 || p.len() != target.len() {
        return vec![f64::NAN; grid.len()];
    }
    let mut out = vec![0.0; grid.len()];
    for (yi, ti) in p.chunks_exact(3).zip(target.chunks_exact(3)) {
        for (o, a) in out.iter_mut().zip(grid) {
            *o += (0..3)
                .map(|c| (a * yi[c] as f64 - ti[c] as f64).powi(2))
                .sum::<f64>()
                .sqrt();
        }
    }
    out.iter().map(|e| e / n as f64 * unit).collect()
}
