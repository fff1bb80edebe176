//! `librplus`: the command-line entry point. Thin: parses arguments, calls the library, prints.
//! One module per command group; the arguments of every command are in `args`.
#![forbid(unsafe_code)]

#[global_allocator]
static ALLOCATOR: librplus::GlobalAllocator = librplus::GlobalAllocator;

mod args;
mod bench;
mod calibrate_error;
mod data;
mod discover;
mod evaluate;
mod experiments;
mod fem;
mod mesh;
mod register;
mod study;
mod train;
mod util;

use anyhow::{Context, Result};
use args::{BenchCmd, Cli, Command, FemCmd, MeshCmd, PhantomCmd};
use bench::{bench_basis, bench_register};
use clap::Parser;
use data::{generate, phantom_effect};
use evaluate::evaluate;
use experiments::experiments;
use fem::fem_sag;
use mesh::{mesh_convert, mesh_info, mesh_tetra};
use register::{register_files, register_scenario};
use serde_json::json;
use train::{ensemble, train};

fn main() {
    let cli = Cli::parse();
    if let Err(e) = run(cli) {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

fn run(cli: Cli) -> Result<()> {
    let device: librplus::gcn::device::ComputeDevice = cli
        .device
        .parse()
        .map_err(|e: librplus::gcn::GcnError| anyhow::anyhow!("--device: {e}"))?;
    librplus::gcn::device::select(device).map_err(|e| anyhow::anyhow!("--device: {e}"))?;
    match cli.command {
        Command::Mesh(MeshCmd::Info { file, common }) => mesh_info(&file, &common),
        Command::Mesh(MeshCmd::Convert {
            input,
            output,
            common,
            ascii,
        }) => mesh_convert(&input, &output, &common, ascii),
        Command::Mesh(MeshCmd::Tetra {
            surface,
            edge_mm,
            out,
            common,
            all_pieces,
        }) => mesh_tetra(&surface, edge_mm, &out, &common, all_pieces),
        Command::Fem(FemCmd::Sag {
            mesh,
            common,
            out,
            model,
            load_scale,
        }) => fem_sag(&mesh, &common, out.as_deref(), model, load_scale),
        Command::Bench(BenchCmd::Basis {
            mesh,
            common,
            rhs,
            repeat,
            seed,
            ordering,
        }) => bench_basis(&mesh, &common, rhs, repeat, seed, ordering.into()),
        Command::Bench(BenchCmd::Register(args)) => bench_register(&args),
        Command::Bench(BenchCmd::Gcn {
            nodes,
            avg_degree,
            kernel,
            hidden,
            layers,
            threads,
            seed,
            warmup,
            repeats,
        }) => (|| -> Result<()> {
            let b = librplus::gcn::bench::StackBench {
                nodes,
                avg_degree,
                kernel,
                hidden,
                layers,
                seed,
                warmup,
                repeats,
            };
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads.max(1))
                .build()
                .context("building the thread pool")?;
            let t = pool
                .install(|| librplus::gcn::bench::run(&b))
                .map_err(|e| anyhow::anyhow!("{e}"))?;
            let mut v = serde_json::to_value(&t)?;
            v["impl"] = json!(match librplus::gcn::device::chosen() {
                librplus::gcn::device::ComputeDevice::Cpu =>
                    "librplus (burn 0.22.1 flex, CSR sparse product)".to_string(),
                d => format!("librplus (burn 0.22.1 on {d}, gather/scatter-add product)"),
            });
            v["nodes"] = json!(nodes);
            v["hidden"] = json!(hidden);
            v["layers"] = json!(layers);
            v["kernel"] = json!(kernel);
            v["threads"] = json!(threads);
            v["repeats"] = json!(repeats);
            println!("{v}");
            Ok(())
        })(),
        Command::Generate(args) => generate(&args),
        Command::Register(args) if args.preop.is_some() => register_files(&args),
        Command::Register(args) => register_scenario(&args),
        Command::Evaluate(args) => evaluate(&args),
        Command::CalibrateError(args) => calibrate_error::calibrate_error(&args),
        Command::CalibrateAbstain(args) => calibrate_error::calibrate_abstain(&args),
        Command::Train(args) => train(&args),
        Command::Experiments(args) => experiments(&args),
        Command::Ensemble(args) => ensemble(&args),
        Command::Discover(args) => discover::discover(&args),
        Command::DiscoverScore(args) => discover::discover_score(&args),
        Command::DiscoverStudy(args) => study::discover_study(&args),
        Command::Phantom(PhantomCmd::Effect {
            surface,
            edge_mm,
            first_seed,
            seeds,
            common,
        }) => phantom_effect(surface.as_deref(), edge_mm, first_seed, seeds, &common),
    }
}
