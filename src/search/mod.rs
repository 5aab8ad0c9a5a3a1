//! `gaitscope search`: the damage that breaks a policy, or that separates two, found by
//! black-box search (CMA-ES, with random search at the same budget as the reference) over
//! damage schedules ([`space`]) under a severity budget; the best re-run on held-out seeds,
//! the winner shrunk to a minimal counterexample.
//!
//! Every evaluation is one line of `candidates.jsonl` in the output folder, in a fixed order,
//! so the folder is the state: a killed search re-drives the same deterministic optimiser and
//! takes each evaluation it already has from the file (checked to be the same candidate).

pub mod space;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::io::Write;
use std::path::{Path, PathBuf};

use crate::damage::N_ACTUATORS;
use crate::eval::stats::Rate;
pub use space::{Anatomy, Unit};
use space::{PushSpace, Schedule, Space};

/// Evaluations per search, at most.
pub const MAX_EVALUATIONS: usize = 100_000;
/// Episodes per candidate (search seeds) or held-out re-run, at most.
pub const MAX_EPISODES: usize = 10_000;
/// Episodes run together in one lockstep batch: fixed, so outcomes do not depend on --threads.
const LOCKSTEP_CHUNK: usize = 8;
/// Search seeds start here (eval's seeds are `EVAL_SEED_BASE + i`, i < 100,000): disjoint.
pub const SEARCH_SEED_BASE: u64 = 2_000_000_000;
/// candidates.jsonl's size, at most (a line is ~1–20 KB).
const MAX_LOG_BYTES: u64 = 1 << 30;

#[derive(Debug, thiserror::Error)]
pub enum SearchError {
    #[error("invalid search options: {0}")]
    Options(String),
    #[error(transparent)]
    Eval(#[from] crate::eval::EvalError),
    #[error(transparent)]
    Checkpoint(#[from] crate::policy::checkpoint::CheckpointError),
    #[error(transparent)]
    Scenario(#[from] crate::damage::scenario::ScenarioError),
    #[error(transparent)]
    Plot(#[from] crate::plots::PlotError),
    #[error(transparent)]
    Record(#[from] crate::telemetry::RecordError),
    #[error("{path}: {what}")]
    Io {
        path: PathBuf,
        what: &'static str,
        #[source]
        source: std::io::Error,
    },
    #[error(
        "{path} holds another search ({differs}): resume only with the same command, or choose \
         another --out"
    )]
    Different { path: PathBuf, differs: String },
    #[error("{path} line {line}: {reason}")]
    Corrupt {
        path: PathBuf,
        line: usize,
        reason: String,
    },
}

fn io<'a>(path: &'a Path, what: &'static str) -> impl FnOnce(std::io::Error) -> SearchError + 'a {
    move |source| SearchError::Io {
        path: path.to_path_buf(),
        what,
        source,
    }
}

/// What is searched for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Objective {
    /// Damage under which the (first) model fails: success low, then final distance high.
    Break,
    /// Damage under which the first model fails and the second succeeds: success(B) − success(A).
    Separate,
}

/// How candidates are proposed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Method {
    Cma,
    Random,
}

impl Method {
    pub fn name(self) -> &'static str {
        match self {
            Method::Cma => "cma",
            Method::Random => "random",
        }
    }
}

/// One episode of one model under one candidate.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EpisodeOutcome {
    pub seed: u64,
    pub success: bool,
    pub steps: usize,
    pub final_distance: f64,
}

/// Runs schedules: one list of outcomes per model (in the order of [`SearchOptions::models`]),
/// one outcome per seed, in seed order.
pub trait Evaluate: Sync {
    /// The Ant's joint and leg names the schedules are written and described in.
    fn anatomy(&self) -> &Anatomy;
    fn evaluate(
        &self,
        schedule: &Schedule,
        seeds: &[u64],
    ) -> Result<Vec<Vec<EpisodeOutcome>>, SearchError>;

    /// Records one episode of every model under `scenario` (a scenario file's JSON) from
    /// `seed` to `path`, with `caption` under the recording's key; `None` where this evaluator
    /// has nothing to record (a synthetic one).
    fn record(
        &self,
        _scenario: &serde_json::Value,
        _seed: u64,
        _path: &Path,
        _caption: &str,
    ) -> Result<Option<PathBuf>, SearchError> {
        Ok(None)
    }
}

/// A model's identity in the log: label, folder, weights' CRC.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ModelId {
    pub label: String,
    pub path: String,
    pub model_crc32: u32,
}

/// Everything that decides a search's result (written as search.json; a resume must match).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SearchOptions {
    /// A, then B for [`Objective::Separate`] (B is the one that should succeed).
    pub models: Vec<ModelId>,
    pub objective: Objective,
    pub method: Method,
    /// Also run random search at the same budget, as the reference.
    pub reference: bool,
    pub severity_budget: f64,
    /// What a damage gene acts on: a joint (the default; absent from search.json) or a leg.
    #[serde(default, skip_serializing_if = "Unit::is_joint")]
    pub unit: Unit,
    /// Over the budget, keep the largest damages whole (`--concentrate`); absent when off.
    #[serde(default, skip_serializing_if = "is_false")]
    pub concentrate: bool,
    pub latest_onset: usize,
    /// One push per schedule as well, under this impulse budget (`--push-impulse`); absent
    /// from a search without pushes.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pushes: Option<PushSpace>,
    pub evaluations: usize,
    pub episodes: usize,
    pub held_out_episodes: usize,
    pub held_out_seed_base: u64,
    pub top: usize,
    pub shrink_evaluations: usize,
    /// Search-seed episodes' worth of the failure a shrinking step may give back
    /// (`--shrink-slack`; 0: none, the strict rule). On a chaotic walk a 1 % nudge to a joint
    /// flips an outcome or two, and the strict rule keeps such nudges as if they were damage.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub shrink_slack: usize,
    pub max_steps: usize,
    /// The goal's distance at reset, to put final distances on one scale.
    pub goal_distance: f64,
    pub seed: u64,
    pub world: String,
    pub version: String,
}

impl SearchOptions {
    pub fn check(&self) -> Result<(), SearchError> {
        let bad = |m: String| Err(SearchError::Options(m));
        if !(self.severity_budget.is_finite()
            && self.severity_budget > 0.0
            && self.severity_budget <= space::MAX_SEVERITY)
        {
            return bad(format!(
                "--budget must lie in (0, {}] (Σ(1 − scale) over the joints; 1 = one joint dead, 2 one leg), got {}",
                space::MAX_SEVERITY,
                self.severity_budget
            ));
        }
        if let Some(p) = &self.pushes {
            if !(p.step_seconds.is_finite() && p.step_seconds > 0.0) {
                return bad(format!("an env step of {} s", p.step_seconds));
            }
            let most = PushSpace::max_impulse(p.step_seconds);
            if !(p.impulse.is_finite() && p.impulse > 0.0 && p.impulse <= most) {
                return bad(format!(
                    "--push-impulse must lie in (0, {most}] N·s (a push of at most {} N for at \
                     most {} steps of {} s), got {}",
                    crate::damage::MAX_PUSH_NEWTONS,
                    space::MAX_SEARCH_PUSH_STEPS,
                    p.step_seconds,
                    p.impulse
                ));
            }
        }
        if !(1..=MAX_EVALUATIONS).contains(&self.evaluations) {
            return bad(format!(
                "--evaluations must lie in 1..={MAX_EVALUATIONS}, got {}",
                self.evaluations
            ));
        }
        for (flag, n) in [
            ("--episodes", self.episodes),
            ("--held-out", self.held_out_episodes),
        ] {
            if !(1..=MAX_EPISODES).contains(&n) {
                return bad(format!("{flag} must lie in 1..={MAX_EPISODES}, got {n}"));
            }
        }
        if self.shrink_slack >= self.episodes {
            return bad(format!(
                "--shrink-slack ({}) must be below --episodes ({}): a shrink that may give back \
                 every search episode keeps nothing of the failure",
                self.shrink_slack, self.episodes
            ));
        }
        if self.top == 0 || self.top > 100 {
            return bad(format!("--top must lie in 1..=100, got {}", self.top));
        }
        if self.max_steps == 0 || self.max_steps > crate::config::MAX_EPISODE_STEPS {
            return bad(format!(
                "--max-steps must lie in 1..={}, got {}",
                crate::config::MAX_EPISODE_STEPS,
                self.max_steps
            ));
        }
        if self.latest_onset >= self.max_steps {
            return bad(format!(
                "--latest-onset ({}) must come before the step limit ({})",
                self.latest_onset, self.max_steps
            ));
        }
        let want = match self.objective {
            Objective::Break => 1,
            Objective::Separate => 2,
        };
        if self.models.len() != want {
            return bad(format!("{:?} needs {want} model(s)", self.objective));
        }
        if !(self.goal_distance.is_finite() && self.goal_distance > 0.0) {
            return bad(format!("goal distance {}", self.goal_distance));
        }
        Ok(())
    }

    /// The space the genes decode into, with `anatomy`'s legs where a gene damages a leg.
    fn space(&self, anatomy: &Anatomy) -> Space {
        Space {
            severity_budget: self.severity_budget,
            latest_onset: self.latest_onset,
            pushes: self.pushes,
            legs: match self.unit {
                Unit::Joint => None,
                Unit::Leg => Some(anatomy.legs.clone().map(|(_, actuators)| actuators)),
            },
            concentrate: self.concentrate,
        }
    }

    /// The seeds every candidate runs on (the same for all: paired).
    pub fn search_seeds(&self) -> Vec<u64> {
        let base = SEARCH_SEED_BASE + self.seed.wrapping_mul(MAX_EPISODES as u64);
        (0..self.episodes as u64).map(|i| base + i).collect()
    }

    pub fn held_out_seeds(&self) -> Vec<u64> {
        (0..self.held_out_episodes as u64)
            .map(|i| self.held_out_seed_base + i)
            .collect()
    }
}

/// What the search maximises for one candidate, from its outcomes: for [`Objective::Break`]
/// failure rate + 0.01 · mean final distance (as a fraction of the goal's, at most 1); for
/// [`Objective::Separate`] success(B) − success(A) + 0.01 · mean (distance A − distance B) as a
/// fraction. The distance terms only order candidates with equal success.
/// Successes among `o`, as a rate with its Wilson interval.
fn success(o: &[EpisodeOutcome]) -> Rate {
    Rate::new(o.iter().filter(|e| e.success).count(), o.len())
}

pub fn score(objective: Objective, outcomes: &[Vec<EpisodeOutcome>], goal: f64) -> f64 {
    let rate = |o: &[EpisodeOutcome]| success(o).rate;
    let dist = |o: &[EpisodeOutcome]| {
        o.iter()
            .map(|e| (e.final_distance / goal).clamp(0.0, 1.0))
            .sum::<f64>()
            / o.len().max(1) as f64
    };
    match objective {
        Objective::Break => (1.0 - rate(&outcomes[0])) + 0.01 * dist(&outcomes[0]),
        Objective::Separate => {
            rate(&outcomes[1]) - rate(&outcomes[0])
                + 0.01 * (dist(&outcomes[0]) - dist(&outcomes[1]))
        }
    }
}

fn is_zero(n: &usize) -> bool {
    *n == 0
}

fn is_false(b: &bool) -> bool {
    !*b
}

/// The part of the score a shrunk schedule must keep: failure rate, or the success gap.
fn success_part(objective: Objective, success: &[f64]) -> f64 {
    match objective {
        Objective::Break => 1.0 - success[0],
        Objective::Separate => success[1] - success[0],
    }
}

/// Which part of the search an evaluation belongs to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Phase {
    Search,
    Reference,
    HeldOut,
    Shrink,
    /// No damage on the search seeds: what those seeds give anyway, the level the search's
    /// own success rates are to be read against.
    Undamaged,
}

/// One line of candidates.jsonl.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Candidate {
    pub index: usize,
    pub phase: Phase,
    pub method: Method,
    pub schedule: Schedule,
    pub severity: f64,
    pub score: f64,
    /// Success rate per model.
    pub success: Vec<f64>,
    pub outcomes: Vec<Vec<EpisodeOutcome>>,
    pub models: Vec<ModelId>,
    pub search_seed: u64,
    pub version: String,
}

/// The log: what earlier runs evaluated (to replay), and the file new lines go to.
struct Log {
    path: PathBuf,
    done: Vec<Candidate>,
    next: usize,
    file: std::fs::File,
}

impl Log {
    /// Opens (or starts) candidates.jsonl: every complete line is kept; a torn last line (a kill
    /// mid-write) is cut off.
    fn open(path: &Path) -> Result<Self, SearchError> {
        let (done, keep) = match existing(path)? {
            Some(_) => read_log(path)?,
            None => (Vec::new(), 0),
        };
        let file = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(path)
            .map_err(io(path, "cannot open"))?;
        file.set_len(keep).map_err(io(path, "cannot truncate"))?;
        Ok(Log {
            path: path.to_path_buf(),
            done,
            next: 0,
            file,
        })
    }

    fn append(&mut self, c: &Candidate) -> Result<(), SearchError> {
        let mut line = serde_json::to_string(c).map_err(|e| SearchError::Corrupt {
            path: self.path.clone(),
            line: c.index + 1,
            reason: e.to_string(),
        })?;
        line.push('\n');
        self.file
            .write_all(line.as_bytes())
            .map_err(io(&self.path, "cannot write"))
    }
}

/// The complete lines of a log, each in its place (a torn last line, from a kill mid-write, is
/// left out), and their length in bytes.
fn read_log(path: &Path) -> Result<(Vec<Candidate>, u64), SearchError> {
    let text =
        crate::files::read_text_capped(path, MAX_LOG_BYTES).map_err(io(path, "cannot read"))?;
    let corrupt = |line: usize, reason: String| SearchError::Corrupt {
        path: path.to_path_buf(),
        line,
        reason,
    };
    let mut done = Vec::new();
    let mut keep = 0u64;
    for (i, line) in text.split_inclusive('\n').enumerate() {
        if !line.ends_with('\n') {
            break;
        }
        let c: Candidate = serde_json::from_str(line).map_err(|e| corrupt(i + 1, e.to_string()))?;
        if c.index != i {
            return Err(corrupt(
                i + 1,
                format!("index {} where {i} belongs", c.index),
            ));
        }
        keep += line.len() as u64;
        done.push(c);
    }
    Ok((done, keep))
}

/// A search folder's search.json.
fn read_options(path: &Path) -> Result<SearchOptions, SearchError> {
    let text = crate::files::read_text_capped(path, 1 << 20)
        .map_err(io(path, "cannot read (is this a search folder?)"))?;
    serde_json::from_str(&text).map_err(|e| SearchError::Corrupt {
        path: path.to_path_buf(),
        line: e.line(),
        reason: e.to_string(),
    })
}

/// The search in progress: options, the evaluator, the log.
struct Run<'a> {
    opts: &'a SearchOptions,
    evaluator: &'a dyn Evaluate,
    log: Log,
    progress: indicatif::ProgressBar,
}

impl Run<'_> {
    /// Evaluates (or replays from the log) one schedule on `seeds`.
    fn evaluate(
        &mut self,
        phase: Phase,
        method: Method,
        schedule: &Schedule,
        seeds: &[u64],
    ) -> Result<Candidate, SearchError> {
        let index = self.log.next;
        self.log.next += 1;
        self.progress.inc(1);
        if let Some(done) = self.log.done.get(index) {
            let same = done.phase == phase
                && done.method == method
                && done.schedule == *schedule
                && done.outcomes.iter().all(|o| {
                    o.len() == seeds.len() && o.iter().zip(seeds).all(|(e, s)| e.seed == *s)
                });
            if !same {
                return Err(SearchError::Different {
                    path: self.log.path.clone(),
                    differs: format!(
                        "evaluation {index} was {:?} {} {:?}, now {phase:?} {} {schedule:?}",
                        done.phase,
                        done.method.name(),
                        done.schedule,
                        method.name()
                    ),
                });
            }
            return Ok(done.clone());
        }
        let outcomes = self.evaluator.evaluate(schedule, seeds)?;
        let c = Candidate {
            index,
            phase,
            method,
            schedule: schedule.clone(),
            severity: round9(schedule.severity()),
            score: score(self.opts.objective, &outcomes, self.opts.goal_distance),
            success: outcomes.iter().map(|o| success(o).rate).collect(),
            outcomes,
            models: self.opts.models.clone(),
            search_seed: self.opts.seed,
            version: self.opts.version.clone(),
        };
        self.log.append(&c)?;
        Ok(c)
    }

    /// `evaluations` candidates from `method`, best first at the end.
    fn search(&mut self, phase: Phase, method: Method) -> Result<Vec<Candidate>, SearchError> {
        let seeds = self.opts.search_seeds();
        let space = self.opts.space(self.evaluator.anatomy());
        let budget = self.opts.evaluations;
        let mut found = Vec::with_capacity(budget);
        match method {
            Method::Random => {
                use rand::{Rng, SeedableRng};
                let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(self.opts.seed);
                for _ in 0..budget {
                    let genome: Vec<f64> =
                        (0..space.genes()).map(|_| rng.random::<f64>()).collect();
                    found.push(self.evaluate(phase, method, &space.decode(&genome), &seeds)?);
                }
            }
            Method::Cma => {
                // CMA-ES from the budget spread evenly over the joints (the largest damage
                // that needs no scaling down: per leg the same per joint), onsets mid-range and
                // a push (if any) in the middle of its ranges; a run that converges (or stalls
                // on a flat stretch) before the budget restarts there with the next seed.
                let even = (self.opts.severity_budget / N_ACTUATORS as f64).min(0.5);
                let units = space.units().len();
                let start: Vec<f64> = (0..space.genes())
                    .map(|g| if g < units { even } else { 0.5 })
                    .collect();
                let mut restart = 0u64;
                while found.len() < budget {
                    let mut failure = None;
                    let cma_seed = self.opts.seed.wrapping_add(restart.wrapping_mul(0x9E37));
                    let remaining = budget - found.len();
                    {
                        let found = &mut found;
                        let failure = &mut failure;
                        let this = &mut *self;
                        let seeds = &seeds;
                        let objective = move |x: &cmaes::DVector<f64>| -> f64 {
                            if found.len() >= budget || failure.is_some() {
                                return 0.0; // past the budget: not evaluated, not logged
                            }
                            match this.evaluate(phase, method, &space.decode(x.as_slice()), seeds) {
                                Ok(c) => {
                                    let s = c.score;
                                    found.push(c);
                                    -s
                                }
                                Err(e) => {
                                    *failure = Some(e);
                                    0.0
                                }
                            }
                        };
                        let mut cma = cmaes::CMAESOptions::new(start.clone(), 0.3)
                            .seed(cma_seed)
                            .build(objective)
                            .map_err(|e| SearchError::Options(format!("CMA-ES: {e:?}")))?;
                        // One generation at a time, until the budget is spent or CMA-ES stops.
                        while cma.next().is_none() && cma.function_evals() < remaining {}
                    }
                    if let Some(e) = failure {
                        return Err(e);
                    }
                    restart += 1;
                }
            }
        }
        Ok(found)
    }

    /// Greedy shrinking: take the first single reduction that keeps the failure (its
    /// success part at least the start's, less the slack) until none does, or the shrink
    /// budget is spent. The bar stays the start's, so slack never accumulates over steps.
    fn shrink(&mut self, start: &Candidate) -> Result<Shrunk, SearchError> {
        let seeds = self.opts.search_seeds();
        let space = self.opts.space(self.evaluator.anatomy());
        let slack = self.opts.shrink_slack as f64 / self.opts.episodes as f64;
        let target = success_part(self.opts.objective, &start.success) - slack;
        let mut current = start.clone();
        let mut spent = 0;
        'outer: loop {
            for reduced in space.reductions(&current.schedule) {
                if spent >= self.opts.shrink_evaluations {
                    return Ok(Shrunk {
                        candidate: current,
                        evaluations: spent,
                        minimal: false,
                    });
                }
                spent += 1;
                let c = self.evaluate(Phase::Shrink, self.opts.method, &reduced, &seeds)?;
                if success_part(self.opts.objective, &c.success) >= target - 1e-12 {
                    current = c;
                    continue 'outer;
                }
            }
            return Ok(Shrunk {
                candidate: current,
                evaluations: spent,
                minimal: true,
            });
        }
    }
}

/// The file's length, or `None` where nothing is there (a FIFO or a device is an error).
fn existing(path: &Path) -> Result<Option<u64>, SearchError> {
    match crate::files::regular_len(path) {
        Ok(n) => Ok(Some(n)),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(source) => Err(SearchError::Io {
            path: path.to_path_buf(),
            what: "cannot read",
            source,
        }),
    }
}

fn round9(x: f64) -> f64 {
    (x * 1e9).round() / 1e9
}

/// The shrinker's result.
#[derive(Debug, Clone)]
pub struct Shrunk {
    pub candidate: Candidate,
    pub evaluations: usize,
    /// No single reduction keeps the failure (false: the shrink budget ran out first).
    pub minimal: bool,
}

/// A top candidate re-run on held-out seeds.
#[derive(Debug, Clone)]
pub struct Confirmed {
    pub name: String,
    pub search: Candidate,
    pub held_out: Candidate,
    /// Success per model on the held-out seeds.
    pub rates: Vec<Rate>,
}

/// What a search found.
#[derive(Debug, Clone)]
pub struct SearchReport {
    pub options: SearchOptions,
    pub anatomy: Anatomy,
    /// Every candidate of the search (and of the reference), in evaluation order.
    pub searched: Vec<Candidate>,
    pub reference: Vec<Candidate>,
    pub top: Vec<Confirmed>,
    pub reference_best: Option<Confirmed>,
    pub shrunk: Shrunk,
    pub shrunk_held_out: Confirmed,
    /// Success per model on the held-out seeds with no damage (the reference for the rest).
    pub undamaged: Vec<Rate>,
    /// Success per model on the search seeds with no damage (the search column's reference).
    pub undamaged_search: Vec<f64>,
    /// The recording of top-1's worst held-out episode, and its seed.
    pub worst: Option<(PathBuf, u64)>,
    /// The files written, for the terminal.
    pub written: Vec<PathBuf>,
}

/// The best distinct schedules, best first (ties: less severe, then earlier).
fn best_distinct(candidates: &[Candidate], n: usize) -> Vec<Candidate> {
    let mut sorted: Vec<&Candidate> = candidates.iter().collect();
    sorted.sort_by(|a, b| {
        b.score
            .total_cmp(&a.score)
            .then(a.severity.total_cmp(&b.severity))
            .then(a.index.cmp(&b.index))
    });
    let mut out: Vec<Candidate> = Vec::new();
    for c in sorted {
        if out.len() == n {
            break;
        }
        if !out.iter().any(|o| o.schedule == c.schedule) {
            out.push(c.clone());
        }
    }
    out
}

/// Runs a search into `out` (created, or resumed if it holds this search): search, reference,
/// held-out confirmation of the top candidates, shrinking, then the files.
pub fn run(
    opts: &SearchOptions,
    evaluator: &dyn Evaluate,
    out: &Path,
) -> Result<SearchReport, SearchError> {
    opts.check()?;
    std::fs::create_dir_all(out).map_err(io(out, "cannot create"))?;
    let options_path = out.join("search.json");
    let log_path = out.join("candidates.jsonl");
    let options_json = serde_json::to_string_pretty(opts).map_err(|e| SearchError::Corrupt {
        path: options_path.clone(),
        line: 0,
        reason: e.to_string(),
    })? + "\n";
    match existing(&options_path)? {
        Some(_) => {
            let theirs = read_options(&options_path)?;
            if theirs != *opts {
                return Err(SearchError::Different {
                    path: out.to_path_buf(),
                    differs: differences(&theirs, opts),
                });
            }
        }
        None => {
            if existing(&log_path)?.is_some() {
                return Err(SearchError::Different {
                    path: out.to_path_buf(),
                    differs: "candidates.jsonl without search.json".into(),
                });
            }
            crate::policy::checkpoint::write_atomic(&options_path, options_json.as_bytes())
                .map_err(|e| SearchError::Options(e.to_string()))?;
        }
    }
    let log = Log::open(&log_path)?;
    let total = opts.evaluations * (1 + opts.reference as usize)
        + (opts.top + opts.reference as usize + 3)
        + opts.shrink_evaluations;
    let progress = crate::progress::bar(total as u64, "search candidates");
    let mut run = Run {
        opts,
        evaluator,
        log,
        progress,
    };
    let searched = run.search(Phase::Search, opts.method)?;
    let reference = if opts.reference {
        run.search(Phase::Reference, Method::Random)?
    } else {
        Vec::new()
    };
    let held_out_seeds = opts.held_out_seeds();
    let confirm = |run: &mut Run, name: String, c: &Candidate| {
        let held = run.evaluate(Phase::HeldOut, c.method, &c.schedule, &held_out_seeds)?;
        let rates = held.outcomes.iter().map(|o| success(o)).collect();
        Ok::<_, SearchError>(Confirmed {
            name,
            search: c.clone(),
            held_out: held,
            rates,
        })
    };
    let mut top = Vec::new();
    for (i, c) in best_distinct(&searched, opts.top).iter().enumerate() {
        top.push(confirm(&mut run, format!("top-{}", i + 1), c)?);
    }
    let reference_best = match best_distinct(&reference, 1).first() {
        Some(c) => Some(confirm(&mut run, "reference-best".into(), c)?),
        None => None,
    };
    let shrunk = run.shrink(&top[0].search)?;
    let shrunk_held_out = confirm(&mut run, "minimal".into(), &shrunk.candidate)?;
    // The same held-out seeds with no damage at all: what each model does anyway.
    let undamaged = run.evaluate(
        Phase::HeldOut,
        opts.method,
        &Schedule::healthy(),
        &held_out_seeds,
    )?;
    let undamaged = undamaged.outcomes.iter().map(|o| success(o)).collect();
    // And the search seeds with no damage: a search success rate near this one found nothing.
    let undamaged_search = run
        .evaluate(
            Phase::Undamaged,
            opts.method,
            &Schedule::healthy(),
            &opts.search_seeds(),
        )?
        .success;
    run.progress.finish_and_clear();
    let worst = record_worst(opts, evaluator, &top[0], out)?;
    let mut report = SearchReport {
        options: opts.clone(),
        anatomy: evaluator.anatomy().clone(),
        searched,
        reference,
        top,
        reference_best,
        shrunk,
        shrunk_held_out,
        undamaged,
        undamaged_search,
        worst: worst.clone(),
        written: vec![options_path, log_path],
    };
    report.written.extend(write_outputs(&report, out)?);
    report.written.extend(worst.map(|(path, _)| path));
    Ok(report)
}

/// Top-1's worst held-out episode (for [`Objective::Break`]: a failure, farthest from the goal;
/// for [`Objective::Separate`]: A failing where B succeeds, A farthest), recorded to worst.rrd
/// with the scenario's edits as damage events on its timeline.
fn record_worst(
    opts: &SearchOptions,
    evaluator: &dyn Evaluate,
    top: &Confirmed,
    out: &Path,
) -> Result<Option<(PathBuf, u64)>, SearchError> {
    let held = &top.held_out.outcomes;
    let worst = (0..held[0].len())
        .max_by(|&i, &j| {
            let rank = |k: usize| {
                let a = &held[0][k];
                let separated = held.get(1).is_none_or(|b| b[k].success);
                (!a.success && separated, !a.success, a.final_distance)
            };
            let (ri, rj) = (rank(i), rank(j));
            ri.0.cmp(&rj.0)
                .then(ri.1.cmp(&rj.1))
                .then(ri.2.total_cmp(&rj.2))
                .then(j.cmp(&i))
        })
        .map(|k| held[0][k].seed);
    let Some(seed) = worst else {
        return Ok(None);
    };
    let anatomy = evaluator.anatomy();
    let scenario =
        top.search
            .schedule
            .scenario_json(&format!("search-{}", top.name), "", &anatomy.joints);
    let caption = format!(
        "Seed {seed}, the worst of top-1's {} held-out episodes under `{}.json` \
         ({}), found by `gaitscope search` ({}, budget {}). Held-out success: {}.",
        held[0].len(),
        top.name,
        top.search.schedule.describe(anatomy),
        top.search.method.name(),
        opts.severity_budget,
        opts.models
            .iter()
            .zip(&top.rates)
            .map(|(m, r)| format!("{} {}", m.label, pct(r)))
            .collect::<Vec<_>>()
            .join(", ")
    );
    let path = out.join("worst.rrd");
    Ok(evaluator
        .record(&scenario, seed, &path, &caption)?
        .map(|p| (p, seed)))
}

/// One finding of a finished search, for the live viewer's "next failure": a scenario file of
/// the folder and the held-out seeds on which it broke the (first) model — where, against B,
/// B succeeded.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Finding {
    /// The file's stem: `top-1`, `reference-best`, `minimal`.
    pub name: String,
    /// The scenario file's text (as `--scenario` and the page's upload take it).
    pub scenario: String,
    pub description: String,
    pub failing_seeds: Vec<u64>,
}

/// The findings of a finished search folder, in its summary's order (top candidates, the
/// reference's best, the minimal one), each with the held-out seeds that failed.
pub fn findings(dir: &Path) -> Result<Vec<Finding>, SearchError> {
    let options_path = dir.join("search.json");
    let opts = read_options(&options_path)?;
    let (log, _) = read_log(&dir.join("candidates.jsonl"))?;
    let held: Vec<&Candidate> = log.iter().filter(|c| c.phase == Phase::HeldOut).collect();
    // Held-out runs in the order `run` makes them: the top ones, the reference's best, the
    // minimal one, then no damage.
    let mut names: Vec<String> = (1..=opts.top).map(|i| format!("top-{i}")).collect();
    if opts.reference {
        names.push("reference-best".into());
    }
    names.push("minimal".into());
    let mut out = Vec::new();
    for (name, c) in names.iter().zip(&held) {
        let path = dir.join(format!("{name}.json"));
        if existing(&path)?.is_none() {
            continue; // fewer distinct top candidates than --top
        }
        let scenario =
            crate::files::read_text_capped(&path, 1 << 20).map_err(io(&path, "cannot read"))?;
        let parsed = crate::damage::scenario::Scenario::from_json(&scenario, name)?;
        let failing_seeds = (0..c.outcomes[0].len())
            .filter(|&k| {
                !c.outcomes[0][k].success && c.outcomes.get(1).is_none_or(|b| b[k].success)
            })
            .map(|k| c.outcomes[0][k].seed)
            .collect();
        out.push(Finding {
            name: name.clone(),
            scenario,
            description: parsed.description,
            failing_seeds,
        });
    }
    if out.is_empty() {
        return Err(SearchError::Options(format!(
            "{} holds no finished search (no held-out runs yet)",
            dir.display()
        )));
    }
    Ok(out)
}

/// Which options differ, by name (for a refused resume).
fn differences(a: &SearchOptions, b: &SearchOptions) -> String {
    let (Ok(serde_json::Value::Object(a)), Ok(serde_json::Value::Object(b))) =
        (serde_json::to_value(a), serde_json::to_value(b))
    else {
        return "options".into();
    };
    let names: Vec<String> = a
        .iter()
        .filter(|(k, v)| b.get(*k) != Some(v))
        .map(|(k, v)| {
            format!(
                "{k}: {v} then, {} now",
                b.get(k).unwrap_or(&serde_json::Value::Null)
            )
        })
        .collect();
    names.join("; ")
}

/// A rate as `25.0 % [12.1, 44.0]`.
fn pct(r: &Rate) -> String {
    format!(
        "{:.1} % [{:.1}, {:.1}]",
        100.0 * r.rate,
        100.0 * r.wilson_low,
        100.0 * r.wilson_high
    )
}

/// The scenario files, summary.md and the search curve.
fn write_outputs(report: &SearchReport, out: &Path) -> Result<Vec<PathBuf>, SearchError> {
    let o = &report.options;
    let mut written = Vec::new();
    let what = match o.objective {
        Objective::Break => format!("{} fails", o.models[0].label),
        Objective::Separate => format!(
            "{} fails where {} succeeds",
            o.models[0].label, o.models[1].label
        ),
    };
    let confirmed: Vec<&Confirmed> = report
        .top
        .iter()
        .chain(&report.reference_best)
        .chain(std::iter::once(&report.shrunk_held_out))
        .collect();
    for c in &confirmed {
        let description = format!(
            "gaitscope search ({}, budget {}): {what}; {}; held-out success {}",
            c.search.method.name(),
            o.severity_budget,
            c.search.schedule.describe(&report.anatomy),
            c.rates.iter().map(pct).collect::<Vec<_>>().join(" vs ")
        );
        let json = c.search.schedule.scenario_json(
            &format!("search-{}", c.name),
            &description,
            &report.anatomy.joints,
        );
        let path = out.join(format!("{}.json", c.name));
        let text = serde_json::to_string_pretty(&json).unwrap_or_default() + "\n";
        crate::policy::checkpoint::write_atomic(&path, text.as_bytes())
            .map_err(|e| SearchError::Options(e.to_string()))?;
        written.push(path);
    }
    // The curve: best score so far against evaluations, per method.
    let curve = |cands: &[Candidate]| {
        let mut best = f64::NEG_INFINITY;
        cands
            .iter()
            .enumerate()
            .map(|(i, c)| {
                best = best.max(c.score);
                ((i + 1) as f64, best)
            })
            .collect::<Vec<_>>()
    };
    let mut lines = vec![crate::plots::Line {
        name: o.method.name().into(),
        colour: 0,
        points: curve(&report.searched),
        faint: false,
    }];
    if !report.reference.is_empty() {
        lines.push(crate::plots::Line {
            name: "random (reference)".into(),
            colour: 1,
            points: curve(&report.reference),
            faint: false,
        });
    }
    let png = out.join("search-curve.png");
    crate::plots::line_panels(
        &png,
        "evaluations",
        1,
        &[crate::plots::LinePanel {
            title: format!("best score so far: {what}"),
            y_label: "score".into(),
            lines,
            y_range: None,
            legend: Some(plotters::chart::SeriesLabelPosition::LowerRight),
        }],
    )?;
    written.push(png);
    let mut md = String::new();
    md.push_str(&format!("# gaitscope search: {what}\n\n"));
    md.push_str(&format!(
        "Models: {}. World `{}`. Damage: per {} a scale in [0, 1] from an onset step ≤ {}, \
         Σ(1 − scale) ≤ {} (fatigue off{}){}. {} evaluations of {} by {}{}, each on the same {} \
         search seeds (from {}), step limit {}. Score: {}. The top {} re-run on {} held-out seeds \
         (from {}: `gaitscope eval --scenario FILE --episodes {} --seed {} --max-steps {}` gives \
         the same episodes).\n\n",
        o.models
            .iter()
            .map(|m| format!("`{}` ({:08x})", m.label, m.model_crc32))
            .collect::<Vec<_>>()
            .join(", "),
        o.world,
        match o.unit {
            Unit::Joint => "joint",
            Unit::Leg => "leg (both its joints)",
        },
        o.latest_onset,
        o.severity_budget,
        if o.concentrate {
            "; over the budget the largest damages kept whole, the rest cut"
        } else {
            ""
        },
        match &o.pushes {
            Some(p) => format!(
                "; and one horizontal push on the torso or a leg, at most {} N for at most {} \
                 steps, with an impulse of at most {} N·s, from an onset step ≤ {}",
                crate::damage::MAX_PUSH_NEWTONS,
                space::MAX_SEARCH_PUSH_STEPS,
                p.impulse,
                o.latest_onset
            ),
            None => String::new(),
        },
        o.evaluations,
        report.searched.len(),
        o.method.name(),
        if o.reference {
            ", and as many by random search (the reference)"
        } else {
            ""
        },
        o.episodes,
        o.search_seeds().first().copied().unwrap_or(0),
        o.max_steps,
        match o.objective {
            Objective::Break => "failure rate + 0.01 × mean final distance / goal distance",
            Objective::Separate => {
                "success(B) − success(A) + 0.01 × mean (distance A − distance B) / goal distance"
            }
        },
        report.top.len(),
        o.held_out_episodes,
        o.held_out_seed_base,
        o.held_out_episodes,
        o.held_out_seed_base,
        o.max_steps,
    ));
    let unit = match o.unit {
        Unit::Joint => "joint",
        Unit::Leg => "leg",
    };
    md.push_str(&format!("| file | method | damage ({unit} scale @ onset; push) | severity | score | search success | held-out success |\n|---|---|---|---:|---:|---|---|\n"));
    for c in &confirmed {
        md.push_str(&format!(
            "| `{}.json` | {} | {} | {:.3} | {:.3} | {} | {} |\n",
            c.name,
            if c.name == "minimal" {
                "shrunk".into()
            } else {
                c.search.method.name().to_string()
            },
            c.search.schedule.describe(&report.anatomy),
            c.search.severity,
            c.search.score,
            c.search
                .success
                .iter()
                .map(|s| format!("{:.1} %", 100.0 * s))
                .collect::<Vec<_>>()
                .join(" vs "),
            c.rates.iter().map(pct).collect::<Vec<_>>().join(" vs "),
        ));
    }
    md.push_str(&format!(
        "| (no damage) | – | – | 0 | – | {} | {} |\n",
        report
            .undamaged_search
            .iter()
            .map(|s| format!("{:.1} %", 100.0 * s))
            .collect::<Vec<_>>()
            .join(" vs "),
        report
            .undamaged
            .iter()
            .map(pct)
            .collect::<Vec<_>>()
            .join(" vs ")
    ));
    let best = |c: &[Candidate]| c.iter().map(|c| c.score).fold(f64::NEG_INFINITY, f64::max);
    md.push_str(&format!(
        "\nSuccess is per model ({}). Search success is on the seeds the search chose by, so it is \
         biased toward failure (the winner's curse): read it against the no-damage row's search \
         success, the same seeds undamaged; the held-out column is the estimate, with 95 % \
         Wilson intervals.\n\nBest score: {} {:.3}{}.\n\n",
        o.models
            .iter()
            .map(|m| m.label.as_str())
            .collect::<Vec<_>>()
            .join(" vs "),
        o.method.name(),
        best(&report.searched),
        if report.reference.is_empty() {
            String::new()
        } else {
            format!(", random {:.3}", best(&report.reference))
        }
    ));
    md.push_str(&format!(
        "**Minimal counterexample** (`minimal.json`): {} after {} shrink evaluations{}, from top-1's {}.\n\n",
        report.shrunk.candidate.schedule.describe(&report.anatomy),
        report.shrunk.evaluations,
        if report.shrunk.minimal {
            format!(
                ": no single further reduction (drop a {unit} or the push, raise a scale by 0.1, \
                 halve the push, a later onset) keeps the failure"
            )
        } else {
            " (the shrink budget ran out: it may shrink further)".to_string()
        },
        report.top[0].search.schedule.describe(&report.anatomy),
    ));
    if report.options.shrink_slack > 0 {
        md.push_str(&format!(
            "Shrinking kept the failure to within {} of the {} search episodes of top-1's \
             (`--shrink-slack`), so nudges that flip an outcome or two on a chaotic walk are \
             dropped rather than kept as damage.\n\n",
            report.options.shrink_slack, report.options.episodes
        ));
    }
    if let Some((_, seed)) = &report.worst {
        md.push_str(&format!(
            "`worst.rrd`: top-1's worst held-out episode (seed {seed}), every model side by side, \
             the scenario's edits as damage events (open it with `gaitscope view`).\n\n"
        ));
    }
    md.push_str("![best score against evaluations, per method](search-curve.png)\n");
    let path = out.join("summary.md");
    crate::policy::checkpoint::write_atomic(&path, md.as_bytes())
        .map_err(|e| SearchError::Options(e.to_string()))?;
    written.push(path);
    Ok(written)
}

/// Checkpoints acting under schedules: each schedule becomes a scenario, and each model runs
/// it in its own world on the seeds, in lockstep batches, through eval's stepping.
pub struct PolicyEvaluator {
    actors: Vec<(String, crate::lane::Actor)>,
    anatomy: Anatomy,
    step_seconds: f64,
    max_steps: usize,
    pool: rayon::ThreadPool,
}

impl PolicyEvaluator {
    pub fn new(
        models: &[(String, PathBuf)],
        max_steps: usize,
        threads: usize,
    ) -> Result<Self, SearchError> {
        let mut actors = Vec::new();
        for (label, dir) in models {
            let policy = crate::policy::Policy::load(dir, None)?;
            actors.push((label.clone(), crate::lane::Actor::from_policy(dir, policy)));
        }
        let world = actors[0].1.world(&crate::config::GaitConfig::default());
        let env = crate::env::AntEnv::new(world, 0).map_err(crate::eval::EvalError::Env)?;
        let pairs: [[usize; 2]; crate::env::N_LEGS] =
            env.leg_actuators().try_into().map_err(|pairs: Vec<_>| {
                SearchError::Options(format!(
                    "the model's legs do not each have a hip and an ankle ({} of {} do)",
                    pairs.len(),
                    crate::env::N_LEGS
                ))
            })?;
        let anatomy = Anatomy {
            joints: env.damage().joint_names().clone(),
            legs: std::array::from_fn(|l| (env.leg_names()[l].clone(), pairs[l])),
        };
        let step_seconds = env.dt();
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads.max(1))
            .build()
            .map_err(|e| SearchError::Options(format!("thread pool: {e}")))?;
        Ok(PolicyEvaluator {
            actors,
            anatomy,
            step_seconds,
            max_steps,
            pool,
        })
    }

    /// What every episode runs under: `scenario` (a scenario file's JSON), severe as eval's
    /// scenarios (the rule names no condition; fatigue is off), the search's step limit. Each
    /// model runs it in its own world.
    fn requested(
        &self,
        scenario: &serde_json::Value,
        origin: &str,
    ) -> Result<crate::config::GaitConfig, SearchError> {
        let scenario = crate::damage::scenario::Scenario::from_json(&scenario.to_string(), origin)?;
        let mut requested = crate::config::GaitConfig::default();
        requested.damage.condition =
            crate::damage::ConditionChoice::Fixed(crate::damage::Condition::Severe);
        requested.damage.scenario = Some(scenario);
        requested.env.max_episode_steps = self.max_steps;
        Ok(requested)
    }

    /// Seconds per env step in the first model's world (a push's impulse is newtons × this ×
    /// steps).
    pub fn step_seconds(&self) -> f64 {
        self.step_seconds
    }

    /// The first model's world: its goal distance and name.
    pub fn world(&self) -> crate::config::GaitConfig {
        self.actors[0]
            .1
            .world(&crate::config::GaitConfig::default())
    }
}

impl Evaluate for PolicyEvaluator {
    fn anatomy(&self) -> &Anatomy {
        &self.anatomy
    }

    fn record(
        &self,
        scenario: &serde_json::Value,
        seed: u64,
        path: &Path,
        caption: &str,
    ) -> Result<Option<PathBuf>, SearchError> {
        let name = scenario["name"].as_str().unwrap_or("search");
        let opts = crate::telemetry::RecordOptions {
            actors: self.actors.iter().map(|(_, a)| a.clone()).collect(),
            config: self.requested(scenario, name)?,
            episodes: 1,
            seed,
            sink: crate::telemetry::Sink::File(path.to_path_buf()),
            fork: None,
            start: None,
            attribution: false,
            caption: Some(caption.to_string()),
        };
        crate::telemetry::record(opts, &std::sync::atomic::AtomicBool::new(false))?;
        Ok(Some(path.to_path_buf()))
    }

    fn evaluate(
        &self,
        schedule: &Schedule,
        seeds: &[u64],
    ) -> Result<Vec<Vec<EpisodeOutcome>>, SearchError> {
        let json = schedule.scenario_json("search-candidate", "", &self.anatomy.joints);
        let requested = self.requested(&json, "search candidate")?;
        let case = crate::eval::Case::scenario("search-candidate");
        let mut all = Vec::new();
        for (label, actor) in &self.actors {
            let config = actor.world(&requested);
            let batches: Vec<Result<Vec<crate::eval::EpisodeRecord>, crate::eval::EvalError>> =
                self.pool.install(|| {
                    seeds
                        .par_chunks(LOCKSTEP_CHUNK)
                        .map(|chunk| {
                            crate::eval::run_lockstep(actor, label, &config, case, chunk, 0)
                        })
                        .collect()
                });
            let mut outcomes = Vec::with_capacity(seeds.len());
            for batch in batches {
                outcomes.extend(batch?.into_iter().map(|r| EpisodeOutcome {
                    seed: r.seed,
                    success: r.success,
                    steps: r.steps,
                    final_distance: round9(r.final_distance),
                }));
            }
            all.push(outcomes);
        }
        Ok(all)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::{AtomicUsize, Ordering};

    const HIP_2: usize = 4; // actuator order: hip_4, ankle_4, hip_1, ankle_1, hip_2, …

    /// A planted failure: every episode fails exactly when hip_2 runs below 0.3 from before
    /// step 50; otherwise it succeeds, ending nearer the goal the less hip_2 is damaged and the
    /// later (a slope for the distance tie-break, as a real policy's would be).
    /// Other planted failures ([`leg_rule`], [`push_rule`]) swap the rule: whether a schedule
    /// fails every episode, and how far from the goal its episodes end.
    struct Planted {
        anatomy: Anatomy,
        calls: AtomicUsize,
        rule: fn(&Schedule) -> (bool, f64),
    }

    impl Planted {
        fn new() -> Self {
            Self::by(|s| (Self::fails(s), Self::distance(s)))
        }
        fn by(rule: fn(&Schedule) -> (bool, f64)) -> Self {
            Planted {
                anatomy: Anatomy::ant(),
                calls: AtomicUsize::new(0),
                rule,
            }
        }
        fn fails(s: &Schedule) -> bool {
            s.scales[HIP_2] < 0.3 && s.onsets[HIP_2] < 50
        }
        /// The final distance: larger the more hip_2 is damaged and the earlier.
        fn distance(s: &Schedule) -> f64 {
            3.0 * (1.0 - s.scales[HIP_2]) * (1.0 - s.onsets[HIP_2] as f64 / 101.0)
        }
    }

    impl Evaluate for Planted {
        fn anatomy(&self) -> &Anatomy {
            &self.anatomy
        }
        fn evaluate(
            &self,
            s: &Schedule,
            seeds: &[u64],
        ) -> Result<Vec<Vec<EpisodeOutcome>>, SearchError> {
            self.calls.fetch_add(1, Ordering::SeqCst);
            let (fails, distance) = (self.rule)(s);
            Ok(planted_outcomes(seeds, fails, distance))
        }
    }

    /// One model's episodes on `seeds`, all failing or all succeeding, each ending `distance`
    /// from the goal: what a planted evaluator returns.
    fn planted_outcomes(seeds: &[u64], fail: bool, distance: f64) -> Vec<Vec<EpisodeOutcome>> {
        vec![
            seeds
                .iter()
                .map(|&seed| EpisodeOutcome {
                    seed,
                    success: !fail,
                    steps: 100,
                    final_distance: round9(distance),
                })
                .collect(),
        ]
    }

    fn options(method: Method, evaluations: usize) -> SearchOptions {
        SearchOptions {
            models: vec![ModelId {
                label: "planted".into(),
                path: "-".into(),
                model_crc32: 0,
            }],
            objective: Objective::Break,
            method,
            reference: false,
            severity_budget: 1.0,
            unit: Unit::Joint,
            concentrate: false,
            latest_onset: 100,
            pushes: None,
            evaluations,
            episodes: 2,
            held_out_episodes: 4,
            held_out_seed_base: 7,
            top: 2,
            shrink_evaluations: 200,
            shrink_slack: 0,
            max_steps: 500,
            goal_distance: 7.07,
            seed: 3,
            world: "paper".into(),
            version: "test".into(),
        }
    }

    /// The first evaluation (1-based) that found the planted failure, if any.
    fn first_hit(found: &[Candidate]) -> Option<usize> {
        found
            .iter()
            .position(|c| c.success[0] == 0.0)
            .map(|i| i + 1)
    }

    #[test]
    fn cma_finds_the_planted_failure_and_random_search_does_not() {
        let budget = 500;
        let mut hits = Vec::new();
        for method in [Method::Cma, Method::Random] {
            let dir = tempfile::tempdir().unwrap();
            let planted = Planted::new();
            let report = run(&options(method, budget), &planted, dir.path()).unwrap();
            // The budget is spent exactly, never exceeded.
            assert_eq!(report.searched.len(), budget);
            assert!(report.searched.iter().all(|c| c.severity <= 1.0 + 1e-9));
            hits.push(first_hit(&report.searched));
            if method == Method::Cma {
                let best = &report.top[0];
                assert!(Planted::fails(&best.search.schedule), "{best:?}");
                assert_eq!(best.rates[0].successes, 0);
                // Shrunk: still fails, and no single further reduction does.
                let shrunk = &report.shrunk;
                assert!(shrunk.minimal);
                let s = &shrunk.candidate.schedule;
                assert!(Planted::fails(s), "{s:?}");
                assert_eq!(s.damaged().collect::<Vec<_>>(), vec![HIP_2], "{s:?}");
                for r in options(method, budget).space(&Anatomy::ant()).reductions(s) {
                    assert!(!Planted::fails(&r), "{r:?} still fails");
                }
                // Every evaluation is one line, in order.
                let lines = std::fs::read_to_string(dir.path().join("candidates.jsonl")).unwrap();
                assert_eq!(lines.lines().count(), planted.calls.load(Ordering::SeqCst));
            }
        }
        eprintln!(
            "planted failure first found at evaluation: cma {:?}, random {:?}",
            hits[0], hits[1]
        );
        let cma = hits[0].expect("CMA-ES found the planted failure");
        assert!(hits[1].is_none_or(|r| r > cma), "{hits:?}");
    }

    /// back_leg's actuators: hip_3 and ankle_3.
    const BACK_LEG: [usize; 2] = [6, 7];

    /// A planted leg failure: every episode fails exactly when back_leg runs below 0.3 from
    /// before step 50 — what a search by legs looks for in one gene.
    fn leg_fails(s: &Schedule) -> bool {
        BACK_LEG
            .iter()
            .all(|&i| s.scales[i] < 0.3 && s.onsets[i] < 50)
    }

    fn leg_rule(s: &Schedule) -> (bool, f64) {
        let d = (1.0 - s.scales[BACK_LEG[0]]) * (1.0 - s.onsets[BACK_LEG[0]] as f64 / 101.0);
        (leg_fails(s), 3.0 * d)
    }

    #[test]
    fn a_search_by_legs_finds_a_dead_leg_and_shrinks_to_it() {
        let opts = SearchOptions {
            unit: Unit::Leg,
            concentrate: true,
            severity_budget: 2.0,
            ..options(Method::Cma, 200)
        };
        let dir = tempfile::tempdir().unwrap();
        let planted = Planted::by(leg_rule);
        let report = run(&opts, &planted, dir.path()).unwrap();
        // Every candidate damages whole legs, within the budget (a leg costs 2 at scale 0).
        for c in &report.searched {
            assert!(c.severity <= 2.0 + 1e-9);
            for (_, [a, b]) in Anatomy::ant().legs {
                let s = &c.schedule;
                assert_eq!((s.scales[a], s.onsets[a]), (s.scales[b], s.onsets[b]));
            }
        }
        let best = &report.top[0].search.schedule;
        assert!(leg_fails(best), "{best:?}");
        let shrunk = &report.shrunk.candidate.schedule;
        assert!(report.shrunk.minimal && leg_fails(shrunk), "{shrunk:?}");
        assert_eq!(shrunk.damaged().collect::<Vec<_>>(), BACK_LEG, "{shrunk:?}");
        for r in opts.space(&Anatomy::ant()).reductions(shrunk) {
            assert!(!leg_fails(&r), "{r:?} still fails");
        }
        // Described and written as the leg; the summary says what a gene acted on.
        assert!(shrunk.describe(&Anatomy::ant()).starts_with("back_leg "));
        let summary = std::fs::read_to_string(dir.path().join("summary.md")).unwrap();
        assert!(
            summary.contains("Damage: per leg (both its joints)"),
            "{summary}"
        );
        assert!(
            summary.contains("`minimal.json` | shrunk | back_leg "),
            "{summary}"
        );
        assert!(
            summary.contains("damage (leg scale @ onset; push)"),
            "{summary}"
        );
        assert!(summary.contains("(drop a leg or the push,"), "{summary}");
        assert!(
            summary.contains("the largest damages kept whole"),
            "{summary}"
        );
        let written: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(dir.path().join("search.json")).unwrap())
                .unwrap();
        assert_eq!(written["unit"], "leg");
        assert_eq!(written["concentrate"], true);
        // A search by joints writes no unit: the folders of earlier searches resume unchanged.
        let joints = serde_json::to_value(options(Method::Cma, 200)).unwrap();
        assert!(joints.get("unit").is_none() && joints.get("concentrate").is_none());
    }

    /// A planted push failure: every episode fails exactly when the torso is pushed with at
    /// least 15 N·s before step 50, whatever the joints; nearer the goal the weaker the push.
    fn push_fails(s: &Schedule) -> bool {
        s.push
            .as_ref()
            .is_some_and(|p| p.body == "torso" && p.impulse(0.05) >= 15.0 && p.onset < 50)
    }

    fn push_rule(s: &Schedule) -> (bool, f64) {
        let d = s.push.as_ref().map_or(0.0, |p| {
            let torso = if p.body == "torso" { 1.0 } else { 0.3 };
            torso * (p.impulse(0.05) / 40.0).min(1.0) * (1.0 - p.onset as f64 / 101.0)
        });
        (push_fails(s), 3.0 * d)
    }

    #[test]
    fn a_planted_push_is_found_within_its_impulse_budget_and_shrunk_to_itself() {
        let dir = tempfile::tempdir().unwrap();
        let opts = SearchOptions {
            pushes: Some(PushSpace {
                impulse: 40.0,
                step_seconds: 0.05,
            }),
            ..options(Method::Cma, 200)
        };
        let planted = Planted::by(push_rule);
        let report = run(&opts, &planted, dir.path()).unwrap();
        assert_eq!(report.searched.len(), 200);
        for c in &report.searched {
            assert!(c.severity <= 1.0 + 1e-9);
            if let Some(p) = &c.schedule.push {
                assert!(p.impulse(0.05) <= 40.0 + 1e-9, "{p:?}");
            }
        }
        let best = &report.top[0];
        assert!(push_fails(&best.search.schedule), "{best:?}");
        // The search seeds undamaged: the planted evaluator succeeds there.
        assert_eq!(report.undamaged_search, vec![1.0]);
        // Shrunk to the push alone, which still fails, and no single reduction of it does.
        let s = &report.shrunk.candidate.schedule;
        assert!(report.shrunk.minimal);
        assert!(push_fails(s), "{s:?}");
        assert_eq!(s.damaged().count(), 0, "{s:?}");
        for r in opts.space(&Anatomy::ant()).reductions(s) {
            assert!(!push_fails(&r), "{r:?} still fails");
        }
        // The written scenario carries the push; the summary says pushes were searched.
        let top = std::fs::read_to_string(dir.path().join("minimal.json")).unwrap();
        let read = crate::damage::scenario::Scenario::from_json(&top, "minimal").unwrap();
        assert_eq!(read.pushes.len(), 1);
        let summary = std::fs::read_to_string(dir.path().join("summary.md")).unwrap();
        assert!(summary.contains("at most 40 N·s"), "{summary}");
        // A search without pushes writes no push key (its files read as before).
        let plain = tempfile::tempdir().unwrap();
        run(&options(Method::Random, 5), &Planted::new(), plain.path()).unwrap();
        for f in ["search.json", "candidates.jsonl"] {
            let text = std::fs::read_to_string(plain.path().join(f)).unwrap();
            assert!(!text.contains("push"), "{f}: {text}");
        }
    }

    /// Chaos, planted: hip_2 below 0.3 before step 50 fails every search episode but the first
    /// seed's, which fails only if some other joint is nudged at all (as a 1 % change flips an
    /// outcome on a chaotic walk). The strict shrinker keeps a nudge; one episode of slack
    /// drops every nudge and leaves hip_2 alone, whose failure is within that slack.
    struct PlantedChaos(Planted);

    impl Evaluate for PlantedChaos {
        fn anatomy(&self) -> &Anatomy {
            &self.0.anatomy
        }
        fn evaluate(
            &self,
            s: &Schedule,
            seeds: &[u64],
        ) -> Result<Vec<Vec<EpisodeOutcome>>, SearchError> {
            self.0.calls.fetch_add(1, Ordering::SeqCst);
            let nudged = s.damaged().any(|i| i != HIP_2);
            // Planted's slope toward the failure, for the search to follow.
            let mut outcomes = planted_outcomes(seeds, Planted::fails(s), Planted::distance(s));
            if Planted::fails(s) && !nudged {
                outcomes[0][0].success = true;
            }
            Ok(outcomes)
        }
    }

    #[test]
    fn shrink_slack_drops_the_nudges_a_chaotic_walk_rewards() {
        let episodes = 4;
        let mut minimal = Vec::new();
        for slack in [0, 1] {
            let dir = tempfile::tempdir().unwrap();
            let opts = SearchOptions {
                episodes,
                shrink_slack: slack,
                ..options(Method::Cma, 500)
            };
            let report = run(&opts, &PlantedChaos(Planted::new()), dir.path()).unwrap();
            // Top-1 fails every search episode, which takes hip_2 and a nudge.
            assert_eq!(report.top[0].search.success, vec![0.0]);
            let s = report.shrunk.candidate.schedule.clone();
            assert!(report.shrunk.minimal && Planted::fails(&s), "{s:?}");
            let summary = std::fs::read_to_string(dir.path().join("summary.md")).unwrap();
            assert_eq!(summary.contains("`--shrink-slack`"), slack > 0);
            minimal.push(s.damaged().collect::<Vec<_>>());
        }
        // Strict: a nudge stays beside hip_2 (dropping it gives back one episode).
        assert!(
            minimal[0].contains(&HIP_2) && minimal[0].len() >= 2,
            "{minimal:?}"
        );
        // One episode of slack: hip_2 alone.
        assert_eq!(minimal[1], vec![HIP_2]);
        // Slack as large as the search's episodes is refused.
        let err = SearchOptions {
            episodes,
            shrink_slack: episodes,
            ..options(Method::Cma, 10)
        }
        .check()
        .unwrap_err()
        .to_string();
        assert!(
            err.contains("--shrink-slack (4) must be below --episodes (4)"),
            "{err}"
        );
    }

    #[test]
    fn a_killed_search_resumes_to_the_same_files() {
        let whole = tempfile::tempdir().unwrap();
        let opts = SearchOptions {
            reference: true,
            ..options(Method::Cma, 40)
        };
        let planted = Planted::new();
        run(&opts, &planted, whole.path()).unwrap();
        let all = planted.calls.load(Ordering::SeqCst);
        let log = std::fs::read_to_string(whole.path().join("candidates.jsonl")).unwrap();
        // Killed after 30 evaluations, in the middle of writing the 31st line.
        let resumed = tempfile::tempdir().unwrap();
        let kept: String = log.split_inclusive('\n').take(30).collect();
        let torn = &log.split_inclusive('\n').nth(30).unwrap()[..50];
        std::fs::write(resumed.path().join("candidates.jsonl"), kept + torn).unwrap();
        std::fs::copy(
            whole.path().join("search.json"),
            resumed.path().join("search.json"),
        )
        .unwrap();
        let again = Planted::new();
        run(&opts, &again, resumed.path()).unwrap();
        assert_eq!(again.calls.load(Ordering::SeqCst), all - 30);
        for file in [
            "candidates.jsonl",
            "summary.md",
            "top-1.json",
            "minimal.json",
            "search.json",
        ] {
            assert_eq!(
                std::fs::read(whole.path().join(file)).unwrap(),
                std::fs::read(resumed.path().join(file)).unwrap(),
                "{file}"
            );
        }
        // Another search in the same folder is refused, naming what differs.
        let other = SearchOptions {
            severity_budget: 2.0,
            ..opts.clone()
        };
        let err = run(&other, &Planted::new(), resumed.path()).unwrap_err();
        assert!(
            err.to_string()
                .contains("severity_budget: 1.0 then, 2.0 now"),
            "{err}"
        );
    }

    #[test]
    fn bad_options_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        for (opts, says) in [
            (
                SearchOptions {
                    severity_budget: f64::NAN,
                    ..options(Method::Cma, 5)
                },
                "--budget must lie in (0, 8]",
            ),
            (
                SearchOptions {
                    severity_budget: 9.0,
                    ..options(Method::Cma, 5)
                },
                "--budget",
            ),
            (options(Method::Cma, 0), "--evaluations must lie in 1..="),
            (
                SearchOptions {
                    pushes: Some(PushSpace {
                        impulse: 501.0,
                        step_seconds: 0.05,
                    }),
                    ..options(Method::Cma, 5)
                },
                "--push-impulse must lie in (0, 500] N·s",
            ),
            (
                SearchOptions {
                    pushes: Some(PushSpace {
                        impulse: f64::INFINITY,
                        step_seconds: 0.05,
                    }),
                    ..options(Method::Cma, 5)
                },
                "--push-impulse",
            ),
            (
                SearchOptions {
                    latest_onset: 500,
                    ..options(Method::Cma, 5)
                },
                "--latest-onset (500) must come before the step limit (500)",
            ),
            (
                SearchOptions {
                    objective: Objective::Separate,
                    ..options(Method::Cma, 5)
                },
                "needs 2 model(s)",
            ),
        ] {
            let err = run(&opts, &Planted::new(), dir.path()).unwrap_err();
            assert!(err.to_string().contains(says), "{err}");
        }
        // A FIFO where the log belongs is refused, not waited on.
        let fifo_dir = tempfile::tempdir().unwrap();
        crate::files::mkfifo(&fifo_dir.path().join("candidates.jsonl"));
        let err = run(&options(Method::Cma, 5), &Planted::new(), fifo_dir.path()).unwrap_err();
        assert!(err.to_string().contains("candidates.jsonl"), "{err}");
    }
}
