//! Which cases a caller may use: the ready cases once the server has preloaded, a case by id
//! (NOT_FOUND worded the same whether it does not exist or the caller may not see it), and an
//! evicted case loaded again when asked for.

use crate::auth::Principal;
use crate::cases::Case;
use crate::error::{ServiceError, Unavailable};
use crate::shared::{MAX_CASE_ID, Shared};
use std::sync::Arc;

/// The ready cases; UNAVAILABLE while the server still preloads.
pub(crate) fn cases(shared: &Shared) -> Result<crate::registry::Ready, ServiceError> {
    if !shared.registry.preloaded() {
        return Err(Unavailable::Preloading.into());
    }
    Ok(shared.registry.ready())
}

/// Whether `who` may use a case named `id` (whether or not it exists).
pub(crate) fn visible(id: &str, who: &Principal) -> bool {
    id.len() <= MAX_CASE_ID && who.may_use(id)
}

/// The NOT_FOUND (or INVALID_ARGUMENT for an overlong id) a caller gets for case `id` that it
/// may not see or that has no state, worded as for any unknown case.
pub(crate) fn not_found(
    shared: &Arc<Shared>,
    id: &str,
    field: &str,
    who: &Principal,
) -> ServiceError {
    case(shared, id, field, who)
        .err()
        .unwrap_or_else(|| ServiceError::UnknownCase {
            field: field.into(),
            id: id.into(),
            known: Vec::new(),
        })
}

/// The case `id` if `who` may use it; NOT_FOUND, worded the same, when it does not exist or
/// `who` may not use it (a caller learns nothing of other tenants' cases).
pub(crate) fn case(
    shared: &Arc<Shared>,
    id: &str,
    field: &str,
    who: &Principal,
) -> Result<Arc<Case>, ServiceError> {
    if id.len() > MAX_CASE_ID {
        return Err(ServiceError::field(
            field,
            format!(
                "is {} bytes long; case ids are at most {MAX_CASE_ID}",
                id.len()
            ),
        ));
    }
    let cases = cases(shared)?;
    match cases.get(id) {
        Some(c) if who.may_use(id) => Ok(c.clone()),
        // An uploaded case evicted while idle: loaded again, the caller retries.
        None if who.may_use(id) && shared.registry.is_evicted(id) => {
            crate::preload::reload(shared, id);
            let stage = shared
                .registry
                .status(id)
                .map(|s| format!("{}, {:.0} %", s.stage, 100.0 * s.fraction))
                .unwrap_or_default();
            Err(Unavailable::Reloading {
                field: field.to_string(),
                id: id.to_string(),
                stage,
            }
            .into())
        }
        _ => Err(ServiceError::UnknownCase {
            field: field.to_string(),
            id: id.to_string(),
            known: cases.keys().filter(|k| who.may_use(k)).cloned().collect(),
        }),
    }
}
