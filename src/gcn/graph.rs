//! The graphs SR-GCN convolves over. The mesh graph: every tet edge in both directions, with
//! Cartesian pseudo-coordinates of the preoperative node positions (normalised to [0, 1] over the
//! graph). The bipartite graph between measured points and their nearest
//! LIBR-deformed vertices is built with the sample ([`super::sample::SampleData::build`]).

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
}
