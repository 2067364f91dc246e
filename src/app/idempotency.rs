//! The Idempotency-Key rule, written once for every command that creates a resource: the same key with the
//! same request answers the resource the first request created; the same key with a different request is
//! refused (`idempotency_key_reused`). The key is looked up before the work and claimed in the transaction
//! that inserts the resource, so two racing requests cannot both create one.

use super::App;
use super::error::{AppResult, refused};
use crate::error_code::ErrorCode;
use crate::jobs::{IdempotencyKey, Inserted};

/// What a key says about a request.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Replay {
    /// No earlier request used the key (or no key was sent): do the work.
    New,
    /// An earlier, identical request created this resource (its id): answer it again.
    Existing(String),
}

/// A key with the fingerprint of the request that carries it.
pub type Fingerprinted = IdempotencyKey;

fn reused() -> super::AppError {
    refused(
        ErrorCode::IdempotencyKeyReused,
        "this Idempotency-Key was used with a different request",
    )
}

/// The answer for a key already recorded with `fingerprint` (the earlier request's) for `resource_id`.
fn compare(key: &IdempotencyKey, resource_id: String, fingerprint: &str) -> AppResult<Replay> {
    if fingerprint != key.fingerprint {
        return Err(reused());
    }
    Ok(Replay::Existing(resource_id))
}

impl App {
    /// Before the work: whether `key` was used already, and by an identical request.
    pub async fn replay(&self, key: Option<&IdempotencyKey>) -> AppResult<Replay> {
        let Some(key) = key else {
            return Ok(Replay::New);
        };
        match self.db.idempotency_lookup(key.route, &key.key).await? {
            None => Ok(Replay::New),
            Some((id, fingerprint)) => compare(key, id, &fingerprint),
        }
    }
}

/// After an insert guarded by `key`: `New` when this request created the resource, otherwise the resource of
/// the request that won the race (or a refusal when that request differed).
pub fn settle(inserted: Inserted, key: Option<&IdempotencyKey>) -> AppResult<Replay> {
    match (inserted, key) {
        (Inserted::New, _) => Ok(Replay::New),
        (
            Inserted::Existing {
                resource_id,
                fingerprint,
            },
            Some(key),
        ) => compare(key, resource_id, &fingerprint),
        (Inserted::Existing { resource_id, .. }, None) => Ok(Replay::Existing(resource_id)),
    }
}
