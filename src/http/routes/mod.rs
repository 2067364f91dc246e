//! Route handlers, one file per resource.

pub mod datasets;
pub mod dicomweb;
pub mod events;
pub mod feed;
pub mod health;
pub mod jobs;
pub mod limits;
pub mod results;
pub mod rules;
pub mod scans;
pub mod series;
pub mod stow;
pub mod uploads;
