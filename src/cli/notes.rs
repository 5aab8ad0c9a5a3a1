//! The library reports what it notices on the way (a refilled buffer, a dropped metrics line)
//! through the `log` facade rather than printing (issue 50: printing at the edge). The binary
//! prints gaitscope's own notes and warnings on stderr; other crates' log lines stay silent, as
//! they were before a logger existed.

use log::{Level, LevelFilter, Log, Metadata, Record};

struct Notes;

impl Log for Notes {
    fn enabled(&self, metadata: &Metadata<'_>) -> bool {
        metadata.level() <= Level::Info && is_ours(metadata.target())
    }

    fn log(&self, record: &Record<'_>) {
        if self.enabled(record.metadata()) {
            eprintln!("{}", line(record.level(), record.args()));
        }
    }

    fn flush(&self) {}
}

fn is_ours(target: &str) -> bool {
    target == "gaitscope" || target.starts_with("gaitscope::")
}

/// The line a user sees: `note: …` for information, `warning: …` and `error: …` otherwise.
fn line(level: Level, message: &std::fmt::Arguments<'_>) -> String {
    let tag = match level {
        Level::Error => "error",
        Level::Warn => "warning",
        Level::Info | Level::Debug | Level::Trace => "note",
    };
    format!("{tag}: {message}")
}

/// Installs the logger once, before any command runs.
pub(crate) fn install() {
    static NOTES: Notes = Notes;
    // Fails only when a logger is already set, which then keeps printing.
    if log::set_logger(&NOTES).is_ok() {
        log::set_max_level(LevelFilter::Info);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_gaitscope_notes_and_warnings_print() {
        let notes = Notes;
        let meta = |level, target| Metadata::builder().level(level).target(target).build();
        assert!(notes.enabled(&meta(Level::Info, "gaitscope::train::resume")));
        assert!(notes.enabled(&meta(Level::Warn, "gaitscope")));
        assert!(!notes.enabled(&meta(Level::Debug, "gaitscope::train")));
        assert!(!notes.enabled(&meta(Level::Warn, "re_sdk::recording_stream")));
        assert!(!notes.enabled(&meta(Level::Info, "gaitscopeish")));
        assert_eq!(line(Level::Warn, &format_args!("x {}", 1)), "warning: x 1");
        assert_eq!(
            line(Level::Info, &format_args!("refilled")),
            "note: refilled"
        );
    }
}
