//! What can stop an evaluation, a benchmark or a training run.

use crate::dataset::DatasetError;
use crate::gcn::GcnError;
use crate::mesh::io::IoError;
use crate::pipeline::PipelineError;
use crate::register::RegisterError;
use crate::util::FileError;

/// Why an evaluation, benchmark or training run stopped; each says what to change.
#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    /// An option is out of its range or unknown (a method, split, decay, scale grid); the message
    /// names it and what is accepted.
    #[error("{0}")]
    Parameter(String),
    /// The dataset cannot serve this run (too few geometries or patterns for the split, no
    /// training or validation sample, no test geometry).
    #[error("{0}")]
    Data(String),
    /// Training diverged (a non-finite loss) or a model does not fit the run.
    #[error("{0}")]
    Training(String),
    /// An invariant of this module failed (a bug; please report).
    #[error("internal: {0}")]
    Internal(String),
    /// A plot could not be drawn.
    #[error("plot: {0}")]
    Plot(String),
    /// The dataset could not be read.
    #[error(transparent)]
    Dataset(#[from] DatasetError),
    /// A case could not be prepared or registered.
    #[error(transparent)]
    Pipeline(#[from] PipelineError),
    /// A registration stage failed.
    #[error(transparent)]
    Register(#[from] RegisterError),
    /// The SR-GCN failed.
    #[error(transparent)]
    Gcn(#[from] GcnError),
    /// The V2S network failed.
    #[error(transparent)]
    V2s(#[from] crate::v2s::V2sError),
    /// A file could not be read or written.
    #[error(transparent)]
    File(#[from] FileError),
    /// A mesh file could not be written.
    #[error(transparent)]
    Mesh(#[from] IoError),
    /// What failed, for which scenario, geometry or stage.
    #[error("{context}: {source}")]
    In {
        /// Where (a scenario id, "refit", "initial model DIR").
        context: String,
        /// What failed.
        source: Box<EvalError>,
    },
}

impl EvalError {
    /// `source`, said to have happened in `context`.
    pub fn within(context: impl Into<String>, source: impl Into<EvalError>) -> Self {
        Self::In {
            context: context.into(),
            source: Box::new(source.into()),
        }
    }
}

impl<E: std::error::Error + Send + Sync> From<plotters::drawing::DrawingAreaErrorKind<E>>
    for EvalError
{
    fn from(e: plotters::drawing::DrawingAreaErrorKind<E>) -> Self {
        Self::Plot(e.to_string())
    }
}
