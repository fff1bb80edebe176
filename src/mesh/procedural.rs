//! Procedural test meshes (boxes), so tests and benchmarks need no binary fixtures.

use super::{TetMesh, TriSurface};

/// The unit cube `[0, 1]³` as 12 outward triangles on 8 vertices.
pub fn unit_cube_surface() -> TriSurface {
    let nodes = (0..8)
        .map(|i| [(i & 1) as f64, ((i >> 1) & 1) as f64, ((i >> 2) & 1) as f64])
        .collect();
    let quads = [
        [0, 2, 3, 1],
        [4, 5, 7, 6],
        [0, 1, 5, 4],
        [2, 6, 7, 3],
        [0, 4, 6, 2],
        [1, 3, 7, 5],
    ];
    let triangles = quads
        .iter()
        .flat_map(|q| [[q[0], q[1], q[2]], [q[0], q[2], q[3]]])
        .collect();
    TriSurface::new_unchecked(nodes, triangles)
}

/// A box `[0, size]` split into `divisions` cubes per axis, each cut into 6 tets around its main
/// diagonal (Kuhn subdivision, conforming). Interior nodes are moved by up to `jitter · h / 2` per
/// axis with a fixed pseudo-random sequence so the tets are irregular but still positive.
pub fn box_mesh(size: [f64; 3], divisions: [usize; 3], jitter: f64) -> TetMesh {
    let [nx, ny, nz] = divisions.map(|d| d.max(1));
    let h = [
        size[0] / nx as f64,
        size[1] / ny as f64,
        size[2] / nz as f64,
    ];
    let id = |i: usize, j: usize, k: usize| (i + (nx + 1) * (j + (ny + 1) * k)) as u32;
    let mut rng = crate::util::SplitMix64::new(0x5eed);
    let mut nodes = Vec::with_capacity((nx + 1) * (ny + 1) * (nz + 1));
    for k in 0..=nz {
        for j in 0..=ny {
            for i in 0..=nx {
                let mut p = [i as f64 * h[0], j as f64 * h[1], k as f64 * h[2]];
                let interior = [(i, nx), (j, ny), (k, nz)];
                for (a, &(c, n)) in interior.iter().enumerate() {
                    let r = rng.next_f64() - 0.5;
                    if c > 0 && c < n {
                        p[a] += jitter * h[a] * r;
                    }
                }
                nodes.push(p);
            }
        }
    }
    const PERMS: [[usize; 3]; 6] = [
        [0, 1, 2],
        [0, 2, 1],
        [1, 0, 2],
        [1, 2, 0],
        [2, 0, 1],
        [2, 1, 0],
    ];
    let mut tets = Vec::with_capacity(6 * nx * ny * nz);
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                let corner = |o: [usize; 3]| id(i + o[0], j + o[1], k + o[2]);
                for perm in PERMS {
                    let mut o = [0usize; 3];
                    let v0 = corner(o);
                    o[perm[0]] = 1;
                    let v1 = corner(o);
                    o[perm[1]] = 1;
                    let v2 = corner(o);
                    let v3 = corner([1, 1, 1]);
                    tets.push([v0, v1, v2, v3]);
                }
            }
        }
    }
    let mut mesh = TetMesh::new(nodes, tets).expect("box mesh indices are in range");
    mesh.orient_positive();
    mesh
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn box_volume_counts_and_boundary() {
        let m = box_mesh([2.0, 3.0, 4.0], [2, 3, 4], 0.2);
        assert_eq!(m.num_nodes(), 3 * 4 * 5);
        assert_eq!(m.num_tets(), 6 * 24);
        assert!((m.volume() - 24.0).abs() < 1e-12);
        m.validate().unwrap();
        let s = m.boundary_surface().unwrap();
        let st = s.stats();
        assert!(st.closed && st.consistently_oriented);
        assert_eq!(st.genus, 0);
        assert!((st.signed_volume_mm3 - 24.0).abs() < 1e-12);
        // boundary of a 2x3x4 grid: 2 triangles per boundary square
        assert_eq!(st.triangles, 2 * 2 * (2 * 3 + 3 * 4 + 2 * 4));
    }
}
