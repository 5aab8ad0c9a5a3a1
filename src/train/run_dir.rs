//! A training run's folder on disk: one trainer at a time, and checkpoints that land as a set.
//!
//! A checkpoint generation is several files (weights, `checkpoint.json`, optimiser state, train
//! state, replay buffer). Renaming them one by one would let a kill in between pair new weights
//! with an old optimiser or buffer, so a save is a small redo log:
//! 1. every file is written and fsynced under a staging name (`NAME.staged.tmp`);
//! 2. a manifest (`save-pending.json`: each file's name, length and CRC-32) is written atomically;
//! 3. each staged file is renamed over its final name;
//! 4. the manifest is removed.
//!
//! A kill before 2 leaves the previous generation untouched (the staged files are dropped on the
//! next open); a kill after 2 leaves a manifest that [`RunDir::recover`] completes. Readers
//! (`eval`, `probe`) take no lock; the weights' CRC in `checkpoint.json` catches the instant of
//! step 3 for them.

use serde::{Deserialize, Serialize};
use std::fs::File;
use std::io::{Read, Write};
use std::path::{Path, PathBuf};

use crate::policy::checkpoint::{CheckpointError, write_atomic};

/// Held (flock) by the trainer for its whole life; holds its pid as text.
pub const LOCK_FILE: &str = "train.lock";
/// The manifest of a save whose files are staged but not all renamed into place yet.
pub const PENDING_FILE: &str = crate::policy::checkpoint::PENDING_SAVE_FILE;
const STAGING_SUFFIX: &str = ".staged.tmp";

#[derive(Debug, thiserror::Error)]
pub enum RunDirError {
    #[error(
        "{dir} is being trained by another process (pid {holder}); stop that trainer first (Ctrl-C, or `scripts/seed-runs.sh stop`)"
    )]
    Locked { dir: PathBuf, holder: String },
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
    #[error("{path}: cannot complete the interrupted save: {reason}")]
    Recover {
        path: PathBuf,
        #[source]
        reason: crate::Cause,
    },
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> RunDirError + '_ {
    move |source| RunDirError::Io {
        path: path.to_owned(),
        source,
    }
}

/// Which folder a file of a generation lives in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Place {
    /// The run folder.
    Run,
    /// The replay folder (`train --replay-dir`; the run folder by default).
    Replay,
}

/// One file of a generation, as the manifest lists it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct ManifestEntry {
    name: String,
    place: Place,
    len: u64,
    crc32: u32,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct Manifest {
    step: u64,
    files: Vec<ManifestEntry>,
}

/// A point inside a save, for the fault-injection tests: the hook is called after each one, and
/// an error from it ends the save right there, as a kill would (nothing is cleaned up).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SaveStage {
    /// The i-th file is written and fsynced under its staging name.
    Staged(usize),
    /// The manifest is in place: from here on the new generation wins.
    ManifestWritten,
    /// The i-th file is renamed over its final name.
    Renamed(usize),
    /// The manifest is removed: the save is complete.
    Done,
}

/// What [`RunDir::recover`] found.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Recovery {
    /// No interrupted save.
    Clean,
    /// A save was interrupted before its manifest: its staged files were dropped and the
    /// previous generation stands.
    RolledBack { dropped: usize },
    /// A save was interrupted after its manifest: it was completed (generation `step`).
    /// `missing_replay` names a replay buffer that was not found (another `--replay-dir`).
    RolledForward {
        step: u64,
        missing_replay: Option<PathBuf>,
    },
}

/// A run folder locked for one trainer.
#[derive(Debug)]
pub struct RunDir {
    dir: PathBuf,
    replay_dir: PathBuf,
    /// Keeps the OS lock; released when dropped or when the process dies.
    _lock: File,
}

impl RunDir {
    /// Creates the folders if needed and takes the run's exclusive lock, or says who holds it.
    pub fn lock(dir: &Path, replay_dir: &Path) -> Result<Self, RunDirError> {
        for d in [dir, replay_dir] {
            std::fs::create_dir_all(d).map_err(io(d))?;
        }
        let path = dir.join(LOCK_FILE);
        let mut file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path)
            .map_err(io(&path))?;
        match file.try_lock() {
            Ok(()) => {}
            Err(std::fs::TryLockError::WouldBlock) => {
                let mut holder = String::new();
                let _ = file.read_to_string(&mut holder);
                let holder = match holder.trim() {
                    "" => "unknown".to_string(),
                    pid => pid.to_string(),
                };
                return Err(RunDirError::Locked {
                    dir: dir.to_owned(),
                    holder,
                });
            }
            Err(std::fs::TryLockError::Error(e)) => return Err(io(&path)(e)),
        }
        file.set_len(0).map_err(io(&path))?;
        file.write_all(std::process::id().to_string().as_bytes())
            .map_err(io(&path))?;
        Ok(Self {
            dir: dir.to_owned(),
            replay_dir: replay_dir.to_owned(),
            _lock: file,
        })
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }

    pub fn replay_dir(&self) -> &Path {
        &self.replay_dir
    }

    pub fn path(&self, place: Place, name: &str) -> PathBuf {
        match place {
            Place::Run => self.dir.join(name),
            Place::Replay => self.replay_dir.join(name),
        }
    }

    /// Finishes or drops an interrupted save, so the folder holds exactly one generation.
    pub fn recover(&self) -> Result<Recovery, RunDirError> {
        let manifest_path = self.dir.join(PENDING_FILE);
        let Some(text) = read_if_exists(&manifest_path)? else {
            let dropped = self.drop_staged()?;
            return Ok(if dropped == 0 {
                Recovery::Clean
            } else {
                Recovery::RolledBack { dropped }
            });
        };
        let bad = |reason: String| RunDirError::Recover {
            path: manifest_path.clone(),
            reason: reason.into(),
        };
        let manifest: Manifest =
            serde_json::from_slice(&text).map_err(|e| bad(format!("unreadable manifest: {e}")))?;
        let mut missing_replay = None;
        for entry in &manifest.files {
            let target = self.path(entry.place, &entry.name);
            let staged = staging_path(&target);
            if staged.exists() {
                let bytes = std::fs::read(&staged).map_err(io(&staged))?;
                if !entry.matches(&bytes) {
                    return Err(bad(format!(
                        "{} does not match the manifest (disk corruption?)",
                        staged.display()
                    )));
                }
                std::fs::rename(&staged, &target).map_err(io(&target))?;
            } else {
                match read_if_exists(&target)? {
                    Some(bytes) if entry.matches(&bytes) => {}
                    // A buffer kept elsewhere (`--replay-dir`) on a machine that no longer has it:
                    // the generation stands without it, and the resume refills.
                    None if entry.place == Place::Replay => missing_replay = Some(target),
                    _ => {
                        return Err(bad(format!(
                            "neither a staged nor a final {} matching the manifest",
                            target.display()
                        )));
                    }
                }
            }
        }
        sync_dir(&self.dir)?;
        std::fs::remove_file(&manifest_path).map_err(io(&manifest_path))?;
        Ok(Recovery::RolledForward {
            step: manifest.step,
            missing_replay,
        })
    }

    /// Writes one generation as a set (see the module doc).
    pub fn commit(&self, step: u64, files: &[(Place, &str, &[u8])]) -> Result<(), RunDirError> {
        self.commit_with(step, files, &mut |_| Ok(()))
    }

    /// [`Self::commit`] with a hook after each stage (fault injection in the tests).
    pub fn commit_with(
        &self,
        step: u64,
        files: &[(Place, &str, &[u8])],
        hook: &mut dyn FnMut(SaveStage) -> std::io::Result<()>,
    ) -> Result<(), RunDirError> {
        let hooked = |stage: SaveStage, hook: &mut dyn FnMut(SaveStage) -> std::io::Result<()>| {
            hook(stage).map_err(|source| RunDirError::Io {
                path: self.dir.clone(),
                source,
            })
        };
        let mut entries = Vec::with_capacity(files.len());
        for (i, &(place, name, bytes)) in files.iter().enumerate() {
            let target = self.path(place, name);
            let staged = staging_path(&target);
            let mut file = File::create(&staged).map_err(io(&staged))?;
            file.write_all(bytes).map_err(io(&staged))?;
            file.sync_all().map_err(io(&staged))?;
            entries.push(ManifestEntry {
                name: name.to_string(),
                place,
                len: bytes.len() as u64,
                crc32: crc32fast::hash(bytes),
            });
            hooked(SaveStage::Staged(i), hook)?;
        }
        let manifest = Manifest {
            step,
            files: entries,
        };
        let manifest_path = self.dir.join(PENDING_FILE);
        let json = serde_json::to_vec_pretty(&manifest).map_err(|e| RunDirError::Recover {
            path: manifest_path.clone(),
            reason: e.into(),
        })?;
        write_atomic(&manifest_path, &json)?;
        sync_dir(&self.dir)?;
        hooked(SaveStage::ManifestWritten, hook)?;
        for (i, &(place, name, _)) in files.iter().enumerate() {
            let target = self.path(place, name);
            std::fs::rename(staging_path(&target), &target).map_err(io(&target))?;
            hooked(SaveStage::Renamed(i), hook)?;
        }
        sync_dir(&self.dir)?;
        if self.replay_dir != self.dir {
            sync_dir(&self.replay_dir)?;
        }
        std::fs::remove_file(&manifest_path).map_err(io(&manifest_path))?;
        hooked(SaveStage::Done, hook)
    }

    /// Removes staged files of a save that never wrote its manifest.
    fn drop_staged(&self) -> Result<usize, RunDirError> {
        let mut dropped = 0;
        let mut dirs = vec![&self.dir];
        if self.replay_dir != self.dir {
            dirs.push(&self.replay_dir);
        }
        for dir in dirs {
            let entries = std::fs::read_dir(dir).map_err(io(dir))?;
            for entry in entries {
                let path = entry.map_err(io(dir))?.path();
                let staged = path
                    .file_name()
                    .and_then(|n| n.to_str())
                    .is_some_and(|n| n.ends_with(STAGING_SUFFIX));
                if staged {
                    std::fs::remove_file(&path).map_err(io(&path))?;
                    dropped += 1;
                }
            }
        }
        Ok(dropped)
    }
}

impl ManifestEntry {
    fn matches(&self, bytes: &[u8]) -> bool {
        bytes.len() as u64 == self.len && crc32fast::hash(bytes) == self.crc32
    }
}

/// True when `dir` holds a save that a trainer must complete before the weights can be read.
pub fn has_pending_save(dir: &Path) -> bool {
    dir.join(PENDING_FILE).exists()
}

fn staging_path(target: &Path) -> PathBuf {
    let mut name = target.file_name().unwrap_or_default().to_os_string();
    name.push(STAGING_SUFFIX);
    target.with_file_name(name)
}

fn read_if_exists(path: &Path) -> Result<Option<Vec<u8>>, RunDirError> {
    match std::fs::read(path) {
        Ok(bytes) => Ok(Some(bytes)),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(e) => Err(io(path)(e)),
    }
}

/// Makes the folder's renames durable (a rename lives in the directory's own data).
fn sync_dir(dir: &Path) -> Result<(), RunDirError> {
    File::open(dir).and_then(|d| d.sync_all()).map_err(io(dir))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn generation(tag: &str) -> Vec<(Place, &'static str, Vec<u8>)> {
        ["weights", "meta.json", "optimizer", "state.json"]
            .iter()
            .map(|n| (Place::Run, *n, format!("{tag}:{n}").into_bytes()))
            .chain([(
                Place::Replay,
                "replay.bin",
                format!("{tag}:replay").into_bytes(),
            )])
            .collect()
    }

    fn commit_gen(
        run: &RunDir,
        step: u64,
        tag: &str,
        hook: &mut dyn FnMut(SaveStage) -> std::io::Result<()>,
    ) -> Result<(), RunDirError> {
        let files = generation(tag);
        let refs: Vec<(Place, &str, &[u8])> = files
            .iter()
            .map(|(p, n, b)| (*p, *n, b.as_slice()))
            .collect();
        run.commit_with(step, &refs, hook)
    }

    /// Which generation every file holds: `Some(tag)` only if all agree.
    fn holds(run: &RunDir) -> Option<String> {
        let tags: Vec<String> = generation("x")
            .iter()
            .map(|(place, name, _)| {
                let text = std::fs::read_to_string(run.path(*place, name)).unwrap_or_default();
                text.split(':').next().unwrap_or_default().to_string()
            })
            .collect();
        tags.iter().all(|t| *t == tags[0]).then(|| tags[0].clone())
    }

    fn all_stages(n: usize) -> Vec<SaveStage> {
        (0..n)
            .map(SaveStage::Staged)
            .chain([SaveStage::ManifestWritten])
            .chain((0..n).map(SaveStage::Renamed))
            .chain([SaveStage::Done])
            .collect()
    }

    #[test]
    fn a_kill_at_any_stage_leaves_one_whole_generation() {
        let n = generation("x").len();
        let stages = all_stages(n);
        assert_eq!(stages.len(), 2 * n + 2);
        for (k, &kill_at) in stages.iter().enumerate() {
            let tmp = tempfile::tempdir().unwrap();
            let (dir, replay) = (tmp.path().join("run"), tmp.path().join("replay"));
            let run = RunDir::lock(&dir, &replay).unwrap();
            commit_gen(&run, 100, "old", &mut |_| Ok(())).unwrap();
            let killed = commit_gen(&run, 200, "new", &mut |stage| {
                if stage == kill_at {
                    Err(std::io::Error::other("killed"))
                } else {
                    Ok(())
                }
            });
            assert!(killed.is_err(), "stage {kill_at:?}");
            drop(run);
            // The next trainer to open the folder.
            let run = RunDir::lock(&dir, &replay).unwrap();
            let recovery = run.recover().unwrap();
            let manifest_at = n; // index of ManifestWritten
            let expected = if k < manifest_at { "old" } else { "new" };
            assert_eq!(
                holds(&run).as_deref(),
                Some(expected),
                "killed at {kill_at:?}"
            );
            match kill_at {
                SaveStage::Staged(i) => {
                    assert_eq!(recovery, Recovery::RolledBack { dropped: i + 1 })
                }
                SaveStage::Done => assert_eq!(recovery, Recovery::Clean),
                _ => assert_eq!(
                    recovery,
                    Recovery::RolledForward {
                        step: 200,
                        missing_replay: None
                    }
                ),
            }
            // Nothing staged or pending is left behind, and a second recovery finds it clean.
            assert!(!has_pending_save(&dir));
            assert_eq!(run.recover().unwrap(), Recovery::Clean);
        }
    }

    #[test]
    fn a_pending_save_whose_replay_folder_is_gone_completes_without_it() {
        let tmp = tempfile::tempdir().unwrap();
        let (dir, replay) = (tmp.path().join("run"), tmp.path().join("replay"));
        let run = RunDir::lock(&dir, &replay).unwrap();
        let _ = commit_gen(&run, 200, "new", &mut |stage| match stage {
            SaveStage::ManifestWritten => Err(std::io::Error::other("killed")),
            _ => Ok(()),
        });
        drop(run);
        // Another machine: the run folder came along, the replay folder did not.
        std::fs::remove_dir_all(&replay).unwrap();
        let run = RunDir::lock(&dir, &replay).unwrap();
        let Recovery::RolledForward { missing_replay, .. } = run.recover().unwrap() else {
            panic!("expected a roll-forward");
        };
        assert_eq!(missing_replay, Some(replay.join("replay.bin")));
        assert_eq!(std::fs::read(dir.join("weights")).unwrap(), b"new:weights");
    }

    #[test]
    fn a_corrupt_staged_file_is_refused_not_renamed() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("run");
        let run = RunDir::lock(&dir, &dir).unwrap();
        commit_gen(&run, 100, "old", &mut |_| Ok(())).unwrap();
        let _ = commit_gen(&run, 200, "new", &mut |stage| match stage {
            SaveStage::ManifestWritten => Err(std::io::Error::other("killed")),
            _ => Ok(()),
        });
        std::fs::write(dir.join(format!("weights{STAGING_SUFFIX}")), b"new:garbage").unwrap();
        let err = run.recover().unwrap_err().to_string();
        assert!(err.contains("does not match the manifest"), "{err}");
        assert_eq!(std::fs::read(dir.join("weights")).unwrap(), b"old:weights");
    }

    #[test]
    fn a_second_trainer_is_refused_with_the_holders_pid() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("run");
        let first = RunDir::lock(&dir, &dir).unwrap();
        let err = RunDir::lock(&dir, &dir).unwrap_err();
        assert!(
            matches!(&err, RunDirError::Locked { holder, .. } if *holder == std::process::id().to_string()),
            "{err}"
        );
        drop(first);
        RunDir::lock(&dir, &dir).expect("the lock is released with its holder");
    }
}
