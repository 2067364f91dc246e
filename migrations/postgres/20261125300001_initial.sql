-- The PostgreSQL twin of the SQLite schema in the folder above (its migrations up to 20261125000001_leases),
-- for a job database shared by several ctrecon processes. The same tables, columns and meanings:
-- timestamps are microseconds since the Unix epoch (UTC), JSON columns hold the typed API objects as text,
-- and every integer is BIGINT (read as i64 by both adapters).

CREATE TABLE datasets (
    id          TEXT PRIMARY KEY NOT NULL,          -- UUIDv7
    kind        TEXT NOT NULL CHECK (kind IN ('upload', 'simulation')),
    geometry    TEXT NOT NULL,
    shape       TEXT NOT NULL,
    dtype       TEXT NOT NULL,
    bytes       BIGINT NOT NULL,
    sha256      TEXT NOT NULL,
    phantom     TEXT,
    noise       TEXT,
    created_us  BIGINT NOT NULL
);

CREATE TABLE jobs (
    id               TEXT PRIMARY KEY NOT NULL,     -- UUIDv7: ordered by creation
    kind             TEXT NOT NULL,
    status           TEXT NOT NULL CHECK (status IN ('queued', 'running', 'succeeded', 'failed', 'canceled')),
    progress         BIGINT NOT NULL DEFAULT 0,
    stage            TEXT NOT NULL DEFAULT 'queued',
    spec             TEXT NOT NULL,
    dataset_id       TEXT NOT NULL,
    estimate_bytes   BIGINT NOT NULL,
    attempts         BIGINT NOT NULL DEFAULT 0,
    cancel_requested BIGINT NOT NULL DEFAULT 0,
    error            TEXT,
    result           TEXT,
    created_us       BIGINT NOT NULL,
    started_us       BIGINT,
    finished_us      BIGINT,
    -- A running job's lease (see the SQLite migration 20261125000001_leases).
    lease_expires_us BIGINT
);

CREATE INDEX jobs_status ON jobs (status, id);
CREATE INDEX jobs_created ON jobs (created_us);
CREATE INDEX jobs_lease ON jobs (lease_expires_us) WHERE status = 'running';

-- The unique key is what makes an Idempotency-Key safe with several API processes: the second insert of
-- a key conflicts and reads the first one's resource.
CREATE TABLE idempotency_keys (
    route        TEXT NOT NULL,
    key          TEXT NOT NULL,
    fingerprint  TEXT NOT NULL,
    resource_id  TEXT NOT NULL,
    created_us   BIGINT NOT NULL,
    PRIMARY KEY (route, key)
);

CREATE TABLE uploads (
    id            TEXT PRIMARY KEY NOT NULL,
    status        TEXT NOT NULL CHECK (status IN ('open', 'completed')),
    instances     BIGINT NOT NULL DEFAULT 0,
    bytes         BIGINT NOT NULL DEFAULT 0,
    outcome       TEXT,
    created_us    BIGINT NOT NULL,
    completed_us  BIGINT
);

CREATE TABLE upload_files (
    upload_id   TEXT NOT NULL REFERENCES uploads (id) ON DELETE CASCADE,
    sha256      TEXT NOT NULL,
    label       TEXT NOT NULL,
    bytes       BIGINT NOT NULL,
    series_uid  TEXT NOT NULL,
    created_us  BIGINT NOT NULL,
    -- Order of arrival (SQLite's rowid).
    seq         BIGSERIAL NOT NULL,
    PRIMARY KEY (upload_id, sha256)
);

CREATE TABLE series (
    id          TEXT PRIMARY KEY NOT NULL,
    upload_id   TEXT NOT NULL REFERENCES uploads (id),
    series_uid  TEXT NOT NULL,
    record      TEXT NOT NULL,
    created_us  BIGINT NOT NULL
);

CREATE INDEX series_upload ON series (upload_id);
CREATE INDEX series_uid ON series (series_uid);

CREATE TABLE missing_blobs (
    kind         TEXT NOT NULL CHECK (kind IN ('series', 'dataset')),
    id           TEXT NOT NULL,
    detected_us  BIGINT NOT NULL,
    PRIMARY KEY (kind, id)
);
