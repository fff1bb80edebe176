//! Name (step 3): forward selection of effects, round by round, each candidate screened on the
//! current linearization and the most promising confirmed on their own.

use super::confirm::{Confirmed, confirm};
use super::cv::AmplitudePrior;
use super::family::{pair_candidates, search_family, shape_uncertainty};
use super::find::Found;
use super::rows::CohortRows;
use super::search::{self, Candidate, Current, SearchContext};
use super::stats::{bic_change, paired};
use super::{CandidateRecord, DiscoverError, DiscoverParams, NamedEffect, Sweep, in_time};
use crate::register::PreopModel;
use crate::register::physics::model::{ModelSolver, Sites};
use crate::register::physics::{EffectKind, Physics};

/// What naming leaves: the final model, its linearization, every candidate's record and the
/// named effects.
pub(super) struct Named {
    pub(super) cur: Current,
    pub(super) cur_rows: CohortRows,
    pub(super) records: Vec<CandidateRecord>,
    pub(super) named: Vec<NamedEffect>,
}

/// Step 3, forward selection: each round searches every kind (and support × load pairs) on the
/// current model, confirms the most promising on their own linearization, and names the best
/// that passes the rule.
pub(super) fn name(
    model: &PreopModel,
    sweeps: &[Sweep],
    params: &DiscoverParams,
    found: &Found,
    progress: &(dyn Fn(&str, usize, usize) + Sync),
) -> Result<Named, DiscoverError> {
    let libr = &params.pipeline.libr;
    let sites = Sites {
        posterior: &model.posterior,
        falciform: &model.falciform,
    };
    let solver = std::sync::Arc::new(ModelSolver::new(
        &model.mesh,
        &libr.basis.material,
        sites,
        &Physics::none(),
    )?);
    let mut cur = Current {
        physics: Physics::none(),
        basis: found.basis.clone(),
        solver,
        a: found.a.clone(),
        prior: found.prior.clone(),
        amplitude: AmplitudePrior::none(found.a.ncols()),
        score: found.base_score.clone(),
    };
    // The rows the current model is linearized at: its own registrations' correspondences.
    let mut cur_rows = found.rows.clone();
    let mut records: Vec<CandidateRecord> = found.refine_record.iter().cloned().collect();
    let mut named: Vec<NamedEffect> = Vec::new();
    for round in 0..params.max_effects {
        let kinds: Vec<EffectKind> = params
            .kinds
            .iter()
            .copied()
            .filter(|k| !cur.physics.effects.iter().any(|e| e.kind == *k))
            .collect();
        if kinds.is_empty() {
            break;
        }
        let ctx = SearchContext {
            mesh: &model.mesh,
            sites,
            libr,
            rows: &cur_rows,
            geom: &found.geom,
            noise_var: found.noise_var,
        };
        let r = Round {
            ctx: &ctx,
            cur: &cur,
            round,
            params,
            progress,
        };
        let screened = r.screen(&kinds, &mut records)?;
        let Some(best) = r.confirm_best(screened, &found.prepared, sweeps, &mut records)? else {
            break;
        };
        let conf = best.name(round, &mut named);
        cur_rows = conf.rows;
        cur = conf.current;
    }
    Ok(Named {
        cur,
        cur_rows,
        records,
        named,
    })
}

/// One round of forward selection on the current model.
struct Round<'a> {
    ctx: &'a SearchContext<'a>,
    cur: &'a Current,
    round: usize,
    params: &'a DiscoverParams,
    progress: &'a (dyn Fn(&str, usize, usize) + Sync),
}

/// A screened candidate: the family's best, the family, and its record's index.
type Screened = (Candidate, Vec<Candidate>, usize);

/// A candidate that passed the rule on its own linearization, with its evidence.
struct Passing {
    conf: Confirmed,
    top: Candidate,
    family: Vec<Candidate>,
    z: f64,
    gain: f64,
    delta_bic: f64,
}

impl Round<'_> {
    /// Screen: every kind searched on the current linearization (shape parameters by the full
    /// fit, maximum likelihood), and with neither a support nor a load in the model yet, each
    /// support's best searched again with every load kind carried by it (a load and what
    /// carries it are one signature). Every family's best is recorded; the promising ones (they
    /// lower the held-out misfit or the BIC on the current linearization, which understates a
    /// large effect: the confirmation decides) are returned.
    fn screen(
        &self,
        kinds: &[EffectKind],
        records: &mut Vec<CandidateRecord>,
    ) -> Result<Vec<Screened>, DiscoverError> {
        let (round, params, cur) = (self.round, self.params, self.cur);
        let mut screened: Vec<Screened> = Vec::new();
        let mut consider = |top: Candidate, family: Vec<Candidate>| {
            let (z, t, gain) = paired(&cur.score, &top.score);
            let delta_bic = bic_change(&cur.score, &top.score, top.parameters);
            records.push(CandidateRecord {
                round,
                kind: top.kinds(),
                effect: top.describe(),
                heldout_rms_mm: top.score.heldout_mse.sqrt(),
                gain,
                rank_z: z,
                t,
                delta_bic,
                relinearized: false,
                significant: false,
            });
            if gain > 0.0 || delta_bic < 0.0 {
                screened.push((top, family, records.len() - 1));
            }
        };
        let mut supports = Vec::new();
        for (i, kind) in kinds.iter().enumerate() {
            (self.progress)(&format!("round {round}: searching {kind}"), i, kinds.len());
            in_time(params, &format!("searching {kind} (round {round})"))?;
            let family = search_family(self.ctx, cur, *kind, &params.grid)?;
            let Some(top) = search::best_fit(&family) else {
                continue;
            };
            if kind.is_support() {
                supports.push(top.clone());
            }
            consider(top, family);
        }
        let loads: Vec<EffectKind> = kinds.iter().copied().filter(|k| k.is_load()).collect();
        if !cur.physics.has_support() && !cur.physics.effects.iter().any(|e| e.kind.is_load()) {
            for s in &supports {
                let what = format!("pairs with {}", s.effect.kind);
                (self.progress)(&format!("round {round}: {what}"), 0, 1);
                in_time(params, &format!("{what} (round {round})"))?;
                for (top, family) in pair_candidates(self.ctx, cur, s, &loads, &params.grid)? {
                    consider(top, family);
                }
            }
        }
        Ok(screened)
    }

    /// Confirms the most promising on their own linearization: each sweep registered again
    /// with the augmented model, its misfit linearized at the new correspondences, and the two
    /// models compared unit by unit, each at its own fit (a large hidden effect moves the
    /// correspondences plain LIBR converged to; rows linearized there understate it). Every
    /// confirmation is recorded; the one removing the most misfit among those that pass wins.
    fn confirm_best(
        &self,
        mut screened: Vec<Screened>,
        prepared: &crate::pipeline::Prepared,
        sweeps: &[Sweep],
        records: &mut Vec<CandidateRecord>,
    ) -> Result<Option<Passing>, DiscoverError> {
        let (round, params) = (self.round, self.params);
        screened.sort_by(|a, b| records[b.2].gain.total_cmp(&records[a.2].gain));
        screened.truncate(params.confirmations.max(1));
        let mut passing: Vec<Passing> = Vec::new();
        for (top, family, _) in screened {
            (self.progress)(&format!("round {round}: confirming {}", top.kinds()), 0, 1);
            in_time(
                params,
                &format!("confirming {} (round {round})", top.kinds()),
            )?;
            let Some(conf) = confirm(
                self.ctx,
                prepared,
                sweeps,
                params,
                self.cur,
                &top,
                self.progress,
            )?
            else {
                continue;
            };
            let (z, t, gain) = paired(&conf.compared.0, &conf.compared.1);
            let delta_bic = bic_change(&conf.compared.0, &conf.compared.1, top.parameters);
            let significant = z > params.z_threshold && gain > params.min_gain && delta_bic < 0.0;
            records.push(CandidateRecord {
                round,
                kind: top.kinds(),
                effect: confirmed_description(&conf, &top),
                heldout_rms_mm: conf.compared.1.heldout_mse.sqrt(),
                gain,
                rank_z: z,
                t,
                delta_bic,
                relinearized: true,
                significant,
            });
            if significant {
                passing.push(Passing {
                    conf,
                    top,
                    family,
                    z,
                    gain,
                    delta_bic,
                });
            }
        }
        Ok(passing.into_iter().max_by(|a, b| a.gain.total_cmp(&b.gain)))
    }
}

/// How a confirmed candidate reads in the record: its effect as confirmed (refitted where its
/// amplitudes were fitted again), after the support that carries it for a pair.
fn confirmed_description(conf: &Confirmed, top: &Candidate) -> String {
    let mut effect = conf
        .physics
        .effects
        .iter()
        .rev()
        .find(|e| e.kind == top.effect.kind)
        .cloned()
        .unwrap_or_else(|| top.effect.clone());
    if let Some(e) = conf.refitted.as_ref() {
        effect = e.clone();
    }
    match &top.partner {
        Some(p) => format!("{} + {}", p.describe(), effect.describe()),
        None => effect.describe(),
    }
}

impl Passing {
    /// Names the effect (and, for a pair, the support that carries it, with the same
    /// evidence) and returns the confirmation, whose model the next round starts from.
    fn name(self, round: usize, named: &mut Vec<NamedEffect>) -> Confirmed {
        let Passing {
            conf,
            top,
            family,
            z,
            gain,
            delta_bic,
        } = self;
        let before = conf.compared.0.heldout_mse.sqrt();
        let uncertainty = shape_uncertainty(&top, &family);
        let effect = conf.refitted.clone().unwrap_or_else(|| top.effect.clone());
        let evidence = serde_json::json!({
            "heldout_rms_before_mm": before,
            "heldout_rms_after_mm": conf.compared.1.heldout_mse.sqrt(),
            "gain": gain,
            "rank_z": z,
            "delta_bic": delta_bic,
            "round": round,
            "candidates_tried": family.len(),
        });
        if let Some(p) = &top.partner {
            let mut with = evidence.clone();
            with["named_with"] = serde_json::json!(effect.kind.name());
            named.push(NamedEffect {
                effect: p.clone(),
                uncertainty: serde_json::json!({}),
                evidence: with,
            });
        }
        named.push(NamedEffect {
            effect,
            uncertainty,
            evidence,
        });
        conf
    }
}
