//! LIBR+ at registration time: a trained SR-GCN prepared for one preoperative mesh (its frame and
//! graphs, built once before surgery), and the correction of one LIBR result.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

use super::io::TrainedModel;
use super::model::MeshGraphs;
use super::sample::{CaseFrame, SampleData};
use super::train::correct;
use crate::mesh::TetMesh;
use crate::mesh::rigid::Rigid;
use crate::register::Measurements;
use crate::register::correspondence::{Correspondence, CorrespondenceParams};
use burn::tensor::Device;

/// What a correction is assumed to cost before one has been timed (s).
const FIRST_ESTIMATE_S: f64 = 0.15;

/// A trained SR-GCN ready for one case.
#[derive(Debug)]
pub struct LibrPlusCase {
    /// The network (shared between cases).
    pub model: Arc<TrainedModel>,
    /// The case's normalisation and mesh graph.
    pub frame: CaseFrame,
    /// The mesh graph and its coarse levels on the CPU device.
    pub graphs: MeshGraphs,
    /// Running estimate of one correction's time (f64 bits, seconds): a decaying maximum.
    estimate: AtomicU64,
}

impl LibrPlusCase {
    /// Prepares `model` for the preoperative `mesh`.
    pub fn new(model: Arc<TrainedModel>, mesh: &TetMesh) -> Result<Self, String> {
        let frame = CaseFrame::new(mesh).map_err(|e| e.to_string())?;
        let graphs = frame
            .mesh_graphs(&model.config, &Device::flex())
            .map_err(|e| e.to_string())?;
        Ok(Self {
            model,
            frame,
            graphs,
            estimate: AtomicU64::new(FIRST_ESTIMATE_S.to_bits()),
        })
    }

    /// Expected time of one correction (s): a decaying maximum of the last ones (a slower
    /// correction raises it at once, faster ones lower it by a tenth of the gap each), so a
    /// deadline plan built on it errs towards answering with LIBR rather than late.
    pub fn expected_seconds(&self) -> f64 {
        f64::from_bits(self.estimate.load(Ordering::Relaxed))
    }

    /// Folds the time of one whole correction stage (s) into [`LibrPlusCase::expected_seconds`].
    pub fn record_seconds(&self, s: f64) {
        let old = self.expected_seconds();
        let new = if s > old { s } else { 0.9 * old + 0.1 * s };
        self.estimate.store(new.to_bits(), Ordering::Relaxed);
    }

    /// Corrects LIBR's displacement `u` (image frame, `transform` image → physical) for the
    /// measurements it was fitted to; returns the LIBR+ displacement and the network's share of
    /// the time (s; the rest builds the sample: graphs, matches, features). `cparams` are the
    /// correspondence settings of LIBR's last iteration. The caller records the stage's time
    /// ([`LibrPlusCase::record_seconds`]).
    #[allow(clippy::too_many_arguments)]
    pub fn correct(
        &self,
        mesh: &TetMesh,
        correspondence: &Correspondence,
        cparams: &CorrespondenceParams,
        meas: &Measurements,
        u: &[f64],
        transform: &Rigid,
    ) -> Result<(Vec<f64>, f64), String> {
        let sample = SampleData::build(
            &self.model.config,
            &self.frame,
            mesh,
            correspondence,
            cparams,
            meas,
            u,
            transform,
            None,
        )
        .map_err(|e| e.to_string())?;
        let t1 = Instant::now();
        let out = correct(&self.model, &self.frame, &self.graphs, &sample, u)
            .map_err(|e| e.to_string())?;
        let network_s = t1.elapsed().as_secs_f64();
        if out.iter().any(|x| !x.is_finite()) {
            return Err("the network's correction is not finite".into());
        }
        Ok((out, network_s))
    }
}
