//! Deformation patterns after the LIBR+ paper, randomised from a seed: what loads the "true organ".
//!
//! All patterns include gravity on a supine patient (+y, LPS) and the posterior support: isotropic
//! springs on the bare-area nodes (stiffness per unit surface area, lumped to nodes, the diaphragm
//! attachment) and, on the rest of the posterior surface, the organ bed: a unilateral contact
//! ([`ContactSpring`]: pushes back when the organ presses into it, lets it lift off) plus a weak
//! isotropic attachment (`attachment_fraction` of the bed stiffness: connective tissue,
//! friction). The linear model can only carry the bed as bilateral springs. On top:
//!
//! - **L** (laparoscopic, left-lobe retraction): a patch of the left lobe's inferior ridge is lifted
//!   anteriorly and superiorly by a retractor (prescribed displacement).
//! - **R** (laparoscopic, right-lobe packing): a surgical pack under the right lobe pushes a patch of
//!   its posterior-inferior surface anteriorly and superiorly (surface traction).
//! - **W** (laparoscopic, whole organ): stronger gravity plus insufflation pressure on the whole
//!   anterior surface.
//! - **V** (open surgery, test only): posterior packing over a large part of the posterior surface
//!   pushing the organ anteriorly, plus gravity.
//! - **H** (not in the paper; held organ, local tool): the liver held fixed at its hilum (a
//!   patch of the visceral surface right of the falciform plane, mid-height) and its bare area
//!   (the vena cava and diaphragm attachment), prescribed zero displacement, with no other support and no gravity, and a tool pushing one anterior region
//!   30–60 mm roughly inwards (prescribed displacement with a cosine taper). The dataset measures
//!   it with no misalignment, a navigation start equal to the true alignment and the surface
//!   patch grown from the pushed spot ([`LoadCase::focus`]): the case where fitting rigid motion
//!   freely turns a local push into a global rotation. Opt in with `generate --patterns H`.
//! - **X** (not in the paper; a training augmentation, opt in with `generate --patterns`): a
//!   random table tilt and either one to three soft-edged packs of random size, force and centre
//!   anywhere off the bare area, each pushing roughly inwards, or a broad pressure on a random cap
//!   of the surface (half the draws each).
//!
//! Loads are dead loads on the reference configuration (see `fem::hyperelastic`).

use super::PhantomError;
use crate::fem::{ContactSpring, Dirichlet, NodeSpring, loads};
use crate::mesh::{BoundarySurface, TetMesh, TriSurface};
use crate::register::anatomy::{AnatomyLabels, Region};
use crate::util::SplitMix64;

/// A deformation pattern.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
pub enum Pattern {
    /// Left-lobe retraction.
    L,
    /// Right-lobe packing.
    R,
    /// Whole-organ gravity and pneumoperitoneum.
    W,
    /// Open surgery: posterior packing, large anterior motion (test only).
    V,
    /// Held organ, local tool: fixed at the hilum, one anterior region pushed 30–60 mm (not one
    /// of the paper's patterns; measured without misalignment, see the module doc).
    H,
    /// Random packs anywhere off the bare area, or a broad pressure on a random cap of the
    /// surface: a training augmentation for learning residuals of loads the named patterns do not
    /// cover (not one of the paper's patterns; never a test pattern).
    X,
}

/// Parameters shared by all patterns (units: mm, kPa, mN).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PatternParams {
    /// Body force of gravity (mN/mm³), along +y. Default 0.0104.
    pub gravity: f64,
    /// Bare-area spring stiffness per unit area (mN/mm per mm²). Default 0.5.
    pub bare_area_stiffness: f64,
    /// Organ-bed contact stiffness per unit area on the posterior surface. Default 0.08.
    pub bed_stiffness: f64,
    /// Bilateral isotropic attachment of the bed as a fraction of `bed_stiffness`. Default 0.1.
    pub attachment_fraction: f64,
    /// Multiplier of every pattern's load magnitudes (lift, pack traction, pressure). Default 1.
    pub load_scale: f64,
}

impl Default for PatternParams {
    fn default() -> Self {
        Self {
            gravity: 0.0104,
            bare_area_stiffness: 0.5,
            bed_stiffness: 0.08,
            attachment_fraction: 0.1,
            load_scale: 1.0,
        }
    }
}

/// One randomised load case: constraints, springs and dead loads.
#[derive(Debug, Clone)]
pub struct LoadCase {
    /// Pattern.
    pub pattern: Pattern,
    /// Seed it was drawn from.
    pub seed: u64,
    /// Prescribed displacements (retractor).
    pub dirichlet: Dirichlet,
    /// Support springs (bare area, bed attachment).
    pub springs: Vec<NodeSpring>,
    /// Unilateral bed contacts.
    pub contacts: Vec<ContactSpring>,
    /// External dead load (mN, node-major): `gravity + surface`.
    pub load: Vec<f64>,
    /// The gravity part of `load`.
    pub gravity: Vec<f64>,
    /// The surface part of `load` (packing tractions, insufflation pressure).
    pub surface: Vec<f64>,
    /// What was drawn, for provenance.
    pub description: String,
    /// Where a local tool acts (a node of the mesh), when the pattern has one: the dataset grows
    /// the measured surface patch from there ([`Pattern::H`]).
    pub focus: Option<u32>,
    /// Whether the organ is held in place (the pattern fixes a region): the dataset then measures
    /// it without misalignment, the navigation start being the true alignment ([`Pattern::H`]).
    pub held: bool,
}

/// Area lumped to each node from the boundary triangles (a third of each triangle).
fn node_areas(nodes: &[[f64; 3]], triangles: &[[u32; 3]], n: usize) -> Vec<f64> {
    let mut a = vec![0.0; n];
    let s = TriSurface::new(nodes.to_vec(), triangles.to_vec()).ok();
    if let Some(s) = s {
        for (t, area) in triangles.iter().zip(s.triangle_areas()) {
            for &v in t {
                a[v as usize] += area / 3.0;
            }
        }
    }
    a
}

/// Adds a uniform traction on the boundary triangles whose three nodes satisfy `inside`; returns
/// how many triangles were loaded.
fn push_patch(
    load: &mut [f64],
    nodes: &[[f64; 3]],
    triangles: &[[u32; 3]],
    traction: [f64; 3],
    inside: impl Fn(usize) -> bool,
) -> usize {
    let patch: Vec<[u32; 3]> = triangles
        .iter()
        .copied()
        .filter(|t| t.iter().all(|&v| inside(v as usize)))
        .collect();
    loads::add_traction(load, nodes, &patch, &vec![traction; patch.len()]);
    patch.len()
}

/// Adds a pack of total force `force` (mN) along the unit `dir`, pressing over a soft-edged patch
/// of the boundary: the traction falls off as a Gaussian of width `sigma` from `c`, cut at
/// 2σ, scaled so the forces add up to `force` whatever the local mesh and surface area. Returns the
/// number of loaded triangles and the peak traction (kPa).
pub fn gaussian_patch(
    load: &mut [f64],
    nodes: &[[f64; 3]],
    triangles: &[[u32; 3]],
    c: [f64; 3],
    sigma: f64,
    dir: [f64; 3],
    force: f64,
) -> Result<(usize, f64), PhantomError> {
    let patch: Vec<[u32; 3]> = triangles
        .iter()
        .copied()
        .filter(|t| t.iter().all(|&v| dist(nodes[v as usize], c) <= 2.0 * sigma))
        .collect();
    let weight = |t: &[u32; 3]| {
        let m = [0, 1, 2].map(|a| t.iter().map(|&v| nodes[v as usize][a]).sum::<f64>() / 3.0);
        (-0.5 * (dist(m, c) / sigma).powi(2)).exp()
    };
    let mut unit_load = vec![0.0; load.len()];
    let tractions: Vec<[f64; 3]> = patch.iter().map(|t| dir.map(|d| d * weight(t))).collect();
    loads::add_traction(&mut unit_load, nodes, &patch, &tractions);
    let total = unit_load
        .chunks_exact(3)
        .map(|f| f[0] * dir[0] + f[1] * dir[1] + f[2] * dir[2])
        .sum::<f64>();
    if total <= 0.0 {
        return Err(PhantomError::Geometry(
            "the packing patch has no area".into(),
        ));
    }
    for (l, u) in load.iter_mut().zip(&unit_load) {
        *l += u * force / total;
    }
    Ok((patch.len(), force / total))
}

fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

/// Rotation matrix (row-major) of `angle` radians about the unit `axis` (Rodrigues).
fn rotation(axis: [f64; 3], angle: f64) -> [[f64; 3]; 3] {
    let (s, c) = angle.sin_cos();
    let [x, y, z] = axis;
    let t = 1.0 - c;
    [
        [c + x * x * t, x * y * t - z * s, x * z * t + y * s],
        [y * x * t + z * s, c + y * y * t, y * z * t - x * s],
        [z * x * t - y * s, z * y * t + x * s, c + z * z * t],
    ]
}

fn unit(v: [f64; 3]) -> [f64; 3] {
    let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    if l > 0.0 { v.map(|x| x / l) } else { v }
}

/// Gravity (mN/mm³) on a patient tilted `head_up_deg` (reverse Trendelenburg: gravity gains an
/// inferior component) and `lateral_deg` (rolled: gravity gains a left/right component); supine
/// and level it is `+y`.
pub fn tilted_gravity(magnitude: f64, head_up_deg: f64, lateral_deg: f64) -> [f64; 3] {
    let (t, p) = (head_up_deg.to_radians(), lateral_deg.to_radians());
    [
        magnitude * p.sin() * t.cos(),
        magnitude * p.cos() * t.cos(),
        -magnitude * t.sin(),
    ]
}

/// Draws a load case of `pattern` for a labelled liver mesh.
pub fn load_case(
    mesh: &TetMesh,
    labels: &AnatomyLabels,
    pattern: Pattern,
    params: &PatternParams,
    seed: u64,
) -> Result<LoadCase, PhantomError> {
    let n = mesh.num_nodes();
    let nodes = mesh.nodes();
    let boundary = mesh.boundary()?;
    let surface = TriSurface::new(nodes.to_vec(), boundary.triangles.clone())?;
    let normals = surface.vertex_normals();
    let area = node_areas(nodes, &boundary.triangles, n);
    if !(params.load_scale >= 0.0 && params.load_scale.is_finite()) {
        return Err(PhantomError::Geometry(format!(
            "load_scale must be finite and ≥ 0, got {}",
            params.load_scale
        )));
    }
    let mut draw = Draw(SplitMix64::new(
        seed ^ (pattern as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15),
    ));
    let (lo, hi) = mesh.bounding_box();
    let x_f = {
        let f = AnatomyLabels::nodes_where(&labels.falciform);
        if f.is_empty() {
            0.5 * (lo[0] + hi[0])
        } else {
            f.iter().map(|&i| nodes[i as usize][0]).sum::<f64>() / f.len() as f64
        }
    };
    let scene = Scene {
        mesh,
        labels,
        params,
        nodes,
        normals: &normals,
        boundary: &boundary,
        x_f,
        centroid_z: 0.5 * (lo[2] + hi[2]),
        lo,
        hi,
        ls: params.load_scale,
        n,
    };
    let (mut springs, mut contacts) = supports(labels, params, &normals, &area)?;
    let mut out = Applied {
        load: vec![0.0; 3 * n],
        gravity: vec![0.0; 3 * n],
        dirichlet: Dirichlet::new(n),
    };
    let mut focus = None;
    let d = &mut draw;
    let description = match pattern {
        Pattern::H => {
            // Held at the hilum (the visceral surface just right of the falciform plane at 45 %
            // of the height) and the bare area; no other support, no gravity.
            springs.clear();
            contacts.clear();
            let (description, v) = scene.held(d, &mut out)?;
            focus = Some(v);
            description
        }
        Pattern::L => scene.left_lobe_retraction(d, &mut out)?,
        Pattern::R => scene.right_lobe_pack(d, &mut out)?,
        Pattern::W => scene.insufflation(d, &mut out),
        Pattern::X => scene.augmentation(d, &mut out)?,
        Pattern::V => scene.posterior_packing(d, &mut out),
    };
    let Applied {
        mut load,
        gravity,
        dirichlet,
    } = out;
    // `load` holds the surface part so far.
    let surface_load = load.clone();
    for (l, g) in load.iter_mut().zip(&gravity) {
        *l += g;
    }
    Ok(LoadCase {
        gravity,
        surface: surface_load,
        pattern,
        seed,
        dirichlet,
        springs,
        contacts,
        load,
        description,
        held: pattern == Pattern::H,
        focus,
    })
}

/// The supports every pattern but H keeps: the bare area's springs, and the posterior surface
/// on the bed (contact springs along the normal, a fraction of them attached).
fn supports(
    labels: &AnatomyLabels,
    params: &PatternParams,
    normals: &[[f64; 3]],
    area: &[f64],
) -> Result<(Vec<NodeSpring>, Vec<ContactSpring>), PhantomError> {
    let mut springs = Vec::new();
    let mut contacts = Vec::new();
    for i in 0..area.len() {
        if labels.bare_area[i] {
            springs.push(NodeSpring::isotropic(
                i as u32,
                params.bare_area_stiffness * area[i],
            ));
        } else if labels.region[i] == Region::Posterior {
            let k = params.bed_stiffness * area[i];
            springs.push(NodeSpring::isotropic(
                i as u32,
                params.attachment_fraction * k,
            ));
            contacts.push(ContactSpring {
                node: i as u32,
                normal: normals[i],
                stiffness: k,
            });
        }
    }
    if !labels.bare_area.iter().any(|&b| b) {
        return Err(PhantomError::Geometry(
            "the mesh has no bare-area nodes to support it".into(),
        ));
    }
    Ok((springs, contacts))
}

/// The random draws of a load case, in order.
struct Draw(SplitMix64);

impl Draw {
    /// Uniform in `[lo, hi)`.
    fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.0.next_f64()
    }
}

/// What the patterns apply: surface loads, gravity and prescribed displacements.
struct Applied {
    load: Vec<f64>,
    gravity: Vec<f64>,
    dirichlet: Dirichlet,
}

/// The element `r` ∈ [0, 1) of the way through `cands` (not empty).
fn pick(cands: &[u32], r: f64) -> u32 {
    cands[((r * cands.len() as f64) as usize).min(cands.len() - 1)]
}

/// A labelled liver as the patterns read it.
#[derive(Clone, Copy)]
struct Scene<'a> {
    mesh: &'a TetMesh,
    labels: &'a AnatomyLabels,
    params: &'a PatternParams,
    nodes: &'a [[f64; 3]],
    normals: &'a [[f64; 3]],
    boundary: &'a BoundarySurface,
    /// The falciform plane's x (the mid-plane of the box without a falciform ligament).
    x_f: f64,
    centroid_z: f64,
    lo: [f64; 3],
    hi: [f64; 3],
    /// The load scale.
    ls: f64,
    n: usize,
}

impl Scene<'_> {
    /// A random table tilt, `head_up` and `lateral` ranges in degrees, its gravity applied;
    /// returns the angles drawn.
    fn tilt(
        &self,
        d: &mut Draw,
        out: &mut Applied,
        head_up: (f64, f64),
        lateral: (f64, f64),
    ) -> (f64, f64) {
        let (rt, lat) = (
            d.uniform(head_up.0, head_up.1),
            d.uniform(lateral.0, lateral.1),
        );
        let g = tilted_gravity(self.params.gravity, rt, lat);
        loads::add_body_force(&mut out.gravity, self.mesh, g);
        (rt, lat)
    }

    /// Pattern H: held at the hilum and the bare area, a tool pushing the anterior surface; returns the description and the tool's node.
    fn held(&self, d: &mut Draw, out: &mut Applied) -> Result<(String, u32), PhantomError> {
        let Scene {
            labels,
            nodes,
            normals,
            boundary,
            x_f,
            lo,
            hi,
            ls,
            ..
        } = *self;
        let width = hi[0] - lo[0];
        let q = [x_f - 0.08 * width, hi[1], lo[2] + 0.45 * (hi[2] - lo[2])];
        let visceral: Vec<u32> = labels
            .nodes_in(Region::Posterior)
            .into_iter()
            .filter(|&i| !labels.bare_area[i as usize])
            .collect();
        let hilum = visceral
            .iter()
            .copied()
            .min_by(|&a, &b| {
                dist(nodes[a as usize], q)
                    .total_cmp(&dist(nodes[b as usize], q))
                    .then(a.cmp(&b))
            })
            .ok_or_else(|| {
                PhantomError::Geometry("no visceral (posterior) surface to hold".into())
            })?;
        let h = nodes[hilum as usize];
        let held_radius = d.uniform(20.0, 30.0);
        let mut held = 0;
        for &v in &boundary.nodes {
            if dist(nodes[v as usize], h) <= held_radius || labels.bare_area[v as usize] {
                out.dirichlet.prescribe_node(v, [0.0; 3]);
                held += 1;
            }
        }
        // The tool: an anterior node at least 60 mm from the hilum, pushed roughly inwards.
        let cands: Vec<u32> = labels
            .nodes_in(Region::Anterior)
            .into_iter()
            .filter(|&i| dist(nodes[i as usize], h) >= 60.0)
            .collect();
        if cands.is_empty() {
            return Err(PhantomError::Geometry(
                "no anterior surface 60 mm from the hilum for the tool".into(),
            ));
        }
        let v = pick(&cands, d.uniform(0.0, 1.0));
        let c = nodes[v as usize];
        let tip = d.uniform(20.0, 30.0);
        let depth = ls * d.uniform(30.0, 60.0);
        let turn = [
            d.uniform(-1.0, 1.0),
            d.uniform(-1.0, 1.0),
            d.uniform(-1.0, 1.0),
        ];
        let dir = unit([0, 1, 2].map(|a| -normals[v as usize][a] + 0.4 * turn[a]));
        let mut pushed = 0;
        for &w in &boundary.nodes {
            let r = dist(nodes[w as usize], c);
            if r <= tip && out.dirichlet.get(3 * w as usize).is_none() {
                let f = 0.5 * (1.0 + (std::f64::consts::PI * r / tip).cos());
                out.dirichlet.prescribe_node(w, dir.map(|d| d * depth * f));
                pushed += 1;
            }
        }
        let description = format!(
            "held at the hilum and bare area: {held} nodes (within {held_radius:.1} mm of {h:.1?}, or bare area) fixed; tool pushes {pushed} nodes within {tip:.1} mm of {c:.1?} by up to {depth:.1} mm along {dir:.2?} (cosine taper); no gravity, no bed"
        );
        Ok((description, v))
    }

    /// Pattern L: table tilt and a retractor turning the left lobe up about a hinge.
    fn left_lobe_retraction(
        &self,
        d: &mut Draw,
        out: &mut Applied,
    ) -> Result<String, PhantomError> {
        let Scene {
            labels,
            nodes,
            boundary,
            x_f,
            centroid_z,
            ls,
            n,
            ..
        } = *self;
        let (rt, lat) = self.tilt(d, out, (10.0, 30.0), (-15.0, 15.0));
        let ridge: Vec<u32> = AnatomyLabels::nodes_where(&labels.inferior_ridge)
            .into_iter()
            .filter(|&i| nodes[i as usize][0] > x_f)
            .collect();
        let cands = if ridge.is_empty() {
            labels
                .nodes_in(Region::Anterior)
                .into_iter()
                .filter(|&i| nodes[i as usize][0] > x_f && nodes[i as usize][2] < centroid_z)
                .collect()
        } else {
            ridge
        };
        if cands.is_empty() {
            return Err(PhantomError::Geometry(
                "no left-lobe surface to retract".into(),
            ));
        }
        let c = nodes[pick(&cands, d.uniform(0.0, 1.0)) as usize];
        let radius = d.uniform(30.0, 50.0);
        // The blade turns the lobe up about a hinge along its superior attachment: an axis
        // roughly along x through the top of the left lobe above the grip point.
        let top = (0..n)
            .filter(|&i| nodes[i][0] > x_f)
            .map(|i| nodes[i][2])
            .fold(f64::NEG_INFINITY, f64::max);
        let hinge = [c[0], c[1] + d.uniform(0.0, 20.0), top];
        let axis = unit([1.0, d.uniform(-0.3, 0.3), d.uniform(-0.3, 0.3)]);
        let angle = -(ls * d.uniform(30.0, 55.0)).to_radians();
        let turn = rotation(axis, angle);
        let mut count = 0;
        let mut lift = 0.0f64;
        for &v in &boundary.nodes {
            let p = nodes[v as usize];
            if dist(p, c) <= radius {
                let r = [p[0] - hinge[0], p[1] - hinge[1], p[2] - hinge[2]];
                let q = [0, 1, 2]
                    .map(|a| hinge[a] + turn[a][0] * r[0] + turn[a][1] * r[1] + turn[a][2] * r[2]);
                let u = [q[0] - p[0], q[1] - p[1], q[2] - p[2]];
                lift = lift.max(dist(q, p));
                out.dirichlet.prescribe_node(v, u);
                count += 1;
            }
        }
        Ok(format!(
            "table tilt {rt:.0}° head-up, {lat:.0}° lateral; retractor grips {count} nodes within {radius:.1} mm of {c:.1?} and turns them {:.0}° about a hinge through {hinge:.1?} along {axis:.2?} (lift up to {lift:.1} mm)",
            -angle.to_degrees()
        ))
    }

    /// Pattern R: table tilt and a pack under the right lobe, posterior-inferior.
    fn right_lobe_pack(&self, d: &mut Draw, out: &mut Applied) -> Result<String, PhantomError> {
        let Scene {
            labels,
            nodes,
            boundary,
            x_f,
            centroid_z,
            ls,
            ..
        } = *self;
        let (rt, lat) = self.tilt(d, out, (10.0, 30.0), (-15.0, 15.0));
        let cands: Vec<u32> = labels
            .nodes_in(Region::Posterior)
            .into_iter()
            .filter(|&i| nodes[i as usize][0] < x_f && nodes[i as usize][2] < centroid_z)
            .collect();
        if cands.is_empty() {
            return Err(PhantomError::Geometry(
                "no right-lobe posterior-inferior surface to pack".into(),
            ));
        }
        let c = nodes[pick(&cands, d.uniform(0.0, 1.0)) as usize];
        // A pack of total force F (mN) pressing over a soft-edged patch.
        let sigma = d.uniform(15.0, 25.0);
        let force = ls * d.uniform(4500.0, 9000.0);
        let dir = unit([d.uniform(-0.2, 0.2), -1.0, d.uniform(0.2, 0.8)]);
        let (patch, peak) = gaussian_patch(
            &mut out.load,
            nodes,
            &boundary.triangles,
            c,
            sigma,
            dir,
            force,
        )?;
        Ok(format!(
            "table tilt {rt:.0}° head-up, {lat:.0}° lateral; pack at {c:.1?} (σ {sigma:.1} mm, {patch} triangles) pushes {:.1} N along {dir:.2?} (peak traction {peak:.2} kPa)",
            force / 1000.0,
        ))
    }

    /// Pattern W: table tilt and insufflation pressure on the anterior surface.
    fn insufflation(&self, d: &mut Draw, out: &mut Applied) -> String {
        let Scene {
            labels,
            nodes,
            boundary,
            ls,
            ..
        } = *self;
        let (rt, lat) = self.tilt(d, out, (20.0, 35.0), (-20.0, 20.0));
        let p = ls * d.uniform(0.1, 0.3);
        let anterior: Vec<[u32; 3]> = boundary
            .triangles
            .iter()
            .copied()
            .filter(|t| {
                t.iter()
                    .all(|&v| labels.region[v as usize] == Region::Anterior)
            })
            .collect();
        loads::add_pressure(&mut out.load, nodes, &anterior, p);
        format!(
            "table tilt {rt:.0}° head-up, {lat:.0}° lateral; insufflation pressure {p:.2} kPa on {} anterior triangles",
            anterior.len()
        )
    }

    /// Pattern X (training augmentation): a random tilt, and random packs or a pressure on a random cap.
    fn augmentation(&self, d: &mut Draw, out: &mut Applied) -> Result<String, PhantomError> {
        // Training augmentation, not a surgical scene: a random table tilt and, on half the
        // draws, one to three soft-edged packs anywhere off the bare area, each pushing
        // roughly inwards (the inward normal at its centre turned by a random offset,
        // typically 20–30°, at most ~65°: the push always has an inward component); on the
        // other half a broad pressure on a random cap of the surface (the 15–50 % of the
        // surface off the bare area farthest along a random direction).
        let (rt, lat) = self.tilt(d, out, (0.0, 35.0), (-20.0, 20.0));
        let cands: Vec<u32> = self
            .boundary
            .nodes
            .iter()
            .copied()
            .filter(|&v| !self.labels.bare_area[v as usize])
            .collect();
        if cands.is_empty() {
            return Err(PhantomError::Geometry(
                "no surface off the bare area to load".into(),
            ));
        }
        let loads_text = if d.uniform(0.0, 1.0) < 0.5 {
            self.random_packs(d, out, &cands)?
        } else {
            self.random_cap(d, out, &cands)?
        };
        Ok(format!(
            "table tilt {rt:.0}° head-up, {lat:.0}° lateral; {loads_text}"
        ))
    }

    /// One to three soft-edged packs centred on `cands`, each pushing roughly inwards.
    fn random_packs(
        &self,
        d: &mut Draw,
        out: &mut Applied,
        cands: &[u32],
    ) -> Result<String, PhantomError> {
        let Scene {
            nodes,
            normals,
            boundary,
            ls,
            ..
        } = *self;
        let packs = 1 + (d.uniform(0.0, 3.0) as usize).min(2);
        let mut parts = Vec::new();
        for _ in 0..packs {
            let v = pick(cands, d.uniform(0.0, 1.0)) as usize;
            let c = nodes[v];
            let sigma = d.uniform(12.0, 45.0);
            let force = ls * d.uniform(3000.0, 9000.0) / (packs as f64).sqrt();
            let turn = [
                d.uniform(-1.0, 1.0),
                d.uniform(-1.0, 1.0),
                d.uniform(-1.0, 1.0),
            ];
            let dir = unit([0, 1, 2].map(|a| -normals[v][a] + 0.6 * turn[a]));
            let (patch, peak) = gaussian_patch(
                &mut out.load,
                nodes,
                &boundary.triangles,
                c,
                sigma,
                dir,
                force,
            )?;
            parts.push(format!(
                "{:.1} N at {c:.1?} along {dir:.2?} (σ {sigma:.1} mm, {patch} triangles, peak {peak:.2} kPa)",
                force / 1000.0
            ));
        }
        Ok(format!("random packs: {}", parts.join("; ")))
    }

    /// A pressure on the cap of the surface off the bare area farthest along a random
    /// direction (15–50 % of `cands`).
    fn random_cap(
        &self,
        d: &mut Draw,
        out: &mut Applied,
        cands: &[u32],
    ) -> Result<String, PhantomError> {
        let Scene {
            labels,
            nodes,
            boundary,
            ls,
            ..
        } = *self;
        let m = unit([
            d.uniform(-1.0, 1.0),
            d.uniform(-1.0, 1.0),
            d.uniform(-1.0, 1.0),
        ]);
        let along = |v: u32| {
            let p = nodes[v as usize];
            p[0] * m[0] + p[1] * m[1] + p[2] * m[2]
        };
        let mut proj: Vec<f64> = cands.iter().map(|&v| along(v)).collect();
        proj.sort_by(f64::total_cmp);
        let fraction = d.uniform(0.15, 0.5);
        let cut = proj[((1.0 - fraction) * proj.len() as f64) as usize % proj.len()];
        let cap: Vec<[u32; 3]> = boundary
            .triangles
            .iter()
            .copied()
            .filter(|t| {
                t.iter()
                    .all(|&v| !labels.bare_area[v as usize] && along(v) >= cut)
            })
            .collect();
        if cap.is_empty() {
            return Err(PhantomError::Geometry(
                "the random cap has no triangles".into(),
            ));
        }
        let p = ls * d.uniform(0.2, 1.2);
        loads::add_pressure(&mut out.load, nodes, &cap, p);
        Ok(format!(
            "pressure {p:.2} kPa on {} triangles, the {:.0} % of the surface farthest along {m:.2?}",
            cap.len(),
            100.0 * fraction
        ))
    }

    /// Pattern V: a slight tilt and packing behind the posterior surface.
    fn posterior_packing(&self, d: &mut Draw, out: &mut Applied) -> String {
        let Scene {
            labels,
            nodes,
            boundary,
            lo,
            hi,
            ls,
            ..
        } = *self;
        let (rt, lat) = self.tilt(d, out, (0.0, 5.0), (-5.0, 5.0));
        let cy = 0.5 * (lo[1] + hi[1]);
        let p = ls * d.uniform(0.8, 1.4);
        let dir = unit([d.uniform(-0.2, 0.2), -1.0, d.uniform(-0.2, 0.4)]);
        let count = push_patch(
            &mut out.load,
            nodes,
            &boundary.triangles,
            dir.map(|d| d * p),
            |v| labels.region[v] == Region::Posterior && !labels.bare_area[v] && nodes[v][1] > cy,
        );
        format!(
            "table tilt {rt:.0}° head-up, {lat:.0}° lateral; posterior packing {p:.2} kPa along {dir:.2?} on {count} triangles"
        )
    }
}
