-- A running job's lease: the worker that claimed it renews it (heartbeat); when it expires (the worker died
-- or lost the database) the job goes back to the queue. NULL when the job is not running, or was claimed
-- without a lease.

ALTER TABLE jobs ADD COLUMN lease_expires_us INTEGER;
