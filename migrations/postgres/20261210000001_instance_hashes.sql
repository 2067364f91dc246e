-- Twin of ../20261210000001_instance_hashes.sql: the SHA-256 of each received instance's file, so that an
-- instance sent again is recognised (same SOP Instance UID and content: nothing added) or replaces the earlier
-- copy (other content). NULL for rows indexed before.
ALTER TABLE instances ADD COLUMN sha256 TEXT;
