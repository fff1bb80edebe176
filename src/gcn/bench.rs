//! The spline-convolution stack benchmark behind `librplus bench gcn`: the graph and network of
//! `../shared/bench/splineconv_peer.py` rebuilt here (N random points in the unit cube, symmetric
//! kNN edges with k chosen so the mean in-degree is closest to the target, PyG Cartesian
//! pseudo-coordinates; layers 6 → hidden … → 3, ELU between, degree-1 open B-splines, mean
//! aggregation, root weight, bias, f32), timed as inference (one forward) and one training step
//! (forward, MSE, backward, Adam), warm-ups then medians.

use std::time::Instant;

use burn::module::Module;
use burn::optim::{AdamConfig, GradientsParams};
use burn::tensor::activation::elu;
use burn::tensor::{Distribution, Tensor};

use super::graph::Graph;
use super::sample::knn;
use super::{GcnError, SplineConv, SplineConvConfig, SplineGraph, cartesian_pseudo};

/// Settings of the benchmark (the peer's flags).
#[derive(Debug, Clone)]
pub struct StackBench {
    /// Nodes.
    pub nodes: usize,
    /// Target mean in-degree.
    pub avg_degree: usize,
    /// Kernel size per dimension (3-D pseudo-coordinates).
    pub kernel: usize,
    /// Hidden width.
    pub hidden: usize,
    /// Layers (≥ 2).
    pub layers: usize,
    /// Seed of the points and weights.
    pub seed: u64,
    /// Untimed repetitions first.
    pub warmup: usize,
    /// Timed repetitions.
    pub repeats: usize,
}

/// What the benchmark measured (ms medians and minima).
#[derive(Debug, Clone, serde::Serialize)]
pub struct StackTimes {
    /// Directed edges.
    pub edges: usize,
    /// The k of the kNN graph.
    pub knn_k: usize,
    /// Building the graph's spline basis and sparse operator (once per graph; the peer redoes
    /// its basis in every forward).
    pub prepare_ms: f64,
    /// One forward pass, graph prepared.
    pub infer_ms_median: f64,
    /// Fastest forward.
    pub infer_ms_min: f64,
    /// One forward including the graph preparation (the peer's contract).
    pub infer_with_prepare_ms_median: f64,
    /// One training step (forward, MSE, backward, Adam).
    pub train_step_ms_median: f64,
    /// Fastest training step.
    pub train_step_ms_min: f64,
}

/// The peer's graph: symmetric kNN over random points, k picked for the mean in-degree.
pub fn random_knn_graph(
    nodes: usize,
    avg_degree: usize,
    seed: u64,
) -> Result<(Graph, usize), GcnError> {
    if nodes < 2 || avg_degree == 0 || avg_degree >= nodes {
        return Err(GcnError::Invalid(format!(
            "need nodes ≥ 2 and 1 ≤ avg_degree < nodes (nodes {nodes}, avg_degree {avg_degree})"
        )));
    }
    let mut rng = crate::util::SplitMix64::new(seed);
    let pos: Vec<[f64; 3]> = (0..nodes)
        .map(|_| [rng.next_f64(), rng.next_f64(), rng.next_f64()])
        .collect();
    // Nearest first, self included (distance 0): drop it.
    let near: Vec<Vec<usize>> = knn(&pos, &pos, avg_degree + 1)
        .into_iter()
        .enumerate()
        .map(|(i, l)| l.into_iter().filter(|&j| j != i).take(avg_degree).collect())
        .collect();
    // (gap to the target degree, k, directed edges)
    type Candidate = (f64, usize, Vec<(usize, usize)>);
    let mut best: Option<Candidate> = None;
    for k in 1..=avg_degree {
        let mut pairs: Vec<(usize, usize)> = near
            .iter()
            .enumerate()
            .flat_map(|(a, l)| l.iter().take(k).flat_map(move |&b| [(a, b), (b, a)]))
            .collect();
        pairs.sort_unstable();
        pairs.dedup();
        let gap = (pairs.len() as f64 / nodes as f64 - avg_degree as f64).abs();
        if best.as_ref().is_none_or(|b| gap <= b.0) {
            best = Some((gap, k, pairs));
        }
    }
    let (_, k, pairs) = best.expect("avg_degree ≥ 1");
    let (targets, sources): (Vec<usize>, Vec<usize>) = pairs.into_iter().unzip();
    let flat: Vec<f64> = pos.iter().flatten().copied().collect();
    let pseudo = cartesian_pseudo(&flat, 3, &targets, &sources)?;
    Ok((
        Graph {
            num_nodes: nodes,
            targets,
            sources,
            pseudo,
        },
        k,
    ))
}

fn forward(layers: &[SplineConv], x: Tensor<2>, g: &SplineGraph) -> Result<Tensor<2>, GcnError> {
    let mut x = x;
    for (l, conv) in layers.iter().enumerate() {
        x = conv.forward(x, g)?;
        if l + 1 < layers.len() {
            x = elu(x, 1.0);
        }
    }
    Ok(x)
}

#[derive(burn::module::Module, Debug)]
struct Stack {
    layers: Vec<SplineConv>,
}

fn median_min(v: Vec<f64>) -> (f64, f64) {
    let min = v.iter().copied().fold(f64::INFINITY, f64::min);
    (crate::util::quantile(&v, 0.5), min)
}

/// Runs the benchmark on the CPU device in the current rayon pool.
pub fn run(b: &StackBench) -> Result<StackTimes, GcnError> {
    if b.layers < 2 || b.hidden == 0 || b.repeats == 0 {
        return Err(GcnError::Invalid(
            "need layers ≥ 2, hidden ≥ 1, repeats ≥ 1".into(),
        ));
    }
    let (graph, knn_k) = random_knn_graph(b.nodes, b.avg_degree, b.seed)?;
    let kernel = super::SplineKernel::new(vec![b.kernel; 3], vec![true; 3], 1)?;
    let plain = super::device::compute();
    let ad = plain.clone().autodiff();
    ad.seed(b.seed);
    let mut dims = vec![6];
    dims.extend(std::iter::repeat_n(b.hidden, b.layers - 1));
    dims.push(3);
    let mut net = Stack {
        layers: dims
            .windows(2)
            .map(|w| SplineConvConfig::new(w[0], w[1], vec![b.kernel; 3], vec![true; 3]).init(&ad))
            .collect::<Result<_, _>>()?,
    };
    let t = Instant::now();
    let g_plain = SplineGraph::from_graph(&graph, &kernel, &plain)?;
    let prepare_ms = t.elapsed().as_secs_f64() * 1e3;
    let g_ad = SplineGraph::from_graph(&graph, &kernel, &ad)?;
    let x = Tensor::<2>::random([b.nodes, 6], Distribution::Normal(0.0, 1.0), &plain);
    let y = Tensor::<2>::random([b.nodes, 3], Distribution::Normal(0.0, 1.0), &plain);
    let x_ad = Tensor::<2>::from_data(x.clone().into_data(), &ad);
    let y_ad = Tensor::<2>::from_data(y.into_data(), &ad);
    let valid = net.valid();
    let timed = |f: &mut dyn FnMut() -> Result<(), GcnError>| -> Result<Vec<f64>, GcnError> {
        let mut v = Vec::new();
        for i in 0..b.warmup + b.repeats {
            let t = Instant::now();
            f()?;
            if i >= b.warmup {
                v.push(t.elapsed().as_secs_f64() * 1e3);
            }
        }
        Ok(v)
    };
    let infer = timed(&mut || {
        let out = forward(&valid.layers, x.clone(), &g_plain)?;
        let _ = out.into_data();
        Ok(())
    })?;
    let infer_prep = timed(&mut || {
        let g = SplineGraph::from_graph(&graph, &kernel, &plain)?;
        let out = forward(&valid.layers, x.clone(), &g)?;
        let _ = out.into_data();
        Ok(())
    })?;
    let mut optim = AdamConfig::new().init();
    let train = timed(&mut || {
        let out = forward(&net.layers, x_ad.clone(), &g_ad)?;
        let loss = (out - y_ad.clone()).powi_scalar(2).mean();
        let grads = GradientsParams::from_grads(loss.backward(), &net);
        net = optim.step(1e-3, net.clone(), grads);
        // A GPU runs the step asynchronously: wait for it (a no-op on the CPU).
        ad.sync()
            .map_err(|e| GcnError::Invalid(format!("device sync: {e:?}")))?;
        Ok(())
    })?;
    let (im, imin) = median_min(infer);
    let (ip, _) = median_min(infer_prep);
    let (tm, tmin) = median_min(train);
    Ok(StackTimes {
        edges: graph.num_edges(),
        knn_k,
        prepare_ms,
        infer_ms_median: im,
        infer_ms_min: imin,
        infer_with_prepare_ms_median: ip,
        train_step_ms_median: tm,
        train_step_ms_min: tmin,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_peer_graph_has_the_asked_mean_degree_and_runs() {
        let (g, k) = random_knn_graph(600, 8, 1).unwrap();
        let mean = g.num_edges() as f64 / 600.0;
        assert!((mean - 8.0).abs() < 1.5, "mean in-degree {mean} (k = {k})");
        // Symmetric, no self loops, pseudo-coordinates in [0, 1] and mirrored.
        let mut e: Vec<_> = g.targets.iter().zip(&g.sources).collect();
        let mut r: Vec<_> = g.sources.iter().zip(&g.targets).collect();
        e.sort();
        r.sort();
        assert_eq!(e, r);
        assert!(g.targets.iter().zip(&g.sources).all(|(a, b)| a != b));
        assert!(g.pseudo.iter().all(|p| (0.0..=1.0).contains(p)));
        let t = run(&StackBench {
            nodes: 300,
            avg_degree: 6,
            kernel: 3,
            hidden: 8,
            layers: 3,
            seed: 2,
            warmup: 0,
            repeats: 1,
        })
        .unwrap();
        assert!(t.infer_ms_median > 0.0 && t.train_step_ms_median > 0.0);
    }
}
