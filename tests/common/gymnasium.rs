//! The Gymnasium reference trajectories in `tests/fixtures/` (made by
//! `scripts/make-fixtures.sh`): one under mild damage, one under severe damage with clipped
//! actions; every joint triggers in both.

use std::path::PathBuf;

/// (condition, path) of every fixture.
pub fn fixtures() -> [(&'static str, PathBuf); 2] {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures");
    ["mild", "severe"].map(|c| (c, dir.join(format!("gymnasium_ant_v4_{c}_parity.json"))))
}

/// The fixture's text; a missing file is a broken checkout, named as such.
pub fn read(path: &std::path::Path) -> String {
    std::fs::read_to_string(path)
        .unwrap_or_else(|e| panic!("fixture {} unreadable: {e}", path.display()))
}
