-- The PostgreSQL twin of the DICOM node's tables (the SQLite migrations 20261125100001_rules_deliveries,
-- 20261125200001_instances, 20261126000001_pending_instances and 20261127000001_claims): processing rules,
-- their runs, deliveries with their instances, and the instance index. The same columns and meanings;
-- every integer is BIGINT, JSON columns hold text.
--
-- With several processes on one database:
-- - a rule run is unique per rule and series content, so the same series assembled by two processes starts
--   one job (the second insert does nothing);
-- - a delivery is claimed by one process (`FOR UPDATE SKIP LOCKED`) until `claimed_until_us`, which the
--   process renews while it sends; only a delivery whose claim expired is queued again by another process;
-- - `indexed_jobs` is taken in the same transaction as a job's instance rows, so a job's results are
--   indexed once however many processes try;
-- - received instances pending assembly are claimed (`claimed_until_us`) by the process that assembles
--   their series, so two processes do not assemble the same arrival twice.

CREATE TABLE rules (
    name        TEXT PRIMARY KEY NOT NULL,
    source      TEXT NOT NULL CHECK (source IN ('api', 'config')),
    spec        TEXT NOT NULL,
    created_us  BIGINT NOT NULL,
    updated_us  BIGINT NOT NULL
);

CREATE TABLE rule_runs (
    id            TEXT PRIMARY KEY NOT NULL,
    rule_name     TEXT NOT NULL,
    content_hash  TEXT NOT NULL,
    series_id     TEXT NOT NULL,
    series_uid    TEXT NOT NULL,
    calling_ae    TEXT,
    job_id        TEXT,
    state         TEXT NOT NULL CHECK (state IN ('running', 'delivering', 'done', 'refused')),
    error         TEXT,
    created_us    BIGINT NOT NULL,
    UNIQUE (rule_name, content_hash)
);

CREATE INDEX rule_runs_state ON rule_runs (state);
CREATE INDEX rule_runs_job ON rule_runs (job_id);

CREATE TABLE deliveries (
    id                TEXT PRIMARY KEY NOT NULL,
    job_id            TEXT NOT NULL,
    run_id            TEXT,
    rule_name         TEXT,
    destination       TEXT NOT NULL,
    state             TEXT NOT NULL CHECK (state IN ('queued', 'sending', 'succeeded', 'failed')),
    attempts          BIGINT NOT NULL DEFAULT 0,
    next_attempt_us   BIGINT,
    last_error        TEXT,
    created_us        BIGINT NOT NULL,
    updated_us        BIGINT NOT NULL,
    finished_us       BIGINT,
    -- A sending delivery belongs to the process that claimed it until then.
    claimed_until_us  BIGINT
);

CREATE INDEX deliveries_due ON deliveries (state, next_attempt_us);
CREATE INDEX deliveries_job ON deliveries (job_id);
CREATE INDEX deliveries_run ON deliveries (run_id);

CREATE TABLE delivery_instances (
    delivery_id       TEXT NOT NULL REFERENCES deliveries (id) ON DELETE CASCADE,
    position          BIGINT NOT NULL,
    file              TEXT NOT NULL,
    sop_class_uid     TEXT NOT NULL,
    sop_instance_uid  TEXT NOT NULL,
    state             TEXT NOT NULL CHECK (state IN ('pending', 'succeeded', 'failed')),
    status            BIGINT,
    detail            TEXT,
    PRIMARY KEY (delivery_id, position)
);

CREATE TABLE instances (
    id                   TEXT PRIMARY KEY NOT NULL,
    upload_id            TEXT REFERENCES uploads (id) ON DELETE CASCADE,
    series_id            TEXT REFERENCES series (id) ON DELETE CASCADE,
    job_id               TEXT REFERENCES jobs (id) ON DELETE CASCADE,
    sop_class_uid        TEXT NOT NULL,
    sop_instance_uid     TEXT NOT NULL,
    transfer_syntax      TEXT NOT NULL,
    study_uid            TEXT NOT NULL,
    series_uid           TEXT NOT NULL,
    patient_id           TEXT,
    patient_name         TEXT,
    patient_birth_date   TEXT,
    patient_sex          TEXT,
    study_date           TEXT,
    study_time           TEXT,
    accession_number     TEXT,
    study_description    TEXT,
    referring_physician  TEXT,
    study_id             TEXT,
    modality             TEXT,
    series_number        BIGINT,
    series_description   TEXT,
    body_part            TEXT,
    instance_number      BIGINT,
    bytes                BIGINT NOT NULL,
    created_us           BIGINT NOT NULL,
    pending              BIGINT NOT NULL DEFAULT 0,
    -- A pending instance belongs to the process assembling its series until then.
    claimed_until_us     BIGINT,
    CHECK ((upload_id IS NULL) <> (job_id IS NULL))
);

CREATE INDEX instances_study ON instances (study_uid);
CREATE INDEX instances_series ON instances (series_uid);
CREATE INDEX instances_sop ON instances (sop_instance_uid);
CREATE INDEX instances_upload ON instances (upload_id);
CREATE INDEX instances_series_id ON instances (series_id);
CREATE INDEX instances_job ON instances (job_id);
CREATE INDEX instances_pending ON instances (pending) WHERE pending = 1;

CREATE TABLE indexed_jobs (
    job_id      TEXT PRIMARY KEY NOT NULL REFERENCES jobs (id) ON DELETE CASCADE,
    instances   BIGINT NOT NULL,
    created_us  BIGINT NOT NULL
);
