//! The stock Rerun viewer: finding a binary whose version matches our SDK, spawning it, and
//! opening recordings in it. We never compile the viewer (see README: `make viewer`).

use std::path::{Path, PathBuf};
use std::process::Command;

/// Environment variable naming a viewer binary to use.
pub const VIEWER_ENV: &str = "GAITSCOPE_RERUN";
/// Where `scripts/setup.sh --viewer` unpacks the viewer from PyPI's rerun-sdk wheel.
pub const BUNDLED_VIEWER: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/.deps/rerun/rerun");
/// Window size the viewer is spawned with (fits next to the panel on a 1920×1080 screen).
pub const VIEWER_WINDOW_SIZE: &str = "1400x1000";

const HOW_TO_GET: &str = "get the matching viewer with `make viewer` (unpacks rerun from PyPI's \
rerun-sdk wheel into .deps/rerun/) or `pip install rerun-sdk==VERSION`, or point --viewer / \
GAITSCOPE_RERUN at one";

#[derive(Debug, thiserror::Error)]
pub enum ViewerError {
    #[error("no Rerun viewer found (looked at {searched}); {how}", how = how_to_get())]
    NotFound { searched: String },
    #[error("the Rerun viewer at {path} is version {found}, but gaitscope logs with the Rerun SDK {expected} (the major.minor versions must match); {how}", how = how_to_get())]
    VersionMismatch {
        path: PathBuf,
        found: String,
        expected: String,
    },
    #[error("cannot run the Rerun viewer at {path}: {reason}")]
    NotRunnable {
        path: PathBuf,
        #[source]
        reason: crate::Cause,
    },
    #[error(
        "no display: {what} needs a window (DISPLAY and WAYLAND_DISPLAY are unset). {hint}",
        hint = headless_hint(what)
    )]
    NoDisplay { what: &'static str },
    #[error("{0} not found")]
    RecordingNotFound(PathBuf),
    #[error("spawning the Rerun viewer: {0}")]
    Spawn(#[source] crate::Cause),
    #[error(
        "no Rerun viewer is listening at {url} ({reason}); start one there (`rerun`, or \
         `make viewer` then `.deps/rerun/rerun`), or leave out --connect to spawn one"
    )]
    Unreachable {
        url: String,
        #[source]
        reason: crate::Cause,
    },
    #[error("{path} is not a Rerun recording: {reason}")]
    NotARecording {
        path: PathBuf,
        #[source]
        reason: crate::Cause,
    },
}

fn how_to_get() -> String {
    HOW_TO_GET.replace("VERSION", &sdk_version())
}

/// The Rerun SDK version we log with, e.g. `0.41.0`.
pub fn sdk_version() -> String {
    rerun::external::re_build_info::CrateVersion::LOCAL.to_string()
}

/// `rerun --version` prints `rerun-cli 0.41.0 (features…) …`: the version is the second word.
pub fn parse_viewer_version(output: &str) -> Option<(u64, u64, u64)> {
    let word = output.split_whitespace().nth(1)?;
    let mut parts = word.split(['.', '-', '+']).map(|p| p.parse::<u64>().ok());
    Some((parts.next()??, parts.next()??, parts.next()??))
}

/// Rerun's own rule: viewer and SDK agree on major and minor.
pub fn versions_compatible(viewer: (u64, u64, u64), sdk: (u64, u64, u64)) -> bool {
    viewer.0 == sdk.0 && viewer.1 == sdk.1
}

fn sdk_triple() -> (u64, u64, u64) {
    let v = rerun::external::re_build_info::CrateVersion::LOCAL;
    (u64::from(v.major), u64::from(v.minor), u64::from(v.patch))
}

/// Checks that `path` runs and has a compatible version.
pub fn check_viewer(path: &Path) -> Result<(), ViewerError> {
    let output =
        Command::new(path)
            .arg("--version")
            .output()
            .map_err(|e| ViewerError::NotRunnable {
                path: path.to_path_buf(),
                reason: e.into(),
            })?;
    let text = String::from_utf8_lossy(&output.stdout);
    let found = parse_viewer_version(&text).ok_or_else(|| ViewerError::NotRunnable {
        path: path.to_path_buf(),
        reason: format!(
            "`--version` printed {:?}, not `rerun-cli X.Y.Z …` (stderr: {})",
            text.trim(),
            String::from_utf8_lossy(&output.stderr).trim()
        )
        .into(),
    })?;
    if !versions_compatible(found, sdk_triple()) {
        return Err(ViewerError::VersionMismatch {
            path: path.to_path_buf(),
            found: format!("{}.{}.{}", found.0, found.1, found.2),
            expected: sdk_version(),
        });
    }
    Ok(())
}

/// The viewer to use: `explicit` (--viewer), else $GAITSCOPE_RERUN, else the one setup unpacked,
/// else `rerun` on PATH; the first that exists must also have a matching version.
pub fn find_viewer(explicit: Option<&Path>) -> Result<PathBuf, ViewerError> {
    let mut candidates: Vec<PathBuf> = Vec::new();
    if let Some(p) = explicit {
        candidates.push(p.to_path_buf());
    } else if let Some(p) = std::env::var_os(VIEWER_ENV).filter(|p| !p.is_empty()) {
        candidates.push(PathBuf::from(p));
    } else {
        candidates.push(PathBuf::from(BUNDLED_VIEWER));
        if let Some(path) = std::env::var_os("PATH") {
            candidates.extend(std::env::split_paths(&path).map(|d| d.join("rerun")));
        }
    }
    match candidates.iter().find(|p| p.is_file()) {
        Some(path) => {
            check_viewer(path)?;
            Ok(path.clone())
        }
        None => Err(ViewerError::NotFound {
            searched: if explicit.is_some() || candidates.len() == 1 {
                candidates[0].display().to_string()
            } else {
                format!("{BUNDLED_VIEWER} and `rerun` on PATH")
            },
        }),
    }
}

/// Fails with a message naming the headless alternative when there is no display to open
/// windows on.
/// What to do instead without a display: the browser first where the command has a web mode.
fn headless_hint(what: &str) -> &'static str {
    if what.contains("live") {
        "Headless, use `gaitscope live --web` (the viewer and the control panel in a browser, \
         e.g. through an SSH tunnel), or `gaitscope record --checkpoint DIR --out FILE.rrd` and \
         open the file where there is a display"
    } else {
        "Headless, open the file on a machine with a display (`gaitscope view FILE.rrd`), or \
         run under Xvfb (scripts/screenshot.sh)"
    }
}

pub fn require_display(what: &'static str) -> Result<(), ViewerError> {
    let set = |k: &str| std::env::var_os(k).is_some_and(|v| !v.is_empty());
    if cfg!(target_os = "linux") && !set("DISPLAY") && !set("WAYLAND_DISPLAY") {
        return Err(ViewerError::NoDisplay { what });
    }
    Ok(())
}

/// A viewer `live` streams to: its address, and its process when this process started it
/// (none when one already listening on Rerun's port was reused).
#[derive(Debug)]
pub struct SpawnedViewer {
    pub url: String,
    pub pid: Option<u32>,
}

impl SpawnedViewer {
    /// Ends the viewer this process started (a scripted `--exit-after` run leaves nothing
    /// behind): SIGTERM, reaped within `patience`, SIGKILL after. Whether one was stopped.
    pub fn stop(&self, patience: std::time::Duration) -> bool {
        let Some(pid) = self.pid else {
            return false;
        };
        let Ok(pid) = libc::pid_t::try_from(pid) else {
            return false;
        };
        // SAFETY: plain syscalls on our own child (found by parent pid and executable), which
        // stays ours until reaped here, so the pid cannot have been reused.
        unsafe {
            libc::kill(pid, libc::SIGTERM);
            let deadline = std::time::Instant::now() + patience;
            let mut status = 0;
            while libc::waitpid(pid, &mut status, libc::WNOHANG) == 0 {
                if std::time::Instant::now() >= deadline {
                    libc::kill(pid, libc::SIGKILL);
                    libc::waitpid(pid, &mut status, 0);
                    break;
                }
                std::thread::sleep(std::time::Duration::from_millis(20));
            }
        }
        true
    }
}

/// This process's children running `exe` (by /proc: parent pid and executable).
fn children_running(exe: &Path) -> Vec<u32> {
    let me = std::process::id();
    let Ok(exe) = exe.canonicalize() else {
        return Vec::new();
    };
    let parent = |pid: u32| -> Option<u32> {
        let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
        // "pid (comm) state ppid …": comm may hold spaces, so split after its ')'.
        stat.rsplit_once(')')?
            .1
            .split_whitespace()
            .nth(1)?
            .parse()
            .ok()
    };
    let Ok(entries) = std::fs::read_dir("/proc") else {
        return Vec::new();
    };
    entries
        .filter_map(|e| e.ok()?.file_name().to_str()?.parse::<u32>().ok())
        .filter(|&pid| parent(pid) == Some(me))
        .filter(|&pid| std::fs::read_link(format!("/proc/{pid}/exe")).is_ok_and(|p| p == exe))
        .collect()
}

/// Starts the viewer listening for our stream (or reuses one already listening on Rerun's
/// port): the address to stream to, and the process if it is ours.
pub fn spawn_viewer(viewer: &Path) -> Result<SpawnedViewer, ViewerError> {
    let before = children_running(viewer);
    let opts = rerun::SpawnOptions {
        executable_path: Some(viewer.display().to_string()),
        // Loopback only: Rerun's default bind (0.0.0.0) would let anyone on the network
        // connect and receive the session.
        extra_args: vec![
            "--window-size".into(),
            VIEWER_WINDOW_SIZE.into(),
            "--bind".into(),
            "127.0.0.1".into(),
        ],
        hide_welcome_screen: true,
        wait_for_bind: true,
        ..Default::default()
    };
    let info = rerun::spawn(&opts).map_err(|e| ViewerError::Spawn(e.into()))?;
    let pid = children_running(viewer)
        .into_iter()
        .find(|pid| !before.contains(pid));
    Ok(SpawnedViewer {
        url: format!("rerun+http://127.0.0.1:{}/proxy", info.port),
        pid,
    })
}

/// Checks that something listens at a `rerun+http(s)://HOST:PORT/proxy` address, so that
/// `live --connect` fails at once instead of streaming into the void.
pub fn check_reachable(url: &str) -> Result<(), ViewerError> {
    use std::net::ToSocketAddrs;
    let err = |reason: String| ViewerError::Unreachable {
        url: url.to_string(),
        reason: reason.into(),
    };
    let rest = url.split_once("://").map_or(url, |(_, rest)| rest);
    let authority = rest.split('/').next().unwrap_or(rest);
    let addrs: Vec<std::net::SocketAddr> = authority
        .to_socket_addrs()
        .map_err(|e| err(format!("cannot resolve '{authority}': {e}")))?
        .collect();
    let timeout = std::time::Duration::from_secs(2);
    if addrs
        .iter()
        .any(|a| std::net::TcpStream::connect_timeout(a, timeout).is_ok())
    {
        Ok(())
    } else {
        Err(err(format!("nothing accepted a connection at {authority}")))
    }
}

/// Checks that `path` is a readable Rerun recording (by its magic bytes).
pub fn check_recording(path: &Path) -> Result<(), ViewerError> {
    use std::io::Read;
    let err = |reason: String| ViewerError::NotARecording {
        path: path.to_path_buf(),
        reason: reason.into(),
    };
    if !path.exists() {
        return Err(ViewerError::RecordingNotFound(path.to_path_buf()));
    }
    let mut magic = [0u8; 4];
    crate::files::open_regular(path)
        .and_then(|mut f| f.read_exact(&mut magic))
        .map_err(|e| err(e.to_string()))?;
    if &magic[..3] != b"RRF" {
        return Err(err(format!(
            "it starts with {magic:?}, not Rerun's RRF header"
        )));
    }
    Ok(())
}

/// Opens a recording in the viewer (its default blueprint is stored in the file) and waits for
/// the viewer to close.
pub fn view_recording(viewer: &Path, recording: &Path) -> Result<(), ViewerError> {
    check_recording(recording)?;
    let status = Command::new(viewer)
        .arg("--window-size")
        .arg(VIEWER_WINDOW_SIZE)
        .arg(recording)
        .status()
        .map_err(|e| ViewerError::NotRunnable {
            path: viewer.to_path_buf(),
            reason: e.into(),
        })?;
    if !status.success() {
        return Err(ViewerError::NotRunnable {
            path: viewer.to_path_buf(),
            reason: format!("it exited with {status}").into(),
        });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn viewer_versions_parse_and_match_on_major_minor() {
        let out = "rerun-cli 0.36.3 (base native_viewer) [rustc 1.95.0] x86_64-unknown-linux-gnu";
        assert_eq!(parse_viewer_version(out), Some((0, 36, 3)));
        assert_eq!(
            parse_viewer_version("rerun-cli 0.37.0-alpha.1"),
            Some((0, 37, 0))
        );
        assert_eq!(parse_viewer_version("command not found"), None);
        assert_eq!(parse_viewer_version(""), None);
        assert!(versions_compatible((0, 36, 0), (0, 36, 3)));
        assert!(!versions_compatible((0, 35, 3), (0, 36, 3)));
        assert!(!versions_compatible((1, 36, 3), (0, 36, 3)));
    }

    #[test]
    fn a_missing_or_wrong_viewer_is_a_clear_error() {
        let dir = tempfile::tempdir().unwrap();
        let missing = dir.path().join("rerun");
        let e = find_viewer(Some(&missing)).unwrap_err().to_string();
        assert!(
            e.contains("no Rerun viewer found") && e.contains("make viewer"),
            "{e}"
        );
        // A "viewer" that reports another version.
        let fake = dir.path().join("old-rerun");
        std::fs::write(&fake, "#!/bin/sh\necho 'rerun-cli 0.20.1 (x)'\n").unwrap();
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&fake, std::fs::Permissions::from_mode(0o755)).unwrap();
        let e = find_viewer(Some(&fake)).unwrap_err().to_string();
        assert!(
            e.contains("version 0.20.1") && e.contains(&sdk_version()),
            "{e}"
        );
    }

    #[test]
    fn connect_addresses_are_checked_for_a_listener() {
        let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let port = listener.local_addr().unwrap().port();
        assert!(check_reachable(&format!("rerun+http://127.0.0.1:{port}/proxy")).is_ok());
        // Port 0 can never hold a listener; a just-closed port can (sandboxed network
        // stacks keep accepting for a moment, and the port may be handed out again).
        let e = check_reachable("rerun+http://127.0.0.1:0/proxy")
            .unwrap_err()
            .to_string();
        assert!(e.contains("no Rerun viewer is listening"), "{e}");
        let e = check_reachable("rerun+http://no-port-given/proxy")
            .unwrap_err()
            .to_string();
        assert!(e.contains("cannot resolve 'no-port-given'"), "{e}");
    }

    #[test]
    fn recordings_are_recognised_by_their_header() {
        let dir = tempfile::tempdir().unwrap();
        let bad = dir.path().join("notes.rrd");
        std::fs::write(&bad, "hello world").unwrap();
        let e = check_recording(&bad).unwrap_err().to_string();
        assert!(e.contains("not a Rerun recording"), "{e}");
        let e = check_recording(&dir.path().join("absent.rrd"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("absent.rrd"), "{e}");
        std::fs::write(&bad, b"RRF2\x00\x00\x00\x00").unwrap();
        assert!(check_recording(&bad).is_ok());
    }
}
