//! The strain-energy laws of the hyperelastic solids: Neo-Hookean (with its energy density and
//! stress as free functions), Mooney–Rivlin and Demiray, with their consistent tangents.

/// A 3 × 3 matrix, row-major.
pub(super) type M3 = [[f64; 3]; 3];

/// `det M`.
fn det3(m: &M3) -> f64 {
    m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
        - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
        + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
}

/// Inverse transpose `F⁻ᵀ` and `J = det F`; `None` when `J ≤ 0` (inverted element).
pub(super) fn inv_transpose(f: &M3) -> Option<(M3, f64)> {
    let j = det3(f);
    if j <= 0.0 || !j.is_finite() {
        return None;
    }
    // Cofactor matrix / J = F⁻ᵀ.
    let c = [
        [
            f[1][1] * f[2][2] - f[1][2] * f[2][1],
            f[1][2] * f[2][0] - f[1][0] * f[2][2],
            f[1][0] * f[2][1] - f[1][1] * f[2][0],
        ],
        [
            f[0][2] * f[2][1] - f[0][1] * f[2][2],
            f[0][0] * f[2][2] - f[0][2] * f[2][0],
            f[0][1] * f[2][0] - f[0][0] * f[2][1],
        ],
        [
            f[0][1] * f[1][2] - f[0][2] * f[1][1],
            f[0][2] * f[1][0] - f[0][0] * f[1][2],
            f[0][0] * f[1][1] - f[0][1] * f[1][0],
        ],
    ];
    Some((c.map(|r| r.map(|x| x / j)), j))
}

/// Neo-Hookean energy density `W` (kPa = mN·mm/mm³) at deformation gradient `F`; `None` if `J ≤ 0`.
pub fn energy_density(f: &M3, lambda: f64, mu: f64) -> Option<f64> {
    let j = det3(f);
    if j <= 0.0 || !j.is_finite() {
        return None;
    }
    let i1: f64 = f.iter().flatten().map(|x| x * x).sum();
    let lj = j.ln();
    Some(0.5 * mu * (i1 - 3.0) - mu * lj + 0.5 * lambda * lj * lj)
}

/// First Piola–Kirchhoff stress `P = μ (F − F⁻ᵀ) + λ ln J F⁻ᵀ` (kPa); `None` if `J ≤ 0`.
pub fn pk1(f: &M3, lambda: f64, mu: f64) -> Option<M3> {
    let (fit, j) = inv_transpose(f)?;
    let c = lambda * j.ln() - mu;
    let mut p = [[0.0; 3]; 3];
    for a in 0..3 {
        for b in 0..3 {
            p[a][b] = mu * f[a][b] + c * fit[a][b];
        }
    }
    Some(p)
}

/// The strain-energy law of a hyperelastic solid with Lamé parameters `λ, μ` (per tet). Every
/// law is stress free at `F = I` and has the same small-strain limit (linear elasticity with
/// `λ, μ`); they differ at large strain. `I₁ = tr C`, `I₂ = ½(I₁² − tr C²)`, `C = FᵀF`, `J = det F`.
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize, serde::Deserialize)]
#[serde(tag = "law", rename_all = "kebab-case", deny_unknown_fields)]
pub enum MaterialLaw {
    /// `W = μ/2 (I₁ − 3) − μ ln J + λ/2 (ln J)²` (Bonet & Wood §6.4.3).
    #[default]
    NeoHookean,
    /// Compressible Mooney–Rivlin: `W = c₁(I₁ − 3) + c₂(I₂ − 3) − 2(c₁ + 2c₂) ln J + λ'/2 (ln J)²`
    /// with `c₁ = (1 − s) μ/2`, `c₂ = s μ/2`, `s` = `i2_share` ∈ [0, 1] (0 is Neo-Hookean), and
    /// `λ' = λ − 4c₂` so that the small-strain limit keeps `λ` (the `I₂` term adds `4c₂` to it).
    MooneyRivlin {
        /// The share `s` of the shear modulus carried by the second invariant.
        i2_share: f64,
    },
    /// Demiray's exponential law (soft tissue, stiffening under stretch), written on the
    /// Neo-Hookean strain measure `Q = I₁ − 3 − 2 ln J` (≥ 0, second order in the strain):
    /// `W = μ/(2b) (exp(bQ) − 1) + λ/2 (ln J)²`, `b` = `stiffening` > 0. It is Neo-Hookean to
    /// second order in `Q` and stiffens beyond.
    Demiray {
        /// The dimensionless stiffening exponent `b`.
        stiffening: f64,
    },
}

impl MaterialLaw {
    /// The law's name as the generator records it.
    pub fn name(&self) -> &'static str {
        match self {
            Self::NeoHookean => "neo-hookean",
            Self::MooneyRivlin { .. } => "mooney-rivlin",
            Self::Demiray { .. } => "demiray",
        }
    }

    /// Checks the law's parameter, naming it.
    pub fn validate(&self) -> Result<(), String> {
        match *self {
            Self::NeoHookean => Ok(()),
            Self::MooneyRivlin { i2_share } if !(0.0..=1.0).contains(&i2_share) => Err(format!(
                "mooney-rivlin i2_share must lie in [0, 1], got {i2_share}"
            )),
            Self::Demiray { stiffening } if !(stiffening > 0.0 && stiffening <= 50.0) => Err(
                format!("demiray stiffening must lie in (0, 50], got {stiffening}"),
            ),
            _ => Ok(()),
        }
    }

    /// Energy density `W` (kPa) at `F`; `None` if `J ≤ 0`.
    pub fn energy_density(&self, f: &M3, lambda: f64, mu: f64) -> Option<f64> {
        match *self {
            Self::NeoHookean => energy_density(f, lambda, mu),
            Self::MooneyRivlin { i2_share } => {
                let j = det3(f);
                if j <= 0.0 || !j.is_finite() {
                    return None;
                }
                let (c1, c2) = mooney_rivlin_constants(i2_share, mu);
                let c = right_cauchy_green(f);
                let i1 = c[0][0] + c[1][1] + c[2][2];
                let i2 = 0.5 * (i1 * i1 - c.iter().flatten().map(|x| x * x).sum::<f64>());
                let lj = j.ln();
                let lambda = lambda - 4.0 * c2;
                Some(
                    c1 * (i1 - 3.0) + c2 * (i2 - 3.0) - 2.0 * (c1 + 2.0 * c2) * lj
                        + 0.5 * lambda * lj * lj,
                )
            }
            Self::Demiray { stiffening: b } => {
                let j = det3(f);
                if j <= 0.0 || !j.is_finite() {
                    return None;
                }
                let i1: f64 = f.iter().flatten().map(|x| x * x).sum();
                let lj = j.ln();
                let q = i1 - 3.0 - 2.0 * lj;
                Some(0.5 * mu / b * ((b * q).exp() - 1.0) + 0.5 * lambda * lj * lj)
            }
        }
    }

    /// First Piola–Kirchhoff stress (kPa) at `F`; `None` if `J ≤ 0`.
    pub fn pk1(&self, f: &M3, lambda: f64, mu: f64) -> Option<M3> {
        match *self {
            Self::NeoHookean => pk1(f, lambda, mu),
            Self::MooneyRivlin { i2_share } => {
                // P = 2c₁F + 2c₂(I₁F − FC) − 2(c₁ + 2c₂)F⁻ᵀ + λ ln J F⁻ᵀ.
                let (fit, j) = inv_transpose(f)?;
                let (c1, c2) = mooney_rivlin_constants(i2_share, mu);
                let c = right_cauchy_green(f);
                let i1 = c[0][0] + c[1][1] + c[2][2];
                let k = (lambda - 4.0 * c2) * j.ln() - 2.0 * (c1 + 2.0 * c2);
                let mut p = [[0.0; 3]; 3];
                for a in 0..3 {
                    for bb in 0..3 {
                        let fc: f64 = (0..3).map(|m| f[a][m] * c[m][bb]).sum();
                        p[a][bb] =
                            2.0 * c1 * f[a][bb] + 2.0 * c2 * (i1 * f[a][bb] - fc) + k * fit[a][bb];
                    }
                }
                Some(p)
            }
            Self::Demiray { stiffening: b } => {
                // P = μ e^{bQ} (F − F⁻ᵀ) + λ ln J F⁻ᵀ.
                let (fit, j) = inv_transpose(f)?;
                let i1: f64 = f.iter().flatten().map(|x| x * x).sum();
                let lj = j.ln();
                let e = (b * (i1 - 3.0 - 2.0 * lj)).exp();
                let mut p = [[0.0; 3]; 3];
                for a in 0..3 {
                    for bb in 0..3 {
                        p[a][bb] = mu * e * (f[a][bb] - fit[a][bb]) + lambda * lj * fit[a][bb];
                    }
                }
                Some(p)
            }
        }
    }

    /// The tangent's per-tet coefficients at `F` (see [`TangentTerms`]); `None` if `J ≤ 0`.
    pub(super) fn tangent_terms(&self, f: &M3, lambda: f64, mu: f64) -> Option<TangentTerms> {
        let (fit, j) = inv_transpose(f)?;
        let lj = j.ln();
        let mut t = TangentTerms {
            fit,
            f: *f,
            shear: mu,
            lambda,
            cross: mu - lambda * lj,
            ff: 0.0,
            ff_swapped: 0.0,
            c: None,
        };
        match *self {
            Self::NeoHookean => {}
            Self::MooneyRivlin { i2_share } => {
                let (c1, c2) = mooney_rivlin_constants(i2_share, mu);
                let c = right_cauchy_green(f);
                let i1 = c[0][0] + c[1][1] + c[2][2];
                let lambda = lambda - 4.0 * c2;
                t.lambda = lambda;
                t.shear = 2.0 * c1 + 2.0 * c2 * i1;
                t.cross = 2.0 * (c1 + 2.0 * c2) - lambda * lj;
                t.ff = 4.0 * c2;
                t.ff_swapped = -2.0 * c2;
                let mut b = [[0.0; 3]; 3];
                for (a, row) in b.iter_mut().enumerate() {
                    for (bb, x) in row.iter_mut().enumerate() {
                        *x = (0..3).map(|m| f[a][m] * f[bb][m]).sum();
                    }
                }
                t.c = Some((c, b, -2.0 * c2));
            }
            Self::Demiray { stiffening: b } => {
                // ∂P/∂F = μe (I⊗I + F⁻ᵀ⊙F⁻ᵀ) + 2μbe (F − F⁻ᵀ)⊗(F − F⁻ᵀ) + the ln J terms:
                // the `ff` term on φ = (F − F⁻ᵀ)g.
                let i1: f64 = f.iter().flatten().map(|x| x * x).sum();
                let e = (b * (i1 - 3.0 - 2.0 * lj)).exp();
                t.shear = mu * e;
                t.cross = mu * e - lambda * lj;
                t.ff = 2.0 * mu * b * e;
                for a in 0..3 {
                    for bb in 0..3 {
                        t.f[a][bb] = f[a][bb] - fit[a][bb];
                    }
                }
            }
        }
        Some(t)
    }
}

/// `c₁, c₂` of the Mooney–Rivlin law with shear modulus `μ = 2(c₁ + c₂)` and `c₂ = s μ/2`.
fn mooney_rivlin_constants(share: f64, mu: f64) -> (f64, f64) {
    ((1.0 - share) * 0.5 * mu, share * 0.5 * mu)
}

/// `C = FᵀF`.
fn right_cauchy_green(f: &M3) -> M3 {
    let mut c = [[0.0; 3]; 3];
    for (a, row) in c.iter_mut().enumerate() {
        for (b, x) in row.iter_mut().enumerate() {
            *x = (0..3).map(|m| f[m][a] * f[m][b]).sum();
        }
    }
    c
}

/// The consistent tangent of every law, written for the node block `(p, q)` of a tet with
/// reference gradients `g_p, g_q`, `h = F⁻ᵀg` and `φ = Fg` (Demiray: `φ = (F − F⁻ᵀ)g`):
/// `K_ab/V = shear (g_p·g_q) δ_ab + λ h_p,a h_q,b + cross h_p,b h_q,a + ff φ_p,a φ_q,b
/// + ff_swapped φ_q,a φ_p,b + k₂ ((g_p·C g_q) δ_ab + B_ab (g_p·g_q))` with `B = FFᵀ`.
#[derive(Debug, Clone, Copy)]
pub(super) struct TangentTerms {
    pub(super) fit: M3,
    pub(super) f: M3,
    pub(super) shear: f64,
    pub(super) lambda: f64,
    pub(super) cross: f64,
    pub(super) ff: f64,
    pub(super) ff_swapped: f64,
    /// `C`, `B` and `k₂` (Mooney–Rivlin only).
    pub(super) c: Option<(M3, M3, f64)>,
}
