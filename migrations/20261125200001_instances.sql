-- The instance index: every DICOM instance ctrecon holds and answers C-FIND/C-MOVE (and later QIDO-RS/WADO-RS)
-- with, at patient, study, series and instance level in one row each (the index is small; levels are
-- grouped when queried). Received instances belong to the upload that recorded them (the file is
-- instances/<upload_id>/<id>.dcm) and, when their series was assembled, to that series; derived results
-- belong to the job that made them (the file is results/<job_id>/instances/<id>.dcm). Deleting the upload,
-- series or job deletes its rows.

CREATE TABLE instances (
    id                   TEXT PRIMARY KEY NOT NULL,   -- UUIDv7, names the file
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
    series_number        INTEGER,
    series_description   TEXT,
    body_part            TEXT,
    instance_number      INTEGER,
    bytes                INTEGER NOT NULL,
    created_us           INTEGER NOT NULL,
    CHECK ((upload_id IS NULL) <> (job_id IS NULL))
);

CREATE INDEX instances_study ON instances (study_uid);
CREATE INDEX instances_series ON instances (series_uid);
CREATE INDEX instances_sop ON instances (sop_instance_uid);
CREATE INDEX instances_upload ON instances (upload_id);
CREATE INDEX instances_series_id ON instances (series_id);
CREATE INDEX instances_job ON instances (job_id);

-- Succeeded jobs whose DICOM results were indexed (with none when the job has no source series), so the
-- catch-up at start does not write them twice.
CREATE TABLE indexed_jobs (
    job_id      TEXT PRIMARY KEY NOT NULL REFERENCES jobs (id) ON DELETE CASCADE,
    instances   INTEGER NOT NULL,
    created_us  INTEGER NOT NULL
);
