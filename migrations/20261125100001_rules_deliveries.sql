-- Automatic processing rules, the jobs they started, and deliveries of DICOM results to DIMSE peers.
-- Timestamps are microseconds since the Unix epoch (UTC); JSON columns hold the typed API objects.

-- A rule: match an arriving series → a volume job → destinations. `source` config rules are read at start.
CREATE TABLE rules (
    name        TEXT PRIMARY KEY NOT NULL,          -- [a-z0-9_-]{1,64}
    source      TEXT NOT NULL CHECK (source IN ('api', 'config')),
    spec        TEXT NOT NULL,                      -- rule JSON
    created_us  INTEGER NOT NULL,
    updated_us  INTEGER NOT NULL
);

-- A rule that fired for a series: one per rule and series content, so the same series arriving again does
-- not run twice.
CREATE TABLE rule_runs (
    id            TEXT PRIMARY KEY NOT NULL,        -- UUIDv7
    rule_name     TEXT NOT NULL,
    content_hash  TEXT NOT NULL,                    -- sha256 of the series UID and its assembled volume
    series_id     TEXT NOT NULL,
    series_uid    TEXT NOT NULL,
    calling_ae    TEXT,                             -- NULL: not received by DIMSE
    job_id        TEXT,                             -- NULL when the job was refused
    state         TEXT NOT NULL CHECK (state IN ('running', 'delivering', 'done', 'refused')),
    error         TEXT,                             -- problem JSON when refused or the job did not succeed
    created_us    INTEGER NOT NULL,
    UNIQUE (rule_name, content_hash)
);

CREATE INDEX rule_runs_state ON rule_runs (state);

-- One send of a job's DICOM results to one peer, retried with backoff while the peer is unreachable.
CREATE TABLE deliveries (
    id               TEXT PRIMARY KEY NOT NULL,     -- UUIDv7
    job_id           TEXT NOT NULL,
    run_id           TEXT,                          -- the rule run that asked for it; NULL: by hand
    rule_name        TEXT,
    destination      TEXT NOT NULL,                 -- AE title of a configured peer
    state            TEXT NOT NULL CHECK (state IN ('queued', 'sending', 'succeeded', 'failed')),
    attempts         INTEGER NOT NULL DEFAULT 0,
    next_attempt_us  INTEGER,                       -- when a queued delivery is due
    last_error       TEXT,
    created_us       INTEGER NOT NULL,
    updated_us       INTEGER NOT NULL,
    finished_us      INTEGER
);

CREATE INDEX deliveries_due ON deliveries (state, next_attempt_us);
CREATE INDEX deliveries_job ON deliveries (job_id);

-- The instances of a delivery (files under results/<job>/dicom/) and what the peer answered for each.
CREATE TABLE delivery_instances (
    delivery_id       TEXT NOT NULL REFERENCES deliveries (id) ON DELETE CASCADE,
    position          INTEGER NOT NULL,
    file              TEXT NOT NULL,
    sop_class_uid     TEXT NOT NULL,
    sop_instance_uid  TEXT NOT NULL,
    state             TEXT NOT NULL CHECK (state IN ('pending', 'succeeded', 'failed')),
    status            INTEGER,                      -- the peer's DIMSE status
    detail            TEXT,
    PRIMARY KEY (delivery_id, position)
);
