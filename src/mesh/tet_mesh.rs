//! The tetrahedral mesh type: construction, validation, topology and geometry.

use super::io::MeshFile;
use super::surface::TriSurface;
use super::union_find::UnionFind;
use super::vec3::{self, bounding_box, tet_signed_volume};
use nalgebra::{Isometry3, Point3};

/// A problem with a tetrahedral mesh; each names the offending tet or node and how to fix it.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MeshError {
    /// The mesh has no nodes or no tetrahedra.
    #[error(
        "mesh has {nodes} nodes and {tets} tetrahedra; a volume mesh needs both (a surface-only file must be tetrahedralized first)"
    )]
    Empty {
        /// Node count.
        nodes: usize,
        /// Tet count.
        tets: usize,
    },
    /// A tet refers to a node that does not exist.
    #[error(
        "tet {tet} refers to node {node}, but the mesh has only {nodes} nodes (0-based indices)"
    )]
    IndexOutOfRange {
        /// Tet index.
        tet: usize,
        /// The bad node index.
        node: u32,
        /// Node count.
        nodes: usize,
    },
    /// A tet uses the same node twice.
    #[error("tet {tet} repeats node {node}: {nodes:?}")]
    RepeatedNode {
        /// Tet index.
        tet: usize,
        /// The repeated node.
        node: u32,
        /// The tet's nodes.
        nodes: [u32; 4],
    },
    /// A node coordinate is NaN or infinite.
    #[error("node {node} has a non-finite coordinate {coords:?}")]
    NonFiniteNode {
        /// Node index.
        node: usize,
        /// Its coordinates.
        coords: [f64; 3],
    },
    /// A tet has (numerically) zero volume.
    #[error(
        "tet {tet} is degenerate: volume {volume:e} mm³ is below {threshold:e} mm³ (flat or collapsed element)"
    )]
    DegenerateTet {
        /// Tet index.
        tet: usize,
        /// Its signed volume in mm³.
        volume: f64,
        /// The threshold used (relative to the tet's longest edge cubed).
        threshold: f64,
    },
    /// A tet has negative orientation.
    #[error(
        "tet {tet} is inverted: signed volume {volume:e} mm³ < 0 (swap two of its nodes, or call TetMesh::orient_positive)"
    )]
    InvertedTet {
        /// Tet index.
        tet: usize,
        /// Its signed volume in mm³.
        volume: f64,
    },
    /// A node is used by no tet.
    #[error("node {node} is used by no tetrahedron (call TetMesh::remove_unused_nodes)")]
    UnusedNode {
        /// Node index.
        node: usize,
    },
    /// Two tets lie on the same side of a shared face (duplicate or overlapping elements).
    #[error(
        "tets {tets:?} overlap: both lie on the same side of their shared face {face:?} (duplicate or tangled elements)"
    )]
    OverlappingTets {
        /// The two tets.
        tets: [usize; 2],
        /// The face's nodes (sorted).
        face: [u32; 3],
    },
    /// More than two tets share a face.
    #[error("face {face:?} is shared by more than two tetrahedra (non-manifold mesh)")]
    NonManifoldFace {
        /// The face's nodes (sorted).
        face: [u32; 3],
    },
}

/// Relative volume below which a tet counts as degenerate: `|V| < DEGENERATE_REL · L_max³`.
pub const DEGENERATE_REL: f64 = 1e-10;

/// A tetrahedral mesh in millimetres with u32 connectivity.
#[derive(Debug, Clone, PartialEq)]
pub struct TetMesh {
    nodes: Vec<[f64; 3]>,
    tets: Vec<[u32; 4]>,
}

/// Boundary faces of a tet mesh, oriented outward, with the tet each belongs to.
#[derive(Debug, Clone)]
pub struct BoundarySurface {
    /// Triangles in global node indices, counter-clockwise seen from outside.
    pub triangles: Vec<[u32; 3]>,
    /// For each triangle, the tet it is a face of.
    pub tet_of_triangle: Vec<u32>,
    /// Sorted unique node indices on the boundary.
    pub nodes: Vec<u32>,
}

/// Node-to-node adjacency (through tet edges) in compressed-row form.
#[derive(Debug, Clone)]
pub struct NodeAdjacency {
    /// `offsets[i]..offsets[i+1]` indexes `neighbors` for node `i`.
    pub offsets: Vec<usize>,
    /// Sorted neighbours of each node (excluding the node itself).
    pub neighbors: Vec<u32>,
}

impl NodeAdjacency {
    /// Neighbours of node `i`.
    pub fn of(&self, i: usize) -> &[u32] {
        &self.neighbors[self.offsets[i]..self.offsets[i + 1]]
    }
}

/// The four outward faces of a positively oriented tet, as local indices.
pub(crate) const TET_FACES: [[usize; 3]; 4] = [[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]];
/// The six edges of a tet, as local index pairs.
pub(crate) const TET_EDGES: [[usize; 2]; 6] = [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]];

impl TetMesh {
    /// Builds a mesh after checking that it is non-empty, every index is in range, no tet repeats a
    /// node and all coordinates are finite. Orientation, degeneracy and unused nodes are checked by
    /// [`TetMesh::validate`].
    pub fn new(nodes: Vec<[f64; 3]>, tets: Vec<[u32; 4]>) -> Result<Self, MeshError> {
        if nodes.is_empty() || tets.is_empty() {
            return Err(MeshError::Empty {
                nodes: nodes.len(),
                tets: tets.len(),
            });
        }
        for (i, p) in nodes.iter().enumerate() {
            if p.iter().any(|c| !c.is_finite()) {
                return Err(MeshError::NonFiniteNode {
                    node: i,
                    coords: *p,
                });
            }
        }
        let n = nodes.len();
        for (t, tet) in tets.iter().enumerate() {
            for (a, &v) in tet.iter().enumerate() {
                if v as usize >= n {
                    return Err(MeshError::IndexOutOfRange {
                        tet: t,
                        node: v,
                        nodes: n,
                    });
                }
                if tet[a + 1..].contains(&v) {
                    return Err(MeshError::RepeatedNode {
                        tet: t,
                        node: v,
                        nodes: *tet,
                    });
                }
            }
        }
        Ok(Self { nodes, tets })
    }

    /// Builds a mesh from a file's nodes and tetrahedra (triangles and other cells are ignored).
    pub fn from_file(file: &MeshFile) -> Result<Self, MeshError> {
        Self::new(file.nodes.clone(), file.tets.clone())
    }

    /// Node coordinates (mm).
    pub fn nodes(&self) -> &[[f64; 3]] {
        &self.nodes
    }

    /// Tetrahedra.
    pub fn tets(&self) -> &[[u32; 4]] {
        &self.tets
    }

    /// Number of nodes.
    pub fn num_nodes(&self) -> usize {
        self.nodes.len()
    }

    /// Number of tetrahedra.
    pub fn num_tets(&self) -> usize {
        self.tets.len()
    }

    /// The four corner coordinates of tet `t`.
    #[inline]
    pub fn tet_points(&self, t: usize) -> [[f64; 3]; 4] {
        let tet = self.tets[t];
        [
            self.nodes[tet[0] as usize],
            self.nodes[tet[1] as usize],
            self.nodes[tet[2] as usize],
            self.nodes[tet[3] as usize],
        ]
    }

    /// Signed volume of tet `t` in mm³ (positive for positive orientation).
    pub fn tet_volume(&self, t: usize) -> f64 {
        tet_signed_volume(&self.tet_points(t))
    }

    /// Signed volumes of all tets (mm³).
    pub fn tet_volumes(&self) -> Vec<f64> {
        (0..self.tets.len()).map(|t| self.tet_volume(t)).collect()
    }

    /// Total volume (sum of signed tet volumes, mm³).
    pub fn volume(&self) -> f64 {
        (0..self.tets.len()).map(|t| self.tet_volume(t)).sum()
    }

    /// Axis-aligned bounding box `(min, max)` in mm.
    pub fn bounding_box(&self) -> ([f64; 3], [f64; 3]) {
        bounding_box(&self.nodes)
    }

    /// All problems, in order: degenerate tets, inverted tets, unused nodes (up to `limit` of them).
    pub fn problems(&self, limit: usize) -> Vec<MeshError> {
        let mut out = Vec::new();
        for t in 0..self.tets.len() {
            if out.len() >= limit {
                return out;
            }
            let p = self.tet_points(t);
            let v = tet_signed_volume(&p);
            let lmax = super::tet_mesh::longest_edge(&p);
            let threshold = DEGENERATE_REL * lmax * lmax * lmax;
            if v.abs() <= threshold {
                out.push(MeshError::DegenerateTet {
                    tet: t,
                    volume: v,
                    threshold,
                });
            } else if v < 0.0 {
                out.push(MeshError::InvertedTet { tet: t, volume: v });
            }
        }
        for (node, used) in self.used_nodes().iter().enumerate() {
            if out.len() >= limit {
                break;
            }
            if !used {
                out.push(MeshError::UnusedNode { node });
            }
        }
        out
    }

    /// Checks orientation, degeneracy and unused nodes; returns the first problem found.
    pub fn validate(&self) -> Result<(), MeshError> {
        match self.problems(1).into_iter().next() {
            Some(e) => Err(e),
            None => Ok(()),
        }
    }

    /// Flips every negatively oriented tet (swaps its last two nodes); returns how many were flipped.
    pub fn orient_positive(&mut self) -> usize {
        let mut flipped = 0;
        for t in 0..self.tets.len() {
            if self.tet_volume(t) < 0.0 {
                self.tets[t].swap(2, 3);
                flipped += 1;
            }
        }
        flipped
    }

    /// For each node, whether some tet uses it.
    pub fn used_nodes(&self) -> Vec<bool> {
        let mut used = vec![false; self.nodes.len()];
        for tet in &self.tets {
            for &v in tet {
                used[v as usize] = true;
            }
        }
        used
    }

    /// Removes nodes no tet uses and renumbers; returns `old_to_new` (`u32::MAX` for removed nodes).
    pub fn remove_unused_nodes(&mut self) -> Vec<u32> {
        let used = self.used_nodes();
        let mut map = vec![u32::MAX; self.nodes.len()];
        let mut nodes = Vec::with_capacity(self.nodes.len());
        for (i, &u) in used.iter().enumerate() {
            if u {
                map[i] = nodes.len() as u32;
                nodes.push(self.nodes[i]);
            }
        }
        for tet in &mut self.tets {
            for v in tet.iter_mut() {
                *v = map[*v as usize];
            }
        }
        self.nodes = nodes;
        map
    }

    /// All tet faces as (sorted node triple, tet, local face), sorted by triple.
    fn sorted_faces(&self) -> Vec<([u32; 3], u32, u8)> {
        let mut faces: Vec<([u32; 3], u32, u8)> = Vec::with_capacity(self.tets.len() * 4);
        for (t, tet) in self.tets.iter().enumerate() {
            for (f, lf) in TET_FACES.iter().enumerate() {
                let mut key = [tet[lf[0]], tet[lf[1]], tet[lf[2]]];
                key.sort_unstable();
                faces.push((key, t as u32, f as u8));
            }
        }
        faces.sort_unstable_by_key(|a| a.0);
        faces
    }

    /// Winding of a tet's outward face relative to its sorted key (true = even permutation),
    /// corrected for the tet's own orientation.
    fn face_winding(&self, t: u32, f: u8) -> bool {
        let tet = self.tets[t as usize];
        let lf = TET_FACES[f as usize];
        let (a, b, c) = (tet[lf[0]], tet[lf[1]], tet[lf[2]]);
        // Even permutation of (min, mid, max) ⇔ even number of inversions.
        let inversions = (a > b) as u8 + (a > c) as u8 + (b > c) as u8;
        let even = inversions % 2 == 0;
        even ^ (self.tet_volume(t as usize) < 0.0)
    }

    /// Boundary faces (faces of exactly one tet), oriented outward for positively oriented tets.
    /// Fails on non-manifold faces (three or more tets) and on two tets lying on the same side of
    /// their shared face (duplicates or tangles).
    pub fn boundary(&self) -> Result<BoundarySurface, MeshError> {
        let faces = self.sorted_faces();
        let mut triangles = Vec::new();
        let mut tet_of_triangle = Vec::new();
        let mut i = 0;
        while i < faces.len() {
            let mut j = i + 1;
            while j < faces.len() && faces[j].0 == faces[i].0 {
                j += 1;
            }
            match j - i {
                1 => {
                    let (_, t, f) = faces[i];
                    let tet = self.tets[t as usize];
                    let lf = TET_FACES[f as usize];
                    triangles.push([tet[lf[0]], tet[lf[1]], tet[lf[2]]]);
                    tet_of_triangle.push(t);
                }
                2 => {
                    let (t1, f1) = (faces[i].1, faces[i].2);
                    let (t2, f2) = (faces[i + 1].1, faces[i + 1].2);
                    if self.face_winding(t1, f1) == self.face_winding(t2, f2) {
                        return Err(MeshError::OverlappingTets {
                            tets: [t1 as usize, t2 as usize],
                            face: faces[i].0,
                        });
                    }
                }
                _ => return Err(MeshError::NonManifoldFace { face: faces[i].0 }),
            }
            i = j;
        }
        let mut nodes: Vec<u32> = triangles.iter().flatten().copied().collect();
        nodes.sort_unstable();
        nodes.dedup();
        Ok(BoundarySurface {
            triangles,
            tet_of_triangle,
            nodes,
        })
    }

    /// Face-connected components (tets sharing a face are connected; tets meeting only at a node
    /// or edge are not, since they can hinge): a component id per tet, and the count.
    pub fn face_components(&self) -> (Vec<u32>, usize) {
        let faces = self.sorted_faces();
        let mut uf = UnionFind::new(self.tets.len());
        for w in faces.windows(2) {
            if w[0].0 == w[1].0 {
                uf.union(w[0].1, w[1].1);
            }
        }
        uf.labels(0..self.tets.len() as u32)
    }

    /// The boundary as a standalone [`TriSurface`] over all mesh nodes (interior nodes unused).
    pub fn boundary_surface(&self) -> Result<TriSurface, MeshError> {
        let b = self.boundary()?;
        Ok(TriSurface::new_unchecked(self.nodes.clone(), b.triangles))
    }

    /// Unique edges `(a, b)` with `a < b`, sorted.
    pub fn edges(&self) -> Vec<[u32; 2]> {
        let mut edges: Vec<[u32; 2]> = Vec::with_capacity(self.tets.len() * 6);
        for tet in &self.tets {
            for e in TET_EDGES {
                let (a, b) = (tet[e[0]], tet[e[1]]);
                edges.push(if a < b { [a, b] } else { [b, a] });
            }
        }
        edges.sort_unstable();
        edges.dedup();
        edges
    }

    /// Node adjacency through tet edges.
    pub fn node_adjacency(&self) -> NodeAdjacency {
        let edges = self.edges();
        let n = self.nodes.len();
        let mut counts = vec![0usize; n + 1];
        for e in &edges {
            counts[e[0] as usize + 1] += 1;
            counts[e[1] as usize + 1] += 1;
        }
        for i in 0..n {
            counts[i + 1] += counts[i];
        }
        let offsets = counts.clone();
        let mut fill = counts;
        let mut neighbors = vec![0u32; edges.len() * 2];
        for e in &edges {
            neighbors[fill[e[0] as usize]] = e[1];
            fill[e[0] as usize] += 1;
            neighbors[fill[e[1] as usize]] = e[0];
            fill[e[1] as usize] += 1;
        }
        for i in 0..n {
            neighbors[offsets[i]..offsets[i + 1]].sort_unstable();
        }
        NodeAdjacency { offsets, neighbors }
    }

    /// For each node, the tets that use it: `(offsets, tets)` in compressed-row form.
    pub fn node_to_tets(&self) -> (Vec<usize>, Vec<u32>) {
        let n = self.nodes.len();
        let mut offsets = vec![0usize; n + 1];
        for tet in &self.tets {
            for &v in tet {
                offsets[v as usize + 1] += 1;
            }
        }
        for i in 0..n {
            offsets[i + 1] += offsets[i];
        }
        let mut fill = offsets.clone();
        let mut out = vec![0u32; offsets[n]];
        for (t, tet) in self.tets.iter().enumerate() {
            for &v in tet {
                out[fill[v as usize]] = t as u32;
                fill[v as usize] += 1;
            }
        }
        (offsets, out)
    }

    /// Connected components (tets sharing a node are connected): a component id per tet, and the
    /// number of components.
    pub fn tet_components(&self) -> (Vec<u32>, usize) {
        let mut uf = UnionFind::new(self.nodes.len());
        for tet in &self.tets {
            uf.union(tet[0], tet[1]);
            uf.union(tet[0], tet[2]);
            uf.union(tet[0], tet[3]);
        }
        uf.labels(self.tets.iter().map(|tet| tet[0]))
    }

    /// Number of connected components.
    pub fn num_components(&self) -> usize {
        self.tet_components().1
    }

    /// Applies a rigid transform to every node.
    pub fn transform(&mut self, iso: &Isometry3<f64>) {
        for p in &mut self.nodes {
            let q = iso.transform_point(&Point3::new(p[0], p[1], p[2]));
            *p = [q.x, q.y, q.z];
        }
    }

    /// Multiplies every coordinate by `factor` (unit change; a negative factor would invert tets and
    /// is rejected by returning `false`).
    pub fn scale(&mut self, factor: f64) -> bool {
        if !(factor.is_finite() && factor > 0.0) {
            return false;
        }
        for p in &mut self.nodes {
            *p = vec3::scale(*p, factor);
        }
        true
    }

    /// A file value with this mesh's nodes and tets and no data arrays.
    pub fn to_file(&self) -> MeshFile {
        MeshFile {
            nodes: self.nodes.clone(),
            tets: self.tets.clone(),
            ..Default::default()
        }
    }
}

/// Longest edge of a tet (mm).
pub fn longest_edge(p: &[[f64; 3]; 4]) -> f64 {
    TET_EDGES
        .iter()
        .map(|e| vec3::norm(vec3::sub(p[e[1]], p[e[0]])))
        .fold(0.0, f64::max)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unit_tet() -> TetMesh {
        TetMesh::new(
            vec![[0., 0., 0.], [1., 0., 0.], [0., 1., 0.], [0., 0., 1.]],
            vec![[0, 1, 2, 3]],
        )
        .unwrap()
    }

    #[test]
    fn unit_tet_volume_and_boundary_outward() {
        let m = unit_tet();
        assert!((m.volume() - 1.0 / 6.0).abs() < 1e-15);
        let s = m.boundary_surface().unwrap();
        assert_eq!(s.triangles().len(), 4);
        assert!((s.signed_volume() - 1.0 / 6.0).abs() < 1e-15);
    }

    #[test]
    fn validation_names_bad_tet() {
        let mut m = TetMesh::new(
            vec![
                [0., 0., 0.],
                [1., 0., 0.],
                [0., 1., 0.],
                [0., 0., 1.],
                [1., 1., 0.],
                [5., 5., 5.],
            ],
            vec![[0, 1, 2, 3], [1, 2, 4, 3], [0, 1, 4, 2]],
        )
        .unwrap();
        // tet 1: det[(−1,1,0),(0,1,0),(−1,0,1)] = −1 → inverted; tet 2 is flat (z = 0).
        let problems = m.problems(10);
        assert!(matches!(problems[0], MeshError::InvertedTet { tet: 1, .. }));
        assert!(matches!(
            problems[1],
            MeshError::DegenerateTet { tet: 2, .. }
        ));
        assert!(matches!(problems[2], MeshError::UnusedNode { node: 5 }));
        assert!(problems[0].to_string().contains("tet 1 is inverted"));
        assert_eq!(m.orient_positive(), 1);
        assert!(m.tet_volume(1) > 0.0);
        let map = m.remove_unused_nodes();
        assert_eq!(map[5], u32::MAX);
        assert_eq!(m.num_nodes(), 5);
    }

    #[test]
    fn constructor_rejects_bad_indices_and_values() {
        let e = TetMesh::new(vec![[0.; 3]; 3], vec![[0, 1, 2, 3]]).unwrap_err();
        assert_eq!(
            e,
            MeshError::IndexOutOfRange {
                tet: 0,
                node: 3,
                nodes: 3
            }
        );
        let e = TetMesh::new(vec![[0.; 3]; 4], vec![[0, 1, 1, 3]]).unwrap_err();
        assert!(matches!(
            e,
            MeshError::RepeatedNode {
                tet: 0,
                node: 1,
                ..
            }
        ));
        let e = TetMesh::new(vec![[0., f64::NAN, 0.]; 4], vec![[0, 1, 2, 3]]).unwrap_err();
        assert!(matches!(e, MeshError::NonFiniteNode { node: 0, .. }));
        assert!(matches!(
            TetMesh::new(vec![], vec![]).unwrap_err(),
            MeshError::Empty { .. }
        ));
    }

    #[test]
    fn components_edges_adjacency() {
        let mut nodes = vec![[0., 0., 0.], [1., 0., 0.], [0., 1., 0.], [0., 0., 1.]];
        nodes.extend(nodes.clone().iter().map(|p| [p[0] + 5., p[1], p[2]]));
        let m = TetMesh::new(nodes, vec![[0, 1, 2, 3], [4, 5, 6, 7]]).unwrap();
        assert_eq!(m.num_components(), 2);
        assert_eq!(m.edges().len(), 12);
        let adj = m.node_adjacency();
        assert_eq!(adj.of(0), &[1, 2, 3]);
        assert_eq!(adj.of(5), &[4, 6, 7]);
    }

    #[test]
    fn duplicate_tets_and_hinges_are_detected() {
        let nodes = vec![
            [0., 0., 0.],
            [1., 0., 0.],
            [0., 1., 0.],
            [0., 0., 1.],
            [1., 1., 1.],
        ];
        let dup = TetMesh::new(nodes.clone(), vec![[0, 1, 2, 3], [0, 1, 2, 3]]).unwrap();
        assert!(matches!(
            dup.boundary().unwrap_err(),
            MeshError::OverlappingTets { tets: [0, 1], .. }
        ));
        // Two tets sharing face (1,2,3) from opposite sides are fine.
        let mut good = TetMesh::new(nodes.clone(), vec![[0, 1, 2, 3], [4, 1, 3, 2]]).unwrap();
        good.orient_positive();
        assert_eq!(good.boundary().unwrap().triangles.len(), 6);
        assert_eq!(good.face_components().1, 1);
        // Sharing only node 0: one node-connected component, two face-connected parts.
        let mut nodes2 = nodes;
        nodes2.extend([[-1., 0., 0.], [0., -1., 0.], [0., 0., -1.]]);
        let hinge = TetMesh::new(nodes2, vec![[0, 1, 2, 3], [0, 5, 7, 6]]).unwrap();
        assert_eq!(hinge.num_components(), 1);
        assert_eq!(hinge.face_components().1, 2);
    }

    #[test]
    fn rigid_transform_preserves_volume() {
        let mut m = unit_tet();
        let iso = Isometry3::new(
            nalgebra::Vector3::new(1.0, -2.0, 3.0),
            nalgebra::Vector3::new(0.3, 0.2, -0.1),
        );
        m.transform(&iso);
        assert!((m.volume() - 1.0 / 6.0).abs() < 1e-14);
        assert!(m.scale(10.0));
        assert!((m.volume() - 1000.0 / 6.0).abs() < 1e-10);
        assert!(!m.scale(-1.0));
    }
}
