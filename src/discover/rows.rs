//! The cohort's linearized misfit rows: every match of every scenario, at the correspondences
//! plain LIBR converged to, as one row per direction (the surface normal for surface and contour
//! points, three axes for vessel points) with its rigid-motion columns; and the spatial blocks
//! (clusters) that cross-validation holds out.

use crate::mesh::vec3::{dist2, dot, sub};
use crate::register::Match;

/// One misfit row: `frame · (y − anchor − Σ bary·u(nodes) − rigid)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Row {
    /// Scenario index in the cohort.
    pub scenario: usize,
    /// Point index in the scenario's measurements.
    pub point: usize,
    /// Spatial block (cluster) of the point.
    pub cluster: usize,
    /// Unit direction of the row (the matched surface's normal, or an axis).
    pub frame: [f64; 3],
    /// Nodes moving the matched model point.
    pub nodes: [u32; 4],
    /// Their interpolation weights.
    pub bary: [f64; 4],
    /// Matched point on the undeformed model (image frame, mm).
    pub anchor: [f64; 3],
    /// Weight of the match.
    pub weight: f64,
    /// `frame · (y − anchor)` (mm): the misfit of the undeformed model.
    pub b: f64,
    /// The six rigid columns (translation x, y, z; rotation about the scenario's centroid, per
    /// unit of rotation × the scenario's radius).
    pub rigid: [f64; 6],
}

impl Row {
    /// The row's value for a node displacement field (node-major 3n): `frame · u(point)`.
    pub fn value(&self, u: &[f64]) -> f64 {
        let mut s = 0.0;
        for (k, &v) in self.nodes.iter().enumerate() {
            let w = self.bary[k];
            if w == 0.0 {
                continue;
            }
            let base = 3 * v as usize;
            s += w
                * (self.frame[0] * u[base]
                    + self.frame[1] * u[base + 1]
                    + self.frame[2] * u[base + 2]);
        }
        s
    }

    /// The row's values for the columns of a row-major 3n × m matrix (a basis).
    pub fn values_into(&self, phi: &[f64], m: usize, out: &mut [f64]) {
        out.iter_mut().for_each(|x| *x = 0.0);
        for (k, &v) in self.nodes.iter().enumerate() {
            let w = self.bary[k];
            if w == 0.0 {
                continue;
            }
            for a in 0..3 {
                let f = w * self.frame[a];
                if f == 0.0 {
                    continue;
                }
                let r = &phi[(3 * v as usize + a) * m..(3 * v as usize + a + 1) * m];
                for (o, x) in out.iter_mut().zip(r) {
                    *o += f * x;
                }
            }
        }
    }
}

/// The rows of a whole cohort and the clusters they fall in.
#[derive(Debug, Clone)]
pub struct CohortRows {
    /// All rows, scenario by scenario.
    pub rows: Vec<Row>,
    /// Number of scenarios.
    pub scenarios: usize,
    /// Number of clusters.
    pub clusters: usize,
    /// Cluster centres (image frame, mm).
    pub centers: Vec<[f64; 3]>,
}

/// Builds the rows of one scenario from its matches (see [`Match`]) and its measured points in the
/// image frame, appending to `out`. `cluster_of` gives each point's cluster.
pub fn scenario_rows(
    scenario: usize,
    matches: &[Match],
    points_image: &[[f64; 3]],
    cluster_of: impl Fn([f64; 3]) -> usize,
    out: &mut Vec<Row>,
) {
    let used: Vec<&Match> = matches.iter().filter(|m| m.weight > 0.0).collect();
    let wsum: f64 = used.iter().map(|m| m.weight).sum();
    if used.is_empty() || wsum <= 0.0 {
        return;
    }
    let mut cen = [0.0; 3];
    for m in &used {
        for a in 0..3 {
            cen[a] += m.weight * m.anchor[a] / wsum;
        }
    }
    let radius = (used
        .iter()
        .map(|m| m.weight * dist2(m.anchor, cen))
        .sum::<f64>()
        / wsum)
        .sqrt()
        .max(1.0);
    for m in used {
        let y = points_image[m.point];
        let len = dot(m.normal, m.normal).sqrt();
        let frames: Vec<[f64; 3]> = if len > 0.0 {
            vec![m.normal.map(|x| x / len)]
        } else {
            vec![[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
        };
        let d = sub(m.anchor, cen);
        let cluster = cluster_of(y);
        for f in frames {
            // e_k × d for the rotation columns, dotted with the frame.
            let rot = [[0.0, -d[2], d[1]], [d[2], 0.0, -d[0]], [-d[1], d[0], 0.0]]
                .map(|c| dot(c, f) / radius);
            out.push(Row {
                scenario,
                point: m.point,
                cluster,
                frame: f,
                nodes: m.nodes,
                bary: m.bary,
                anchor: m.anchor,
                weight: m.weight,
                b: dot(f, sub(y, m.anchor)),
                rigid: [f[0], f[1], f[2], rot[0], rot[1], rot[2]],
            });
        }
    }
}

/// Deterministic k-means (farthest-point start, 20 Lloyd iterations) of points into `k` spatial
/// blocks; returns the centres.
pub fn cluster_centers(points: &[[f64; 3]], k: usize) -> Vec<[f64; 3]> {
    if points.is_empty() || k == 0 {
        return Vec::new();
    }
    // Farthest-point start from the point nearest the mean.
    let mean = {
        let mut m = [0.0; 3];
        for p in points {
            for a in 0..3 {
                m[a] += p[a] / points.len() as f64;
            }
        }
        m
    };
    let first = (0..points.len())
        .min_by(|&a, &b| dist2(points[a], mean).total_cmp(&dist2(points[b], mean)))
        .unwrap_or(0);
    let mut centers = vec![points[first]];
    let mut d: Vec<f64> = points.iter().map(|p| dist2(*p, centers[0])).collect();
    while centers.len() < k {
        let (i, &best) = d
            .iter()
            .enumerate()
            .max_by(|a, b| a.1.total_cmp(b.1))
            .expect("points is not empty");
        if best <= 0.0 {
            break;
        }
        centers.push(points[i]);
        for (j, p) in points.iter().enumerate() {
            d[j] = d[j].min(dist2(*p, points[i]));
        }
    }
    for _ in 0..20 {
        let mut sum = vec![[0.0; 3]; centers.len()];
        let mut count = vec![0usize; centers.len()];
        for p in points {
            let c = nearest(&centers, *p);
            count[c] += 1;
            for a in 0..3 {
                sum[c][a] += p[a];
            }
        }
        for (c, s) in centers.iter_mut().zip(sum.iter().zip(&count)) {
            if *s.1 > 0 {
                *c = s.0.map(|x| x / *s.1 as f64);
            }
        }
    }
    centers
}

/// Index of the nearest centre.
pub fn nearest(centers: &[[f64; 3]], p: [f64; 3]) -> usize {
    (0..centers.len())
        .min_by(|&a, &b| dist2(centers[a], p).total_cmp(&dist2(centers[b], p)))
        .unwrap_or(0)
}
