-- Datasets imported from a scanner's files (`kind` 'scan'), with what the import recorded (`scan`: format,
-- provenance of every value read, notes, preprocessing steps; JSON).
ALTER TABLE datasets DROP CONSTRAINT datasets_kind_check;
ALTER TABLE datasets ADD CONSTRAINT datasets_kind_check CHECK (kind IN ('upload', 'simulation', 'scan'));
ALTER TABLE datasets ADD COLUMN scan TEXT;
