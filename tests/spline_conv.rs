//! SplineConv against `pytorch_spline_conv`'s reference vectors
//! (`tests/reference/spline_conv_vectors.json`), autodiff gradients against central finite
//! differences, and a 9,000-node forward smoke test.

use burn::tensor::{Device, Tensor, TensorData};
use librplus::gcn::{
    Aggregation, GcnError, SplineConv, SplineConvConfig, SplineGraph, SplineKernel,
    cartesian_pseudo, spline_basis,
};
use serde_json::Value;

fn vectors() -> Value {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/tests/reference/spline_conv_vectors.json"
    );
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{path}: {e}"));
    serde_json::from_str(&text).unwrap()
}

fn f(v: &Value) -> f64 {
    v.as_f64().unwrap()
}

fn u(v: &Value) -> usize {
    v.as_u64().unwrap() as usize
}

fn arr(v: &Value) -> &Vec<Value> {
    v.as_array().unwrap()
}

/// Row-major flattening of a nested numeric array, with its shape.
fn flat(v: &Value) -> (Vec<f64>, Vec<usize>) {
    match v {
        Value::Array(items) => {
            let mut out = Vec::new();
            let mut inner = Vec::new();
            for it in items {
                let (vals, shape) = flat(it);
                inner = shape;
                out.extend(vals);
            }
            let mut shape = vec![items.len()];
            shape.extend(inner);
            (out, shape)
        }
        _ => (vec![f(v)], vec![]),
    }
}

fn kernel_of(case: &Value) -> SplineKernel {
    SplineKernel::new(
        arr(&case["kernel_size"]).iter().map(u).collect(),
        arr(&case["is_open"]).iter().map(|v| u(v) != 0).collect(),
        u(&case["degree"]),
    )
    .unwrap()
}

fn edges(case: &Value) -> (Vec<usize>, Vec<usize>) {
    let ei = arr(&case["edge_index"]);
    (
        arr(&ei[0]).iter().map(u).collect(),
        arr(&ei[1]).iter().map(u).collect(),
    )
}

fn to_vec<const D: usize>(t: Tensor<D>) -> Vec<f64> {
    t.into_data()
        .convert::<f64>()
        .try_into_vec::<f64>()
        .unwrap()
}

fn tensor<const D: usize>(vals: &[f64], shape: [usize; D], device: &Device) -> Tensor<D> {
    let v: Vec<f32> = vals.iter().map(|&x| x as f32).collect();
    Tensor::from_data(TensorData::new(v, shape), device)
}

#[test]
fn basis_cases_match_reference() {
    let v = vectors();
    let mut worst = 0f64;
    for (i, case) in arr(&v["basis_cases"]).iter().enumerate() {
        let kernel = kernel_of(case);
        let (pseudo, _) = flat(&case["pseudo"]);
        let b = spline_basis(&pseudo, &kernel).unwrap();
        let (basis, shape) = flat(&case["basis"]);
        let (wi, _) = flat(&case["weight_index"]);
        assert_eq!(shape, vec![b.num_edges, b.num_basis], "case {i}");
        for j in 0..basis.len() {
            worst = worst.max((b.basis[j] - basis[j]).abs());
            assert!((b.basis[j] - basis[j]).abs() <= 1e-9, "case {i} entry {j}");
            assert_eq!(b.weight_index[j], wi[j] as usize, "case {i} entry {j}");
        }
    }
    println!("basis: worst abs error {worst:e}");
}

#[test]
fn cartesian_cases_match_reference() {
    let v = vectors();
    for case in arr(&v["cartesian_cases"]) {
        let (pos, shape) = flat(&case["pos"]);
        let (t, s) = edges(case);
        let got = cartesian_pseudo(&pos, shape[1], &t, &s).unwrap();
        let (want, _) = flat(&case["normalized"]);
        assert_eq!(got.len(), want.len());
        for (g, w) in got.iter().zip(&want) {
            assert!((g - w).abs() <= 1e-9, "{got:?} vs {want:?}");
        }
    }
}

#[test]
fn conv_cases_match_reference() {
    let v = vectors();
    let device = Device::flex();
    let mut worst = 0f64;
    for (i, case) in arr(&v["conv_cases"]).iter().enumerate() {
        let kernel = kernel_of(case);
        let (x, xs) = flat(&case["x"]);
        let (w, ws) = flat(&case["weight"]);
        let (root, rs) = flat(&case["root_weight"]);
        let (bias, _) = flat(&case["bias"]);
        let (pseudo, _) = flat(&case["pseudo"]);
        let (want, _) = flat(&case["out"]);
        let (t, s) = edges(case);
        let config = SplineConvConfig::new(
            ws[1],
            ws[2],
            kernel.kernel_size.clone(),
            kernel.is_open.clone(),
        )
        .with_degree(kernel.degree)
        .with_aggregation(if case["norm"].as_bool().unwrap() {
            Aggregation::Mean
        } else {
            Aggregation::Sum
        });
        let conv = SplineConv::from_tensors(
            &config,
            tensor(&w, [ws[0], ws[1], ws[2]], &device),
            Some(tensor(&root, [rs[0], rs[1]], &device)),
            Some(tensor(&bias, [ws[2]], &device)),
        )
        .unwrap();
        let graph = SplineGraph::new(xs[0], &t, &s, &pseudo, &kernel, &device).unwrap();
        let out = to_vec(
            conv.forward(tensor(&x, [xs[0], xs[1]], &device), &graph)
                .unwrap(),
        );
        let scale = want.iter().fold(0f64, |m, v| m.max(v.abs()));
        for (j, (g, w)) in out.iter().zip(&want).enumerate() {
            let rel = (g - w).abs() / scale;
            worst = worst.max(rel);
            assert!(rel <= 1e-5, "case {i} entry {j}: {g} vs {w}");
        }
    }
    println!("conv: worst relative error {worst:e}");
}

#[test]
fn bad_graphs_are_errors_not_panics() {
    let device = Device::flex();
    let kernel = SplineKernel::new(vec![3], vec![true], 1).unwrap();
    assert!(matches!(
        SplineGraph::new(3, &[0, 3], &[1, 2], &[0.5, 0.5], &kernel, &device),
        Err(GcnError::IndexOutOfRange { index: 3, .. })
    ));
    assert!(SplineGraph::new(3, &[0, 1], &[1], &[0.5, 0.5], &kernel, &device).is_err());
    assert!(SplineGraph::new(3, &[0, 1], &[1, 2], &[0.5], &kernel, &device).is_err());
    assert!(SplineGraph::new(3, &[0, 1], &[1, 2], &[0.5, 1.5], &kernel, &device).is_err());
    let conv = SplineConvConfig::new(2, 2, vec![3], vec![true])
        .init(&device)
        .unwrap();
    let graph = SplineGraph::new(3, &[0, 1], &[1, 2], &[0.5, 0.2], &kernel, &device).unwrap();
    // Wrong node count and wrong channel count.
    assert!(
        conv.forward(Tensor::zeros([4, 2], &device), &graph)
            .is_err()
    );
    assert!(
        conv.forward(Tensor::zeros([3, 3], &device), &graph)
            .is_err()
    );
    // Graph prepared for another kernel.
    let other = SplineKernel::new(vec![4], vec![true], 1).unwrap();
    let g2 = SplineGraph::new(3, &[0, 1], &[1, 2], &[0.5, 0.2], &other, &device).unwrap();
    assert!(conv.forward(Tensor::zeros([3, 2], &device), &g2).is_err());
    assert!(
        SplineConvConfig::new(2, 2, vec![2], vec![true])
            .with_degree(2)
            .init(&device)
            .is_err()
    );
}

/// Small deterministic pseudo-random numbers (xorshift), uniform in [0, 1).
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> f64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }
}

struct Problem {
    n: usize,
    t: Vec<usize>,
    s: Vec<usize>,
    pseudo: Vec<f64>,
    config: SplineConvConfig,
    x: Vec<f64>,
    w: Vec<f64>,
    root: Vec<f64>,
    bias: Vec<f64>,
}

impl Problem {
    fn random(seed: u64, aggregation: Aggregation, degree: usize) -> Self {
        let mut rng = Rng(seed);
        let (n, e, cin, cout) = (7, 18, 3, 2);
        let sizes = if degree == 3 { vec![4, 5] } else { vec![4, 3] };
        let k: usize = sizes.iter().product();
        let config = SplineConvConfig::new(cin, cout, sizes, vec![true, false])
            .with_degree(degree)
            .with_aggregation(aggregation);
        let mut t = Vec::new();
        let mut s = Vec::new();
        for _ in 0..e {
            t.push((rng.next() * (n - 1) as f64) as usize); // node n-1 gets no messages
            s.push((rng.next() * n as f64) as usize);
        }
        let pseudo = (0..e * 2).map(|_| rng.next()).collect();
        let mut r = |len: usize| (0..len).map(|_| rng.next() * 2.0 - 1.0).collect::<Vec<_>>();
        Self {
            n,
            t,
            s,
            pseudo,
            x: r(n * cin),
            w: r(k * cin * cout),
            root: r(cin * cout),
            bias: r(cout),
            config,
        }
    }

    /// Loss `Σ out²` and, on an autodiff device, the gradients w.r.t. x, W, root, bias.
    fn loss(&self, device: &Device, grads: bool) -> (f64, Option<[Vec<f64>; 4]>) {
        let (cin, cout) = (self.config.in_channels, self.config.out_channels);
        let kernel = self.config.kernel().unwrap();
        let k = kernel.num_weights();
        let mut x = tensor(&self.x, [self.n, cin], device);
        if grads {
            x = x.require_grad();
        }
        let conv = SplineConv::from_tensors(
            &self.config,
            tensor(&self.w, [k, cin, cout], device),
            Some(tensor(&self.root, [cin, cout], device)),
            Some(tensor(&self.bias, [cout], device)),
        )
        .unwrap();
        let graph =
            SplineGraph::new(self.n, &self.t, &self.s, &self.pseudo, &kernel, device).unwrap();
        let out = conv.forward(x.clone(), &graph).unwrap();
        let loss = (out.clone() * out).sum();
        let value = to_vec(loss.clone())[0];
        if !grads {
            return (value, None);
        }
        let g = loss.backward();
        let v = |t: Option<Vec<f64>>| t.expect("missing gradient");
        let gx = v(x.grad(&g).map(to_vec));
        let gw = v(conv.weight.val().grad(&g).map(to_vec));
        let gr = v(conv.root.as_ref().unwrap().val().grad(&g).map(to_vec));
        let gb = v(conv.bias.as_ref().unwrap().val().grad(&g).map(to_vec));
        (value, Some([gx, gw, gr, gb]))
    }
}

#[test]
fn gradients_match_finite_differences() {
    let ad = Device::flex().autodiff();
    let plain = Device::flex();
    for (seed, aggregation, degree) in [
        (7u64, Aggregation::Mean, 1),
        (11, Aggregation::Sum, 2),
        (13, Aggregation::Mean, 3),
    ] {
        let p = Problem::random(seed, aggregation, degree);
        let (_, g) = p.loss(&ad, true);
        let g = g.unwrap();
        // The loss is quadratic in each parameter, so central differences are exact up to rounding.
        let h = 1e-2;
        for (which, name) in ["x", "weight", "root", "bias"].iter().enumerate() {
            let len = g[which].len();
            let mut fd = vec![0.0; len];
            for j in 0..len {
                let eval = |delta: f64| {
                    let mut q = Problem {
                        config: p.config.clone(),
                        t: p.t.clone(),
                        s: p.s.clone(),
                        pseudo: p.pseudo.clone(),
                        x: p.x.clone(),
                        w: p.w.clone(),
                        root: p.root.clone(),
                        bias: p.bias.clone(),
                        n: p.n,
                    };
                    let field = match which {
                        0 => &mut q.x,
                        1 => &mut q.w,
                        2 => &mut q.root,
                        _ => &mut q.bias,
                    };
                    field[j] += delta;
                    q.loss(&plain, false).0
                };
                fd[j] = (eval(h) - eval(-h)) / (2.0 * h);
            }
            let norm = fd.iter().map(|v| v * v).sum::<f64>().sqrt();
            let diff = g[which]
                .iter()
                .zip(&fd)
                .map(|(a, b)| (a - b) * (a - b))
                .sum::<f64>()
                .sqrt();
            let rel = diff / norm.max(1e-12);
            println!(
                "{aggregation:?} degree {degree}: d loss / d {name}: relative error {rel:e} (|g| = {norm:.3})"
            );
            assert!(rel <= 1e-2, "{name}: relative error {rel}");
            let max = fd.iter().fold(0f64, |m, v| m.max(v.abs()));
            for (a, b) in g[which].iter().zip(&fd) {
                assert!((a - b).abs() <= 1e-2 * max.max(1e-6), "{name}: {a} vs {b}");
            }
        }
    }
}

#[test]
fn nine_thousand_node_forward_runs() {
    let device = Device::flex();
    let mut rng = Rng(42);
    let n = 9000;
    let pos: Vec<f64> = (0..n * 3).map(|_| rng.next() * 100.0).collect();
    let (mut t, mut s) = (Vec::new(), Vec::new());
    for i in 0..n {
        for _ in 0..6 {
            let j = (rng.next() * n as f64) as usize;
            t.push(i);
            s.push(j);
        }
    }
    let pseudo = cartesian_pseudo(&pos, 3, &t, &s).unwrap();
    let config = SplineConvConfig::new(6, 32, vec![5, 5, 5], vec![true, true, true]);
    let kernel = config.kernel().unwrap();
    let conv = config.init(&device).unwrap();
    let graph = SplineGraph::new(n, &t, &s, &pseudo, &kernel, &device).unwrap();
    let x = tensor(
        &pos.iter().chain(pos.iter()).copied().collect::<Vec<_>>()[..n * 6],
        [n, 6],
        &device,
    );
    let start = std::time::Instant::now();
    let out = to_vec(conv.forward(x, &graph).unwrap());
    // Informational only: no timing assertion.
    println!(
        "9,000-node forward (6 → 32, K = 125): {:?}",
        start.elapsed()
    );
    assert_eq!(out.len(), n * 32);
    assert!(out.iter().all(|v| v.is_finite()));
}
