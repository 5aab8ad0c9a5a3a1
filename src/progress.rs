//! One look for long work's progress bars (eval, probe, video): a bar with ETA on a terminal,
//! nothing when stderr is piped (indicatif hides a bar whose target is not a terminal).

use indicatif::{ProgressBar, ProgressStyle};

/// A bar of `len` units, `what` before it.
pub fn bar(len: u64, what: &str) -> ProgressBar {
    let bar = ProgressBar::new(len);
    let style = ProgressStyle::with_template(
        "{prefix} {bar:30} {pos}/{len} [{elapsed_precise} < {eta_precise}] {msg}",
    )
    .unwrap_or_else(|_| ProgressStyle::default_bar());
    bar.set_style(style);
    bar.set_prefix(what.to_string());
    bar
}
