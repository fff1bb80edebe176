//! The sampling behind [`super::simulate`]: surface patches grown over the anterior surface, dart
//! throwing, ultrasound planes and their contour and vessel points, landmarks.

use super::*;
use crate::mesh::vec3::{add, cross, dot, norm, scale, sub};
use crate::phantom::vessels::VesselTree;
use crate::register::anatomy::{AnatomyLabels, Region};
use crate::util::SplitMix64;
use std::cmp::Ordering;
use std::collections::{BinaryHeap, HashMap};

/// A heap entry ordered by smallest distance first, then smallest index.
#[derive(PartialEq)]
pub(super) struct Near(f64, usize);

impl Eq for Near {}

impl Ord for Near {
    fn cmp(&self, other: &Self) -> Ordering {
        other.0.total_cmp(&self.0).then(other.1.cmp(&self.1))
    }
}

impl PartialOrd for Near {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}

/// Grows the visible patch (indices into `anterior`) until its area reaches `areas_goal[0]`,
/// keeping it within `[areas_goal[1], areas_goal[2]]` where one triangle allows.
pub(super) fn grow_patch(
    tris: &[[u32; 3]],
    anterior: &[usize],
    areas: &[f64],
    xyz: &[[f64; 3]],
    [target, lo, hi]: [f64; 3],
    near: Option<[f64; 3]>,
    rng: &mut SplitMix64,
) -> Vec<usize> {
    let m = anterior.len();
    let centroid: Vec<[f64; 3]> = anterior
        .iter()
        .map(|&t| {
            let p = tris[t].map(|v| xyz[v as usize]);
            scale(add(add(p[0], p[1]), p[2]), 1.0 / 3.0)
        })
        .collect();
    // Edge adjacency among anterior triangles.
    let mut edges: Vec<(u32, u32, usize)> = Vec::with_capacity(3 * m);
    for (i, &t) in anterior.iter().enumerate() {
        let v = tris[t];
        for k in 0..3 {
            let (a, b) = (v[k], v[(k + 1) % 3]);
            edges.push((a.min(b), a.max(b), i));
        }
    }
    edges.sort_unstable();
    let mut adj: Vec<Vec<usize>> = vec![Vec::new(); m];
    let mut s = 0;
    while s < edges.len() {
        let mut e = s + 1;
        while e < edges.len() && edges[e].0 == edges[s].0 && edges[e].1 == edges[s].1 {
            e += 1;
        }
        for x in s..e {
            for y in s..e {
                if x != y {
                    adj[edges[x].2].push(edges[y].2);
                }
            }
        }
        s = e;
    }
    // Area-weighted seed triangle.
    let total: f64 = areas.iter().sum();
    let mut u = rng.next_f64() * total;
    let mut seed = m - 1;
    for (i, &a) in areas.iter().enumerate() {
        if u < a {
            seed = i;
            break;
        }
        u -= a;
    }
    // Or the triangle nearest a given point (a tool's contact: the camera looks there).
    if let Some(q) = near {
        seed = (0..m)
            .min_by(|&a, &b| {
                norm(sub(centroid[a], q))
                    .total_cmp(&norm(sub(centroid[b], q)))
                    .then(a.cmp(&b))
            })
            .unwrap_or(seed);
    }
    let mut dist = vec![f64::INFINITY; m];
    let mut done = vec![false; m];
    let mut heap = BinaryHeap::new();
    dist[seed] = 0.0;
    heap.push(Near(0.0, seed));
    let mut patch = Vec::new();
    let mut area = 0.0;
    while area < target && patch.len() < m {
        let Some(Near(d, i)) = heap.pop() else {
            // Component exhausted: jump to the nearest unvisited anterior triangle.
            let c = centroid[seed];
            let j = (0..m)
                .filter(|&j| !done[j])
                .min_by(|&a, &b| {
                    norm(sub(centroid[a], c))
                        .total_cmp(&norm(sub(centroid[b], c)))
                        .then(a.cmp(&b))
                })
                .expect("patch smaller than the anterior surface");
            dist[j] = norm(sub(centroid[j], c));
            heap.push(Near(dist[j], j));
            continue;
        };
        if done[i] || d > dist[i] {
            continue;
        }
        done[i] = true;
        patch.push(i);
        area += areas[i];
        for &j in &adj[i] {
            let nd = d + norm(sub(centroid[j], centroid[i]));
            if !done[j] && nd < dist[j] {
                dist[j] = nd;
                heap.push(Near(nd, j));
            }
        }
    }
    if area > hi && patch.len() > 1 {
        let last = areas[*patch.last().unwrap()];
        if area - last >= lo {
            patch.pop();
        }
    }
    patch
}

/// Poisson-disk points on triangles: area-weighted candidates kept when no kept point is nearer
/// than `spacing`.
pub(super) fn dart_throw(
    tris: &[[[f64; 3]; 3]],
    areas: &[f64],
    spacing: f64,
    rng: &mut SplitMix64,
) -> Vec<[f64; 3]> {
    let total: f64 = areas.iter().sum();
    if tris.is_empty() || total.is_nan() || total <= 0.0 {
        return Vec::new();
    }
    let mut cdf = Vec::with_capacity(areas.len());
    let mut acc = 0.0;
    for &a in areas {
        acc += a;
        cdf.push(acc);
    }
    let candidates = ((10.0 * total / (spacing * spacing)).ceil() as usize).clamp(1, 2_000_000);
    let cell = |p: [f64; 3]| p.map(|c| (c / spacing).floor() as i64);
    let mut grid: HashMap<[i64; 3], Vec<usize>> = HashMap::new();
    let mut kept: Vec<[f64; 3]> = Vec::new();
    for _ in 0..candidates {
        let u = rng.next_f64() * total;
        let t = cdf.partition_point(|&c| c <= u).min(tris.len() - 1);
        let r1 = rng.next_f64().sqrt();
        let r2 = rng.next_f64();
        let [a, b, c] = tris[t];
        let p = add(
            add(scale(a, 1.0 - r1), scale(b, r1 * (1.0 - r2))),
            scale(c, r1 * r2),
        );
        let g = cell(p);
        let mut free = true;
        'search: for dx in -1..=1 {
            for dy in -1..=1 {
                for dz in -1..=1 {
                    if let Some(list) = grid.get(&[g[0] + dx, g[1] + dy, g[2] + dz]) {
                        if list.iter().any(|&k| norm(sub(kept[k], p)) < spacing) {
                            free = false;
                            break 'search;
                        }
                    }
                }
            }
        }
        if free {
            grid.entry(g).or_default().push(kept.len());
            kept.push(p);
        }
    }
    kept
}

/// Probe contacts: `count` anterior nodes spread by farthest-point sampling from a random start,
/// among nodes touching only anterior triangles (all anterior nodes when there are none).
pub(super) fn spread_contacts(
    tris: &[[u32; 3]],
    anterior: &[usize],
    xyz: &[[f64; 3]],
    count: usize,
    rng: &mut SplitMix64,
) -> Vec<u32> {
    let mut in_anterior = vec![false; xyz.len()];
    let mut elsewhere = vec![false; xyz.len()];
    let mut is_ant_tri = vec![false; tris.len()];
    for &t in anterior {
        is_ant_tri[t] = true;
        for &v in &tris[t] {
            in_anterior[v as usize] = true;
        }
    }
    for (t, tri) in tris.iter().enumerate() {
        if !is_ant_tri[t] {
            for &v in tri {
                elsewhere[v as usize] = true;
            }
        }
    }
    let mut cand: Vec<u32> = (0..xyz.len() as u32)
        .filter(|&v| in_anterior[v as usize] && !elsewhere[v as usize])
        .collect();
    if cand.is_empty() {
        cand = (0..xyz.len() as u32)
            .filter(|&v| in_anterior[v as usize])
            .collect();
    }
    let mut chosen = vec![cand[rng.below(cand.len())]];
    let mut near: Vec<f64> = cand
        .iter()
        .map(|&v| norm(sub(xyz[v as usize], xyz[chosen[0] as usize])))
        .collect();
    while chosen.len() < count {
        let (k, _) =
            near.iter().enumerate().fold(
                (0, f64::NEG_INFINITY),
                |b, (k, &d)| if d > b.1 { (k, d) } else { b },
            );
        let v = cand[k];
        chosen.push(v);
        for (i, &w) in cand.iter().enumerate() {
            near[i] = near[i].min(norm(sub(xyz[w as usize], xyz[v as usize])));
        }
    }
    chosen
}

/// Two unit vectors completing `d` (unit) to an orthonormal basis.
pub(super) fn tangent_basis(d: [f64; 3]) -> ([f64; 3], [f64; 3]) {
    let helper = if d[0].abs() < 0.9 {
        [1.0, 0.0, 0.0]
    } else {
        [0.0, 1.0, 0.0]
    };
    let t1 = cross(d, helper);
    let t1 = scale(t1, 1.0 / norm(t1));
    (t1, cross(d, t1))
}

/// A uniformly random unit vector.
pub(super) fn unit_sphere(rng: &mut SplitMix64) -> [f64; 3] {
    let z = 2.0 * rng.next_f64() - 1.0;
    let phi = 2.0 * std::f64::consts::PI * rng.next_f64();
    let r = (1.0 - z * z).max(0.0).sqrt();
    [r * phi.cos(), r * phi.sin(), z]
}

/// `q` moved onto the plane along its normal (removes rounding only).
pub(super) fn project(pl: &UsPlane, q: [f64; 3]) -> [f64; 3] {
    sub(q, scale(pl.normal, dot(pl.normal, sub(q, pl.origin))))
}

/// Noise-free contour points: the plane's cut through the posterior triangles, chained into
/// polylines and sampled every `us_spacing_mm` of arc length (random phase per polyline), inside
/// the fan.
pub(super) fn contour_points(
    tris: &[[u32; 3]],
    posterior: &[usize],
    xyz: &[[f64; 3]],
    pl: &UsPlane,
    params: &MeasureParams,
    rng: &mut SplitMix64,
) -> Vec<[f64; 3]> {
    let side = |v: u32| dot(pl.normal, sub(xyz[v as usize], pl.origin));
    // Crossing edges (keyed by their sorted nodes) and the triangles linking them.
    let mut key_id: HashMap<(u32, u32), usize> = HashMap::new();
    let mut keys: Vec<(u32, u32)> = Vec::new();
    let mut links: Vec<[usize; 2]> = Vec::new();
    for &t in posterior {
        let v = tris[t];
        let s = v.map(side);
        let mut ends = Vec::with_capacity(2);
        for k in 0..3 {
            let (a, b) = (k, (k + 1) % 3);
            if (s[a] >= 0.0) != (s[b] >= 0.0) {
                let key = (v[a].min(v[b]), v[a].max(v[b]));
                let id = *key_id.entry(key).or_insert_with(|| {
                    keys.push(key);
                    keys.len() - 1
                });
                ends.push(id);
            }
        }
        if ends.len() == 2 {
            links.push([ends[0], ends[1]]);
        }
    }
    let point = |(a, b): (u32, u32)| {
        let (sa, sb) = (side(a), side(b));
        let t = sa / (sa - sb);
        let (pa, pb) = (xyz[a as usize], xyz[b as usize]);
        project(pl, add(pa, scale(sub(pb, pa), t)))
    };
    let pts: Vec<[f64; 3]> = keys.iter().map(|&k| point(k)).collect();
    let mut at: Vec<Vec<usize>> = vec![Vec::new(); keys.len()];
    for (l, e) in links.iter().enumerate() {
        at[e[0]].push(l);
        at[e[1]].push(l);
    }
    // Walk polylines, open ones (from an end) first, in key order for determinism.
    let mut order: Vec<usize> = (0..keys.len()).collect();
    order.sort_by_key(|&i| (at[i].len() == 2, keys[i]));
    let mut used = vec![false; links.len()];
    let mut out = Vec::new();
    let spacing = params.us_spacing_mm;
    for &start in &order {
        while at[start].iter().any(|&l| !used[l]) {
            let mut path = vec![start];
            let mut cur = start;
            while let Some(&l) = at[cur].iter().find(|&&l| !used[l]) {
                used[l] = true;
                cur = if links[l][0] == cur {
                    links[l][1]
                } else {
                    links[l][0]
                };
                path.push(cur);
            }
            let mut next = spacing * rng.next_f64();
            let mut acc = 0.0;
            for w in path.windows(2) {
                let (a, b) = (pts[w[0]], pts[w[1]]);
                let len = norm(sub(b, a));
                if len.is_nan() || len <= 0.0 {
                    continue;
                }
                while next <= acc + len {
                    let q = project(pl, add(a, scale(sub(b, a), (next - acc) / len)));
                    if pl.in_fan(q, params.fan_depth_mm, params.fan_half_angle_deg) {
                        out.push(q);
                    }
                    next += spacing;
                }
                acc += len;
            }
        }
    }
    out
}

/// Noise-free vessel features: where deformed centerline segments cross the plane, inside the fan.
pub(super) fn vessel_points(
    vessels: &VesselTree,
    deformed: &[[f64; 3]],
    pl: &UsPlane,
    params: &MeasureParams,
) -> Vec<[f64; 3]> {
    let mut out = Vec::new();
    for s in &vessels.segments {
        let (pa, pb) = (deformed[s[0] as usize], deformed[s[1] as usize]);
        let (sa, sb) = (
            dot(pl.normal, sub(pa, pl.origin)),
            dot(pl.normal, sub(pb, pl.origin)),
        );
        if (sa >= 0.0) == (sb >= 0.0) {
            continue;
        }
        let q = project(pl, add(pa, scale(sub(pb, pa), sa / (sa - sb))));
        if pl.in_fan(q, params.fan_depth_mm, params.fan_half_angle_deg) {
            out.push(q);
        }
    }
    out
}

/// Landmark nodes: highest falciform node, lateral ends of the inferior ridge, the ridge node
/// nearest the falciform plane; then farthest-point anterior nodes up to `count`.
pub(super) fn choose_landmarks(
    xyz: &[[f64; 3]],
    labels: &AnatomyLabels,
    count: usize,
    rng: &mut SplitMix64,
) -> Vec<u32> {
    let mut chosen: Vec<u32> = Vec::new();
    let push = |v: Option<u32>, chosen: &mut Vec<u32>| {
        if let Some(v) = v {
            if !chosen.contains(&v) {
                chosen.push(v);
            }
        }
    };
    let fal = AnatomyLabels::nodes_where(&labels.falciform);
    let ridge = AnatomyLabels::nodes_where(&labels.inferior_ridge);
    let by = |set: &[u32], key: &dyn Fn(u32) -> f64| -> Option<u32> {
        set.iter()
            .copied()
            .min_by(|&a, &b| key(a).total_cmp(&key(b)).then(a.cmp(&b)))
    };
    push(by(&fal, &|v| -xyz[v as usize][2]), &mut chosen);
    push(by(&ridge, &|v| xyz[v as usize][0]), &mut chosen);
    push(by(&ridge, &|v| -xyz[v as usize][0]), &mut chosen);
    if !fal.is_empty() {
        let xf = fal.iter().map(|&v| xyz[v as usize][0]).sum::<f64>() / fal.len() as f64;
        push(
            by(&ridge, &|v| (xyz[v as usize][0] - xf).abs()),
            &mut chosen,
        );
    }
    chosen.truncate(count);
    let anterior = (0..xyz.len() as u32)
        .filter(|&v| labels.region[v as usize] == Region::Anterior)
        .collect::<Vec<_>>();
    if anterior.is_empty() {
        return chosen;
    }
    if chosen.is_empty() {
        chosen.push(anterior[rng.below(anterior.len())]);
    }
    while chosen.len() < count && chosen.len() < anterior.len() {
        let far = anterior
            .iter()
            .copied()
            .filter(|v| !chosen.contains(v))
            .map(|v| {
                let d = chosen
                    .iter()
                    .map(|&c| norm(sub(xyz[v as usize], xyz[c as usize])))
                    .fold(f64::INFINITY, f64::min);
                (v, d)
            })
            .fold(None::<(u32, f64)>, |b, x| match b {
                Some(b) if b.1 >= x.1 => Some(b),
                _ => Some(x),
            });
        match far {
            Some((v, _)) => chosen.push(v),
            None => break,
        }
    }
    chosen
}
