-- Instances received by STOW-RS are indexed as they are stored and assembled into their series once the
-- series is stable (no instance of it for the stable age); `pending` marks those not yet assembled, so a
-- restart takes them up again.
ALTER TABLE instances ADD COLUMN pending INTEGER NOT NULL DEFAULT 0;
CREATE INDEX instances_pending ON instances (pending) WHERE pending = 1;
