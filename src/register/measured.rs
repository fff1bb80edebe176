//! Measurements checked once, at the edge: [`Checked`] is the only way into the registration's
//! stages (the pipeline's registration, [`super::wicp`], the correspondence of every LIBR
//! iteration), so what it guarantees — one kind per point, features as long as the points or
//! none, finite coordinates, feature codes 0–2, a rotation for the initial alignment — is checked
//! when it is made and never again downstream. It shares its measurements ([`Arc`]): a clone is a
//! pointer, and a streamed session appends in place once its registrations have let go.

use super::{MeasuredKind, Measurements, RegisterError};
use crate::mesh::rigid::Rigid;
use std::ops::Deref;
use std::sync::Arc;

/// Measurements that passed [`validate_measurements`]'s field checks. It may hold no points (a
/// streamed session before its first message, a dataset's empty scenario); what registers
/// checks that there is one ([`not_empty`], a length test).
#[derive(Debug, Clone)]
pub struct Checked {
    meas: Arc<Measurements>,
    /// How many measured points each point stands for (None: one each). A reduced cloud's
    /// points are cell centroids that stand for the points they merged ([`super::reduce`]).
    weight: Option<Arc<Vec<f64>>>,
}

impl Checked {
    /// Checks `meas` ([`validate_measurements`] but for the number of points).
    pub fn new(meas: Measurements) -> Result<Self, RegisterError> {
        Self::from_arc(Arc::new(meas))
    }

    /// [`Checked::new`] for measurements already shared.
    pub fn from_arc(meas: Arc<Measurements>) -> Result<Self, RegisterError> {
        check_fields(&meas)?;
        Ok(Self { meas, weight: None })
    }

    /// Checked measurements whose points stand for `weight[i]` measured points each (a reduced
    /// cloud's centroids). Fails when `weight` is not as long as the points, or a weight is not
    /// finite and positive.
    pub fn weighted(meas: Measurements, weight: Vec<f64>) -> Result<Self, RegisterError> {
        let mut c = Self::new(meas)?;
        if weight.len() != c.points.len() {
            return Err(RegisterError::Measurements(format!(
                "measurements weight has {} values for {} points",
                weight.len(),
                c.points.len()
            )));
        }
        if let Some(i) = weight.iter().position(|w| !(w.is_finite() && *w > 0.0)) {
            return Err(RegisterError::Measurements(format!(
                "measurements weight[{i}] must be finite and > 0, got {}",
                weight[i]
            )));
        }
        c.weight = Some(Arc::new(weight));
        Ok(c)
    }

    /// How many measured points point `i` stands for (1 unless this is a reduced cloud).
    pub fn weight(&self, i: usize) -> f64 {
        self.weight.as_ref().map_or(1.0, |w| w[i])
    }

    /// The number of measured points these points stand for (their weights' sum).
    pub fn represented(&self) -> f64 {
        self.weight
            .as_ref()
            .map_or(self.points.len() as f64, |w| w.iter().sum())
    }

    /// No points yet, with the navigation system's initial alignment (checked as in
    /// [`Checked::new`]).
    pub fn empty(initial_alignment: Option<Rigid>) -> Result<Self, RegisterError> {
        Self::new(Measurements {
            initial_alignment,
            ..Default::default()
        })
    }

    /// Appends points with their kinds and feature codes (`feature` empty: none designated),
    /// checking only what is added. Where no registration still holds these measurements the
    /// append is in place; otherwise this copy gets its own (the holders keep theirs).
    pub fn append(
        &mut self,
        points: Vec<[f64; 3]>,
        kind: Vec<MeasuredKind>,
        feature: Vec<u8>,
    ) -> Result<(), RegisterError> {
        let more = Measurements {
            points,
            kind,
            feature,
            initial_alignment: None,
        };
        check_fields(&more)?;
        let had = self.meas.points.len();
        let m = Arc::make_mut(&mut self.meas);
        // Features kept as long as the points once either side has any.
        if m.feature.is_empty() && !more.feature.is_empty() {
            m.feature.resize(had, 0);
        }
        if !m.feature.is_empty() && more.feature.is_empty() {
            m.feature.resize(had + more.points.len(), 0);
        } else {
            m.feature.extend(more.feature);
        }
        let added = more.points.len();
        m.points.extend(more.points);
        m.kind.extend(more.kind);
        if let Some(w) = &mut self.weight {
            // What is appended stands for itself.
            let w = Arc::make_mut(w);
            w.resize(w.len() + added, 1.0);
        }
        Ok(())
    }

    /// The measurements themselves (a copy unless this is their only holder), to change and
    /// check again; a reduced cloud's weights are not part of them.
    pub fn into_inner(self) -> Measurements {
        Arc::unwrap_or_clone(self.meas)
    }

    /// The shared measurements (for callers that keep a snapshot).
    pub fn shared(&self) -> &Arc<Measurements> {
        &self.meas
    }

    /// The points `keep` (indices into these measurements), as [`Measurements::subset`]: a subset
    /// of checked measurements is checked.
    pub fn subset(&self, keep: &[usize]) -> Checked {
        Checked {
            meas: Arc::new(self.meas.subset(keep)),
            weight: self
                .weight
                .as_ref()
                .map(|w| Arc::new(keep.iter().map(|&i| w[i]).collect())),
        }
    }

    /// These measurements (a copy) with another initial alignment; only the alignment is
    /// checked, as in [`Checked::new`].
    pub fn with_alignment(
        &self,
        initial_alignment: Option<Rigid>,
    ) -> Result<Checked, RegisterError> {
        check_alignment(initial_alignment.as_ref())?;
        let mut meas = (*self.meas).clone();
        meas.initial_alignment = initial_alignment;
        Ok(Checked {
            meas: Arc::new(meas),
            weight: self.weight.clone(),
        })
    }
}

impl Deref for Checked {
    type Target = Measurements;
    fn deref(&self) -> &Measurements {
        &self.meas
    }
}

impl TryFrom<Measurements> for Checked {
    type Error = RegisterError;
    fn try_from(meas: Measurements) -> Result<Self, RegisterError> {
        Checked::new(meas)
    }
}

/// Checks the measurements: at least one point, `kind` (and `feature` when given) as long as
/// `points`, finite coordinates, feature codes 0–2, a finite initial alignment. The error names the
/// field and the index. [`Checked::new`] runs these checks but for the count, once; what takes a
/// [`Checked`] does not run them again.
pub fn validate_measurements(meas: &Measurements) -> Result<(), RegisterError> {
    not_empty(meas)?;
    check_fields(meas)
}

/// A registration needs at least one point.
pub fn not_empty(meas: &Measurements) -> Result<(), RegisterError> {
    if meas.points.is_empty() {
        return Err(RegisterError::Measurements(
            "measurements.points is empty: nothing to register".into(),
        ));
    }
    Ok(())
}

/// [`validate_measurements`] but for the number of points (none is allowed).
fn check_fields(meas: &Measurements) -> Result<(), RegisterError> {
    let n = meas.points.len();
    if meas.kind.len() != n {
        return Err(RegisterError::Measurements(format!(
            "measurements.kind has {} entries, measurements.points has {n}",
            meas.kind.len()
        )));
    }
    if !meas.feature.is_empty() && meas.feature.len() != n {
        return Err(RegisterError::Measurements(format!(
            "measurements.feature has {} entries, measurements.points has {n} (leave it empty when \
             there are no designations)",
            meas.feature.len()
        )));
    }
    if let Some(i) = meas
        .points
        .iter()
        .position(|p| p.iter().any(|c| !c.is_finite()))
    {
        return Err(RegisterError::Measurements(format!(
            "measurements.points[{i}] is not finite: {:?}",
            meas.points[i]
        )));
    }
    if let Some(i) = meas.feature.iter().position(|&f| f > 2) {
        return Err(RegisterError::Measurements(format!(
            "measurements.feature[{i}] is {}, expected 0 (none), 1 (falciform) or 2 (inferior ridge)",
            meas.feature[i]
        )));
    }
    check_alignment(meas.initial_alignment.as_ref())
}

/// The initial alignment, when given: finite, and a rotation to a loose tolerance.
fn check_alignment(t: Option<&Rigid>) -> Result<(), RegisterError> {
    if let Some(t) = t {
        if t.rotation
            .iter()
            .flatten()
            .chain(&t.translation)
            .any(|c| !c.is_finite())
        {
            return Err(RegisterError::Measurements(
                "measurements.initial_alignment is not finite".into(),
            ));
        }
        // A rotation: RᵀR = I to a loose tolerance.
        let r = &t.rotation;
        for i in 0..3 {
            for j in 0..3 {
                let rtr: f64 = (0..3).map(|k| r[k][i] * r[k][j]).sum();
                let want = if i == j { 1.0 } else { 0.0 };
                if (rtr - want).abs() > 1e-6 {
                    return Err(RegisterError::Measurements(format!(
                        "measurements.initial_alignment.rotation is not a rotation (RᵀR[{i}][{j}] \
                         = {rtr})"
                    )));
                }
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn surface(n: usize) -> Measurements {
        Measurements {
            points: (0..n).map(|i| [i as f64, 0.0, 1.0]).collect(),
            kind: vec![MeasuredKind::Surface; n],
            feature: Vec::new(),
            initial_alignment: None,
        }
    }

    /// The constructor refuses what the stages rely on, naming the field and the index; a
    /// clone shares the points.
    #[test]
    fn checked_measurements_are_refused_by_field_and_shared_when_cloned() {
        let mut m = surface(4);
        m.points[2][1] = f64::NAN;
        let e = Checked::new(m).unwrap_err().to_string();
        assert!(e.contains("measurements.points[2]"), "{e}");
        let mut m = surface(4);
        m.kind.pop();
        let e = Checked::new(m).unwrap_err().to_string();
        assert!(e.contains("measurements.kind"), "{e}");
        let mut m = surface(4);
        m.feature = vec![0, 3, 0, 0];
        let e = Checked::new(m).unwrap_err().to_string();
        assert!(e.contains("measurements.feature[1]"), "{e}");
        let mut m = surface(4);
        m.initial_alignment = Some(Rigid {
            rotation: [[2.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            translation: [0.0; 3],
        });
        let e = Checked::new(m).unwrap_err().to_string();
        assert!(e.contains("initial_alignment"), "{e}");
        // No points is a valid set (a session before its first message), but not a registration.
        let empty = Checked::empty(None).unwrap();
        assert!(not_empty(&empty).is_err() && validate_measurements(&empty).is_err());
        let c = Checked::new(surface(4)).unwrap();
        assert!(Arc::ptr_eq(c.shared(), c.clone().shared()));
        assert_eq!(c.clone().into_inner().points, surface(4).points);
    }

    /// An append checks only what it adds and changes nothing when it refuses; features stay as
    /// long as the points once either side has any.
    #[test]
    fn appends_check_the_new_points_and_keep_features_aligned() {
        let mut c = Checked::new(surface(3)).unwrap();
        let e = c
            .append(
                vec![[0.0, f64::INFINITY, 0.0]],
                vec![MeasuredKind::Vessel],
                vec![],
            )
            .unwrap_err()
            .to_string();
        assert!(e.contains("points[0]"), "{e}");
        assert_eq!(c.points.len(), 3);
        assert!(
            c.append(vec![[0.0; 3]; 2], vec![MeasuredKind::Vessel], vec![])
                .is_err()
        );
        assert_eq!(c.kind.len(), 3);
        // Features added to a set without: the earlier points get 0.
        c.append(vec![[1.0; 3]], vec![MeasuredKind::Surface], vec![2])
            .unwrap();
        assert_eq!(c.feature, vec![0, 0, 0, 2]);
        // No features added to a set with: the new points get 0.
        c.append(
            vec![[2.0; 3]; 2],
            vec![MeasuredKind::PosteriorContour; 2],
            vec![],
        )
        .unwrap();
        assert_eq!(c.feature, vec![0, 0, 0, 2, 0, 0]);
        assert_eq!((c.points.len(), c.kind.len()), (6, 6));
        assert!(validate_measurements(&c).is_ok());
        // A new alignment is checked; the points are kept.
        assert!(c.with_alignment(Some(Rigid::identity())).is_ok());
        let bad = Rigid {
            rotation: [[0.0; 3]; 3],
            translation: [0.0; 3],
        };
        assert!(c.with_alignment(Some(bad)).is_err());
    }
}
