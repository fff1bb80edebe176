//! The graphs SR-GCN convolves over. The mesh graph: every tet edge in both directions, with
//! Cartesian pseudo-coordinates of the preoperative node positions (normalised to [0, 1] over the
//! graph). The bipartite graph: each measured point linked, in both directions, to its `n_top`
//! nearest vertices of the **LIBR-deformed** mesh — what exists in surgery; the paper took them
//! from the ground-truth mesh, which does not. Node indices of the bipartite graph are the mesh
//! vertices `0..V` followed by the points `V..V+P`.

use super::{GcnError, cartesian_pseudo};
use crate::mesh::TetMesh;

/// A directed graph for [`super::SplineGraph`]: edge `e` carries a message from `sources[e]` to
/// `targets[e]` with pseudo-coordinates `pseudo[3e..3e+3]` in [0, 1].
#[derive(Debug, Clone, PartialEq)]
pub struct Graph {
    /// Number of nodes.
    pub num_nodes: usize,
    /// Receiving node of each edge (`edge_index[0]`).
    pub targets: Vec<usize>,
    /// Sending node of each edge (`edge_index[1]`).
    pub sources: Vec<usize>,
    /// Cartesian pseudo-coordinates, 3 per edge.
    pub pseudo: Vec<f64>,
}

impl Graph {
    /// Number of edges.
    pub fn num_edges(&self) -> usize {
        self.targets.len()
    }
}

fn flat(points: &[[f64; 3]]) -> Vec<f64> {
    points.iter().flatten().copied().collect()
}

/// The mesh graph of a tet mesh (both directions of every unique tet edge).
pub fn mesh_graph(mesh: &TetMesh) -> Result<Graph, GcnError> {
    let edges = mesh.edges();
    let mut targets = Vec::with_capacity(2 * edges.len());
    let mut sources = Vec::with_capacity(2 * edges.len());
    for [a, b] in edges {
        targets.extend([a as usize, b as usize]);
        sources.extend([b as usize, a as usize]);
    }
    let pos = flat(mesh.nodes());
    let pseudo = cartesian_pseudo(&pos, 3, &targets, &sources)?;
    Ok(Graph {
        num_nodes: mesh.num_nodes(),
        targets,
        sources,
        pseudo,
    })
}

/// The `n_top` nearest of `vertices` to `p` (ties by the lower index), nearest first.
fn nearest(vertices: &[[f64; 3]], p: [f64; 3], n_top: usize) -> Vec<usize> {
    let d2 = |v: &[f64; 3]| (0..3).map(|k| (v[k] - p[k]).powi(2)).sum::<f64>();
    let mut idx: Vec<(f64, usize)> = vertices
        .iter()
        .enumerate()
        .map(|(i, v)| (d2(v), i))
        .collect();
    let cmp = |a: &(f64, usize), b: &(f64, usize)| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1));
    if n_top < idx.len() {
        idx.select_nth_unstable_by(n_top - 1, cmp);
        idx.truncate(n_top);
    }
    idx.sort_by(cmp);
    idx.into_iter().map(|(_, i)| i).collect()
}

/// The bipartite graph between measured `points` and their `n_top` nearest vertices of the
/// deformed mesh (`deformed`: the LIBR-deformed node positions, same frame as the points).
/// Nodes `0..V` are the vertices, `V..V+P` the points; each link is an edge in both directions.
pub fn bipartite_graph(
    deformed: &[[f64; 3]],
    points: &[[f64; 3]],
    n_top: usize,
) -> Result<Graph, GcnError> {
    let v = deformed.len();
    if n_top == 0 || n_top > v {
        return Err(GcnError::Invalid(format!(
            "n_top = {n_top}: need 1 ≤ n_top ≤ {v} (the mesh's vertices)"
        )));
    }
    if let Some(i) = deformed
        .iter()
        .position(|q| !q.iter().all(|x| x.is_finite()))
    {
        return Err(GcnError::Invalid(format!(
            "deformed vertex {i} is not finite"
        )));
    }
    if let Some(i) = points.iter().position(|q| !q.iter().all(|x| x.is_finite())) {
        return Err(GcnError::Invalid(format!("point {i} is not finite")));
    }
    let mut targets = Vec::with_capacity(2 * n_top * points.len());
    let mut sources = Vec::with_capacity(2 * n_top * points.len());
    for (i, &p) in points.iter().enumerate() {
        for vertex in nearest(deformed, p, n_top) {
            targets.extend([vertex, v + i]);
            sources.extend([v + i, vertex]);
        }
    }
    let mut pos = flat(deformed);
    pos.extend(flat(points));
    let pseudo = cartesian_pseudo(&pos, 3, &targets, &sources)?;
    Ok(Graph {
        num_nodes: v + points.len(),
        targets,
        sources,
        pseudo,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::procedural::box_mesh;
    use std::collections::HashMap;

    #[test]
    fn mesh_graph_has_every_edge_both_ways_with_mirrored_pseudo_coordinates() {
        let mesh = box_mesh([30.0, 20.0, 10.0], [3, 2, 2], 0.2);
        let g = mesh_graph(&mesh).unwrap();
        assert_eq!(g.num_edges(), 2 * mesh.edges().len());
        assert_eq!(g.num_nodes, mesh.num_nodes());
        let mut at: HashMap<(usize, usize), usize> = HashMap::new();
        for e in 0..g.num_edges() {
            assert!(
                at.insert((g.targets[e], g.sources[e]), e).is_none(),
                "duplicate edge"
            );
        }
        let mut extreme = 0f64;
        for e in 0..g.num_edges() {
            let r = at[&(g.sources[e], g.targets[e])];
            for d in 0..3 {
                let (a, b) = (g.pseudo[3 * e + d], g.pseudo[3 * r + d]);
                assert!((0.0..=1.0).contains(&a));
                // The reverse edge's offset is the negative: mirrored about 0.5.
                assert!((a + b - 1.0).abs() < 1e-12, "{a} {b}");
                extreme = extreme.max((a - 0.5).abs());
                // Same sign as the position difference target − source.
                let diff = mesh.nodes()[g.targets[e]][d] - mesh.nodes()[g.sources[e]][d];
                assert!(diff * (a - 0.5) >= 0.0);
            }
        }
        // The largest offset reaches the edge of [0, 1].
        assert!((extreme - 0.5).abs() < 1e-12);
    }

    #[test]
    fn bipartite_links_each_point_to_its_nearest_deformed_vertices() {
        let mesh = box_mesh([30.0, 20.0, 10.0], [3, 2, 2], 0.2);
        // A deformation: the "LIBR-deformed" mesh the points are matched against.
        let deformed: Vec<[f64; 3]> = mesh
            .nodes()
            .iter()
            .map(|p| [p[0] + 0.1 * p[1], p[1], p[2] + 0.05 * p[0]])
            .collect();
        let points = vec![[1.0, 2.0, 3.0], [29.0, 19.0, 11.0], [15.0, -4.0, 5.0]];
        let n_top = 4;
        let g = bipartite_graph(&deformed, &points, n_top).unwrap();
        let v = deformed.len();
        assert_eq!(g.num_nodes, v + points.len());
        assert_eq!(g.num_edges(), 2 * n_top * points.len());
        for (i, p) in points.iter().enumerate() {
            let mut linked: Vec<usize> = (0..g.num_edges())
                .filter(|&e| g.sources[e] == v + i)
                .map(|e| g.targets[e])
                .collect();
            linked.sort();
            // Brute force: sort every vertex by distance.
            let mut all: Vec<(f64, usize)> = deformed
                .iter()
                .enumerate()
                .map(|(k, q)| ((0..3).map(|d| (q[d] - p[d]).powi(2)).sum::<f64>(), k))
                .collect();
            all.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
            let mut want: Vec<usize> = all[..n_top].iter().map(|x| x.1).collect();
            want.sort();
            assert_eq!(linked, want, "point {i}");
            // Every link also runs the other way.
            for &k in &linked {
                assert!((0..g.num_edges()).any(|e| g.sources[e] == k && g.targets[e] == v + i));
            }
        }
        assert!(g.pseudo.iter().all(|x| (0.0..=1.0).contains(x)));
        // Matched against the undeformed mesh, the neighbours of the last point differ.
        let g0 = bipartite_graph(mesh.nodes(), &points, n_top).unwrap();
        assert_ne!(g0.targets, g.targets);
    }

    #[test]
    fn bipartite_inputs_are_checked() {
        let mesh = box_mesh([1.0, 1.0, 1.0], [1, 1, 1], 0.0);
        let nodes = mesh.nodes();
        assert!(bipartite_graph(nodes, &[[0.0; 3]], 0).is_err());
        assert!(bipartite_graph(nodes, &[[0.0; 3]], nodes.len() + 1).is_err());
        assert!(bipartite_graph(nodes, &[[f64::NAN, 0.0, 0.0]], 1).is_err());
        assert_eq!(bipartite_graph(nodes, &[], 1).unwrap().num_edges(), 0);
    }
}
