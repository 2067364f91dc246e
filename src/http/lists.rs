//! A cache of rendered `GET /v1/jobs` pages, keyed by the query string. A page is served again only while no
//! job was written since it was rendered (the database's job-write counter still has the value read before
//! the page was queried), so under a load of status polls most lists cost neither a database round trip
//! nor a JSON rendering, and none is ever older than the last write it could show.

use std::sync::Mutex;

use axum::body::Bytes;

/// Pages kept at most (distinct query strings of the current generation).
const ENTRIES: usize = 32;

struct Entry {
    query: String,
    generation: u64,
    body: Bytes,
}

#[derive(Default)]
pub struct ListCache {
    entries: Mutex<Vec<Entry>>,
}

impl ListCache {
    /// The page rendered for `query` at `generation`, if any.
    pub fn get(&self, query: &str, generation: u64) -> Option<Bytes> {
        let entries = self.entries.lock().ok()?;
        entries
            .iter()
            .find(|e| e.generation == generation && e.query == query)
            .map(|e| e.body.clone())
    }

    /// Keep `body`, rendered for `query` from rows read at `generation` (the value before the query).
    pub fn put(&self, query: &str, generation: u64, body: Bytes) {
        // u64::MAX: the counter could not be read; nothing computed then may be reused.
        if generation == u64::MAX {
            return;
        }
        let Ok(mut entries) = self.entries.lock() else {
            return;
        };
        entries.retain(|e| e.generation == generation && e.query != query);
        if entries.len() >= ENTRIES {
            entries.remove(0);
        }
        entries.push(Entry {
            query: query.to_string(),
            generation,
            body,
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_page_is_served_only_for_its_query_and_generation() {
        let c = ListCache::default();
        c.put("status=running", 7, Bytes::from_static(b"a"));
        assert_eq!(c.get("status=running", 7), Some(Bytes::from_static(b"a")));
        assert_eq!(c.get("status=running", 8), None);
        assert_eq!(c.get("", 7), None);
        // A page of a newer generation drops the older ones.
        c.put("", 8, Bytes::from_static(b"b"));
        assert_eq!(c.get("status=running", 7), None);
        c.put("x", u64::MAX, Bytes::from_static(b"c"));
        assert_eq!(c.get("x", u64::MAX), None);
    }
}
