//! `metrics.jsonl`: CleanRL-style names, one line per episode, update report and resume.

use serde::Serialize;
use std::collections::VecDeque;
use std::io::Write;
use std::path::{Path, PathBuf};

use super::{METRICS_FILE, ResumeRecord, TrainError, UpdateStats};
use crate::damage::Condition;

#[derive(Serialize)]
pub(super) struct EpisodeMetrics {
    pub(super) global_step: u64,
    #[serde(rename = "charts/episodic_return")]
    pub(super) episodic_return: f64,
    #[serde(rename = "charts/episodic_length")]
    pub(super) episodic_length: usize,
    #[serde(rename = "charts/success")]
    pub(super) success: bool,
    #[serde(rename = "charts/triggered_joints")]
    pub(super) triggered_joints: usize,
    #[serde(rename = "charts/condition", skip_serializing_if = "Option::is_none")]
    pub(super) condition: Option<Condition>,
}

#[derive(Serialize)]
pub(super) struct ResumeMetrics {
    pub(super) global_step: u64,
    pub(super) resume: ResumeRecord,
}

#[derive(Serialize)]
pub(super) struct UpdateMetrics {
    pub(super) global_step: u64,
    #[serde(flatten)]
    pub(super) stats: UpdateStats,
    #[serde(rename = "charts/SPS")]
    pub(super) sps: f64,
}

/// Appends JSON lines to `metrics.jsonl`, opening the file for each line: a file replaced
/// under a running trainer (a `git stash` or checkout in the work tree) gets the next lines,
/// where a held handle would write on into the unlinked old file and lose them all.
pub(super) struct MetricsLog {
    pub(super) path: PathBuf,
    pub(super) line: Vec<u8>,
}

impl MetricsLog {
    pub(super) fn open(dir: &Path) -> Result<Self, TrainError> {
        let log = Self {
            path: dir.join(METRICS_FILE),
            line: Vec::new(),
        };
        log.append(b"")?;
        Ok(log)
    }

    pub(super) fn write(&mut self, record: &impl Serialize) -> Result<(), TrainError> {
        self.line.clear();
        serde_json::to_writer(&mut self.line, record).map_err(|e| TrainError::Io {
            path: self.path.clone(),
            source: e.into(),
        })?;
        self.line.push(b'\n');
        self.append(&self.line)
    }

    /// One `write` call per line, so a line is never split between two files.
    pub(super) fn append(&self, bytes: &[u8]) -> Result<(), TrainError> {
        std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&self.path)
            .and_then(|mut f| f.write_all(bytes))
            .map_err(|source| TrainError::Io {
                path: self.path.clone(),
                source,
            })
    }
}

/// Rolling return and success rate for the progress bar.
pub(super) struct RecentEpisodes {
    pub(super) capacity: usize,
    pub(super) episodes: VecDeque<(f64, bool)>,
}

impl RecentEpisodes {
    pub(super) fn new(capacity: usize) -> Self {
        Self {
            capacity,
            episodes: VecDeque::new(),
        }
    }
    pub(super) fn push(&mut self, ret: f64, success: bool) {
        if self.episodes.len() == self.capacity {
            self.episodes.pop_front();
        }
        self.episodes.push_back((ret, success));
    }
    pub(super) fn describe(&self, sps: f64) -> String {
        let n = self.episodes.len().max(1) as f64;
        let ret = self.episodes.iter().map(|e| e.0).sum::<f64>() / n;
        let success = self.episodes.iter().filter(|e| e.1).count() as f64 / n;
        format!(
            "{sps:.0} steps/s  return {ret:.1}  success {:.0} % (last {})",
            100.0 * success,
            self.episodes.len()
        )
    }
}
