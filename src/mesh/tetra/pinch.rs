//! Pinch repair of a stuffed mesh: pinched vertices unzipped into one copy per fan of
//! tetrahedra, pinched edges closed by one well-shaped tetrahedron (step 6 of the mesher).

use super::*;
use crate::mesh::tet_mesh::TET_FACES;
use crate::mesh::vec3::{cross, dot, sub, tet_signed_volume};
use crate::mesh::{TetMesh, quality};

/// Labels of face-connected groups among `tets` (indices into `all`), where two tets are joined
/// when they share a key from `keys` (a face through the pinch candidate); labels in first-seen order.
pub(super) fn groups(tets: &[u32], keys: impl Fn(u32, &mut Vec<u64>)) -> Vec<usize> {
    let mut pairs: Vec<(u64, usize)> = Vec::with_capacity(tets.len() * 3);
    let mut buf = Vec::with_capacity(3);
    for (i, &t) in tets.iter().enumerate() {
        buf.clear();
        keys(t, &mut buf);
        pairs.extend(buf.iter().map(|&k| (k, i)));
    }
    pairs.sort_unstable();
    let mut parent: Vec<usize> = (0..tets.len()).collect();
    pub(super) fn root(parent: &mut [usize], mut x: usize) -> usize {
        while parent[x] != x {
            parent[x] = parent[parent[x]];
            x = parent[x];
        }
        x
    }
    for w in pairs.windows(2) {
        if w[0].0 == w[1].0 {
            let (a, b) = (root(&mut parent, w[0].1), root(&mut parent, w[1].1));
            if a != b {
                parent[a.max(b)] = a.min(b);
            }
        }
    }
    let mut label_of_root = vec![usize::MAX; tets.len()];
    let mut next = 0;
    (0..tets.len())
        .map(|i| {
            let r = root(&mut parent, i);
            if label_of_root[r] == usize::MAX {
                label_of_root[r] = next;
                next += 1;
            }
            label_of_root[r]
        })
        .collect()
}

/// What [`repair_pinches`] did.
#[derive(Debug, Default, Clone, Copy)]
pub(super) struct PinchRepair {
    pub(super) copies: usize,
    pub(super) fills: usize,
    pub(super) left: usize,
    pub(super) left_vertices: usize,
}

/// Smallest dihedral angle accepted for a tetrahedron that closes a pinched edge (the paper's bound
/// for the default warp thresholds).
pub(super) const FILL_MIN_DIHEDRAL: f64 = 8.9;

/// Repairs pinches — places where the shape is thinner than the lattice and two parts of the mesh
/// touch (stuffing warps the vertices between them onto both sides of the surface):
///
/// * a boundary vertex whose tets fall into several fans (face-connected through faces at the
///   vertex) gets a copy, at the same position, for every fan but the largest, which keeps the
///   parts apart as they are in the surface and changes no position, volume or angle;
/// * an edge still shared by more than two boundary triangles (its fans meet again around both
///   ends) is closed by one tetrahedron spanning the edge and the far corners of two boundary
///   triangles of different fans, in the gap between them;
///
/// The added tetrahedra have only surface nodes and are accepted only with dihedral angles of at
/// least [`FILL_MIN_DIHEDRAL`]. Rounds repeat until nothing changes (at most 8). A vertex where
/// the outside touches itself while its tets form one ring is left and counted
/// ([`count_pinched_vertices`]).
pub(super) fn repair_pinches(mesh: &mut TetMesh) -> Result<PinchRepair, TetraError> {
    let internal = |e: crate::mesh::MeshError| TetraError::Internal(e.to_string());
    let mut done = PinchRepair::default();
    for _round in 0..8 {
        let b = mesh.boundary().map_err(internal)?;
        let (offsets, incident) = mesh.node_to_tets();
        let mut tets = mesh.tets().to_vec();
        let mut nodes = mesh.nodes().to_vec();
        let mut changed = false;
        for &v in &b.nodes {
            let fan = &incident[offsets[v as usize]..offsets[v as usize + 1]];
            let labels = groups(fan, |t, out| {
                // The three faces through v, keyed by their other two nodes.
                let tet = tets[t as usize];
                for (i, j) in [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)] {
                    let (x, y) = (tet[i], tet[j]);
                    if x != v && y != v {
                        out.push(((x.min(y) as u64) << 32) | x.max(y) as u64);
                    }
                }
            });
            let count = labels.iter().copied().max().map_or(0, |m| m + 1);
            if count < 2 {
                continue;
            }
            let mut sizes = vec![0usize; count];
            for &l in &labels {
                sizes[l] += 1;
            }
            let keep = (0..count)
                .max_by_key(|&c| (sizes[c], usize::MAX - c))
                .unwrap_or(0);
            let mut copy_of = vec![u32::MAX; count];
            for (&t, &l) in fan.iter().zip(&labels) {
                if l == keep {
                    continue;
                }
                if copy_of[l] == u32::MAX {
                    copy_of[l] = nodes.len() as u32;
                    nodes.push(nodes[v as usize]);
                    done.copies += 1;
                }
                for x in tets[t as usize].iter_mut() {
                    if *x == v {
                        *x = copy_of[l];
                    }
                }
            }
            changed = true;
        }
        if !changed {
            let fills = accept_fills(mesh, pinch_fills(mesh, &b, &incident, &offsets));
            done.left = count_pinched_edges(&b) - fills.len();
            done.left_vertices = count_pinched_vertices(&b);
            if fills.is_empty() {
                return Ok(done);
            }
            done.fills += fills.len();
            tets.extend(fills);
        }
        *mesh = TetMesh::new(nodes, tets).map_err(internal)?;
    }
    let b = mesh.boundary().map_err(internal)?;
    done.left = count_pinched_edges(&b);
    done.left_vertices = count_pinched_vertices(&b);
    Ok(done)
}

/// Keeps the closing tetrahedra that fit together: in plan order, a fill is dropped when it repeats
/// one already kept (two pinched edges of one gap can propose the same tetrahedron) or when one of
/// its faces would then be shared by more than two tetrahedra.
pub(super) fn accept_fills(mesh: &TetMesh, fills: Vec<[u32; 4]>) -> Vec<[u32; 4]> {
    use std::collections::HashMap;
    let key = |mut f: [u32; 3]| {
        f.sort_unstable();
        f
    };
    let faces_of = |t: &[u32; 4]| TET_FACES.map(|f| key([t[f[0]], t[f[1]], t[f[2]]]));
    let touched: std::collections::HashSet<u32> = fills.iter().flatten().copied().collect();
    let mut count: HashMap<[u32; 3], usize> = HashMap::new();
    for t in mesh.tets() {
        if t.iter().filter(|v| touched.contains(v)).count() >= 3 {
            for f in faces_of(t) {
                *count.entry(f).or_default() += 1;
            }
        }
    }
    let mut kept: Vec<[u32; 4]> = Vec::new();
    let mut seen = std::collections::HashSet::new();
    for t in fills {
        let mut sorted = t;
        sorted.sort_unstable();
        if !seen.insert(sorted) {
            continue;
        }
        let faces = faces_of(&t);
        if faces
            .iter()
            .any(|f| count.get(f).copied().unwrap_or(0) >= 2)
        {
            continue;
        }
        for f in faces {
            *count.entry(f).or_default() += 1;
        }
        kept.push(t);
    }
    kept
}

/// Boundary vertices whose boundary triangles form more than one fan (their far edges form more
/// than one connected piece): the outside touches itself there, e.g. a crevice of the surface
/// closed off at that vertex at this lattice size. Vertex copies cannot separate such a vertex
/// (its tets form one ring) and no single tetrahedron closes it safely, so it is only counted.
pub(super) fn count_pinched_vertices(b: &crate::mesh::BoundarySurface) -> usize {
    let mut at: Vec<(u32, usize)> = b
        .triangles
        .iter()
        .enumerate()
        .flat_map(|(i, t)| t.iter().map(move |&v| (v, i)))
        .collect();
    at.sort_unstable();
    let mut pinched = 0;
    for run in at.chunk_by(|x, y| x.0 == y.0) {
        let v = run[0].0;
        let link: Vec<(u32, u32)> = run
            .iter()
            .map(|&(_, i)| {
                let t = b.triangles[i];
                let k = t.iter().position(|&x| x == v).unwrap_or(0);
                (t[(k + 1) % 3], t[(k + 2) % 3])
            })
            .collect();
        let mut verts: Vec<u32> = link.iter().flat_map(|&(x, y)| [x, y]).collect();
        verts.sort_unstable();
        verts.dedup();
        let idx = |x: u32| verts.binary_search(&x).unwrap_or(0);
        let mut parent: Vec<usize> = (0..verts.len()).collect();
        fn root(parent: &mut [usize], mut x: usize) -> usize {
            while parent[x] != x {
                parent[x] = parent[parent[x]];
                x = parent[x];
            }
            x
        }
        let mut pieces = verts.len();
        for &(x, y) in &link {
            let (rx, ry) = (root(&mut parent, idx(x)), root(&mut parent, idx(y)));
            if rx != ry {
                parent[rx.max(ry)] = rx.min(ry);
                pieces -= 1;
            }
        }
        if pieces > 1 {
            pinched += 1;
        }
    }
    pinched
}

/// For every boundary edge in more than two boundary triangles, the best closing tetrahedron (see
/// [`repair_pinches`]), positively oriented; edges without an acceptable one are left.
pub(super) fn pinch_fills(
    mesh: &TetMesh,
    b: &crate::mesh::BoundarySurface,
    incident: &[u32],
    offsets: &[usize],
) -> Vec<[u32; 4]> {
    let nodes = mesh.nodes();
    let tets = mesh.tets();
    let mut by_edge: Vec<((u32, u32), usize)> = b
        .triangles
        .iter()
        .enumerate()
        .flat_map(|(i, t)| {
            (0..3).map(move |k| ((t[k].min(t[(k + 1) % 3]), t[k].max(t[(k + 1) % 3])), i))
        })
        .collect();
    by_edge.sort_unstable();
    let mut fills = Vec::new();
    for run in by_edge.chunk_by(|x, y| x.0 == y.0) {
        if run.len() <= 2 {
            continue;
        }
        let (a, c) = run[0].0;
        // Fans of tets around the edge, to pair boundary triangles of different fans.
        let around: Vec<u32> = incident[offsets[a as usize]..offsets[a as usize + 1]]
            .iter()
            .copied()
            .filter(|&t| tets[t as usize].contains(&c))
            .collect();
        let labels = groups(&around, |t, out| {
            out.extend(
                tets[t as usize]
                    .iter()
                    .filter(|&&x| x != a && x != c)
                    .map(|&x| x as u64),
            )
        });
        let fan_of = |tri: usize| -> Option<usize> {
            let t = b.tet_of_triangle[tri];
            around.iter().position(|&x| x == t).map(|i| labels[i])
        };
        let third = |tri: usize| -> u32 {
            b.triangles[tri]
                .iter()
                .copied()
                .find(|&x| x != a && x != c)
                .unwrap_or(a)
        };
        let normal = |tri: usize| -> [f64; 3] {
            let [p, q, r] = b.triangles[tri].map(|v| nodes[v as usize]);
            cross(sub(q, p), sub(r, p))
        };
        let pa = nodes[a as usize];
        let mut best: Option<(f64, [u32; 4])> = None;
        for (i, &(_, ti)) in run.iter().enumerate() {
            for &(_, tj) in &run[i + 1..] {
                let (x, y) = (third(ti), third(tj));
                if x == y || fan_of(ti).is_none() || fan_of(ti) == fan_of(tj) {
                    continue;
                }
                // Each far corner lies outside the other triangle: the tet sits in the gap.
                let (px, py) = (nodes[x as usize], nodes[y as usize]);
                if dot(normal(ti), sub(py, pa)) <= 0.0 || dot(normal(tj), sub(px, pa)) <= 0.0 {
                    continue;
                }
                // Its two new faces must not already be shared by two tets.
                let shared = |u: u32| {
                    incident[offsets[u as usize]..offsets[u as usize + 1]]
                        .iter()
                        .filter(|&&t| {
                            tets[t as usize].contains(&x) && tets[t as usize].contains(&y)
                        })
                        .count()
                };
                if shared(a) >= 2 || shared(c) >= 2 {
                    continue;
                }
                let mut tet = [a, c, x, y];
                let mut p = tet.map(|v| nodes[v as usize]);
                if tet_signed_volume(&p) < 0.0 {
                    tet.swap(2, 3);
                    p.swap(2, 3);
                }
                let lmax = crate::mesh::tet_mesh::longest_edge(&p);
                if tet_signed_volume(&p) <= 1e-9 * lmax * lmax * lmax {
                    continue;
                }
                let q = quality::dihedral_angles_deg(&p)
                    .iter()
                    .copied()
                    .fold(f64::INFINITY, f64::min);
                if q >= FILL_MIN_DIHEDRAL && best.is_none_or(|(bq, _)| q > bq) {
                    best = Some((q, tet));
                }
            }
        }
        if let Some((_, tet)) = best {
            fills.push(tet);
        }
    }
    fills
}

/// Boundary edges shared by more than two boundary triangles (parts touching along an edge).
pub(super) fn count_pinched_edges(b: &crate::mesh::BoundarySurface) -> usize {
    let mut edges: Vec<(u32, u32)> = b
        .triangles
        .iter()
        .flat_map(|t| (0..3).map(move |k| (t[k].min(t[(k + 1) % 3]), t[k].max(t[(k + 1) % 3]))))
        .collect();
    edges.sort_unstable();
    edges
        .chunk_by(|x, y| x == y)
        .filter(|run| run.len() > 2)
        .count()
}
