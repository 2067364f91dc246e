//! Jobs: model and state machine, SQL repository, queue, rayon worker bridge, artifacts.
