//! `librplus evaluate`: methods over a dataset split, with the report, plots and error maps.

use crate::args::EvaluateArgs;
use crate::register::shared_models;
use anyhow::{Context, Result, bail};
use librplus::mesh::io::{self, WriteOptions};
use serde_json::{Value, json};

pub(crate) fn evaluate(a: &EvaluateArgs) -> Result<()> {
    use librplus::eval::report::{self, Split};
    use librplus::pipeline::Method;
    let m = librplus::eval::open(&a.data)?;
    let mut want_plus = false;
    let mut methods = Vec::new();
    for x in a.methods.split(',') {
        match x.trim() {
            "initial" => methods.push(Method::Initial),
            "rigid" => methods.push(Method::Rigid),
            "libr" => methods.push(Method::Libr),
            "librplus" => want_plus = true,
            "v2s" => methods.push(Method::V2s),
            "adaptive" => methods.push(Method::Adaptive),
            other => {
                bail!(
                    "--methods: unknown method {other:?} (initial, rigid, libr, adaptive, v2s, librplus)"
                )
            }
        }
    }
    let model = match (&a.model, want_plus) {
        (Some(dir), _) => Some(shared_models(
            librplus::gcn::io::load_models_on_device(dir)
                .map_err(|e| anyhow::anyhow!("--model: {e}"))?,
        )),
        (None, true) => Some(shared_models(
            librplus::gcn::io::builtin_models()
                .map_err(|e| anyhow::anyhow!("built-in model: {e}"))?,
        )),
        (None, false) => None,
    };
    let v2s = match (&a.v2s_model, methods.contains(&Method::V2s)) {
        (Some(dir), true) => Some(std::sync::Arc::new(
            librplus::v2s::io::load_model_on_device(dir)
                .map_err(|e| anyhow::anyhow!("--v2s-model: {e}"))?,
        )),
        (None, true) => Some(std::sync::Arc::new(
            librplus::v2s::io::builtin_model()
                .map_err(|e| anyhow::anyhow!("built-in V2S model: {e}"))?,
        )),
        (Some(_), false) => bail!("--v2s-model is used with --methods v2s"),
        (None, false) => None,
    };
    if model.is_some() && !methods.contains(&Method::Libr) {
        // LIBR+ corrects LIBR's result: LIBR runs (and is reported) with it.
        methods.push(Method::Libr);
    }
    // With a model: its held-out scenarios, under its split's name; with an ensemble, the
    // scenarios every member held out. A model trained on another dataset (its provenance's
    // parameters hash differs) saw none of this one: no restriction.
    let trained_here = |p: &Value| {
        p["data_parameters_hash"]
            .as_str()
            .is_none_or(|h| h == m.parameters_hash)
    };
    // The provenance of every learned model evaluated: SR-GCN members, then V2S.
    let provenances: Vec<&Value> = model
        .iter()
        .flatten()
        .map(|mm| &mm.provenance)
        .chain(v2s.iter().map(|v| &v.provenance))
        .collect();
    let model_test = match &provenances {
        ps if ps.iter().any(|p| trained_here(p)) => {
            let mut names = Vec::new();
            let mut common: Option<std::collections::BTreeSet<(String, usize)>> = None;
            for p in ps.iter().filter(|p| trained_here(p)) {
                let split = p["split"].as_str().unwrap_or("");
                let sp = librplus::eval::train::TrainSplit::parse(split)
                    .map_err(|e| anyhow::anyhow!("--model provenance: {e}"))?;
                let seed = p["seed"].as_u64().unwrap_or(1);
                let every = p["every"].as_u64().unwrap_or(1) as usize;
                // The test set does not depend on how the model was validated.
                let sets = librplus::eval::train::split_scenarios(
                    &m,
                    &sp,
                    seed,
                    every,
                    librplus::eval::train::Validation::Deformations,
                )
                .map_err(|e| anyhow::anyhow!("--model split on this dataset: {e}"))?;
                let test: std::collections::BTreeSet<_> = sets.test.into_iter().collect();
                common = Some(match common {
                    None => test,
                    Some(c) => c.intersection(&test).cloned().collect(),
                });
                if !names.contains(&sp.name()) {
                    names.push(sp.name());
                }
            }
            Some((names.join("+"), common.unwrap_or_default()))
        }
        _ => None,
    };
    let splits = match &model_test {
        Some(_) => vec![Split::All],
        None => a
            .split
            .split(',')
            .map(|s| Split::parse(s.trim()).map_err(|e| anyhow::anyhow!("--split: {e}")))
            .collect::<Result<Vec<_>>>()?,
    };
    std::fs::create_dir_all(&a.out).with_context(|| a.out.display().to_string())?;
    let params = a.libr.params();
    let physics = match &a.physics {
        None => librplus::register::physics::Physics::none(),
        Some(p) => librplus::register::physics::Physics::read(p)
            .map_err(|e| anyhow::anyhow!("--physics: {e}"))?,
    };
    params
        .libr
        .validate()
        .map_err(|e| anyhow::anyhow!("LIBR options: {e}"))?;
    if let Some(members) = &model {
        let refs: Vec<&librplus::gcn::io::TrainedModel> = members.iter().map(|m| &**m).collect();
        if let Some(why) = librplus::gcn::infer::physics_mismatch(&refs, &physics) {
            eprintln!("warning: LIBR+ is LIBR's answer throughout: {why}");
        }
    }
    let mut summaries = std::collections::BTreeMap::new();
    let mut discovered = serde_json::Map::new();
    let discover_params = a.discover.then(librplus::discover::DiscoverParams::default);
    if a.discover && !methods.contains(&Method::Libr) {
        bail!("--discover scores LIBR with each cohort's physics: --methods must include libr");
    }
    if a.discover && a.physics.is_some() {
        bail!("--discover finds each cohort's physics: leave out --physics");
    }
    let mut all_results = serde_json::Map::new();
    let mut plots = serde_json::Map::new();
    let mut error_maps = serde_json::Map::new();
    for split in splits {
        let bar = indicatif::ProgressBar::new(0).with_style(
            indicatif::ProgressStyle::with_template(
                "{spinner} split {msg} [{bar:30}] {pos}/{len} registrations, {elapsed} (eta {eta})",
            )
            .expect("valid template")
            .progress_chars("=> "),
        );
        let name: String = match &model_test {
            Some((n, _)) => n.clone(),
            None => split.name().to_string(),
        };
        let name = name.as_str();
        bar.set_message(name.to_string());
        let progress = |done: usize, total: usize| {
            bar.set_length(total as u64);
            bar.set_position(done as u64);
        };
        let plus = (model.is_some() || v2s.is_some()).then(|| report::LibrPlusEval {
            models: model.as_deref().unwrap_or(&[]),
            v2s: v2s.as_ref(),
            only: model_test.as_ref().map(|t| &t.1),
        });
        let disc = discover_params
            .as_ref()
            .map(|p| report::DiscoverEval { params: p });
        let results = report::evaluate(
            &a.data, &m, split, &methods, a.every, &params, &physics, plus, disc, &progress,
        );
        bar.finish_and_clear();
        let ev = results?;
        let mut split_plots = Vec::new();
        for (file, png) in [
            (
                format!("tre_by_category_{name}.png"),
                librplus::eval::plot::tre_by_category_png(name, &ev.results),
            ),
            (
                format!("tre_cdf_{name}.png"),
                librplus::eval::plot::tre_cdf_png(name, &ev.results),
            ),
        ] {
            let png = png.map_err(|e| anyhow::anyhow!("plot {file}: {e}"))?;
            let path = a.out.join(&file);
            std::fs::write(&path, png).with_context(|| path.display().to_string())?;
            split_plots.push(file);
        }
        let dir = a.out.join("error_maps").join(name);
        std::fs::create_dir_all(&dir).with_context(|| dir.display().to_string())?;
        let mut split_maps = Vec::new();
        for map in &ev.error_maps {
            if map.scenarios == 0 {
                continue;
            }
            let mesh = &ev.meshes[&map.geometry];
            let file = format!("error_maps/{name}/{}_{}.vtu", map.geometry, map.method);
            let f = map.to_file(mesh)?;
            io::write(a.out.join(&file), &f, WriteOptions::default())?;
            let mean = map.mean_mm();
            split_maps.push(json!({
                "file": file,
                "geometry": map.geometry,
                "method": map.method,
                "scenarios": map.scenarios,
                "nodes": mean.len(),
                "tre_mm": mean.iter().sum::<f64>() / mean.len().max(1) as f64,
            }));
        }
        plots.insert(name.to_string(), json!(split_plots));
        error_maps.insert(name.to_string(), Value::Array(split_maps));
        summaries.insert(name.to_string(), report::summarize(&ev.results));
        if a.discover {
            discovered.insert(name.to_string(), serde_json::to_value(&ev.discovered)?);
        }
        all_results.insert(name.to_string(), serde_json::to_value(&ev.results)?);
    }
    let summary = json!({
        "format": 1,
        "data": a.data.display().to_string(),
        "every": a.every,
        "splits": summaries.iter().map(|(k, v)| (k.clone(), json!({"methods": v}))).collect::<serde_json::Map<_, _>>(),
        "plots": plots,
        "error_maps": error_maps,
    });
    let mut summary = summary;
    if a.discover {
        summary["discovered"] = Value::Object(discovered);
    }
    std::fs::write(
        a.out.join("summary.json"),
        serde_json::to_string_pretty(&summary)? + "\n",
    )?;
    std::fs::write(
        a.out.join("results.json"),
        serde_json::to_string_pretty(&Value::Object(all_results))? + "\n",
    )?;
    std::fs::write(a.out.join("report.md"), report::markdown(&summaries))?;
    if a.json {
        println!("{summary}");
    } else {
        print!("{}", report::markdown(&summaries));
        println!(
            "\nwritten: {}/summary.json, report.md, results.json, tre_by_category_SPLIT.png, tre_cdf_SPLIT.png, error_maps/SPLIT/GEOMETRY_METHOD.vtu",
            a.out.display()
        );
    }
    Ok(())
}
