-- Datasets (uploaded projections and simulations), jobs, and Idempotency-Key records.
-- Timestamps are microseconds since the Unix epoch (UTC); JSON columns hold the typed API objects.

CREATE TABLE datasets (
    id          TEXT PRIMARY KEY NOT NULL,          -- UUIDv7
    kind        TEXT NOT NULL CHECK (kind IN ('upload', 'simulation')),
    geometry    TEXT NOT NULL,                      -- geometry JSON
    shape       TEXT NOT NULL,                      -- JSON array
    dtype       TEXT NOT NULL,                      -- float32 | float64 | uint16
    bytes       INTEGER NOT NULL,                   -- size of the stored .npy file
    sha256      TEXT NOT NULL,                      -- of the stored .npy file
    phantom     TEXT,                               -- simulation: phantom JSON (the truth)
    noise       TEXT,                               -- simulation: noise JSON
    created_us  INTEGER NOT NULL
);

CREATE TABLE jobs (
    id               TEXT PRIMARY KEY NOT NULL,     -- UUIDv7: ordered by creation
    kind             TEXT NOT NULL,
    status           TEXT NOT NULL CHECK (status IN ('queued', 'running', 'succeeded', 'failed', 'canceled')),
    progress         INTEGER NOT NULL DEFAULT 0,
    stage            TEXT NOT NULL DEFAULT 'queued',
    spec             TEXT NOT NULL,                 -- job request JSON
    dataset_id       TEXT NOT NULL,
    estimate_bytes   INTEGER NOT NULL,
    attempts         INTEGER NOT NULL DEFAULT 0,
    cancel_requested INTEGER NOT NULL DEFAULT 0,
    error            TEXT,                          -- problem JSON when failed
    result           TEXT,                          -- result JSON when succeeded
    created_us       INTEGER NOT NULL,
    started_us       INTEGER,
    finished_us      INTEGER
);

CREATE INDEX jobs_status ON jobs (status, id);
CREATE INDEX jobs_created ON jobs (created_us);

CREATE TABLE idempotency_keys (
    route        TEXT NOT NULL,
    key          TEXT NOT NULL,
    fingerprint  TEXT NOT NULL,                     -- sha256 of the canonical request
    resource_id  TEXT NOT NULL,
    created_us   INTEGER NOT NULL,
    PRIMARY KEY (route, key)
);
