//! Triangle surfaces: areas, normals, enclosed volume, closedness, orientation, genus, components.

use super::io::MeshFile;
use super::union_find::UnionFind;
use super::vec3::bounding_box;
use super::vec3::{add, cross, dot, norm, scale, sub};

/// A triangle surface in millimetres (vertices may include ones no triangle uses).
#[derive(Debug, Clone, PartialEq)]
pub struct TriSurface {
    nodes: Vec<[f64; 3]>,
    triangles: Vec<[u32; 3]>,
}

/// Topological and geometric facts about a surface (see [`TriSurface::stats`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct SurfaceStats {
    /// Vertices used by at least one triangle.
    pub vertices: usize,
    /// Triangles.
    pub triangles: usize,
    /// Unique undirected edges.
    pub edges: usize,
    /// Edges with exactly one triangle (holes).
    pub boundary_edges: usize,
    /// Edges with more than two triangles.
    pub nonmanifold_edges: usize,
    /// Interior edges whose two triangles traverse them in the same direction (orientation flips).
    pub misoriented_edges: usize,
    /// Vertex-connected components.
    pub components: usize,
    /// True when every edge has exactly two triangles (watertight, manifold).
    pub closed: bool,
    /// True when neighbouring triangles are consistently oriented.
    pub consistently_oriented: bool,
    /// Euler characteristic V − E + F.
    pub euler_characteristic: i64,
    /// Total genus `(2·components − χ) / 2` (meaningful when closed).
    pub genus: i64,
    /// Enclosed signed volume in mm³ (positive when faces point outward; meaningful when closed).
    pub signed_volume_mm3: f64,
    /// Total area in mm².
    pub area_mm2: f64,
}

/// A problem with a triangle surface; each names the vertex or triangle and what a usable surface
/// needs.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SurfaceError {
    /// A vertex coordinate is NaN or infinite.
    #[error("vertex {vertex} has a non-finite coordinate {position:?}")]
    NonFiniteVertex {
        /// Vertex index.
        vertex: usize,
        /// Its coordinates.
        position: [f64; 3],
    },
    /// A triangle refers to a vertex that does not exist.
    #[error(
        "triangle {triangle} refers to vertex {vertex}, but the surface has only {vertices} vertices"
    )]
    IndexOutOfRange {
        /// Triangle index.
        triangle: usize,
        /// The bad vertex index.
        vertex: u32,
        /// Vertex count.
        vertices: usize,
    },
    /// The surface has no triangles.
    #[error("the surface has no triangles")]
    Empty,
    /// The surface does not enclose a volume.
    #[error(
        "the surface is not closed: {boundary_edges} edges have one triangle and {nonmanifold_edges} have more than two; a liver surface must enclose a volume"
    )]
    NotClosed {
        /// Edges with one triangle.
        boundary_edges: usize,
        /// Edges with more than two triangles.
        nonmanifold_edges: usize,
    },
    /// Neighbouring triangles disagree on orientation.
    #[error(
        "the surface is not consistently oriented: {misoriented_edges} edges are traversed the same way by both triangles"
    )]
    Misoriented {
        /// Edges traversed the same way by both of their triangles.
        misoriented_edges: usize,
    },
}

impl SurfaceStats {
    /// Ok when the surface has triangles and every edge has exactly two (it encloses a volume).
    pub fn check_closed(&self) -> Result<(), SurfaceError> {
        if self.triangles == 0 {
            return Err(SurfaceError::Empty);
        }
        if !self.closed {
            return Err(SurfaceError::NotClosed {
                boundary_edges: self.boundary_edges,
                nonmanifold_edges: self.nonmanifold_edges,
            });
        }
        Ok(())
    }
}

impl TriSurface {
    /// Builds a surface after checking indices and coordinates.
    pub fn new(nodes: Vec<[f64; 3]>, triangles: Vec<[u32; 3]>) -> Result<Self, SurfaceError> {
        if let Some((i, p)) = nodes
            .iter()
            .enumerate()
            .find(|(_, p)| p.iter().any(|c| !c.is_finite()))
        {
            return Err(SurfaceError::NonFiniteVertex {
                vertex: i,
                position: *p,
            });
        }
        let n = nodes.len();
        for (t, tri) in triangles.iter().enumerate() {
            if let Some(&v) = tri.iter().find(|&&v| v as usize >= n) {
                return Err(SurfaceError::IndexOutOfRange {
                    triangle: t,
                    vertex: v,
                    vertices: n,
                });
            }
        }
        Ok(Self { nodes, triangles })
    }

    /// Builds a surface whose indices the caller guarantees to be in range.
    pub(crate) fn new_unchecked(nodes: Vec<[f64; 3]>, triangles: Vec<[u32; 3]>) -> Self {
        Self { nodes, triangles }
    }

    /// Surface from a file's nodes and triangles.
    pub fn from_file(file: &MeshFile) -> Result<Self, SurfaceError> {
        Self::new(file.nodes.clone(), file.triangles.clone())
    }

    /// A file value with this surface's nodes and triangles.
    pub fn to_file(&self) -> MeshFile {
        MeshFile {
            nodes: self.nodes.clone(),
            triangles: self.triangles.clone(),
            ..Default::default()
        }
    }

    /// Vertex coordinates (mm).
    pub fn nodes(&self) -> &[[f64; 3]] {
        &self.nodes
    }

    /// Triangles.
    pub fn triangles(&self) -> &[[u32; 3]] {
        &self.triangles
    }

    fn corners(&self, t: usize) -> [[f64; 3]; 3] {
        let tri = self.triangles[t];
        [
            self.nodes[tri[0] as usize],
            self.nodes[tri[1] as usize],
            self.nodes[tri[2] as usize],
        ]
    }

    /// Area vector of triangle `t`: `(p1−p0)×(p2−p0)/2` (direction = right-hand normal, length = area).
    pub fn area_vector(&self, t: usize) -> [f64; 3] {
        let p = self.corners(t);
        scale(cross(sub(p[1], p[0]), sub(p[2], p[0])), 0.5)
    }

    /// Triangle areas (mm²).
    pub fn triangle_areas(&self) -> Vec<f64> {
        (0..self.triangles.len())
            .map(|t| norm(self.area_vector(t)))
            .collect()
    }

    /// Total area (mm²).
    pub fn area(&self) -> f64 {
        self.triangle_areas().iter().sum()
    }

    /// Area-weighted unit vertex normals (zero for vertices no triangle uses).
    pub fn vertex_normals(&self) -> Vec<[f64; 3]> {
        let mut acc = vec![[0.0; 3]; self.nodes.len()];
        for (t, tri) in self.triangles.iter().enumerate() {
            let a = self.area_vector(t);
            for &v in tri {
                acc[v as usize] = add(acc[v as usize], a);
            }
        }
        for n in &mut acc {
            let l = norm(*n);
            if l > 0.0 {
                *n = scale(*n, 1.0 / l);
            }
        }
        acc
    }

    /// Signed enclosed volume by the divergence theorem (mm³): positive for outward faces.
    pub fn signed_volume(&self) -> f64 {
        (0..self.triangles.len())
            .map(|t| {
                let p = self.corners(t);
                dot(p[0], cross(p[1], p[2])) / 6.0
            })
            .sum()
    }

    /// Axis-aligned bounding box of the vertices used by triangles.
    pub fn bounding_box(&self) -> ([f64; 3], [f64; 3]) {
        let used: Vec<[f64; 3]> = self
            .used_vertices()
            .iter()
            .map(|&v| self.nodes[v as usize])
            .collect();
        bounding_box(&used)
    }

    /// Sorted indices of vertices used by at least one triangle.
    pub fn used_vertices(&self) -> Vec<u32> {
        let mut v: Vec<u32> = self.triangles.iter().flatten().copied().collect();
        v.sort_unstable();
        v.dedup();
        v
    }

    /// Reverses the orientation of every triangle.
    pub fn flip(&mut self) {
        for t in &mut self.triangles {
            t.swap(1, 2);
        }
    }

    /// Vertex-connected components: a component id per triangle and the count.
    pub fn components(&self) -> (Vec<u32>, usize) {
        let mut uf = UnionFind::new(self.nodes.len());
        for t in &self.triangles {
            uf.union(t[0], t[1]);
            uf.union(t[0], t[2]);
        }
        uf.labels(self.triangles.iter().map(|t| t[0]))
    }

    /// A liver surface ready for meshing: the [`largest_component`](Self::largest_component),
    /// oriented outward. Errors when that piece is not closed (it must enclose a volume).
    pub fn largest_closed_outward(&self) -> Result<TriSurface, SurfaceError> {
        let mut surface = self.largest_component();
        surface.stats().check_closed()?;
        if surface.signed_volume() < 0.0 {
            surface.flip();
        }
        Ok(surface)
    }

    /// The component with the most triangles, with unused vertices removed.
    pub fn largest_component(&self) -> TriSurface {
        let (ids, count) = self.components();
        let mut sizes = vec![0usize; count];
        for &c in &ids {
            sizes[c as usize] += 1;
        }
        let best = (0..count)
            .max_by_key(|&c| (sizes[c], usize::MAX - c))
            .unwrap_or(0) as u32;
        let triangles = self
            .triangles
            .iter()
            .zip(&ids)
            .filter(|(_, c)| **c == best)
            .map(|(t, _)| *t)
            .collect();
        TriSurface::new_unchecked(self.nodes.clone(), triangles).compacted()
    }

    /// A copy without vertices no triangle uses (indices renumbered).
    pub fn compacted(&self) -> TriSurface {
        let used = self.used_vertices();
        let mut map = vec![u32::MAX; self.nodes.len()];
        for (new, &old) in used.iter().enumerate() {
            map[old as usize] = new as u32;
        }
        TriSurface {
            nodes: used.iter().map(|&v| self.nodes[v as usize]).collect(),
            triangles: self
                .triangles
                .iter()
                .map(|t| [map[t[0] as usize], map[t[1] as usize], map[t[2] as usize]])
                .collect(),
        }
    }

    /// Topology and geometry summary: closedness, orientation consistency, genus, volume, area.
    pub fn stats(&self) -> SurfaceStats {
        // Directed half-edges keyed by (min, max) with a direction flag.
        let mut half: Vec<(u32, u32, bool)> = Vec::with_capacity(self.triangles.len() * 3);
        for t in &self.triangles {
            for k in 0..3 {
                let (a, b) = (t[k], t[(k + 1) % 3]);
                half.push((a.min(b), a.max(b), a < b));
            }
        }
        half.sort_unstable();
        let (mut edges, mut boundary, mut nonmanifold, mut misoriented) = (0, 0, 0, 0);
        let mut i = 0;
        while i < half.len() {
            let mut j = i + 1;
            while j < half.len() && half[j].0 == half[i].0 && half[j].1 == half[i].1 {
                j += 1;
            }
            edges += 1;
            match j - i {
                1 => boundary += 1,
                2 => {
                    if half[i].2 == half[i + 1].2 {
                        misoriented += 1;
                    }
                }
                _ => nonmanifold += 1,
            }
            i = j;
        }
        let vertices = self.used_vertices().len();
        let components = self.components().1;
        let chi = vertices as i64 - edges as i64 + self.triangles.len() as i64;
        SurfaceStats {
            vertices,
            triangles: self.triangles.len(),
            edges,
            boundary_edges: boundary,
            nonmanifold_edges: nonmanifold,
            misoriented_edges: misoriented,
            components,
            closed: boundary == 0 && nonmanifold == 0,
            consistently_oriented: misoriented == 0,
            euler_characteristic: chi,
            genus: (2 * components as i64 - chi) / 2,
            signed_volume_mm3: self.signed_volume(),
            area_mm2: self.area(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cube() -> TriSurface {
        crate::mesh::procedural::unit_cube_surface()
    }

    #[test]
    fn cube_is_closed_genus_zero_unit_volume() {
        let s = cube().stats();
        assert!(s.closed && s.consistently_oriented);
        assert_eq!((s.vertices, s.edges, s.triangles), (8, 18, 12));
        assert_eq!(s.genus, 0);
        assert!((s.signed_volume_mm3 - 1.0).abs() < 1e-14);
        assert!((s.area_mm2 - 6.0).abs() < 1e-14);
    }

    #[test]
    fn flipped_cube_has_negative_volume_and_normals_point_in() {
        let mut c = cube();
        c.flip();
        assert!((c.signed_volume() + 1.0).abs() < 1e-14);
        let n = c.vertex_normals();
        // vertex 0 at the origin: outward is (-1,-1,-1)/√3; flipped points inward.
        assert!(n[0].iter().all(|&x| (x - 1.0 / 3f64.sqrt()).abs() < 1e-12));
    }

    #[test]
    fn open_surface_and_components() {
        let c = cube();
        let mut tris = c.triangles().to_vec();
        tris.pop();
        let open = TriSurface::new(c.nodes().to_vec(), tris).unwrap().stats();
        assert!(!open.closed);
        assert_eq!(open.boundary_edges, 3);
        // two disjoint cubes: largest component keeps 12 triangles and 8 vertices
        let mut nodes = c.nodes().to_vec();
        nodes.extend(c.nodes().iter().map(|p| [p[0] + 3.0, p[1], p[2]]));
        let mut tris = c.triangles().to_vec();
        tris.extend(c.triangles().iter().take(2).map(|t| t.map(|v| v + 8)));
        let two = TriSurface::new(nodes, tris).unwrap();
        assert_eq!(two.components().1, 2);
        let big = two.largest_component();
        assert_eq!((big.nodes().len(), big.triangles().len()), (8, 12));
    }

    #[test]
    fn rejects_bad_index() {
        assert!(TriSurface::new(vec![[0.0; 3]; 2], vec![[0, 1, 2]]).is_err());
    }
}
