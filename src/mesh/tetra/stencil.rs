//! The stencils of the mesher (step 5): each BCC tetrahedron replaced by its part inside the
//! surface, split into tetrahedra with the largest smallest dihedral angle.

use super::*;
use crate::mesh::quality;
use crate::mesh::spatial::SignedDistance;
use crate::mesh::tet_mesh::TET_FACES;
use crate::mesh::vec3::{add, cross, dot, scale, sub, tet_signed_volume};

/// Everything the stencil stage reads. Output node ids ("global"): lattice point `p` is `p`, cut
/// point `i` is `num_points + i`.
pub(super) struct Fill<'a> {
    pub(super) lat: &'a Lattice,
    pub(super) sign: &'a [i8],
    pub(super) cuts: &'a [Cut],
    pub(super) warped: &'a [(u32, [f64; 3])],
    pub(super) sd: &'a SignedDistance,
}

/// Up to six polytope vertices (inside/on-surface lattice vertices and cut points).
pub(super) const MAX_PV: usize = 8;

/// A face of the inside polytope of one BCC tetrahedron, oriented outward.
#[derive(Clone, Copy)]
pub(super) struct PFace {
    v: [u8; 4],
    len: u8,
    /// Quadrilateral diagonal fixed by the lattice-face rules (as polytope vertex indices), if any.
    diag: Option<(u8, u8)>,
}

impl Fill<'_> {
    pub(super) fn node_position(&self, g: u32) -> [f64; 3] {
        let np = self.lat.num_points as u32;
        if g >= np {
            return self.cuts[(g - np) as usize].pos;
        }
        self.lattice_vertex_position(g)
    }

    pub(super) fn lattice_vertex_position(&self, p: u32) -> [f64; 3] {
        if self.sign[p as usize] == 0 {
            if let Ok(i) = self.warped.binary_search_by_key(&p, |w| w.0) {
                return self.warped[i].1;
            }
        }
        self.lat.position(p)
    }

    /// The BCC tetrahedra between centre `c` and its +x, +y, +z neighbour centres.
    pub(super) fn centre(
        &self,
        c: u32,
        out: &mut Vec<[u32; 4]>,
        all_on: &mut usize,
    ) -> Result<(), TetraError> {
        let d = self.lat.doubled(c);
        for axis in 0..3 {
            let mut d2 = d;
            d2[axis] += 2;
            let Some(c2) = self.lat.index(d2) else {
                continue;
            };
            let (b, cc) = ((axis + 1) % 3, (axis + 2) % 3);
            let ring = [(-1, -1), (1, -1), (1, 1), (-1, 1)];
            let mut corners = [0u32; 4];
            let mut corner_d = [[0i64; 3]; 4];
            for (m, &(ob, oc)) in ring.iter().enumerate() {
                let mut k = d;
                k[axis] += 1;
                k[b] += ob;
                k[cc] += oc;
                corner_d[m] = k;
                corners[m] = self.lat.index(k).ok_or_else(|| {
                    TetraError::Internal(format!("corner {k:?} of centre {d:?} is off the lattice"))
                })?;
            }
            for m in 0..4 {
                let m2 = (m + 1) % 4;
                let mut tet = [c, c2, corners[m], corners[m2]];
                // Positive orientation in exact integer coordinates.
                let (e1, e2, e3) = (
                    [0, 1, 2].map(|a| d2[a] - d[a]),
                    [0, 1, 2].map(|a| corner_d[m][a] - d[a]),
                    [0, 1, 2].map(|a| corner_d[m2][a] - d[a]),
                );
                let det = e1[0] * (e2[1] * e3[2] - e2[2] * e3[1])
                    - e1[1] * (e2[0] * e3[2] - e2[2] * e3[0])
                    + e1[2] * (e2[0] * e3[1] - e2[1] * e3[0]);
                if det < 0 {
                    tet.swap(2, 3);
                }
                self.stuff(tet, out, all_on)?;
            }
        }
        Ok(())
    }

    /// Fills one positively oriented BCC tetrahedron `[centre, centre, corner, corner]`.
    pub(super) fn stuff(
        &self,
        v: [u32; 4],
        out: &mut Vec<[u32; 4]>,
        all_on: &mut usize,
    ) -> Result<(), TetraError> {
        let s = v.map(|p| self.sign[p as usize]);
        let n_in = s.iter().filter(|&&x| x < 0).count();
        let n_out = s.iter().filter(|&&x| x > 0).count();
        if n_in == 0 {
            if n_out == 0 {
                // Four vertices on the surface: keep the tetrahedron if its centroid is inside.
                let p = v.map(|q| self.lattice_vertex_position(q));
                let centroid = scale(add(add(p[0], p[1]), add(p[2], p[3])), 0.25);
                let lmax = crate::mesh::tet_mesh::longest_edge(&p);
                if tet_signed_volume(&p) > 1e-9 * lmax * lmax * lmax && self.sd.eval(centroid) < 0.0
                {
                    out.push(v);
                    *all_on += 1;
                }
            }
            return Ok(());
        }
        if n_out == 0 {
            out.push(v);
            return Ok(());
        }
        self.stuff_crossing(v, s, out)
    }

    /// A BCC tetrahedron with inside and outside vertices: triangulates its inside polytope.
    pub(super) fn stuff_crossing(
        &self,
        v: [u32; 4],
        s: [i8; 4],
        out: &mut Vec<[u32; 4]>,
    ) -> Result<(), TetraError> {
        let poly = self.polytope(v, s)?;
        let mut faces = self.lattice_faces(&poly, v, s)?;
        let free_quad = match self.cut_face(&poly, v, s) {
            Some(f) => {
                let quad = f.len == 4;
                faces.push(f);
                quad
            }
            None => false,
        };
        match best_pulling(&poly, &faces, free_quad) {
            Some((_, t)) => {
                out.extend_from_slice(&t);
                Ok(())
            }
            None => Err(TetraError::NoValidStencil {
                lattice_tet: v,
                signs: s,
            }),
        }
    }

    /// The inside polytope's vertices: the tetrahedron's inside and on-surface lattice vertices,
    /// then the cut points on its crossing edges.
    fn polytope(&self, v: [u32; 4], s: [i8; 4]) -> Result<Polytope, TetraError> {
        let np = self.lat.num_points as u32;
        // Polytope vertices: global ids and positions.
        let mut ids = [0u32; MAX_PV];
        let mut pos = [[0.0f64; 3]; MAX_PV];
        let mut count = 0usize;
        let mut of_lattice = [u8::MAX; 4];
        for i in 0..4 {
            if s[i] <= 0 {
                of_lattice[i] = count as u8;
                ids[count] = v[i];
                pos[count] = self.lattice_vertex_position(v[i]);
                count += 1;
            }
        }
        let mut of_cut = [[u8::MAX; 4]; 4];
        for i in 0..4 {
            for j in (i + 1)..4 {
                if s[i] * s[j] < 0 {
                    let key = edge_key(v[i], v[j]);
                    let ci = self
                        .cuts
                        .binary_search_by_key(&key, |c| c.key)
                        .map_err(|_| {
                            TetraError::Internal(format!(
                                "no cut point on lattice edge {:?}",
                                (v[i], v[j])
                            ))
                        })?;
                    of_cut[i][j] = count as u8;
                    of_cut[j][i] = count as u8;
                    ids[count] = np + ci as u32;
                    pos[count] = self.cuts[ci].pos;
                    count += 1;
                }
            }
        }
        Ok(Polytope {
            ids,
            pos,
            count,
            of_lattice,
            of_cut,
        })
    }

    /// The polytope's faces on the four lattice faces (outward, clipped in order), with the
    /// quadrilaterals' diagonals the lattice-face rules fix.
    fn lattice_faces(
        &self,
        poly: &Polytope,
        v: [u32; 4],
        s: [i8; 4],
    ) -> Result<Vec<PFace>, TetraError> {
        let (of_lattice, of_cut) = (&poly.of_lattice, &poly.of_cut);
        let mut faces: Vec<PFace> = Vec::with_capacity(5);
        for lf in TET_FACES {
            let mut poly = [0u8; 4];
            let mut len = 0usize;
            let mut n_in = 0;
            for e in 0..3 {
                let (x, y) = (lf[e], lf[(e + 1) % 3]);
                if s[x] < 0 {
                    n_in += 1;
                }
                if s[x] <= 0 && len < 4 {
                    poly[len] = of_lattice[x];
                    len += 1;
                }
                if s[x] * s[y] < 0 && len < 4 {
                    poly[len] = of_cut[x][y];
                    len += 1;
                }
            }
            if n_in == 0 || len < 3 {
                continue;
            }
            let diag = if len == 4 {
                // Two inside lattice vertices u, v and one outside w on this face.
                let ins: Vec<usize> = lf.iter().copied().filter(|&x| s[x] < 0).collect();
                let w = lf
                    .iter()
                    .copied()
                    .find(|&x| s[x] > 0)
                    .ok_or_else(|| TetraError::Internal("quad without outside".into()))?;
                let (u, vv) = (ins[0], ins[1]);
                let (pu, pv, pw) = (v[u], v[vv], v[w]);
                let from_u = self.diagonal_from_first(pu, pv, pw);
                Some(if from_u {
                    (of_lattice[u], of_cut[vv][w])
                } else {
                    (of_lattice[vv], of_cut[u][w])
                })
            } else {
                None
            };
            faces.push(PFace {
                v: poly,
                len: len as u8,
                diag,
            });
        }
        Ok(faces)
    }

    /// The cut face: on-surface vertices and cut points, oriented toward the outside vertices
    /// (None when it has fewer than three corners).
    fn cut_face(&self, poly: &Polytope, v: [u32; 4], s: [i8; 4]) -> Option<PFace> {
        let (of_lattice, of_cut, pos) = (&poly.of_lattice, &poly.of_cut, &poly.pos);
        let mut cut_face = [0u8; 4];
        let mut clen = 0usize;
        let ins: Vec<usize> = (0..4).filter(|&i| s[i] < 0).collect();
        let outs: Vec<usize> = (0..4).filter(|&i| s[i] > 0).collect();
        for i in 0..4 {
            if s[i] == 0 && clen < 4 {
                cut_face[clen] = of_lattice[i];
                clen += 1;
            }
        }
        if ins.len() == 2 && outs.len() == 2 {
            let (a, b, c, d) = (ins[0], ins[1], outs[0], outs[1]);
            cut_face = [of_cut[a][c], of_cut[a][d], of_cut[b][d], of_cut[b][c]];
            clen = 4;
        } else {
            for &i in &ins {
                for &o in &outs {
                    if clen < 4 {
                        cut_face[clen] = of_cut[i][o];
                        clen += 1;
                    }
                }
            }
        }
        if clen >= 3 {
            let q = |k: usize| pos[cut_face[k] as usize];
            let normal = if clen == 4 {
                cross(sub(q(2), q(0)), sub(q(3), q(1)))
            } else {
                cross(sub(q(1), q(0)), sub(q(2), q(0)))
            };
            let mut outside = [0.0; 3];
            for &o in &outs {
                outside = add(outside, self.lat.position(v[o]));
            }
            outside = scale(outside, 1.0 / outs.len() as f64);
            if dot(normal, sub(outside, q(0))) < 0.0 {
                cut_face[..clen].reverse();
            }
            return Some(PFace {
                v: cut_face,
                len: clen as u8,
                diag: None,
            });
        }
        None
    }

    /// For a lattice face with inside vertices `u`, `v` and outside vertex `w`: true when the
    /// quadrilateral's diagonal runs from `u` to the cut point on `vw` (else from `v` to the cut
    /// point on `uw`). Short `uv`: the diagonal ends at the cut point on the long edge. Long `uv`:
    /// the parity rule.
    pub(super) fn diagonal_from_first(&self, u: u32, v: u32, w: u32) -> bool {
        let (cu, cv, cw) = (
            self.lat.is_centre(u),
            self.lat.is_centre(v),
            self.lat.is_centre(w),
        );
        if cu != cv {
            // Short uv: the long edge is vw (v, w of one kind) or uw.
            return cv == cw;
        }
        let (du, dv, dw) = (
            self.lat.doubled(u),
            self.lat.doubled(v),
            self.lat.doubled(w),
        );
        let mut negative = 0;
        for k in 0..3 {
            let step = if dv[k] != du[k] {
                dv[k] - du[k]
            } else {
                dw[k] - dv[k]
            };
            if step < 0 {
                negative += 1;
            }
        }
        // Corners: the diagonal with an odd count; centres: even.
        let odd = negative % 2 == 1;
        cu != odd
    }
}

/// The inside polytope of a crossing BCC tetrahedron: its vertices' global ids and positions,
/// and which polytope vertex each lattice vertex and each crossing edge's cut point is.
struct Polytope {
    ids: [u32; MAX_PV],
    pos: [[f64; 3]; MAX_PV],
    count: usize,
    of_lattice: [u8; 4],
    of_cut: [[u8; 4]; 4],
}

/// Pulling triangulations of the polytope from each admissible vertex (both splits of a free
/// cut quadrilateral, the last face, where it is one); the best by its smallest dihedral angle.
fn best_pulling(poly: &Polytope, faces: &[PFace], free_quad: bool) -> Option<(f64, Vec<[u32; 4]>)> {
    let (ids, pos, count) = (&poly.ids, &poly.pos, poly.count);
    let mut best: Option<(f64, Vec<[u32; 4]>)> = None;
    let mut tets: Vec<[u32; 4]> = Vec::with_capacity(4);
    for apex in 0..count as u8 {
        let contains = |f: &PFace, x: u8| f.v[..f.len as usize].contains(&x);
        let admissible = faces.iter().all(|f| match f.diag {
            Some((x, y)) if contains(f, apex) => x == apex || y == apex,
            _ => true,
        });
        if !admissible {
            continue;
        }
        let options = if free_quad && !contains(&faces[faces.len() - 1], apex) {
            2
        } else {
            1
        };
        for option in 0..options {
            tets.clear();
            let mut min_angle = f64::INFINITY;
            let mut valid = true;
            for (fi, f) in faces.iter().enumerate() {
                if contains(f, apex) {
                    continue;
                }
                let fv = &f.v[..f.len as usize];
                let mut tris: [[u8; 3]; 2] = [[0; 3]; 2];
                let ntri = if f.len == 3 {
                    tris[0] = [fv[0], fv[1], fv[2]];
                    1
                } else {
                    // Split along the diagonal through slot `k` and `k + 2`.
                    let k = match f.diag {
                        Some((x, _)) => fv.iter().position(|&y| y == x).unwrap_or(0) % 2,
                        None => {
                            if fi == faces.len() - 1 {
                                option
                            } else {
                                0
                            }
                        }
                    };
                    tris[0] = [fv[k], fv[k + 1], fv[(k + 2) % 4]];
                    tris[1] = [fv[k], fv[(k + 2) % 4], fv[(k + 3) % 4]];
                    2
                };
                for tri in &tris[..ntri] {
                    let p = [
                        pos[tri[0] as usize],
                        pos[tri[2] as usize],
                        pos[tri[1] as usize],
                        pos[apex as usize],
                    ];
                    let vol = tet_signed_volume(&p);
                    let lmax = crate::mesh::tet_mesh::longest_edge(&p);
                    if vol <= 1e-9 * lmax * lmax * lmax {
                        valid = false;
                        break;
                    }
                    let angles = quality::dihedral_angles_deg(&p);
                    min_angle = angles.iter().copied().fold(min_angle, f64::min);
                    tets.push([
                        ids[tri[0] as usize],
                        ids[tri[2] as usize],
                        ids[tri[1] as usize],
                        ids[apex as usize],
                    ]);
                }
                if !valid {
                    break;
                }
            }
            if valid && best.as_ref().is_none_or(|(b, _)| min_angle > *b) {
                best = Some((min_angle, tets.clone()));
            }
        }
    }
    best
}
