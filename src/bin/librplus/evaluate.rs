//! `librplus evaluate`: methods over a dataset split, with the report, plots and error maps.

use crate::args::EvaluateArgs;
use crate::util::Bars;
use anyhow::Result;
use librplus::eval::report_dir::{EvaluateOptions, evaluate_into};

/// Evaluates the methods, writes the report directory and prints the report (or its summary).
pub(crate) fn evaluate(a: &EvaluateArgs) -> Result<()> {
    let options = EvaluateOptions {
        data: a.data.clone(),
        out: a.out.clone(),
        methods: a.methods.clone(),
        model: a.model.clone(),
        v2s_model: a.v2s_model.clone(),
        splits: a.split.clone(),
        every: a.every,
        params: a.libr.params(),
        physics: a.physics.clone(),
        discover: a.discover,
    };
    let report = evaluate_into(&options, &Bars::default())?;
    if a.json {
        println!("{}", report.summary);
    } else {
        print!("{}", report.markdown);
        println!(
            "\nwritten: {}/summary.json, report.md, results.json, tre_by_category_SPLIT.png, tre_cdf_SPLIT.png, error_maps/SPLIT/GEOMETRY_METHOD.vtu",
            a.out.display()
        );
    }
    Ok(())
}
