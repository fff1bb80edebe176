//! The "true organ's" material: a heterogeneous stiffness field over the tets of a liver mesh.
//!
//! Three ingredients, each drawn from a seed, none of which the linear homogeneous LIBR model has:
//! - **Parenchyma variation**: a smooth log-normal field `E(x) = E₀ · exp(σ g(x))`, with `g` a sum
//!   of `modes` random plane waves (random directions, wavelengths around `correlation_mm`,
//!   phases), normalised to unit variance — regional fibrosis/steatosis differences.
//! - **Vessels**: tets whose centroid lies inside the vessel tree's tubes get `vessel_factor × E`.
//! - **Tumours**: `tumours` spheres of radius in `tumour_radius_mm`, fully inside the liver with
//!   `margin_mm` to spare, each `tumour_factor × E` (a random factor in the given range).
//!
//! Poisson's ratio is the same everywhere. The per-tet label (0 parenchyma, 1 vessel, 2 tumour) and
//! the modulus are exported as cell data.

use super::PhantomError;
use super::vessels::VesselTree;
use crate::fem::{LameField, LinearMaterial};
use crate::mesh::io::DataArray;
use crate::mesh::spatial::SignedDistance;
use crate::mesh::{TetMesh, TriSurface};
use crate::util::SplitMix64;

/// Parameters of the tissue field (lengths in mm).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TissueParams {
    /// Parenchyma: Young's modulus E₀ (kPa) and Poisson's ratio. Default 5 kPa, 0.45.
    pub parenchyma: LinearMaterial,
    /// Standard deviation σ of ln(E/E₀) in the parenchyma. Default 0.3.
    pub parenchyma_log_std: f64,
    /// Typical wavelength of the parenchyma variation. Default 60.
    pub correlation_mm: f64,
    /// Number of plane waves in the parenchyma field. Default 12.
    pub modes: usize,
    /// Stiffness multiplier inside vessels, drawn uniformly from this range. Default [3, 10].
    pub vessel_factor: [f64; 2],
    /// Number of tumours, drawn uniformly from this inclusive range. Default [1, 3].
    pub tumours: [usize; 2],
    /// Tumour radius range. Default [8, 18].
    pub tumour_radius_mm: [f64; 2],
    /// Tumour stiffness multiplier range. Default [3, 10].
    pub tumour_factor: [f64; 2],
    /// Clearance between a tumour and the liver surface. Default 5.
    pub margin_mm: f64,
}

impl Default for TissueParams {
    fn default() -> Self {
        Self {
            parenchyma: LinearMaterial::default(),
            parenchyma_log_std: 0.3,
            correlation_mm: 60.0,
            modes: 12,
            vessel_factor: [3.0, 10.0],
            tumours: [1, 3],
            tumour_radius_mm: [8.0, 18.0],
            tumour_factor: [3.0, 10.0],
            margin_mm: 5.0,
        }
    }
}

/// A spherical tumour.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Tumour {
    /// Centre (mm).
    pub center: [f64; 3],
    /// Radius (mm).
    pub radius: f64,
    /// Young's modulus multiplier.
    pub factor: f64,
}

/// Kind of tissue of a tet.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[repr(u8)]
pub enum TissueKind {
    /// Liver parenchyma.
    Parenchyma = 0,
    /// Inside a vessel.
    Vessel = 1,
    /// Inside a tumour.
    Tumour = 2,
}

/// The drawn tissue: per-tet Young's modulus and kind, and the tumours.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Tissue {
    /// Young's modulus per tet (kPa).
    pub youngs_kpa: Vec<f64>,
    /// Kind per tet.
    pub kind: Vec<TissueKind>,
    /// Poisson's ratio (everywhere).
    pub poisson_ratio: f64,
    /// Vessel stiffness multiplier drawn.
    pub vessel_factor: f64,
    /// Tumours placed.
    pub tumours: Vec<Tumour>,
}

fn tet_centroid(mesh: &TetMesh, t: usize) -> [f64; 3] {
    let p = mesh.tet_points(t);
    [0, 1, 2].map(|k| 0.25 * (p[0][k] + p[1][k] + p[2][k] + p[3][k]))
}

fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

impl Tissue {
    /// Draws the tissue of a liver mesh with its vessel tree.
    pub fn build(
        mesh: &TetMesh,
        vessels: &VesselTree,
        params: &TissueParams,
        seed: u64,
    ) -> Result<Self, PhantomError> {
        params.parenchyma.validate()?;
        let ranges = [
            ("vessel_factor", params.vessel_factor),
            ("tumour_radius_mm", params.tumour_radius_mm),
            ("tumour_factor", params.tumour_factor),
        ];
        for (name, r) in ranges {
            if !(r[0] > 0.0 && r[0] <= r[1] && r[1].is_finite()) {
                return Err(PhantomError::Parameter(format!(
                    "{name} must be a range 0 < lo ≤ hi, got {r:?}"
                )));
            }
        }
        if params.tumours[0] > params.tumours[1] {
            return Err(PhantomError::Parameter(format!(
                "tumours must be a range lo ≤ hi, got {:?}",
                params.tumours
            )));
        }
        if !(params.parenchyma_log_std >= 0.0 && params.correlation_mm > 0.0) {
            return Err(PhantomError::Parameter(
                "parenchyma_log_std must be ≥ 0 and correlation_mm > 0".into(),
            ));
        }
        let mut rng = SplitMix64::new(seed ^ 0x7155_0E00_0000_0003);
        let uniform = |lo: f64, hi: f64, rng: &mut SplitMix64| lo + (hi - lo) * rng.next_f64();
        // Parenchyma: random plane waves.
        let waves: Vec<([f64; 3], f64)> = (0..params.modes)
            .map(|_| {
                let z = uniform(-1.0, 1.0, &mut rng);
                let phi = uniform(0.0, std::f64::consts::TAU, &mut rng);
                let r = (1.0 - z * z).sqrt();
                let wavelength = params.correlation_mm * uniform(0.7, 1.5, &mut rng);
                let k = std::f64::consts::TAU / wavelength;
                let phase = uniform(0.0, std::f64::consts::TAU, &mut rng);
                ([k * r * phi.cos(), k * r * phi.sin(), k * z], phase)
            })
            .collect();
        // Each cosine has variance 1/2: the sum of m has variance m/2.
        let norm = if waves.is_empty() {
            0.0
        } else {
            (2.0 / waves.len() as f64).sqrt()
        };
        let field = |p: [f64; 3]| -> f64 {
            norm * waves
                .iter()
                .map(|(k, ph)| (k[0] * p[0] + k[1] * p[1] + k[2] * p[2] + ph).cos())
                .sum::<f64>()
        };
        let vessel_factor = uniform(params.vessel_factor[0], params.vessel_factor[1], &mut rng);
        // Tumours: rejection sampling of centres deep enough, not overlapping each other.
        let boundary = mesh.boundary()?;
        let surface = TriSurface::new(mesh.nodes().to_vec(), boundary.triangles)?;
        let sd = SignedDistance::new(&surface)?;
        let count = params.tumours[0] + rng.below(params.tumours[1] - params.tumours[0] + 1);
        let (lo, hi) = mesh.bounding_box();
        let mut tumours: Vec<Tumour> = Vec::new();
        let mut attempts = 0;
        while tumours.len() < count && attempts < 2000 {
            attempts += 1;
            let radius = uniform(
                params.tumour_radius_mm[0],
                params.tumour_radius_mm[1],
                &mut rng,
            );
            let c = [0, 1, 2].map(|k| uniform(lo[k], hi[k], &mut rng));
            // Shrink the radius over the attempts so a thin liver still gets its tumours.
            let radius = radius * (1.0 - 0.5 * attempts as f64 / 2000.0);
            if -sd.eval(c) < radius + params.margin_mm {
                continue;
            }
            if tumours
                .iter()
                .any(|t| dist(t.center, c) < t.radius + radius + params.margin_mm)
            {
                continue;
            }
            let factor = uniform(params.tumour_factor[0], params.tumour_factor[1], &mut rng);
            tumours.push(Tumour {
                center: c,
                radius,
                factor,
            });
        }
        if tumours.len() < params.tumours[0] {
            return Err(PhantomError::Geometry(format!(
                "could place only {} of {} tumours inside the liver (radius {:?} mm, margin {} mm)",
                tumours.len(),
                params.tumours[0],
                params.tumour_radius_mm,
                params.margin_mm
            )));
        }
        let in_vessel = vessels.tets_inside(mesh);
        let e0 = params.parenchyma.youngs_modulus_kpa;
        let mut youngs = Vec::with_capacity(mesh.num_tets());
        let mut kind = Vec::with_capacity(mesh.num_tets());
        for t in 0..mesh.num_tets() {
            let c = tet_centroid(mesh, t);
            let base = e0 * (params.parenchyma_log_std * field(c)).exp();
            if let Some(tm) = tumours.iter().find(|tm| dist(tm.center, c) <= tm.radius) {
                youngs.push(base * tm.factor);
                kind.push(TissueKind::Tumour);
            } else if in_vessel[t] {
                youngs.push(base * vessel_factor);
                kind.push(TissueKind::Vessel);
            } else {
                youngs.push(base);
                kind.push(TissueKind::Parenchyma);
            }
        }
        Ok(Self {
            youngs_kpa: youngs,
            kind,
            poisson_ratio: params.parenchyma.poisson_ratio,
            vessel_factor,
            tumours,
        })
    }

    /// The per-tet Lamé field of this tissue.
    pub fn lame_field(&self) -> LameField {
        LameField::PerTet(
            self.youngs_kpa
                .iter()
                .map(|&e| LinearMaterial::new(e, self.poisson_ratio).lame())
                .collect(),
        )
    }

    /// Volume fraction of each kind (parenchyma, vessel, tumour).
    pub fn volume_fractions(&self, mesh: &TetMesh) -> [f64; 3] {
        let mut v = [0.0; 3];
        for (t, k) in self.kind.iter().enumerate() {
            v[*k as usize] += mesh.tet_volume(t);
        }
        let total: f64 = v.iter().sum();
        v.map(|x| x / total.max(f64::MIN_POSITIVE))
    }

    /// Cell data arrays `tissue` (0 parenchyma, 1 vessel, 2 tumour) and `youngs_modulus_kpa`.
    pub fn to_cell_data(&self) -> Vec<DataArray> {
        vec![
            DataArray::new(
                "tissue",
                1,
                self.kind.iter().map(|&k| k as u8 as f64).collect(),
            ),
            DataArray::new("youngs_modulus_kpa", 1, self.youngs_kpa.clone()),
        ]
    }

    /// Per-node flag: the node lies inside a tumour (for labels and targets).
    pub fn nodes_in_tumours(&self, mesh: &TetMesh) -> Vec<bool> {
        mesh.nodes()
            .iter()
            .map(|&p| self.tumours.iter().any(|t| dist(t.center, p) <= t.radius))
            .collect()
    }
}
