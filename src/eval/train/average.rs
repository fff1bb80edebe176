//! Weight averaging of a network's parameters over training (an exponential moving average
//! after a warm-up).

use crate::eval::EvalError;
use crate::gcn::model::SrGcn;
use burn::module::{Module, ModuleMapper, ModuleVisitor, Param};
use burn::tensor::Tensor;

/// The float parameters of a module, flattened, in the order [`Module::visit`] gives them.
pub(super) struct FlatParams(pub(super) Vec<Tensor<1>>);

impl ModuleVisitor for FlatParams {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        let t = param.val();
        let n = t.shape().num_elements();
        self.0.push(t.reshape([n]));
    }
}

/// Blends a module's float parameters towards others given in the same order:
/// `p ← keep·p + (1 − keep)·q`.
pub(super) struct Blend {
    towards: std::vec::IntoIter<Tensor<1>>,
    keep: f64,
    mismatch: bool,
}

impl ModuleMapper for Blend {
    fn map_float<const D: usize>(&mut self, param: Param<Tensor<D>>) -> Param<Tensor<D>> {
        let Some(q) = self.towards.next() else {
            self.mismatch = true;
            return param;
        };
        let keep = self.keep;
        let mut mismatch = false;
        let out = param.map(|p| {
            let dims = p.dims();
            if q.dims()[0] != dims.iter().product::<usize>() {
                mismatch = true;
                return p;
            }
            p.mul_scalar(keep) + q.reshape(dims).mul_scalar(1.0 - keep)
        });
        self.mismatch |= mismatch;
        out
    }
}

/// An exponential moving average of a network's weights (Polyak averaging): after step `t` the
/// average moves towards the weights by `1 − keep`, with `keep = min(decay, (1 + t)/(10 + t))`,
/// so the first steps, far from where training ends, are soon forgotten.
pub struct WeightAverage {
    net: Option<SrGcn>,
    decay: f64,
    steps: u64,
}

impl WeightAverage {
    /// An average with `decay` per step, in [0, 1).
    pub fn new(decay: f64) -> Result<Self, EvalError> {
        if !(0.0..1.0).contains(&decay) {
            return Err(EvalError::Parameter(format!(
                "weight-average decay must be in [0, 1), got {decay}"
            )));
        }
        Ok(Self {
            net: None,
            decay,
            steps: 0,
        })
    }

    /// Takes the weights after a step (a plain-device copy, `SrGcn::valid`).
    pub fn update(&mut self, net: SrGcn) -> Result<(), EvalError> {
        self.steps += 1;
        self.net = Some(match self.net.take() {
            None => net,
            Some(avg) => {
                let mut flat = FlatParams(Vec::new());
                net.visit(&mut flat);
                let t = self.steps as f64;
                let mut blend = Blend {
                    towards: flat.0.into_iter(),
                    keep: self.decay.min((1.0 + t) / (10.0 + t)),
                    mismatch: false,
                };
                let out = avg.map(&mut blend);
                if blend.mismatch || blend.towards.next().is_some() {
                    return Err(EvalError::Internal(
                        "internal: the averaged network's parameters differ".into(),
                    ));
                }
                out
            }
        });
        Ok(())
    }

    /// The average so far (`None` before the first update).
    pub fn get(&self) -> Option<&SrGcn> {
        self.net.as_ref()
    }

    /// Steps taken in.
    pub fn steps(&self) -> u64 {
        self.steps
    }
}
