//! `librplus train` (one SR-GCN or V2S model, trained and tested) and `librplus ensemble`.

use crate::args::{EnsembleArgs, TrainArgs, TrainMethod};
use crate::util::Bars;
use anyhow::Result;
use librplus::eval::train_run::{
    NetworkOptions, SrgcnOptions, TrainRunOptions, TrainRunOutcome, TrainedNetwork, V2sOptions,
    train_and_test,
};
use serde_json::json;

pub(crate) fn ensemble(a: &EnsembleArgs) -> Result<()> {
    let command: Vec<String> = std::env::args().collect();
    let names = librplus::gcn::io::make_ensemble(
        &a.out,
        &a.models,
        json!({ "command": command.join(" ") }),
    )?;
    let models = librplus::gcn::io::load_models_on_device(&a.out)?;
    println!("{}: ensemble of {} networks", a.out.display(), names.len());
    for (name, m) in names.iter().zip(&models) {
        let p = &m.provenance;
        println!(
            "  {name}: split {}, correction scale {}, test LIBR {} → LIBR+ {} mm",
            p["split"].as_str().unwrap_or("?"),
            m.config.correction_scale,
            p["metrics"]["test_libr_tre_mm"]
                .as_f64()
                .map_or("?".into(), |x| format!("{x:.3}")),
            p["metrics"]["test_librplus_tre_mm"]
                .as_f64()
                .map_or("?".into(), |x| format!("{x:.3}")),
        );
    }
    Ok(())
}

/// Trains and tests one model, and prints its test figures.
pub(crate) fn train(a: &TrainArgs) -> Result<()> {
    let outcome = train_and_test(&train_options(a), &Bars::default())?;
    print_outcome(&outcome);
    Ok(())
}

/// The training run `train`'s arguments describe.
pub(crate) fn train_options(a: &TrainArgs) -> TrainRunOptions {
    let network = match a.method {
        TrainMethod::Srgcn => NetworkOptions::Srgcn(srgcn_options(a)),
        TrainMethod::V2s => NetworkOptions::V2s(V2sOptions {
            config: librplus::v2s::model::V2sConfig::new()
                .with_grid(a.grid)
                .with_width(a.v2s_width)
                .with_depth(a.v2s_depth)
                .with_convs(a.v2s_convs),
            learning_rate: a.v2s_lr,
        }),
    };
    TrainRunOptions {
        data: a.data.clone(),
        out: a.out.clone(),
        split: a.split.clone(),
        every: a.every,
        seed: a.seed,
        validation: a.validation.get(),
        epochs: a.epochs,
        patience: a.patience,
        schedule: a.schedule.get(),
        max_minutes: a.max_minutes,
        params: a.libr.params(),
        physics: a.physics.clone(),
        init: a.init.clone(),
        network,
        origin: crate::util::origin(),
    }
}

/// The SR-GCN options of `train`'s arguments.
fn srgcn_options(a: &TrainArgs) -> SrgcnOptions {
    let config = librplus::gcn::model::SrGcnConfig::new()
        .with_misfit_input(a.misfit_input)
        .with_surface_input(a.surface_input)
        .with_load_input(a.load_input)
        .with_diagnostic_truth_neighbours(a.diagnostic_truth_neighbours)
        .with_width(a.width)
        .with_convs(a.convs)
        .with_kernel_size(a.kernel_size)
        .with_levels(a.levels)
        .with_resolution(a.resolution)
        .with_pool_ratio(a.pool_ratio)
        .with_clusters(a.clusters)
        .with_coarse_convs(a.coarse_convs)
        .with_residual(!a.no_residual)
        .with_n_top(a.n_top);
    SrgcnOptions {
        config,
        sparse_weight: a.sparse_weight,
        ablation: a.ablation,
        epochs_bipartite: a.epochs_bipartite,
        learning_rate: a.lr,
        refit_loss: !a.no_refit_loss,
        average_epochs: a.average_epochs,
        weight_decay: a.weight_decay,
        position_jitter: a.position_jitter,
    }
}

/// Prints a run's test: the two methods' mean TREs over the held-out scenarios, then per
/// category.
pub(crate) fn print_outcome(r: &TrainRunOutcome) {
    let a = &r.test.all;
    let (first, second) = match r.network {
        TrainedNetwork::Srgcn => {
            println!(
                "split {}: test LIBR {:.3} mm, LIBR+ {:.3} mm (ratio {:.3}) over {} scenarios; training {:.0} s, LIBR solutions {:.0} s",
                r.split,
                a.first_mean(),
                a.second_mean(),
                a.second / a.first.max(1e-12),
                a.count,
                r.train_seconds,
                r.libr_seconds
            );
            ("LIBR", "LIBR+")
        }
        TrainedNetwork::V2s => {
            println!(
                "V2S, split {}: test wICP {:.3} mm, V2S {:.3} mm over {} scenarios; training {:.0} s",
                r.split,
                a.first_mean(),
                a.second_mean(),
                a.count,
                r.train_seconds
            );
            ("wICP", "V2S")
        }
    };
    for (k, v) in &r.test.by_category {
        println!(
            "  {k:<12} {first} {:.3}  {second} {:.3}  ({} scenarios)",
            v.first_mean(),
            v.second_mean(),
            v.count
        );
    }
}
