-- Claims with an end, so that a database shared by several processes (the PostgreSQL twin) and this one
-- follow the same rule: a `sending` delivery belongs to the process that claimed it until
-- `claimed_until_us` (renewed while it sends), and a received instance pending assembly belongs to the
-- process assembling its series until its `claimed_until_us`. The one process that owns a SQLite database
-- releases both at start (whatever is left was its own, before a stop).
ALTER TABLE deliveries ADD COLUMN claimed_until_us INTEGER;
ALTER TABLE instances ADD COLUMN claimed_until_us INTEGER;
