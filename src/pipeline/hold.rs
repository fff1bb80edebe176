//! A held organ: the navigation system says the organ is held in place (by the surgeon's
//! instruments, a retractor, its own attachments) and its start trusted.
//!
//! What changes ([`PipelineParams::held`](super::PipelineParams::held)):
//! - the rigid stage trusts the start to [`HELD_SIGMA_MM`](crate::register::prior::HELD_SIGMA_MM)
//!   unless the request gives its own uncertainty, so the pose search does not run;
//! - the deformable fit holds, softly, the surface the data do not see: every boundary node
//!   farther than [`HoldParams::clearance_mm`] from every measured point stays near where the
//!   trusted pose puts it ([`Hold`]). A tool pushing one spot of a held organ dents it there and
//!   leaves the far side in place; a free-floating basis would instead spread the dent into a
//!   rigid-like drift of the whole organ, which the data (all on the near side) cannot tell apart.
//! - LIBR's correspondences are weighted by a robust kernel instead of trimmed by the median:
//!   the dent's own points, far from the undeformed surface, are what trimming would cut;
//! - the deformable fit's rigid correction is not pulled towards the start: the hold anchors the
//!   organ, and the correction must stay free to carry the rigid part that the free-floating basis
//!   projects out of a dent (held organ, local tool, pattern H seed 301, adaptive LIBR: with the
//!   pose prior as well 6.4 mm mean TRE, worse than doing nothing at 5.9; without it 4.1).
//!
//! The held region is not declared: it is what the data leave unseen. A case whose physics
//! declares where the organ is held (`fixation`) says more and is used as it is.

use crate::mesh::rigid::Rigid;
use crate::mesh::vec3::dist2;
use crate::register::libr::Hold;
use crate::register::{Checked, PreopModel, RegisterError};

/// How a held organ's unseen surface is held.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct HoldParams {
    /// A boundary node is held when no measured point lies within this distance of it (mm).
    /// Default 45 (held organ, local tool, pattern H seed 301, adaptive LIBR with levels
    /// 25,100,300: 30 mm → 3.81 mm mean TRE, 45 → 3.56, 60 → 3.62).
    pub clearance_mm: f64,
    /// Total weight of the held nodes relative to the data's ([`Hold::weight`]). Default 1.
    pub weight: f64,
    /// LIBR's correspondences trimmed by the median as usual, instead of weighted by the robust
    /// kernel. Default false: the kernel (held organ, pattern H seeds 301 / 302: LIBR 5.10 / 5.26
    /// → 4.33 / 4.56 mm, adaptive 3.95 / 4.18 → 3.88 / 4.02).
    pub trimmed: bool,
    /// At most this many held nodes, spread evenly over the held surface (farthest-point
    /// sampling; their total weight stays [`Self::weight`]); 0: every node the clearance leaves.
    /// Each held node is three rows of every fit's least squares, and a paper-preset liver
    /// leaves 400–900 of them, as many rows as the data's: held adaptive LIBR then took twice
    /// adaptive LIBR's time. Default 128.
    #[serde(default = "default_max_nodes")]
    pub max_nodes: usize,
}

fn default_max_nodes() -> usize {
    128
}

impl Default for HoldParams {
    fn default() -> Self {
        Self {
            clearance_mm: 45.0,
            weight: 1.0,
            trimmed: false,
            max_nodes: default_max_nodes(),
        }
    }
}

impl HoldParams {
    /// Checks the parameters; the message names the bad field.
    pub fn validate(&self) -> Result<(), RegisterError> {
        if !(self.clearance_mm.is_finite() && self.clearance_mm > 0.0) {
            return Err(RegisterError::Parameter(format!(
                "hold clearance_mm must be finite and > 0, got {}",
                self.clearance_mm
            )));
        }
        if !(self.weight.is_finite() && self.weight > 0.0) {
            return Err(RegisterError::Parameter(format!(
                "hold weight must be finite and > 0, got {}",
                self.weight
            )));
        }
        Ok(())
    }
}

/// The hold of a held organ at `pose` (image → physical): the boundary nodes of `model` with no
/// measured point within `params.clearance_mm` (at most `params.max_nodes` of them, spread
/// evenly: [`spread_evenly`]), held where `pose` puts it.
pub fn hold(
    model: &PreopModel,
    meas: &Checked,
    pose: &Rigid,
    params: &HoldParams,
) -> Result<Hold, RegisterError> {
    params.validate()?;
    let inv = pose.inverse();
    let pts: Vec<[f64; 3]> = meas.points.iter().map(|&p| inv.apply(p)).collect();
    let c2 = params.clearance_mm * params.clearance_mm;
    let nodes: Vec<u32> = model
        .boundary_flags()
        .iter()
        .enumerate()
        .filter(|&(i, &b)| {
            let x = model.mesh.nodes()[i];
            b && pts.iter().all(|&p| dist2(p, x) > c2)
        })
        .map(|(i, _)| i as u32)
        .collect();
    let nodes = spread_evenly(model.mesh.nodes(), &nodes, &pts, params.max_nodes);
    let physical = nodes
        .iter()
        .map(|&v| pose.apply(model.mesh.nodes()[v as usize]))
        .collect();
    Ok(Hold {
        nodes,
        physical,
        weight: params.weight,
    })
}

/// At most `k` of `nodes` (all of them when `k` is 0 or not fewer), spread evenly: farthest-point
/// sampling from the node farthest from the measured points' centroid, each next node the one
/// farthest from those chosen (the lowest index on a tie). Returned in index order.
pub fn spread_evenly(
    positions: &[[f64; 3]],
    nodes: &[u32],
    measured: &[[f64; 3]],
    k: usize,
) -> Vec<u32> {
    if k == 0 || nodes.len() <= k {
        return nodes.to_vec();
    }
    let n = measured.len().max(1) as f64;
    let c = measured.iter().fold([0.0; 3], |a, p| {
        [a[0] + p[0] / n, a[1] + p[1] / n, a[2] + p[2] / n]
    });
    let at = |j: usize| positions[nodes[j] as usize];
    // The farthest by squared distance; the first on a tie.
    let farthest = |d: &[f64]| {
        d.iter()
            .enumerate()
            .fold(
                (0, f64::NEG_INFINITY),
                |b, (j, &v)| if v > b.1 { (j, v) } else { b },
            )
            .0
    };
    let to_centre: Vec<f64> = (0..nodes.len()).map(|j| dist2(at(j), c)).collect();
    let mut chosen = vec![farthest(&to_centre)];
    let mut near: Vec<f64> = (0..nodes.len())
        .map(|j| dist2(at(j), at(chosen[0])))
        .collect();
    while chosen.len() < k {
        let next = farthest(&near);
        chosen.push(next);
        for (j, d) in near.iter_mut().enumerate() {
            *d = d.min(dist2(at(j), at(next)));
        }
    }
    let mut out: Vec<u32> = chosen.into_iter().map(|j| nodes[j]).collect();
    out.sort_unstable();
    out
}
