-- Datasets imported from a scanner's files (`kind` 'scan'), with what the import recorded (`scan`: format,
-- provenance of every value read, notes, preprocessing steps; JSON). SQLite cannot change a CHECK constraint
-- in place: the table is rebuilt (no other table references it).
CREATE TABLE datasets_new (
    id          TEXT PRIMARY KEY NOT NULL,          -- UUIDv7
    kind        TEXT NOT NULL CHECK (kind IN ('upload', 'simulation', 'scan')),
    geometry    TEXT NOT NULL,                      -- geometry JSON
    shape       TEXT NOT NULL,                      -- JSON array
    dtype       TEXT NOT NULL,                      -- float32 | float64 | uint16
    bytes       INTEGER NOT NULL,                   -- size of the stored .npy file
    sha256      TEXT NOT NULL,                      -- of the stored .npy file
    phantom     TEXT,                               -- simulation: phantom JSON (the truth)
    noise       TEXT,                               -- simulation: noise JSON
    created_us  INTEGER NOT NULL,
    scan        TEXT                                -- scan: import record JSON
);
INSERT INTO datasets_new (id, kind, geometry, shape, dtype, bytes, sha256, phantom, noise, created_us)
    SELECT id, kind, geometry, shape, dtype, bytes, sha256, phantom, noise, created_us FROM datasets;
DROP TABLE datasets;
ALTER TABLE datasets_new RENAME TO datasets;
