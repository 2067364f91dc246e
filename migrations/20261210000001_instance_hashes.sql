-- The SHA-256 of each received instance's file, so that an instance sent again is recognised: the same SOP
-- Instance UID with the same content adds nothing, with other content it replaces the earlier copy (one
-- received copy per SOP Instance UID). NULL for rows indexed before (their next copy replaces them).
ALTER TABLE instances ADD COLUMN sha256 TEXT;
