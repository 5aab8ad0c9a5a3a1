//! Saving and resuming a run: its identity (what a resume must match), the checkpoint saved as
//! one set under the folder's lock, and a resume that reads it all back — weights, optimisers,
//! RNGs, auxiliary heads and the replay buffer (or refills one).

use candle_core::{Device, Tensor};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use super::adam::Adam;
use super::replay::ReplayBuffer;
use super::run_dir::{Place, Recovery, RunDir, SaveStage};
use super::sac::SacLearner;
use super::{
    METRICS_FILE, OPTIMIZER_FILE, REPLAY_FILE, STATE_FILE, TrainError, TrainOptions, aux,
    new_replay, validate_options,
};
use crate::policy::checkpoint::{
    self, CheckpointError, TrainingRecord, load_expected_tensors, safetensors_bytes, write_atomic,
};
use crate::policy::{EncoderKind, SacModel};

/// Optimiser, RNG and counter state for `--resume`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub(super) struct TrainState {
    pub(super) steps_done: u64,
    pub(super) episodes_done: u64,
    pub(super) wall_time_s: f64,
    pub(super) adam_steps: [u64; 3],
    /// Draws warm-up actions and exploration noise.
    pub(super) action_rng: ChaCha8Rng,
    /// Draws replay samples and the update's reparameterisation noise.
    pub(super) update_rng: ChaCha8Rng,
    pub(super) replay_saved: bool,
    /// Ties this state to the weights it was saved with.
    pub(super) model_crc32: u32,
    /// Ties it to its optimiser file and buffer (absent in runs saved before these were kept).
    #[serde(default)]
    pub(super) optimizer_crc32: Option<u32>,
    #[serde(default)]
    pub(super) replay_crc32: Option<u32>,
    /// Ties it to its auxiliary heads (`aux.safetensors`; runs with `--aux` only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub(super) aux_crc32: Option<u32>,
    /// The auxiliary heads' normalisation and Adam step counts (runs with `--aux` only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub(super) aux: Option<aux::AuxState>,
    /// The `--replay-dir` the buffer was saved in (absent: the run folder).
    #[serde(default)]
    pub(super) replay_dir: Option<PathBuf>,
    /// Every resume of this run, in order.
    #[serde(default)]
    pub(super) resumes: Vec<ResumeRecord>,
    /// The model a warm-started run (`--init-from`) began from.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub(super) warm_start: Option<super::WarmStart>,
}

/// Where a resumed run's replay buffer came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BufferSource {
    /// `replay.bin` was found and matched its checksum.
    Restored,
    /// No (or too small a) buffer: the current policy collected one before updates resumed.
    Refilled,
}

/// One resume, as `train_state.json` and `metrics.jsonl` record it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ResumeRecord {
    /// The step the run resumed at.
    pub step: u64,
    pub buffer: BufferSource,
    /// Transitions read back from `replay.bin`.
    pub restored_transitions: usize,
    /// Transitions collected by the current policy (sampled actions, no updates) before the
    /// first update; they do not count as training steps.
    pub refill_transitions: usize,
    /// Episodes (whole or partial) the refill stepped through.
    pub refill_episodes: u64,
}

/// The resumes a run folder records (`train_state.json`; empty for runs that never resumed or
/// were saved before resumes were recorded).
pub fn read_resumes(dir: &Path) -> Result<Vec<ResumeRecord>, TrainError> {
    Ok(read_state(&dir.join(STATE_FILE))?.resumes)
}

/// The most a train_state.json may hold: a few KB, and a line more per resume.
const MAX_STATE_BYTES: u64 = 4 << 20;

/// The most the optimiser's or the auxiliary heads' safetensors may hold: Adam's two moments of
/// the largest model here are a few MB.
const MAX_STATE_FILE_BYTES: u64 = 256 << 20;

/// A run's train_state.json: a regular file within [`MAX_STATE_BYTES`], parsed.
fn read_state(path: &Path) -> Result<TrainState, TrainError> {
    let text = crate::files::read_text_capped(path, MAX_STATE_BYTES).map_err(|source| {
        TrainError::Read {
            path: path.to_owned(),
            source,
        }
    })?;
    let state: TrainState = serde_json::from_str(&text).map_err(|e| TrainError::State {
        path: path.to_owned(),
        reason: e.into(),
    })?;
    // The time a run has trained: what the summary divides by. A century is past any run.
    if !(0.0..=MAX_WALL_TIME_S).contains(&state.wall_time_s) {
        return Err(TrainError::State {
            path: path.to_owned(),
            reason: format!(
                "wall_time_s {:e} must lie in [0, {MAX_WALL_TIME_S:e}] seconds",
                state.wall_time_s
            )
            .into(),
        });
    }
    Ok(state)
}

/// The most wall time a run's state may record, in seconds (a hundred years).
const MAX_WALL_TIME_S: f64 = 100.0 * 365.25 * 86_400.0;

/// What a run is, as the command line states it: a resume must match the run's own (and may
/// leave any of it out); a fresh run takes it.
#[derive(Debug, Clone, Copy, Default)]
pub struct RunIdentity {
    pub encoder: Option<EncoderKind>,
    pub aux: Option<crate::policy::AuxKind>,
    pub aux_weight: Option<f64>,
}

impl RunIdentity {
    /// The run in `dir`, if the stated identity matches it.
    pub fn check_against(&self, dir: &Path) -> Result<checkpoint::CheckpointMeta, TrainError> {
        let meta = checkpoint::read_meta(dir)?;
        let found = meta.net.encoder;
        if let Some(expected) = self.encoder
            && expected != found
        {
            return Err(TrainError::Options(format!(
                "{} is a '{found}' run; --encoder {expected} does not match",
                dir.display()
            )));
        }
        let run = meta.sac.aux;
        if self.aux.is_some_and(|kind| kind != run.kind)
            || self.aux_weight.is_some_and(|w| w != run.weight)
        {
            return Err(TrainError::Options(format!(
                "{} trains with --aux {} (weight {}); --aux/--aux-weight cannot change on resume",
                dir.display(),
                aux_name(run.kind),
                run.weight
            )));
        }
        Ok(meta)
    }

    /// The auxiliary loss of a fresh run.
    pub fn fresh_aux(&self) -> Result<crate::policy::AuxConfig, TrainError> {
        let mut aux = crate::policy::AuxConfig::default();
        if let Some(kind) = self.aux {
            aux.kind = kind;
        }
        if let Some(w) = self.aux_weight {
            if aux.is_off() {
                return Err(TrainError::Options(
                    "--aux-weight needs --aux dynamics".into(),
                ));
            }
            aux.weight = w;
        }
        Ok(aux)
    }
}

pub(super) fn aux_name(kind: crate::policy::AuxKind) -> &'static str {
    match kind {
        crate::policy::AuxKind::None => "none",
        crate::policy::AuxKind::Dynamics => "dynamics",
    }
}

/// Saves one generation (weights, checkpoint.json, optimiser, train state, replay buffer) as a
/// set, after checking that every number in it is finite: a diverged run never replaces the
/// last good checkpoint.
pub(super) fn save_run(
    run: &RunDir,
    opts: &TrainOptions,
    learner: &mut SacLearner,
    state: &mut TrainState,
    replay: &ReplayBuffer,
    hook: &mut dyn FnMut(SaveStage) -> std::io::Result<()>,
) -> Result<(), TrainError> {
    let record = TrainingRecord {
        env: opts.env.clone(),
        sac: opts.sac.clone(),
        seed: opts.seed,
        steps_done: state.steps_done,
        episodes_done: state.episodes_done,
        wall_time_s: state.wall_time_s,
        imported_from: None,
    };
    learner.sync_model()?;
    let diverged = |what: String| TrainError::Diverged {
        step: state.steps_done,
        what,
    };
    for (name, var) in learner.model.all_params() {
        let values = var.as_tensor().flatten_all()?.to_vec1::<f32>()?;
        if values.iter().any(|v| !v.is_finite()) {
            return Err(diverged(format!("weight tensor '{name}'")));
        }
    }
    let optimizers = [&learner.actor_opt, &learner.critic_opt, &learner.alpha_opt];
    for (group, opt) in ["actor", "critic", "alpha"].iter().zip(&optimizers) {
        if opt
            .moments()
            .any(|(m, v)| m.iter().chain(v).any(|x| !x.is_finite()))
        {
            return Err(diverged(format!("the {group} optimiser's state")));
        }
    }
    let aux_bytes = match &learner.aux {
        Some(aux) => {
            if !aux.is_finite()? {
                return Err(diverged("the auxiliary heads (aux.safetensors)".into()));
            }
            let tensors = aux.tensors()?;
            Some(safetensors_bytes(
                tensors.iter().map(|(n, t)| (n.as_str(), t)),
            )?)
        }
        None => None,
    };
    let (model_bytes, meta) = learner.model.checkpoint_bytes(&record)?;
    let meta_json = checkpoint::meta_json(&opts.out, &meta)?;
    let tensors = optimizer_tensors(&optimizers)?;
    let optimizer_bytes = safetensors_bytes(tensors.iter().map(|(n, t)| (n.as_str(), t)))?;
    let replay_bytes = if opts.save_replay {
        let mut bytes = Vec::new();
        replay
            .write_to(&mut bytes)
            .map_err(|source| TrainError::Io {
                path: run.path(Place::Replay, REPLAY_FILE),
                source,
            })?;
        Some(bytes)
    } else {
        None
    };
    state.adam_steps = [
        learner.actor_opt.t,
        learner.critic_opt.t,
        learner.alpha_opt.t,
    ];
    state.replay_saved = opts.save_replay;
    state.model_crc32 = meta.model_crc32;
    state.optimizer_crc32 = Some(crc32fast::hash(&optimizer_bytes));
    state.replay_crc32 = replay_bytes.as_deref().map(crc32fast::hash);
    state.aux_crc32 = aux_bytes.as_deref().map(crc32fast::hash);
    state.aux = learner.aux.as_ref().map(aux::AuxHeads::state);
    let path = opts.out.join(STATE_FILE);
    let state_json = serde_json::to_vec_pretty(state).map_err(|e| TrainError::State {
        path: path.clone(),
        reason: e.into(),
    })?;
    let mut files: Vec<(Place, &str, &[u8])> = vec![
        (Place::Run, checkpoint::MODEL_FILE, &model_bytes),
        (Place::Run, OPTIMIZER_FILE, &optimizer_bytes),
    ];
    if let Some(bytes) = &aux_bytes {
        files.push((Place::Run, aux::AUX_FILE, bytes));
    }
    if let Some(bytes) = &replay_bytes {
        files.push((Place::Replay, REPLAY_FILE, bytes));
    }
    // checkpoint.json last: a reader between two renames sees the old JSON, whose CRC refuses
    // the new weights, rather than new JSON over old weights.
    files.push((Place::Run, STATE_FILE, &state_json));
    files.push((Place::Run, checkpoint::META_FILE, &meta_json));
    run.commit_with(state.steps_done, &files, hook)?;
    Ok(())
}

pub(super) fn optimizer_tensors(
    optimizers: &[&Adam; 3],
) -> Result<Vec<(String, Tensor)>, TrainError> {
    let mut out = Vec::new();
    for (group, opt) in ["actor", "critic", "alpha"].iter().zip(optimizers) {
        for (i, (m, v)) in opt.moments().enumerate() {
            out.push((
                format!("{group}.{i:03}.m"),
                Tensor::from_slice(m, m.len(), &Device::Cpu)?,
            ));
            out.push((
                format!("{group}.{i:03}.v"),
                Tensor::from_slice(v, v.len(), &Device::Cpu)?,
            ));
        }
    }
    Ok(out)
}

/// A run folder opened for `--resume`: locked, any interrupted save settled, everything loaded.
pub(super) struct Resumed {
    pub(super) run: RunDir,
    pub(super) learner: SacLearner,
    pub(super) state: TrainState,
    pub(super) replay: ReplayBuffer,
    /// `refill_transitions` holds the buffer size to reach before updating (when refilled).
    pub(super) record: ResumeRecord,
}

pub(super) fn resume_run(opts: &mut TrainOptions, device: &Device) -> Result<Resumed, TrainError> {
    let dir = opts.out.clone();
    if !dir.is_dir() {
        return Err(CheckpointError::NoSuchDir(dir).into());
    }
    // The buffer's folder: the command line's, else the run's own. A folder the run recorded
    // elsewhere is used only when the command line names it again: train_state.json is a file
    // anyone can edit, and the trainer writes (and renames) replay.bin wherever it points.
    let replay_dir = match (&opts.replay_dir, recorded_replay_dir(&dir)) {
        (Some(given), _) => given.clone(),
        (None, Some(recorded)) if recorded != dir => {
            return Err(TrainError::ReplayDirNotConfirmed {
                state: dir.join(STATE_FILE),
                recorded,
            });
        }
        (None, _) => dir.clone(),
    };
    let run = RunDir::lock(&dir, &replay_dir)?;
    match run.recover()? {
        Recovery::Clean => {}
        Recovery::RolledBack { dropped } => log::info!(
            "dropped {dropped} staged files of a save that was interrupted before it completed; resuming from the last complete checkpoint"
        ),
        Recovery::RolledForward {
            step,
            missing_replay,
        } => {
            log::info!("completed the checkpoint of step {step}, whose save was interrupted");
            if let Some(path) = missing_replay {
                log::info!("its replay buffer {} is not here", path.display());
            }
        }
    }
    let (learner, mut state, meta) = load_run(&dir, Some(opts.net.encoder), device)?;
    // The run's own settings win over the command line's, except the total step count, the
    // replay folder and the refill size; a hand-edited checkpoint.json is checked like a fresh run.
    opts.net = meta.net.clone();
    opts.sac = meta.sac.clone();
    opts.env = meta.env.clone();
    opts.seed = meta.seed;
    validate_options(opts).map_err(|e| match e {
        TrainError::Options(m) => TrainError::Options(format!(
            "{}: {m}",
            dir.join(checkpoint::META_FILE).display()
        )),
        e => e,
    })?;
    state.replay_dir = (replay_dir != dir).then(|| replay_dir.clone());
    let mut replay = new_replay(opts);
    let path = run.path(Place::Replay, REPLAY_FILE);
    if state.replay_saved {
        restore_replay(&path, state.replay_crc32, &mut replay)?;
    }
    // Updates must never start from a near-empty buffer: refill to this size first.
    let floor = opts
        .sac
        .buffer_size
        .min(usize::try_from(state.steps_done).unwrap_or(usize::MAX))
        .min(opts.refill);
    let refill = replay.len() < floor;
    if refill && path.exists() {
        log::info!(
            "{} holds {} transitions, fewer than the {floor} a resume needs; refilling the rest",
            path.display(),
            replay.len()
        );
    }
    let record = ResumeRecord {
        step: state.steps_done,
        buffer: if refill {
            BufferSource::Refilled
        } else {
            BufferSource::Restored
        },
        restored_transitions: replay.len(),
        refill_transitions: if refill { floor } else { 0 },
        refill_episodes: 0,
    };
    truncate_metrics(&dir, state.steps_done)?;
    Ok(Resumed {
        run,
        learner,
        state,
        replay,
        record,
    })
}

/// The replay folder a run recorded, if its state file can be read (before the lock is taken,
/// so a torn or missing state only means "the run folder").
pub(super) fn recorded_replay_dir(dir: &Path) -> Option<PathBuf> {
    read_state(&dir.join(STATE_FILE)).ok()?.replay_dir
}

/// Reads `replay.bin` into `replay` when it exists and belongs to this checkpoint. A buffer whose
/// checksum does not match `train_state.json` is never used: it is set aside as
/// `replay.bin.mismatched`, said so, and the buffer refilled (typically a buffer kept in
/// `--replay-dir` by a trainer that went on past the checkpoint a fresh checkout holds). A file
/// with no checksum to check (older runs) that fails to parse or holds a non-finite number is an
/// error.
pub(super) fn restore_replay(
    path: &Path,
    crc32: Option<u32>,
    replay: &mut ReplayBuffer,
) -> Result<(), TrainError> {
    // Only a regular file of exactly the size this run's buffer saves to is read: a FIFO, a
    // device or a file of any other size is judged before a byte of it is.
    let expected_len = replay.file_len();
    let read_error = |source| TrainError::Read {
        path: path.to_owned(),
        source,
    };
    let len = match crate::files::regular_len(path) {
        Ok(len) => len,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            log::info!(
                "{} is missing (it is git-ignored; keep it with --replay-dir); the buffer will be refilled",
                path.display()
            );
            return Ok(());
        }
        Err(e) => return Err(read_error(e)),
    };
    let refuse = |reason: String| TrainError::State {
        path: path.to_owned(),
        reason: format!("{reason}; delete it to resume with a refilled buffer").into(),
    };
    let set_aside = |why: String| -> Result<(), TrainError> {
        let aside = path.with_extension("bin.mismatched");
        std::fs::rename(path, &aside).map_err(|e| TrainError::Io {
            path: aside.clone(),
            source: e,
        })?;
        log::warn!(
            "{}: {why} (corrupt, or saved by another run or a later save of this one); not used, \
             moved to {}; the buffer will be refilled",
            path.display(),
            aside.display()
        );
        Ok(())
    };
    if len != expected_len {
        let why = format!("{len} bytes, where this run's buffer saves to {expected_len}");
        return match crc32 {
            Some(_) => set_aside(why),
            None => Err(refuse(why)),
        };
    }
    let bytes = crate::files::read_capped(path, expected_len).map_err(read_error)?;
    if let Some(expected) = crc32 {
        let found = crc32fast::hash(&bytes);
        if found != expected {
            return set_aside(format!(
                "CRC-32 {found:08x} does not match train_state.json's {expected:08x}"
            ));
        }
    }
    replay.read_from(&mut bytes.as_slice()).map_err(refuse)
}

/// A run's learner as it was saved: weights, and the optimisers' moments and step counts.
pub fn load_learner(dir: &Path, device: &Device) -> Result<SacLearner, TrainError> {
    Ok(load_run(dir, None, device)?.0)
}

pub(super) fn load_run(
    dir: &Path,
    encoder: Option<EncoderKind>,
    device: &Device,
) -> Result<(SacLearner, TrainState, checkpoint::CheckpointMeta), TrainError> {
    let (model, meta) = SacModel::load(dir, encoder, device)?;
    let state_path = dir.join(STATE_FILE);
    let state = read_state(&state_path).map_err(|e| match e {
        TrainError::Read { path, source } if source.kind() == std::io::ErrorKind::NotFound => {
            TrainError::State {
                path,
                reason: "missing; was this folder written by `gaitscope train`?".into(),
            }
        }
        e => e,
    })?;
    if state.model_crc32 != meta.model_crc32 || state.steps_done != meta.steps_done {
        return Err(TrainError::State {
            path: state_path,
            reason: "does not belong to the weights next to it (interrupted save?)".into(),
        });
    }
    let mut learner = SacLearner::new(model, meta.sac.clone(), device.clone());
    let opt_path = dir.join(OPTIMIZER_FILE);
    let bytes = crate::files::read_capped(&opt_path, MAX_STATE_FILE_BYTES).map_err(|source| {
        CheckpointError::Read {
            path: opt_path.clone(),
            source,
        }
    })?;
    if let Some(expected) = state.optimizer_crc32 {
        let found = crc32fast::hash(&bytes);
        if found != expected {
            return Err(TrainError::State {
                path: opt_path,
                reason: format!(
                    "CRC-32 {found:08x} does not match train_state.json's {expected:08x}: this optimiser state belongs to another run or save"
                ).into(),
            });
        }
    }
    let expected: BTreeMap<String, Vec<usize>> =
        optimizer_tensors(&[&learner.actor_opt, &learner.critic_opt, &learner.alpha_opt])?
            .into_iter()
            .map(|(n, t)| (n, t.dims().to_vec()))
            .collect();
    let tensors =
        load_expected_tensors(dir, &opt_path, &bytes, &expected, meta.net.encoder, device)?;
    for ((group, opt), t) in ["actor", "critic", "alpha"]
        .iter()
        .zip([
            &mut learner.actor_opt,
            &mut learner.critic_opt,
            &mut learner.alpha_opt,
        ])
        .zip(state.adam_steps)
    {
        let moments = (0..opt.len())
            .map(|i| {
                let get = |s: &str| tensors[&format!("{group}.{i:03}.{s}")].to_vec1::<f32>();
                Ok((get("m")?, get("v")?))
            })
            .collect::<Result<Vec<_>, candle_core::Error>>()?;
        opt.set_moments(t, moments)
            .map_err(|reason| TrainError::State {
                path: opt_path.clone(),
                reason: reason.into(),
            })?;
    }
    if !meta.sac.aux.is_off() {
        load_aux(dir, &mut learner, &state, meta.seed, device)?;
    }
    Ok((learner, state, meta))
}

/// The auxiliary heads of a run trained with `--aux`, checked against its train state.
pub(super) fn load_aux(
    dir: &Path,
    learner: &mut SacLearner,
    state: &TrainState,
    seed: u64,
    device: &Device,
) -> Result<(), TrainError> {
    let path = dir.join(aux::AUX_FILE);
    let bad = |reason: String| TrainError::State {
        path: path.clone(),
        reason: reason.into(),
    };
    let bytes = crate::files::read_capped(&path, MAX_STATE_FILE_BYTES)
        .map_err(|e| bad(format!("cannot read ({e}); the run trains with --aux")))?;
    let found = crc32fast::hash(&bytes);
    if state.aux_crc32 != Some(found) {
        return Err(bad(format!(
            "CRC-32 {found:08x} does not match train_state.json's {}: these heads belong to another run or save",
            state
                .aux_crc32
                .map_or("(none)".into(), |c| format!("{c:08x}"))
        )));
    }
    let tensors = candle_core::safetensors::load_buffer(&bytes, device)
        .map_err(|e| bad(format!("not a safetensors file: {e}")))?;
    let Some(saved) = &state.aux else {
        return Err(TrainError::State {
            path: dir.join(STATE_FILE),
            reason: "has no auxiliary-loss state, but the run trains with --aux".into(),
        });
    };
    learner.init_aux(seed)?;
    if let Some(heads) = &mut learner.aux {
        heads.restore(&tensors, saved).map_err(bad)?;
    }
    Ok(())
}

/// Drops metric lines logged after `steps_done` (work lost since the last checkpoint), and says
/// how many lines it dropped because they were not JSON with a step.
pub(super) fn truncate_metrics(dir: &Path, steps_done: u64) -> Result<(), TrainError> {
    let path = dir.join(METRICS_FILE);
    let text = match crate::files::read_text_capped(&path, super::curves::MAX_METRICS_BYTES) {
        Ok(text) => text,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(()),
        Err(e) => {
            return Err(TrainError::State {
                path,
                reason: format!("cannot read the run's log ({e})").into(),
            });
        }
    };
    let mut corrupt = 0usize;
    let kept: String = text
        .lines()
        .filter(|line| {
            let step = serde_json::from_str::<serde_json::Value>(line)
                .ok()
                .and_then(|v| v["global_step"].as_u64());
            if step.is_none() && !line.trim().is_empty() {
                corrupt += 1;
            }
            step.is_some_and(|s| s <= steps_done)
        })
        .map(|l| format!("{l}\n"))
        .collect();
    if corrupt > 0 {
        log::warn!(
            "{}: dropped {corrupt} line(s) that are not JSON metrics with a global_step",
            path.display()
        );
    }
    write_atomic(&path, kept.as_bytes()).map_err(TrainError::from)
}
