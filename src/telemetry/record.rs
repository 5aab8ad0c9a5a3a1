//! `gaitscope record`: every model's episodes in lockstep through a [`Session`], to a file
//! written under `<name>.partial` and renamed once complete (or to memory, for tests).

use super::session::*;
use super::{Sink, TelemetryError};
use crate::config::GaitConfig;

/// What `gaitscope record` does.
pub struct RecordOptions {
    pub actors: Vec<Actor>,
    pub config: GaitConfig,
    pub episodes: usize,
    pub seed: u64,
    pub sink: Sink,
    /// Fork the first model in every episode before step `at`, with these edits (lane
    /// [`FORK_ROOT`], drawn beside the others).
    pub fork: Option<crate::rollout::Fork>,
    /// Every episode starts from this state (`--init-state`).
    pub start: Option<crate::lane::StartState>,
    /// Log why z moved with every step (encoder models).
    pub attribution: bool,
    /// How the recorded episode was chosen ([`crate::eval::typical::TypicalPick::caption`]),
    /// shown under the key.
    pub caption: Option<String>,
}

/// Outcome of a recording.
pub struct RecordSummary {
    pub steps: u64,
    pub episodes: usize,
    /// How each lane's episode ended, episode by episode (what `record` prints).
    pub endings: Vec<LaneEnding>,
    pub interrupted: bool,
    pub storage: Option<rerun::sink::MemorySinkStorage>,
}

/// Reads a recording file through with Rerun's own decoder (message by message, so memory
/// stays bounded however large the file): the number of whole messages, or where and how it
/// breaks off — a message cut off by the file's end (a full disk, a killed writer) or one the
/// decoder refuses (damaged bytes).
pub fn read_back(path: &std::path::Path) -> Result<usize, String> {
    let file = crate::files::open_regular(path).map_err(|e| format!("reading it back: {e}"))?;
    let len = file
        .metadata()
        .map_err(|e| format!("reading it back: {e}"))?
        .len();
    let mut messages = 0;
    // The decoder ends quietly at a message cut off by the end of the file; what it did not
    // consume is that cut-off message.
    let mut decoded = re_log_encoding::DecoderApp::decode_lazy(std::io::BufReader::new(file));
    for message in &mut decoded {
        let _whole =
            message.map_err(|e| format!("it breaks off after {messages} whole messages ({e})"))?;
        messages += 1;
    }
    let read = decoded.num_bytes_processed();
    if read < len {
        return Err(format!(
            "it breaks off after {messages} whole messages, {} bytes into the next",
            len - read
        ));
    }
    Ok(messages)
}

/// The longest a recording's final flush to its file may take.
pub(super) const FILE_FLUSH_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(60);

/// A recording file being written under `<name>.partial`, renamed to `<name>` when complete:
/// a failed write (a full disk) never leaves a truncated file under the name asked for.
pub struct PartialFile {
    path: std::path::PathBuf,
    partial: std::path::PathBuf,
}

impl PartialFile {
    pub fn new(path: &std::path::Path) -> Self {
        let mut name = path.file_name().unwrap_or_default().to_os_string();
        name.push(".partial");
        Self {
            path: path.to_path_buf(),
            partial: path.with_file_name(name),
        }
    }

    /// Where the sink writes until the file is complete.
    pub fn partial(&self) -> &std::path::Path {
        &self.partial
    }

    /// Renames the flushed file into place (the writer finishes it, footer included, when the
    /// stream closes; the open file keeps those writes across the rename).
    pub fn rename_into_place(&self) -> Result<(), RecordError> {
        std::fs::rename(&self.partial, &self.path).map_err(|e| RecordError::Incomplete {
            path: self.path.clone(),
            reason: format!("renaming {} into place: {e}", self.partial.display()).into(),
        })
    }

    /// Whether the file written so far reads back whole with Rerun's own decoder: every
    /// message complete, none cut off by a failed write. For a session whose stream did not
    /// flush, where a full disk and a closed viewer look alike. The file stays where it is.
    pub fn check_whole(&self) -> Result<usize, RecordError> {
        read_back(&self.partial).map_err(|reason| RecordError::Incomplete {
            path: self.path.clone(),
            reason: format!(
                "{reason} (is the disk full, or the file larger than the system allows?); what \
                 was written stays at {}",
                self.partial.display()
            )
            .into(),
        })
    }

    /// Removes the incomplete file; the error says why it is incomplete.
    fn abandon(&self, e: TelemetryError) -> RecordError {
        let _ = std::fs::remove_file(&self.partial);
        RecordError::Incomplete {
            path: self.path.clone(),
            reason: format!("{e} (is the disk full, or the file larger than the system allows?)")
                .into(),
        }
    }
}

/// Removes a file when dropped (whatever is there by then).
struct RemoveOnDrop(std::path::PathBuf);

impl Drop for RemoveOnDrop {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.0);
    }
}

/// Entity roots for several models: `ant` alone, else each model's label (made unique).
pub fn model_roots(actors: &[Actor]) -> Vec<String> {
    let mut roots: Vec<String> = Vec::new();
    for actor in actors {
        let mut root = if actors.len() == 1 {
            "ant".to_string()
        } else {
            actor.label()
        };
        while roots.contains(&root) {
            root.push('_');
        }
        roots.push(root);
    }
    roots
}

/// Runs `episodes` episodes per actor, all actors in lockstep on the same seeds (episode k uses
/// seed + k), logging every step. Stops early, with everything flushed, when `stop` is set.
pub fn record(
    opts: RecordOptions,
    stop: &std::sync::atomic::AtomicBool,
) -> Result<RecordSummary, RecordError> {
    if let (Some(fork), Some(actor)) = (&opts.fork, opts.actors.first()) {
        // Checked before the file is created, as every front-end checks a fork.
        fork.validate(&actor.world(&opts.config))?;
    }
    let roots = model_roots(&opts.actors);
    let recording_id = format!(
        "gaitscope-{}-seed{}-{}",
        roots.join("-"),
        opts.seed,
        opts.episodes
    );
    let labels: Vec<String> = opts.actors.iter().map(Actor::label).collect();
    let titles = super::view_titles(&labels, &roots);
    // A file is written under a temporary name and renamed once complete: a failed write (a
    // full disk) never leaves a truncated recording under the name asked for.
    let file = match &opts.sink {
        Sink::File(path) => Some(PartialFile::new(path)),
        _ => None,
    };
    let sink = match &file {
        Some(f) => Sink::File(f.partial.clone()),
        None => opts.sink.clone(),
    };
    // Declared before the session, so dropped after it (the file closed first): a recording
    // that stops on an error (a state refused at the episode's start, a fork that never came)
    // leaves no `.partial` behind. After the rename there is nothing left to remove.
    let _leftover = file.as_ref().map(|f| RemoveOnDrop(f.partial.clone()));
    let views = super::ViewOptions::for_worlds(opts.actors.iter().map(|a| a.world(&opts.config)))
        .with_latent(opts.actors.iter().map(Actor::has_z));
    let (rec, storage) = super::open_titled(&sink, &recording_id, &roots, &titles, views)?;
    let specs = opts
        .actors
        .into_iter()
        .zip(roots)
        .enumerate()
        .map(|(k, (actor, root))| LaneSpec {
            actor,
            root,
            world_offset: side_by_side_offset(k),
        })
        .collect();
    let mut session = Session::new(rec, specs, opts.config)?;
    session.set_start_state(opts.start.map(std::sync::Arc::new));
    session.set_attribution(opts.attribution)?;
    session.set_caption(opts.caption)?;
    let mut episodes_done = 0;
    let mut interrupted = false;
    let mut endings = Vec::new();
    'episodes: for k in 0..opts.episodes {
        session.start_episode(opts.seed.wrapping_add(k as u64))?;
        let mut forked = false;
        while !session.is_over() {
            if stop.load(std::sync::atomic::Ordering::Relaxed) {
                interrupted = true;
                break 'episodes;
            }
            if let Some(fork) = &opts.fork
                && !forked
                && fork.due(session.lanes()[0].core())
            {
                session.fork(&fork.edits)?;
                forked = true;
            }
            session.step()?;
        }
        if let Some(fork) = &opts.fork
            && !forked
        {
            return Err(RecordError::ForkBeyondEpisode {
                episode: k + 1,
                source: fork.beyond(session.lanes()[0].core()),
            });
        }
        // Episodes counted from 1, as every message names them.
        endings.extend(session.endings(k + 1));
        episodes_done += 1;
    }
    match &file {
        // Bounded: a file writer that died on a write error has left a queued flush unanswered
        // (seen with Rerun 0.36's FileSink), so an unbounded flush could hang.
        Some(f) => match session.flush_within(FILE_FLUSH_TIMEOUT) {
            Ok(()) => f.rename_into_place()?,
            Err(e) => {
                // Dropping the stream would join the thread still waiting on that flush: leave
                // it to the process's exit rather than hang.
                std::mem::forget(session);
                return Err(f.abandon(e));
            }
        },
        None => session.flush()?,
    }
    Ok(RecordSummary {
        steps: session.global_step(),
        episodes: episodes_done,
        endings,
        interrupted,
        storage,
    })
}
