-- DICOM uploads and the CT series assembled from them.
-- An upload is `open` while instances are appended one by one, `completed` once its series were assembled.

CREATE TABLE uploads (
    id            TEXT PRIMARY KEY NOT NULL,        -- UUIDv7
    status        TEXT NOT NULL CHECK (status IN ('open', 'completed')),
    instances     INTEGER NOT NULL DEFAULT 0,
    bytes         INTEGER NOT NULL DEFAULT 0,
    outcome       TEXT,                             -- JSON of the completion (series, refused files)
    created_us    INTEGER NOT NULL,
    completed_us  INTEGER
);

-- Instances of an open upload; the file is uploads/<upload_id>/<sha256>.dcm.
CREATE TABLE upload_files (
    upload_id   TEXT NOT NULL REFERENCES uploads (id) ON DELETE CASCADE,
    sha256      TEXT NOT NULL,
    label       TEXT NOT NULL,                      -- client-supplied name, for messages only
    bytes       INTEGER NOT NULL,
    series_uid  TEXT NOT NULL,
    created_us  INTEGER NOT NULL,
    PRIMARY KEY (upload_id, sha256)
);

-- Assembled series; the HU volume is series/<id>.npy.
CREATE TABLE series (
    id          TEXT PRIMARY KEY NOT NULL,          -- UUIDv7
    upload_id   TEXT NOT NULL REFERENCES uploads (id),
    series_uid  TEXT NOT NULL,
    record      TEXT NOT NULL,                      -- JSON: report, frame, shape, HU range, warnings, file
    created_us  INTEGER NOT NULL
);

CREATE INDEX series_upload ON series (upload_id);
CREATE INDEX series_uid ON series (series_uid);
