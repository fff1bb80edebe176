//! Material parameters for linear elasticity (units: kPa).

use super::error::FemError;

/// Isotropic linear-elastic material. Defaults are liver-like: E = 5 kPa, ν = 0.45.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct LinearMaterial {
    /// Young's modulus E in kPa (liver parenchyma ≈ 2–10 kPa). Default 5.
    pub youngs_modulus_kpa: f64,
    /// Poisson's ratio ν, in (−1, 0.5) (soft tissue ≈ 0.45–0.49). Default 0.45.
    pub poisson_ratio: f64,
}

impl Default for LinearMaterial {
    fn default() -> Self {
        Self {
            youngs_modulus_kpa: 5.0,
            poisson_ratio: 0.45,
        }
    }
}

impl LinearMaterial {
    /// A material with the given E (kPa) and ν.
    pub fn new(youngs_modulus_kpa: f64, poisson_ratio: f64) -> Self {
        Self {
            youngs_modulus_kpa,
            poisson_ratio,
        }
    }

    /// Checks E > 0 and −1 < ν < 0.5; the message names the bad field.
    pub fn validate(&self) -> Result<(), FemError> {
        if !(self.youngs_modulus_kpa.is_finite() && self.youngs_modulus_kpa > 0.0) {
            return Err(FemError::InvalidParameter {
                field: "youngs_modulus_kpa",
                message: format!("must be finite and > 0, got {}", self.youngs_modulus_kpa),
            });
        }
        if !(self.poisson_ratio > -1.0 && self.poisson_ratio < 0.5) {
            return Err(FemError::InvalidParameter {
                field: "poisson_ratio",
                message: format!("must be in (-1, 0.5), got {}", self.poisson_ratio),
            });
        }
        Ok(())
    }

    /// Lamé parameters (λ, μ) in kPa.
    pub fn lame(&self) -> (f64, f64) {
        let (e, nu) = (self.youngs_modulus_kpa, self.poisson_ratio);
        let lambda = e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu));
        let mu = e / (2.0 * (1.0 + nu));
        (lambda, mu)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lame_reproduces_e_and_nu() {
        let m = LinearMaterial::new(5.0, 0.45);
        let (l, mu) = m.lame();
        // E = μ(3λ + 2μ)/(λ + μ), ν = λ / (2(λ + μ)).
        assert!((mu * (3.0 * l + 2.0 * mu) / (l + mu) - 5.0).abs() < 1e-12);
        assert!((l / (2.0 * (l + mu)) - 0.45).abs() < 1e-12);
        assert!(LinearMaterial::new(5.0, 0.5).validate().is_err());
        assert!(LinearMaterial::new(-1.0, 0.3).validate().is_err());
    }
}
