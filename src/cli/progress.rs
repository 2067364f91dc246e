//! A terminal progress bar as a [`Progress`] sink (hidden when stderr is not a terminal).

use std::io::IsTerminal;

use indicatif::{ProgressBar, ProgressStyle};

use crate::recon::Progress;

/// Progress shown on stderr.
pub struct Bar(ProgressBar);

impl Bar {
    pub fn new() -> Self {
        let bar = if std::io::stderr().is_terminal() {
            ProgressBar::new(1000)
        } else {
            ProgressBar::hidden()
        };
        if let Ok(style) =
            ProgressStyle::with_template("{msg:>14} [{bar:40}] {percent:>3}% {elapsed_precise}")
        {
            bar.set_style(style.progress_chars("=> "));
        }
        Self(bar)
    }
    pub fn finish(&self) {
        self.0.finish_and_clear();
    }
}

impl Default for Bar {
    fn default() -> Self {
        Self::new()
    }
}

impl Progress for Bar {
    fn report(&self, stage: &str, fraction: f64, iteration: Option<usize>, residual: Option<f64>) {
        self.0
            .set_position((fraction.clamp(0.0, 1.0) * 1000.0) as u64);
        let msg = match (iteration, residual) {
            (Some(i), Some(r)) => format!("{stage} {i} r={r:.3e}"),
            (Some(i), None) => format!("{stage} {i}"),
            _ => stage.to_string(),
        };
        self.0.set_message(msg);
    }
}
