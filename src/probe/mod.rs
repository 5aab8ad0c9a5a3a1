//! `gaitscope probe`: what does z know about the damage?
//!
//! Rollouts across the three conditions record z, the raw observation and the truth (condition,
//! which joints are effectively damaged, steps since the first trigger). Linear probes
//! (linfa-logistic) are trained on a 70/30 split *by episode* with standardised features; PCA
//! (linfa-reduction) gives the latent's main axes. The fitted probes and PCA basis are saved as
//! `probe.json` next to the checkpoint, where telemetry and the live viewer pick them up.

//!
//! The module follows the data: [`collect`] records rollouts, `linear` fits and scores one
//! probe, `pca` holds the latent's basis, [`file`] fits them all into `probe.json`, and
//! [`figures`] draws them.

mod collect;
mod cv;
mod figures;
mod file;
mod linear;
mod onset;
mod pca;
pub mod pipeline;

pub use collect::{ProbeStep, collect};
pub use cv::{CvScores, LatencyPoint, MeanSd, ProbeCv, ProbeReport, episode_folds, probe_cv};
pub use figures::figures;
pub use file::{ProbeFile, fit_probes, save};
pub use linear::{LinearProbe, ProbeResult, Scores, Standardizer, scores, split_by_episode};
pub use onset::{ONSET_GROUPS, ONSET_RANGE, OnsetAttribution, onset_attribution, onset_figure};
pub use pca::PcaBasis;

use std::path::PathBuf;

use crate::env::EnvError;
use crate::plots::PlotError;
use crate::policy::checkpoint::CheckpointError;

pub const PROBE_FILE: &str = "probe.json";

#[derive(Debug, thiserror::Error)]
pub enum ProbeError {
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
    #[error(transparent)]
    Env(#[from] EnvError),
    #[error("policy inference failed: {0}")]
    Policy(#[from] candle_core::Error),
    #[error(transparent)]
    Lane(#[from] crate::lane::LaneError),
    #[error("{0} has no context encoder, so there is no z to probe")]
    NoLatent(PathBuf),
    #[error("fitting the {what} probe: {reason}")]
    Fit {
        what: String,
        #[source]
        reason: crate::Cause,
    },
    #[error(transparent)]
    Plot(#[from] PlotError),
    #[error("cannot read {path}: {reason}")]
    Read {
        path: PathBuf,
        #[source]
        reason: crate::Cause,
    },
    #[error("{0}")]
    Options(String),
    #[error("explaining z")]
    Explain(#[from] crate::explain::ExplainError),
}
