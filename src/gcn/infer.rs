//! LIBR+ at registration time: a trained SR-GCN prepared for one preoperative mesh (its frame and
//! graphs, built once before surgery), and the correction of one LIBR result.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

use super::GcnError;
use super::io::TrainedModel;
use super::model::MeshGraphs;
use super::model::{SrGcnConfig, Target};
use super::sample::{CaseFrame, Registered, SampleData};
use crate::mesh::TetMesh;

/// What a correction is assumed to cost before one has been timed (s).
const FIRST_ESTIMATE_S: f64 = 0.15;

/// One network of a [`LibrPlusCase`], with its graphs of the case's mesh.
#[derive(Debug)]
pub struct Member {
    /// The network (shared between cases).
    pub model: Arc<TrainedModel>,
    /// The mesh graph and its coarse levels on the CPU device, as this network's configuration
    /// builds them.
    pub graphs: MeshGraphs,
}

/// A trained SR-GCN, or an ensemble of them, ready for one case. An ensemble's correction is the
/// mean of its members' (each scaled by its own `correction_scale`): networks trained apart
/// err apart on a liver none of them saw, and the mean errs less.
#[derive(Debug)]
pub struct LibrPlusCase {
    /// The networks (at least one).
    pub members: Vec<Member>,
    /// The case's normalisation.
    pub frame: CaseFrame,
    /// Running estimate of one correction's time (f64 bits, seconds): a decaying maximum.
    estimate: AtomicU64,
}

impl LibrPlusCase {
    /// Prepares `models` (one network, or the members of an ensemble) for the preoperative
    /// `mesh`.
    pub fn new(models: Vec<Arc<TrainedModel>>, mesh: &TetMesh) -> Result<Self, GcnError> {
        if models.is_empty() {
            return Err(GcnError::Unusable(
                "no SR-GCN model given (an ensemble needs at least one member)".into(),
            ));
        }
        if models.iter().any(|m| m.config.diagnostic_truth_neighbours) {
            return Err(GcnError::Unusable("the SR-GCN model was trained with --diagnostic-truth-neighbours (the LIBR+ paper's ground-truth leak, a diagnostic): it needs the ground truth and cannot register".into()));
        }
        let frame = CaseFrame::new(mesh)?;
        let members = models
            .into_iter()
            .map(|model| {
                let graphs = frame.mesh_graphs(&model.config, &crate::gcn::device::compute())?;
                Ok(Member { model, graphs })
            })
            .collect::<Result<Vec<_>, GcnError>>()?;
        Ok(Self {
            members,
            frame,
            estimate: AtomicU64::new(FIRST_ESTIMATE_S.to_bits()),
        })
    }

    /// The first (or only) network.
    pub fn model(&self) -> &Arc<TrainedModel> {
        &self.members[0].model
    }

    /// When LIBR+ abstains ([`crate::gcn::abstain`]): the networks' rule, when every member
    /// carries the same one; None (never) otherwise.
    pub fn abstain_rule(&self) -> Option<&crate::gcn::abstain::AbstainRule> {
        let first = self.members[0].model.abstain.as_deref()?;
        self.members
            .iter()
            .all(|m| m.model.abstain.as_deref() == Some(first))
            .then_some(first)
    }

    /// Expected time of one correction (s): a decaying maximum of the last ones (a slower
    /// correction raises it at once, faster ones lower it by a tenth of the gap each), so a
    /// deadline plan built on it errs towards answering with LIBR rather than late.
    pub fn expected_seconds(&self) -> f64 {
        f64::from_bits(self.estimate.load(Ordering::Relaxed))
    }

    /// Why the networks do not apply to a case whose LIBR carries `physics`, if they do not
    /// ([`physics_mismatch`]).
    pub fn mismatch(&self, physics: &crate::register::physics::Physics) -> Option<String> {
        let models: Vec<&TrainedModel> = self.members.iter().map(|m| &*m.model).collect();
        physics_mismatch(&models, physics)
    }

    /// Lowers [`LibrPlusCase::expected_seconds`] by 2 %: for a caller that skipped the
    /// correction because the estimate did not fit its time budget. Skipped corrections are not
    /// timed, so without this one slow correction (a busy machine) would keep the estimate
    /// above the budget, and the correction skipped, for good; with it the correction is tried
    /// again after a few dozen skipped updates and timed anew.
    pub fn relax_estimate(&self) {
        let old = self.expected_seconds();
        self.estimate
            .store((0.98 * old).to_bits(), Ordering::Relaxed);
    }

    /// Folds the time of one whole correction stage (s) into [`LibrPlusCase::expected_seconds`].
    pub fn record_seconds(&self, s: f64) {
        let old = self.expected_seconds();
        let new = if s > old { s } else { 0.9 * old + 0.1 * s };
        self.estimate.store(new.to_bits(), Ordering::Relaxed);
    }

    /// Corrects LIBR's answer `libr.u` (image frame, `libr.transform` image → physical) for the
    /// measurements it was fitted to; returns the LIBR+ displacement and the network's share of
    /// the time (s; the rest builds the sample: graphs, matches, features). `libr.cparams` are the
    /// correspondence settings of LIBR's last iteration. The caller records the stage's time
    /// ([`LibrPlusCase::record_seconds`]).
    ///
    /// The correction is damped where LIBR finds little deformation: it is scaled by
    /// `min(1, ū / DEFORMATION_GATE_MM)` with ū LIBR's mean node displacement. The network
    /// learned the residual of LIBR under surgical loads, which grows with the deformation; on an
    /// undeformed liver measured exactly LIBR is exact, and the ungated correction moved it by
    /// 0.7–1.8 mm (`tests/sanity.rs`). Registrations with ū ≥ 2 mm (every surgical pattern of the
    /// phantom) are unchanged.
    pub fn correct(&self, libr: &Registered<'_>) -> Result<Corrected, GcnError> {
        let (outs, network_seconds) = self.member_corrections(libr)?;
        Ok(ensemble_mean(outs, libr.u, network_seconds))
    }

    /// Each member's corrected displacement, in order, and the networks' time (s).
    fn member_corrections(&self, libr: &Registered<'_>) -> Result<(Vec<Vec<f64>>, f64), GcnError> {
        let u = libr.u;
        let mut network_s = 0.0;
        let mut outs: Vec<Vec<f64>> = Vec::new();
        // Members whose configurations build the same sample share it.
        let mut built: Option<(usize, SampleData)> = None;
        for (k, m) in self.members.iter().enumerate() {
            let reuse = built
                .as_ref()
                .is_some_and(|(j, _)| same_inputs(&self.members[*j].model, &m.model));
            if !reuse {
                let sample = SampleData::build(&m.model.config, &self.frame, libr)?;
                built = Some((k, sample));
            }
            let sample = &built.as_ref().expect("built above").1;
            let t1 = Instant::now();
            let out = correct(&m.model, &self.frame, &m.graphs, sample, u)?;
            network_s += t1.elapsed().as_secs_f64();
            if out.iter().any(|x| !x.is_finite()) {
                return Err(GcnError::NonFinite(if self.members.len() == 1 {
                    "the network's correction is not finite".into()
                } else {
                    format!("ensemble member {}: its correction is not finite", k + 1)
                }));
            }
            outs.push(out);
        }
        Ok((outs, network_s))
    }
}

/// The ensemble's answer from its members' corrected displacements `outs` of LIBR's `u`: their
/// mean, damped by [`deformation_gate`], with the members' disagreement (RMS over nodes of each
/// member's distance from the mean; None for one member) and the correction's RMS over nodes.
fn ensemble_mean(outs: Vec<Vec<f64>>, u: &[f64], network_seconds: f64) -> Corrected {
    let mut sum = vec![0.0; u.len()];
    for out in &outs {
        for (s, x) in sum.iter_mut().zip(out) {
            *s += x;
        }
    }
    let n = outs.len() as f64;
    let gate = deformation_gate(u);
    for s in sum.iter_mut() {
        *s /= n;
    }
    let nodes = (u.len() / 3).max(1) as f64;
    let spread_mm = (outs.len() > 1).then(|| {
        let ss: f64 = outs
            .iter()
            .flat_map(|o| o.iter().zip(&sum).map(|(a, b)| (a - b) * (a - b)))
            .sum();
        gate * (ss / (nodes * outs.len() as f64)).sqrt()
    });
    let correction_rms_mm = gate
        * (sum
            .iter()
            .zip(u)
            .map(|(a, b)| (a - b) * (a - b))
            .sum::<f64>()
            / nodes)
            .sqrt();
    if gate < 1.0 {
        for (s, &x) in sum.iter_mut().zip(u) {
            *s = x + gate * (*s - x);
        }
    }
    Corrected {
        u: sum,
        network_seconds,
        spread_mm,
        correction_rms_mm,
    }
}

/// What [`LibrPlusCase::correct`] returns.
#[derive(Debug, Clone, PartialEq)]
pub struct Corrected {
    /// The LIBR+ displacement (image frame, node-major).
    pub u: Vec<f64>,
    /// The networks' share of the time (s).
    pub network_seconds: f64,
    /// An ensemble's disagreement: the RMS over nodes and members of a member's correction's
    /// distance from the members' mean (mm, gated as the correction is); `None` for one network.
    pub spread_mm: Option<f64>,
    /// RMS over nodes of the applied correction (mm).
    pub correction_rms_mm: f64,
}

/// Why networks do not apply to a LIBR carrying `physics`, if they do not: a network learns the
/// residual of the LIBR it was trained on (its provenance's `physics_hash`; plain LIBR when
/// absent) and corrects nothing else.
pub fn physics_mismatch(
    models: &[&TrainedModel],
    physics: &crate::register::physics::Physics,
) -> Option<String> {
    let want = (!physics.is_empty()).then(|| physics.hash());
    let bad = models
        .iter()
        .position(|m| m.provenance["physics_hash"].as_str().map(str::to_string) != want)?;
    Some(if physics.is_empty() {
        format!(
            "SR-GCN member {} learned the residual of LIBR with physics, and this case's LIBR \
             is plain",
            bad + 1
        )
    } else {
        format!(
            "the SR-GCN learned the residual of another LIBR (member {}), and this case's carries \
             {}: train one with --physics",
            bad + 1,
            physics.kinds().join(", ")
        )
    })
}

/// LIBR's mean node displacement (mm) from which the SR-GCN's correction applies in full
/// ([`LibrPlusCase::correct`]).
pub const DEFORMATION_GATE_MM: f64 = 2.0;

/// `min(1, ū / DEFORMATION_GATE_MM)` for LIBR's displacement `u` (node-major).
pub fn deformation_gate(u: &[f64]) -> f64 {
    let n = (u.len() / 3).max(1) as f64;
    let mean = u
        .chunks_exact(3)
        .map(|c| (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt())
        .sum::<f64>()
        / n;
    (mean / DEFORMATION_GATE_MM).min(1.0)
}

/// Whether two networks read the same sample ([`SampleData::build`] depends on these switches).
fn same_inputs(a: &TrainedModel, b: &TrainedModel) -> bool {
    let (a, b) = (&a.config, &b.config);
    a.bipartite == b.bipartite
        && a.n_top == b.n_top
        && a.libr_input == b.libr_input
        && a.misfit_input == b.misfit_input
        && a.surface_input == b.surface_input
        && a.load_input == b.load_input
        && a.diagnostic_truth_neighbours == b.diagnostic_truth_neighbours
        && a.target == b.target
}

/// LIBR+ correction of one sample: node displacements (image frame, mm) to use instead of LIBR's.
/// `u` is LIBR's displacement the sample was built from.
pub fn correct(
    model: &TrainedModel,
    frame: &CaseFrame,
    graph: &MeshGraphs,
    s: &SampleData,
    u: &[f64],
) -> Result<Vec<f64>, GcnError> {
    let y = predict(model, graph, s)?;
    apply_prediction(&model.config, frame, u, &y)
}

/// The network's raw output for one sample (`[n, 3]` row-major, in the frame's output units).
pub fn predict(
    model: &TrainedModel,
    graph: &MeshGraphs,
    s: &SampleData,
) -> Result<Vec<f32>, GcnError> {
    let device = super::device::compute();
    let (x, bip) = s.tensors(&model.config, &device)?;
    let out = match &bip {
        Some(b) => model.net.forward_bipartite(b)?,
        None => None,
    };
    let y = model
        .net
        .forward_mesh(x, graph, bip.as_ref().zip(out.as_ref()))?;
    y.into_data()
        .convert::<f32>()
        .try_to_vec::<f32>()
        .map_err(|e| GcnError::Invalid(format!("{e:?}")))
}

/// Node displacements from a raw prediction `y` ([`predict`]) as `config` says: LIBR's `u` plus
/// `correction_scale` times the residual, or the predicted displacement itself.
pub fn apply_prediction(
    config: &SrGcnConfig,
    frame: &CaseFrame,
    u: &[f64],
    y: &[f32],
) -> Result<Vec<f64>, GcnError> {
    let unit = frame.unit_mm();
    if y.len() != u.len() {
        return Err(GcnError::Invalid(
            "prediction size differs from the mesh".into(),
        ));
    }
    let k = unit * config.correction_scale;
    Ok(match config.target {
        Target::Residual => u.iter().zip(y).map(|(a, b)| a + k * *b as f64).collect(),
        Target::Gt => y.iter().map(|b| unit * *b as f64).collect(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gcn::model::SrGcnConfig;

    #[test]
    fn a_slow_correction_raises_the_estimate_at_once_and_skips_let_it_fall_again() {
        let mesh = crate::mesh::procedural::box_mesh([40.0, 30.0, 20.0], [4, 3, 2], 0.0);
        let cfg = SrGcnConfig::new().with_width(4).with_levels(1);
        let model = Arc::new(TrainedModel::untrained(cfg, 1).unwrap());
        let case = LibrPlusCase::new(vec![model.clone(), model], &mesh).unwrap();
        assert_eq!(case.members.len(), 2);
        assert_eq!(case.expected_seconds(), FIRST_ESTIMATE_S);
        // One slow correction: the estimate is that at once.
        case.record_seconds(0.5);
        assert_eq!(case.expected_seconds(), 0.5);
        // Faster ones lower it by a tenth of the gap.
        case.record_seconds(0.1);
        assert!((case.expected_seconds() - 0.46).abs() < 1e-12);
        // Skipped corrections are not timed; each lowers it by 2 %, so a budget that leaves
        // 0.15 s is met again after a few dozen skips, not never.
        let mut skips = 0;
        while case.expected_seconds() > 0.15 {
            case.relax_estimate();
            skips += 1;
        }
        assert!((40..=80).contains(&skips), "{skips} skips");
        assert!(LibrPlusCase::new(Vec::new(), &mesh).is_err());
    }
}
