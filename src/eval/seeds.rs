//! Evaluation across training seeds: runs of one model (`encoder-lstm`, `encoder-lstm-s1`, …)
//! form a group; a group's success is the mean over its seeds with a stratified bootstrap
//! interval (rliable's protocol: resample seeds, then episodes within each), encoders are paired
//! with the baseline run of the same training seed, and every episode is sorted into a failure
//! mode.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Binomial, Distribution};
use serde::Serialize;
use std::collections::BTreeMap;

use super::Case;
use super::stats::{McNemar, Rate, mcnemar_counts, recovery_fraction};
use super::{EpisodeRecord, RecoveryFraction, SUCCESS_BUDGETS, episodes_of};
use crate::damage::Condition;
use crate::policy::EncoderKind;

/// Bootstrap resamples per interval.
pub const BOOTSTRAP_REPS: usize = 10_000;
/// The bootstrap's RNG seed: the same episodes give the same intervals.
pub const BOOTSTRAP_SEED: u64 = 0x5EED_B007;

/// The model a run belongs to: its folder name without a trailing `-s<seed>`
/// (`encoder-lstm-s2` → `encoder-lstm`; seed 0 lives in `encoder-lstm` itself).
pub fn group_of(label: &str) -> String {
    match label.rsplit_once("-s") {
        Some((stem, seed))
            if !stem.is_empty() && !seed.is_empty() && seed.bytes().all(|b| b.is_ascii_digit()) =>
        {
            stem.to_string()
        }
        _ => label.to_string(),
    }
}

/// How an episode ended, for the failure-mode tables: an early ending (the torso left the
/// height band — leapt above it or collapsed below it — or the simulation went unstable) split
/// by whether damage could have caused it. Which early ending it was is
/// [`EpisodeRecord::ending`], counted beside these in [`FailureCounts`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum FailureMode {
    Success,
    /// Ended early before any step ran under damage (no trigger yet, or only on the step it
    /// ended; no joint weakened by a scenario yet): damage cannot have caused it.
    TerminatedBeforeDamage,
    /// Ended early with at least one step taken under damage.
    TerminatedAfterDamage,
    /// Neither reached the goal nor ended early within the step limit (upright or upside down).
    TimedOut,
}

impl EpisodeRecord {
    pub fn failure_mode(&self) -> FailureMode {
        if self.success {
            FailureMode::Success
        } else if !self.terminated {
            FailureMode::TimedOut
        } else if self.damage_onset.is_some_and(|t| t < self.steps) {
            FailureMode::TerminatedAfterDamage
        } else {
            FailureMode::TerminatedBeforeDamage
        }
    }

    /// A step ran under damage, or a joint triggered on the last step of an episode that timed
    /// out rather than fell (the episodes where adapting to damage can matter at all).
    pub fn reached_damage(&self) -> bool {
        self.damage_onset
            .is_some_and(|t| t < self.steps || (t == self.steps && !self.terminated))
    }
}

/// Episodes per failure mode, and what the early endings and timeouts were.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct FailureCounts {
    pub success: usize,
    pub terminated_before_damage: usize,
    pub terminated_after_damage: usize,
    pub timed_out: usize,
    /// Early endings by kind (before and after damage together): the torso above the height
    /// band, below it, an unstable simulation, and — in evaluations saved before endings were
    /// named — not recorded.
    pub leapt: usize,
    pub collapsed: usize,
    pub unstable: usize,
    pub early_unrecorded: usize,
    /// Timeouts with the torso's up axis below the horizon (a flipped Ant stays in the band).
    pub timed_out_upside_down: usize,
}

impl FailureCounts {
    pub fn of<'a>(episodes: impl IntoIterator<Item = &'a EpisodeRecord>) -> Self {
        use crate::env::Ending;
        let mut c = Self::default();
        for e in episodes {
            let mode = e.failure_mode();
            match mode {
                FailureMode::Success => c.success += 1,
                FailureMode::TerminatedBeforeDamage => c.terminated_before_damage += 1,
                FailureMode::TerminatedAfterDamage => c.terminated_after_damage += 1,
                FailureMode::TimedOut => c.timed_out += 1,
            }
            let early = matches!(
                mode,
                FailureMode::TerminatedBeforeDamage | FailureMode::TerminatedAfterDamage
            );
            match e.ending {
                Some(Ending::Leapt) => c.leapt += 1,
                Some(Ending::Collapsed) => c.collapsed += 1,
                Some(Ending::Unstable) => c.unstable += 1,
                Some(Ending::TimeoutUpsideDown) => c.timed_out_upside_down += 1,
                None if early => c.early_unrecorded += 1,
                _ => {}
            }
        }
        c
    }

    pub fn total(&self) -> usize {
        self.success + self.terminated_before_damage + self.terminated_after_damage + self.timed_out
    }

    /// The early endings by kind, in words ("leapt 11, collapsed 1"; "none").
    pub fn early_kinds(&self) -> String {
        let kinds: Vec<String> = [
            ("leapt above the band", self.leapt),
            ("collapsed below it", self.collapsed),
            ("unstable", self.unstable),
            ("kind not recorded", self.early_unrecorded),
        ]
        .iter()
        .filter(|(_, n)| *n > 0)
        .map(|(what, n)| format!("{what} {n}"))
        .collect();
        if kinds.is_empty() {
            "none".to_string()
        } else {
            kinds.join(", ")
        }
    }
}

/// A mean over seeds with its 95 % bootstrap interval.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Interval {
    pub mean: f64,
    pub low: f64,
    pub high: f64,
}

/// The bootstrap distribution of the mean success rate over seeds: each resample draws as many
/// seeds as there are, with replacement, then each drawn seed's episodes with replacement (a
/// binomial draw at that seed's rate is exactly that), and averages the drawn seeds' rates.
/// `seeds` holds (successes, episodes) per seed.
pub fn bootstrap_means(seeds: &[(usize, usize)], reps: usize, rng_seed: u64) -> Vec<f64> {
    let mut rng = ChaCha8Rng::seed_from_u64(rng_seed);
    let usable: Vec<(usize, usize)> = seeds.iter().copied().filter(|&(_, n)| n > 0).collect();
    if usable.is_empty() {
        return Vec::new();
    }
    let binomials: Vec<Option<Binomial>> = usable
        .iter()
        .map(|&(k, n)| Binomial::new(n as u64, k as f64 / n as f64).ok())
        .collect();
    (0..reps)
        .map(|_| {
            let mut sum = 0.0;
            for _ in 0..usable.len() {
                let s = rng.random_range(0..usable.len());
                let (k, n) = usable[s];
                let drawn = match &binomials[s] {
                    Some(b) => b.sample(&mut rng),
                    None => k as u64,
                };
                sum += drawn as f64 / n as f64;
            }
            sum / usable.len() as f64
        })
        .collect()
}

/// Mean over seeds of each seed's rate, with the 2.5 and 97.5 percentiles of
/// [`bootstrap_means`].
pub fn stratified_bootstrap(seeds: &[(usize, usize)], reps: usize, rng_seed: u64) -> Interval {
    let rates: Vec<f64> = seeds
        .iter()
        .filter(|&&(_, n)| n > 0)
        .map(|&(k, n)| k as f64 / n as f64)
        .collect();
    let mut draws = bootstrap_means(seeds, reps, rng_seed);
    if draws.is_empty() {
        return Interval {
            mean: f64::NAN,
            low: f64::NAN,
            high: f64::NAN,
        };
    }
    draws.sort_by(f64::total_cmp);
    Interval {
        mean: rates.iter().sum::<f64>() / rates.len() as f64,
        low: quantile(&draws, 0.025),
        high: quantile(&draws, 0.975),
    }
}

/// Linear-interpolated quantile of sorted values (type 7, numpy's default).
fn quantile(sorted: &[f64], q: f64) -> f64 {
    let pos = q * (sorted.len() - 1) as f64;
    let (i, frac) = (pos.floor() as usize, pos - pos.floor());
    match sorted.get(i + 1) {
        Some(next) => sorted[i] + frac * (next - sorted[i]),
        None => sorted[i],
    }
}

/// The interquartile mean (rliable, Agarwal et al. 2021): the mean of the middle half of the
/// sorted scores, cutting ⌊n/4⌋ from each end (scipy's `trim_mean(x, 0.25)`, which rliable
/// calls): of 8 scores the middle 4, of 6 the middle 4, of 3 all three.
pub fn iqm(scores: &[f64]) -> f64 {
    if scores.is_empty() {
        return f64::NAN;
    }
    let mut sorted = scores.to_vec();
    sorted.sort_by(f64::total_cmp);
    let cut = sorted.len() / 4;
    let middle = &sorted[cut..sorted.len() - cut];
    middle.iter().sum::<f64>() / middle.len() as f64
}

/// rliable's probability of improvement P(X > Y) on one task: over every pair of a run of X and
/// a run of Y, 1 when X's score is higher, ½ when equal, 0 when lower (the Mann–Whitney U
/// statistic over m·n).
pub fn probability_of_improvement(x: &[f64], y: &[f64]) -> f64 {
    if x.is_empty() || y.is_empty() {
        return f64::NAN;
    }
    let wins: f64 = x
        .iter()
        .flat_map(|a| y.iter().map(move |b| (a, b)))
        .map(|(a, b)| match a.total_cmp(b) {
            std::cmp::Ordering::Greater => 1.0,
            std::cmp::Ordering::Equal => 0.5,
            std::cmp::Ordering::Less => 0.0,
        })
        .sum();
    wins / (x.len() * y.len()) as f64
}

/// One bootstrap resample of per-seed rates: the seeds drawn with replacement, then each drawn
/// seed's episodes (a binomial draw at its rate), as [`bootstrap_means`] does.
fn resample_rates(seeds: &[(usize, usize)], rng: &mut ChaCha8Rng) -> Vec<f64> {
    (0..seeds.len())
        .map(|_| {
            let (k, n) = seeds[rng.random_range(0..seeds.len())];
            let drawn = match Binomial::new(n as u64, k as f64 / n as f64) {
                Ok(b) => b.sample(rng),
                Err(_) => k as u64,
            };
            drawn as f64 / n as f64
        })
        .collect()
}

fn rates_of(seeds: &[(usize, usize)]) -> Vec<(usize, usize)> {
    seeds.iter().copied().filter(|&(_, n)| n > 0).collect()
}

fn percentile_interval(point: f64, mut draws: Vec<f64>) -> Interval {
    if draws.is_empty() || point.is_nan() {
        return Interval {
            mean: point,
            low: f64::NAN,
            high: f64::NAN,
        };
    }
    draws.sort_by(f64::total_cmp);
    Interval {
        mean: point,
        low: quantile(&draws, 0.025),
        high: quantile(&draws, 0.975),
    }
}

/// The IQM of the seeds' success rates with its 95 % stratified bootstrap interval (`mean`
/// holds the IQM).
pub fn iqm_bootstrap(seeds: &[(usize, usize)], reps: usize, rng_seed: u64) -> Interval {
    let usable = rates_of(seeds);
    let rates: Vec<f64> = usable.iter().map(|&(k, n)| k as f64 / n as f64).collect();
    let mut rng = ChaCha8Rng::seed_from_u64(rng_seed);
    let draws = if usable.is_empty() {
        Vec::new()
    } else {
        (0..reps)
            .map(|_| iqm(&resample_rates(&usable, &mut rng)))
            .collect()
    };
    percentile_interval(iqm(&rates), draws)
}

/// P(X > Y) over the two groups' per-seed success rates, with its 95 % bootstrap interval
/// (each group's seeds and episodes resampled independently; `mean` holds the estimate).
pub fn improvement_bootstrap(
    x: &[(usize, usize)],
    y: &[(usize, usize)],
    reps: usize,
    rng_seed: u64,
) -> Interval {
    let (x, y) = (rates_of(x), rates_of(y));
    let rate = |s: &[(usize, usize)]| -> Vec<f64> {
        s.iter().map(|&(k, n)| k as f64 / n as f64).collect()
    };
    let point = probability_of_improvement(&rate(&x), &rate(&y));
    let mut rng = ChaCha8Rng::seed_from_u64(rng_seed);
    let draws = if x.is_empty() || y.is_empty() {
        Vec::new()
    } else {
        (0..reps)
            .map(|_| {
                let (a, b) = (resample_rates(&x, &mut rng), resample_rates(&y, &mut rng));
                probability_of_improvement(&a, &b)
            })
            .collect()
    };
    percentile_interval(point, draws)
}

/// The smallest two-sided p the sign-flip test can give with `seeds` paired seeds: the observed
/// signs and their mirror image are 2 of the 2ⁿ sign patterns.
pub fn sign_flip_floor(seeds: usize) -> f64 {
    2.0 / 2f64.powi(seeds as i32)
}

/// Seed-level paired test: flips the sign of every seed's difference (encoder − baseline rate)
/// in all 2^S ways; p is the share of flips whose |sum| is at least the observed one. With three
/// seeds its smallest possible value is 0.25: three seeds cannot be significant at seed level.
pub fn seed_sign_flip_p(differences: &[f64]) -> f64 {
    let s = differences.len();
    if s == 0 || s > 20 {
        return f64::NAN;
    }
    let observed = differences.iter().sum::<f64>().abs();
    let as_large = (0u32..1 << s)
        .filter(|mask| {
            let sum: f64 = differences
                .iter()
                .enumerate()
                .map(|(i, d)| if mask >> i & 1 == 1 { -d } else { *d })
                .sum();
            sum.abs() >= observed - 1e-12
        })
        .count();
    as_large as f64 / (1u64 << s) as f64
}

/// Pooled paired test over seeds: the Cochran–Mantel–Haenszel test with each pair as a stratum,
/// which is McNemar's test on the discordant pairs summed over seeds (continuity-corrected χ²
/// and the exact sign test: the paired permutation test of the pooled difference).
pub fn pooled_mcnemar(per_seed: &[McNemar]) -> McNemar {
    mcnemar_counts(
        per_seed.iter().map(|m| m.b).sum(),
        per_seed.iter().map(|m| m.c).sum(),
    )
}

/// One run (training seed) of a group under one condition.
#[derive(Debug, Clone, Serialize)]
pub struct SeedCell {
    pub model: String,
    pub train_seed: u64,
    pub success: BTreeMap<usize, Rate>,
    pub failure_modes: FailureCounts,
    /// Success@500 among the episodes that reached damage ([`EpisodeRecord::reached_damage`]).
    pub success_after_damage: Rate,
}

/// A group (every seed of one model) under one condition.
#[derive(Debug, Clone, Serialize)]
pub struct GroupCell {
    pub group: String,
    pub encoder: EncoderKind,
    pub condition: Case,
    pub runs: Vec<SeedCell>,
    /// Mean over seeds of success within each budget, with its stratified bootstrap interval.
    pub success: BTreeMap<usize, Interval>,
    /// rliable's IQM of the seeds' success@500 (the middle half of the runs), with its 95 %
    /// stratified bootstrap interval.
    pub success_iqm: Interval,
    /// Summed over seeds.
    pub failure_modes: FailureCounts,
    /// Mean over seeds (the seeds where any episode reached damage), with its interval.
    pub success_after_damage: Interval,
}

/// A model group against a reference group under one condition, on success@500, each run of
/// the model paired with the reference's run of its training seed on the same eval seeds. The
/// reference is the baseline for every encoder, and for two encoders the later-listed one (as in
/// [`Improvement`]: `encoder-lstm` against `encoder-mlp`, `encoder-lstm` against
/// `encoder-lstm-aux`).
#[derive(Debug, Clone, Serialize)]
pub struct GroupComparison {
    pub model: String,
    pub reference: String,
    pub condition: Case,
    /// (training seed, McNemar: b = reference only, c = model only).
    pub per_seed: Vec<(u64, McNemar)>,
    pub pooled: McNemar,
    /// Mean over paired seeds of (model − reference) success rate.
    pub mean_difference: f64,
    pub seed_sign_flip_p: f64,
}

/// An encoder group's recovery fraction, per training seed and from the group means.
#[derive(Debug, Clone, Serialize)]
pub struct GroupRecovery {
    pub encoder: String,
    pub per_seed: Vec<(u64, RecoveryFraction)>,
    pub of_means: RecoveryFraction,
}

/// rliable's probability of improvement of one group over another under one condition, on the
/// runs' success@500.
#[derive(Debug, Clone, Serialize)]
pub struct Improvement {
    pub better: String,
    pub than: String,
    pub condition: Case,
    /// P(better > than) over all pairs of their runs, with its 95 % bootstrap interval.
    pub probability_of_improvement: Interval,
}

#[derive(Debug, Clone, Serialize)]
pub struct AcrossSeeds {
    pub bootstrap_reps: usize,
    pub bootstrap_seed: u64,
    pub groups: Vec<GroupCell>,
    pub comparisons: Vec<GroupComparison>,
    pub recovery: Vec<GroupRecovery>,
    /// Every encoder group against the baseline, and each pair of encoder groups.
    pub improvements: Vec<Improvement>,
}

/// The runs of two groups with a training seed in common: (seed, reference run, model run).
fn paired_by_seed<'a>(
    model_runs: &'a [(u64, String)],
    reference_runs: &'a [(u64, String)],
) -> Vec<(u64, &'a String, &'a String)> {
    model_runs
        .iter()
        .filter_map(|(seed, m)| {
            reference_runs
                .iter()
                .find(|(s, _)| s == seed)
                .map(|(_, r)| (*seed, r, m))
        })
        .collect()
}

/// Groups the episodes by model and compares each encoder group with the baseline group and
/// with each other encoder group.
pub fn across_seeds(episodes: &[EpisodeRecord], conditions: &[Case]) -> AcrossSeeds {
    // Groups and their runs in the order they were evaluated; runs (training seed, label)
    // sorted by training seed.
    type Group = (String, EncoderKind, Vec<(u64, String)>);
    let mut groups: Vec<Group> = Vec::new();
    for e in episodes {
        let g = match groups.iter_mut().find(|(g, _, _)| *g == e.group) {
            Some(g) => g,
            None => {
                groups.push((e.group.clone(), e.encoder, Vec::new()));
                groups.last_mut().expect("just pushed")
            }
        };
        if !g.2.iter().any(|(_, m)| *m == e.model) {
            g.2.push((e.train_seed, e.model.clone()));
        }
    }
    for g in &mut groups {
        g.2.sort();
    }
    let run_episodes = |model: &str, condition: Case| episodes_of(episodes, model, condition);
    let success_rate = |eps: &[&EpisodeRecord], budget: usize| {
        Rate::new(
            eps.iter().filter(|e| e.success_within(budget)).count(),
            eps.len(),
        )
    };
    let after_damage = |eps: &[&EpisodeRecord]| {
        let reached: Vec<&&EpisodeRecord> = eps.iter().filter(|e| e.reached_damage()).collect();
        Rate::new(reached.iter().filter(|e| e.success).count(), reached.len())
    };

    let mut cells = Vec::new();
    for (group, encoder, runs) in &groups {
        for &condition in conditions {
            let mut seed_cells = Vec::new();
            for (train_seed, model) in runs {
                let eps = run_episodes(model, condition);
                seed_cells.push(SeedCell {
                    model: model.clone(),
                    train_seed: *train_seed,
                    success: SUCCESS_BUDGETS
                        .iter()
                        .map(|&b| (b, success_rate(&eps, b)))
                        .collect(),
                    failure_modes: FailureCounts::of(eps.iter().copied()),
                    success_after_damage: after_damage(&eps),
                });
            }
            let counts = |pick: &dyn Fn(&SeedCell) -> Rate| -> Vec<(usize, usize)> {
                seed_cells
                    .iter()
                    .map(|c| {
                        let r = pick(c);
                        (r.successes, r.n)
                    })
                    .collect()
            };
            let success = SUCCESS_BUDGETS
                .iter()
                .map(|&b| {
                    let interval = stratified_bootstrap(
                        &counts(&|c| c.success[&b]),
                        BOOTSTRAP_REPS,
                        BOOTSTRAP_SEED,
                    );
                    (b, interval)
                })
                .collect();
            let failure_modes =
                FailureCounts::of(runs.iter().flat_map(|(_, m)| run_episodes(m, condition)));
            let success_iqm = iqm_bootstrap(
                &counts(&|c| c.success[&500]),
                BOOTSTRAP_REPS,
                BOOTSTRAP_SEED,
            );
            cells.push(GroupCell {
                group: group.clone(),
                encoder: *encoder,
                condition,
                success_iqm,
                success_after_damage: stratified_bootstrap(
                    &counts(&|c| c.success_after_damage),
                    BOOTSTRAP_REPS,
                    BOOTSTRAP_SEED,
                ),
                runs: seed_cells,
                success,
                failure_modes,
            });
        }
    }

    // Each run of `model` against the run of `reference` with its training seed, per condition.
    let compare = |(model, model_runs): (&str, &[(u64, String)]),
                   (reference, reference_runs): (&str, &[(u64, String)])| {
        let paired = paired_by_seed(model_runs, reference_runs);
        let mut out = Vec::new();
        for &condition in conditions {
            let mut per_seed = Vec::new();
            let mut differences = Vec::new();
            for &(seed, ref_run, model_run) in &paired {
                let (r, m) = (
                    run_episodes(ref_run, condition),
                    run_episodes(model_run, condition),
                );
                let pairs: Vec<(bool, bool)> = r
                    .iter()
                    .zip(&m)
                    .filter(|(x, y)| x.seed == y.seed)
                    .map(|(x, y)| (x.success_within(500), y.success_within(500)))
                    .collect();
                let n = pairs.len().max(1) as f64;
                let diff = pairs.iter().map(|&(x, y)| y as i32 - x as i32).sum::<i32>();
                differences.push(f64::from(diff) / n);
                per_seed.push((seed, super::stats::mcnemar(pairs)));
            }
            let tables: Vec<McNemar> = per_seed.iter().map(|(_, m)| *m).collect();
            out.push(GroupComparison {
                model: model.to_string(),
                reference: reference.to_string(),
                condition,
                pooled: pooled_mcnemar(&tables),
                mean_difference: if differences.is_empty() {
                    f64::NAN
                } else {
                    differences.iter().sum::<f64>() / differences.len() as f64
                },
                seed_sign_flip_p: seed_sign_flip_p(&differences),
                per_seed,
            });
        }
        out
    };
    let encoder_groups: Vec<&Group> = groups
        .iter()
        .filter(|(_, k, _)| *k != EncoderKind::None)
        .collect();
    let baseline = groups.iter().find(|(_, k, _)| *k == EncoderKind::None);
    // (model, reference): each encoder against the baseline, then each pair of encoders in
    // evaluation order, the later-listed the reference. The paired tests and the probability of
    // improvement both run over these.
    let mut pairs: Vec<(&Group, &Group)> = Vec::new();
    if let Some(base) = baseline {
        pairs.extend(encoder_groups.iter().map(|&e| (e, base)));
    }
    for (i, &a) in encoder_groups.iter().enumerate() {
        pairs.extend(encoder_groups[i + 1..].iter().map(|&b| (a, b)));
    }
    let comparisons: Vec<GroupComparison> = pairs
        .iter()
        .flat_map(|&((m, _, m_runs), (r, _, r_runs))| compare((m, m_runs), (r, r_runs)))
        .collect();
    let mut recovery = Vec::new();
    if let Some((base, _, base_runs)) = baseline {
        let cell = |g: &str, c: Case| cells.iter().find(|x| x.group == g && x.condition == c);
        for (group, _, runs) in encoder_groups.iter().copied() {
            let paired = paired_by_seed(runs, base_runs);
            let rate = |model: &str, c: Case| {
                let eps = run_episodes(model, c);
                (!eps.is_empty()).then(|| success_rate(&eps, 500).rate)
            };
            let rf = |es: f64, bs: f64, bh: f64| RecoveryFraction {
                encoder_severe: es,
                baseline_severe: bs,
                baseline_healthy: bh,
                value: recovery_fraction(es, bs, bh),
            };
            let per_seed: Vec<(u64, RecoveryFraction)> = paired
                .iter()
                .filter_map(|&(seed, base_model, enc_model)| {
                    Some((
                        seed,
                        rf(
                            rate(enc_model, Case::Condition(Condition::Severe))?,
                            rate(base_model, Case::Condition(Condition::Severe))?,
                            rate(base_model, Case::Condition(Condition::Healthy))?,
                        ),
                    ))
                })
                .collect();
            let mean_of = |g: &str, c: Case| cell(g, c).map(|x| x.success[&500].mean);
            if let (Some(es), Some(bs), Some(bh)) = (
                mean_of(group, Case::Condition(Condition::Severe)),
                mean_of(base, Case::Condition(Condition::Severe)),
                mean_of(base, Case::Condition(Condition::Healthy)),
            ) {
                recovery.push(GroupRecovery {
                    encoder: group.clone(),
                    per_seed,
                    of_means: rf(es, bs, bh),
                });
            }
        }
    }
    let mut improvements = Vec::new();
    for ((better, _, _), (than, _, _)) in pairs {
        for &condition in conditions {
            let counts = |g: &str| -> Vec<(usize, usize)> {
                cells
                    .iter()
                    .find(|c| c.group == g && c.condition == condition)
                    .map(|c| {
                        c.runs
                            .iter()
                            .map(|r| (r.success[&500].successes, r.success[&500].n))
                            .collect()
                    })
                    .unwrap_or_default()
            };
            improvements.push(Improvement {
                better: better.to_string(),
                than: than.to_string(),
                condition,
                probability_of_improvement: improvement_bootstrap(
                    &counts(better),
                    &counts(than),
                    BOOTSTRAP_REPS,
                    BOOTSTRAP_SEED,
                ),
            });
        }
    }
    AcrossSeeds {
        bootstrap_reps: BOOTSTRAP_REPS,
        bootstrap_seed: BOOTSTRAP_SEED,
        groups: cells,
        comparisons,
        recovery,
        improvements,
    }
}

impl AcrossSeeds {
    /// How the episodes ended, per model and condition (one seed or several).
    fn failure_modes_markdown(&self) -> String {
        let interval = |i: &Interval| {
            format!(
                "{:.0} % [{:.0}, {:.0}]",
                100.0 * i.mean,
                100.0 * i.low,
                100.0 * i.high
            )
        };
        let mut s = "\n**Failure modes** (episodes summed over seeds; an early ending — the torso leaving \
              the height band, above or below, or an unstable simulation — counts as after damage \
              once a step was taken with a joint triggered, dead or weakened by a scenario; a \
              timeout upside down is one with the torso's up axis below the horizon) and **success \
              among the episodes that reached damage**, the only ones where adapting to damage can \
              matter (mean over seeds [95 % bootstrap], episodes)\n\n\
              | model | condition | success | ended early before damage | ended early after damage | \
              how they ended early | timed out | success once damaged |\n\
              |---|---|---:|---:|---:|---|---:|---:|\n"
            .to_string();
        for g in &self.groups {
            let f = g.failure_modes;
            let n = f.total().max(1) as f64;
            let share = |k: usize| format!("{k} ({:.0} %)", 100.0 * k as f64 / n);
            let reached: usize = g.runs.iter().map(|r| r.success_after_damage.n).sum();
            let after = if reached == 0 {
                "– (no episode reached damage)".to_string()
            } else {
                format!("{} (n = {reached})", interval(&g.success_after_damage))
            };
            s += &format!(
                "| {} | {} | {} | {} | {} | {} | {}, {} upside down | {after} |\n",
                g.group,
                g.condition,
                share(f.success),
                share(f.terminated_before_damage),
                share(f.terminated_after_damage),
                f.early_kinds(),
                share(f.timed_out),
                f.timed_out_upside_down,
            );
        }
        s
    }

    /// The tables of the evaluation across seeds, as Markdown.
    /// Whether some model was evaluated with more than one training seed: only then do the
    /// across-seed tables and seed-level tests mean anything.
    pub fn has_several_seeds(&self) -> bool {
        self.groups.iter().any(|g| g.runs.len() > 1)
    }

    pub fn markdown(&self) -> String {
        if !self.has_several_seeds() {
            return "One training seed per model: the per-run tables above and the failure \
                    modes below are the whole story (the across-seed section needs several runs \
                    of a model, e.g. `--checkpoint checkpoints/seeds/*-s*`).\n"
                .to_string()
                + &self.failure_modes_markdown();
        }
        let pct = |r: f64| format!("{:.0} %", 100.0 * r);
        let interval = |i: &Interval| {
            format!(
                "{:.0} % [{:.0}, {:.0}]",
                100.0 * i.mean,
                100.0 * i.low,
                100.0 * i.high
            )
        };
        let mut s = format!(
            "**Across training seeds** (success: each seed, then the mean over seeds with its 95 % \
             stratified bootstrap interval: seeds, then episodes within each, {} resamples)\n\n\
             | model | condition | seeds | success@500 per seed | success@500 | IQM success@500 | success@350 | success@250 |\n\
             |---|---|---|---|---:|---:|---:|---:|\n",
            self.bootstrap_reps
        );
        for g in &self.groups {
            let seeds: Vec<String> = g.runs.iter().map(|r| r.train_seed.to_string()).collect();
            let per_seed: Vec<String> = g.runs.iter().map(|r| pct(r.success[&500].rate)).collect();
            s += &format!(
                "| {} | {} | {} | {} | {} | {} | {} | {} |\n",
                g.group,
                g.condition,
                seeds.join(", "),
                per_seed.join(", "),
                interval(&g.success[&500]),
                interval(&g.success_iqm),
                interval(&g.success[&350]),
                interval(&g.success[&250]),
            );
        }
        s += &self.failure_modes_markdown();
        if !self.comparisons.is_empty() {
            s += "\n**Paired by training seed**: each encoder against the baseline, and each \
                  pair of encoders (success@500 on the same eval seeds; b = reference only, c = \
                  model only; mean Δ = model − reference; pooled: Cochran–Mantel–Haenszel with \
                  pairs as strata, i.e. McNemar on the summed discordant pairs, and its exact sign \
                  test; seed sign-flip: the paired permutation test over seeds' mean differences, \
                  two-sided; with n paired seeds it cannot go below 2/2ⁿ, its floor: 0.25 with \
                  three seeds, 0.031 with six)\n\n\
                  | model | reference | condition | per seed b/c (exact p) | pooled b/c | χ² | \
                  p (χ²) | p (exact) | mean Δ | seed sign-flip p (floor) |\n\
                  |---|---|---|---|---:|---:|---:|---:|---:|---:|\n";
            for c in &self.comparisons {
                let per_seed: Vec<String> = c
                    .per_seed
                    .iter()
                    .map(|(seed, m)| format!("s{seed}: {}/{} ({:.3})", m.b, m.c, m.p_exact))
                    .collect();
                let p = c.pooled;
                s += &format!(
                    "| {} | {} | {} | {} | {}/{} | {:.2} | {:.3} | {:.3} | {:+.1} pt | {:.3} ({:.3}) |\n",
                    c.model,
                    c.reference,
                    c.condition,
                    per_seed.join("; "),
                    p.b,
                    p.c,
                    p.chi2,
                    p.p_chi2,
                    p.p_exact,
                    100.0 * c.mean_difference,
                    c.seed_sign_flip_p,
                    sign_flip_floor(c.per_seed.len()),
                );
            }
        }
        if !self.improvements.is_empty() {
            s += "\n**Probability of improvement** (rliable, Agarwal et al. 2021: over every pair of \
                  a run of the first model and a run of the second, the share where the first's \
                  success@500 is higher, ties counting ½; 0.5 = no difference; 95 % bootstrap \
                  interval over seeds and episodes. The IQM column above is rliable's interquartile \
                  mean: the mean of the middle half of the runs)\n\n\
                  | model | than | condition | P(improvement) |\n|---|---|---|---:|\n";
            for i in &self.improvements {
                let p = i.probability_of_improvement;
                s += &format!(
                    "| {} | {} | {} | {:.2} [{:.2}, {:.2}] |\n",
                    i.better, i.than, i.condition, p.mean, p.low, p.high
                );
            }
        }
        for r in &self.recovery {
            let show = |rf: &RecoveryFraction| match rf.value {
                Some(v) => format!(
                    "{v:.2} = ({} − {}) / ({} − {})",
                    pct(rf.encoder_severe),
                    pct(rf.baseline_severe),
                    pct(rf.baseline_healthy),
                    pct(rf.baseline_severe)
                ),
                None => format!(
                    "undefined: the baseline loses nothing (healthy {}, severe {})",
                    pct(rf.baseline_healthy),
                    pct(rf.baseline_severe)
                ),
            };
            s += &format!(
                "\nRecovery fraction of {} = (encoder severe − baseline severe) / (baseline healthy \
                 − baseline severe), success@500: of the means over seeds {}",
                r.encoder,
                show(&r.of_means)
            );
            for (seed, rf) in &r.per_seed {
                s += &format!("; seed {seed}: {}", show(rf));
            }
            s += "\n";
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::damage::N_ACTUATORS;

    #[test]
    fn runs_group_by_their_name_without_the_seed() {
        assert_eq!(group_of("encoder-lstm-s2"), "encoder-lstm");
        assert_eq!(group_of("encoder-lstm"), "encoder-lstm");
        assert_eq!(group_of("baseline-s10"), "baseline");
        // Not a seed suffix: kept whole.
        assert_eq!(group_of("walker-strong"), "walker-strong");
        assert_eq!(group_of("-s1"), "-s1");
        assert_eq!(group_of("run-s"), "run-s");
    }

    /// Two seeds, one always succeeds and one never: episode resampling changes nothing, so the
    /// mean of a resample is 0, ½ or 1 with probabilities ¼, ½, ¼ and the 95 % interval is [0, 1].
    #[test]
    fn bootstrap_of_two_opposite_seeds_is_hand_checkable() {
        let seeds = [(50, 50), (0, 50)];
        let draws = bootstrap_means(&seeds, 20_000, 3);
        let share = |v: f64| draws.iter().filter(|&&d| d == v).count() as f64 / draws.len() as f64;
        assert!((share(0.5) - 0.5).abs() < 0.02, "{}", share(0.5));
        assert!((share(0.0) - 0.25).abs() < 0.02 && (share(1.0) - 0.25).abs() < 0.02);
        assert_eq!(share(0.0) + share(0.5) + share(1.0), 1.0);
        let i = stratified_bootstrap(&seeds, 20_000, 3);
        assert_eq!((i.mean, i.low, i.high), (0.5, 0.0, 1.0));
        // One seed that always succeeds: no uncertainty left to resample.
        let i = stratified_bootstrap(&[(40, 40)], 1_000, 3);
        assert_eq!((i.mean, i.low, i.high), (1.0, 1.0, 1.0));
    }

    /// One seed at 50/100: the episode bootstrap of a proportion has SD √(p(1 − p)/n) = 0.05,
    /// so the interval is ≈ 0.5 ± 1.96 · 0.05.
    #[test]
    fn bootstrap_of_one_seed_matches_the_binomial_spread() {
        let i = stratified_bootstrap(&[(50, 100)], 20_000, 11);
        assert!(
            (i.low - 0.402).abs() < 0.015 && (i.high - 0.598).abs() < 0.015,
            "{i:?}"
        );
    }

    #[test]
    fn bootstrap_is_deterministic_under_its_seed() {
        let seeds = [(30, 50), (41, 50), (12, 50)];
        assert_eq!(
            bootstrap_means(&seeds, 500, 7),
            bootstrap_means(&seeds, 500, 7)
        );
        assert_ne!(
            bootstrap_means(&seeds, 500, 7),
            bootstrap_means(&seeds, 500, 8)
        );
    }

    /// Seeds with (b, c) = (1, 4), (2, 3), (0, 3): pooled b = 3, c = 10. χ² = (|10 − 3| − 1)²/13
    /// = 36/13 = 2.7692, p = erfc(√(2.7692/2)) = 0.0961; exact p = 2·P(Bin(13, ½) ≤ 3) =
    /// 2·(1 + 13 + 78 + 286)/8192 = 756/8192 = 0.09229.
    #[test]
    fn pooled_paired_test_matches_hand_computation() {
        let tables = [(1, 4), (2, 3), (0, 3)].map(|(b, c)| mcnemar_counts(b, c));
        let p = pooled_mcnemar(&tables);
        assert_eq!((p.b, p.c), (3, 10));
        assert!((p.chi2 - 36.0 / 13.0).abs() < 1e-12, "{}", p.chi2);
        assert!((p.p_chi2 - 0.0961).abs() < 1e-4, "{}", p.p_chi2);
        assert!((p.p_exact - 756.0 / 8192.0).abs() < 1e-12, "{}", p.p_exact);
    }

    /// Differences 0.1, 0.2, 0.3: of the 8 sign patterns only all-plus and all-minus reach
    /// |sum| = 0.6, so p = 2/8; with one negative seed (0.1, 0.2, −0.3, sum 0), every pattern
    /// reaches it.
    #[test]
    fn seed_sign_flip_enumerates_every_pattern() {
        assert_eq!(seed_sign_flip_p(&[0.1, 0.2, 0.3]), 0.25);
        assert_eq!(seed_sign_flip_p(&[0.1, 0.2, -0.3]), 1.0);
        // 0.1, 0.2, 0.4: |sums| 0.7, 0.5, 0.3, 0.1 twice each; ≥ 0.7 only the two extremes.
        assert_eq!(seed_sign_flip_p(&[0.1, 0.2, 0.4]), 0.25);
        assert_eq!(seed_sign_flip_p(&[0.5]), 1.0);
        // Six seeds all one way: 2 of 64 patterns are as extreme, p = 0.031.
        let six = [0.1, 0.05, 0.2, 0.15, 0.1, 0.3];
        assert_eq!(seed_sign_flip_p(&six), 2.0 / 64.0);
        // The floor is what all-one-way seeds give.
        assert_eq!(sign_flip_floor(3), seed_sign_flip_p(&[0.1, 0.2, 0.3]));
        assert_eq!(sign_flip_floor(6), seed_sign_flip_p(&six));
        assert_eq!(sign_flip_floor(4), 0.125);
    }

    #[test]
    fn iqm_is_the_mean_of_the_middle_half() {
        // rliable's definition (scipy.stats.trim_mean(x, 0.25)): of 8 values the middle 4.
        let eight = [0.9, 0.1, 0.5, 0.3, 0.7, 0.2, 0.6, 0.4];
        assert!((iqm(&eight) - (0.3 + 0.4 + 0.5 + 0.6) / 4.0).abs() < 1e-12);
        // 6 values: ⌊6/4⌋ = 1 cut from each end.
        let six = [0.0, 1.0, 0.2, 0.4, 0.6, 0.8];
        assert!((iqm(&six) - 0.5).abs() < 1e-12);
        // 3 values: nothing cut.
        assert!((iqm(&[0.1, 0.2, 0.9]) - 0.4).abs() < 1e-12);
        assert!(iqm(&[]).is_nan());
    }

    #[test]
    fn probability_of_improvement_counts_pairs_with_ties_as_half() {
        // Pairs (x > y): 0.5 vs {0.4, 0.5, 0.9} → 1, ½, 0; 0.7 vs them → 1, 1, 0: 3.5 / 6.
        let p = probability_of_improvement(&[0.5, 0.7], &[0.4, 0.5, 0.9]);
        assert!((p - 3.5 / 6.0).abs() < 1e-12);
        assert_eq!(probability_of_improvement(&[0.2], &[0.2]), 0.5);
        assert_eq!(probability_of_improvement(&[0.9, 0.8], &[0.1, 0.2]), 1.0);
        assert!(
            (probability_of_improvement(&[0.5, 0.7], &[0.4, 0.5, 0.9])
                + probability_of_improvement(&[0.4, 0.5, 0.9], &[0.5, 0.7])
                - 1.0)
                .abs()
                < 1e-12,
            "P(X > Y) + P(Y > X) = 1"
        );
    }

    #[test]
    fn bootstrap_intervals_hold_the_estimate_and_shrink_with_certainty() {
        let x = [
            (80, 100),
            (90, 100),
            (70, 100),
            (85, 100),
            (75, 100),
            (95, 100),
        ];
        let y = [
            (20, 100),
            (30, 100),
            (10, 100),
            (25, 100),
            (15, 100),
            (35, 100),
        ];
        let i = iqm_bootstrap(&x, 2_000, 1);
        assert!(
            (i.mean - 0.825).abs() < 1e-12,
            "IQM of the middle four rates"
        );
        assert!(i.low <= i.mean && i.mean <= i.high && i.high - i.low < 0.2);
        let p = improvement_bootstrap(&x, &y, 2_000, 1);
        assert_eq!(p.mean, 1.0);
        assert!(p.low > 0.9, "every resample keeps x above y: {p:?}");
        // Two groups with the same runs: 0.5, and an interval on both sides of it.
        let same = improvement_bootstrap(&x, &x, 2_000, 1);
        assert_eq!(same.mean, 0.5);
        assert!(same.low < 0.5 && same.high > 0.5, "{same:?}");
    }

    /// What damaged an episode, and from which step.
    #[derive(Debug, Clone, Copy)]
    enum Onset {
        Never,
        /// Fatigue triggered a joint during this step (it scales the next one).
        Trigger(usize),
        /// A scenario weakened a joint before this step ran (`ood`: no trigger at all).
        Scenario(usize),
    }

    fn episode(success: bool, terminated: bool, steps: usize, onset: Onset) -> EpisodeRecord {
        let mut trigger_steps = [None; N_ACTUATORS];
        let (first_trigger, damage_onset) = match onset {
            Onset::Never => (None, None),
            Onset::Trigger(t) => (Some(t), Some(t + 1)),
            Onset::Scenario(s) => (None, Some(s)),
        };
        trigger_steps[3] = first_trigger;
        EpisodeRecord {
            model: "m".into(),
            group: "m".into(),
            train_seed: 0,
            encoder: EncoderKind::Lstm,
            condition: Case::Condition(Condition::Severe),
            episode: 0,
            seed: 0,
            success,
            terminated,
            ending: Some(match (success, terminated) {
                (true, _) => crate::env::Ending::Success,
                (false, true) => crate::env::Ending::Leapt,
                (false, false) => crate::env::Ending::Timeout,
            }),
            steps,
            steps_to_success: success.then_some(steps),
            final_distance: 0.0,
            episode_return: 0.0,
            triggered_joints: first_trigger.map_or(0, |_| 2),
            trigger_steps,
            damage_onset,
        }
    }

    #[test]
    fn failure_modes_of_constructed_episodes() {
        use FailureMode::*;
        use Onset::*;
        let cases = [
            // (success, terminated, steps, onset) → mode, reached damage
            ((true, true, 180, Trigger(60)), Success, true),
            ((true, true, 180, Never), Success, false),
            // Fell at step index 49 with no trigger.
            ((false, true, 50, Never), TerminatedBeforeDamage, false),
            // Triggered on the very step it fell: no step was taken under damage.
            (
                (false, true, 50, Trigger(49)),
                TerminatedBeforeDamage,
                false,
            ),
            ((false, true, 50, Trigger(48)), TerminatedAfterDamage, true),
            ((false, true, 300, Trigger(10)), TerminatedAfterDamage, true),
            ((false, false, 500, Trigger(10)), TimedOut, true),
            ((false, false, 500, Trigger(499)), TimedOut, true),
            ((false, false, 500, Never), TimedOut, false),
            // A scenario's weak ankle from the first step (`ood-ankle`), and a fault set before
            // the step the Ant fell on: both falls ran under damage, with no trigger at all.
            ((false, true, 50, Scenario(0)), TerminatedAfterDamage, true),
            ((false, true, 50, Scenario(49)), TerminatedAfterDamage, true),
            ((true, true, 80, Scenario(0)), Success, true),
        ];
        for ((success, terminated, steps, onset), mode, reached) in cases {
            let e = episode(success, terminated, steps, onset);
            assert_eq!(
                e.failure_mode(),
                mode,
                "{success} {terminated} {steps} {onset:?}"
            );
            assert_eq!(
                e.reached_damage(),
                reached,
                "{success} {terminated} {steps} {onset:?}"
            );
        }
        let eps: Vec<EpisodeRecord> = cases
            .iter()
            .map(|&((s, t, n, f), _, _)| episode(s, t, n, f))
            .collect();
        let c = FailureCounts::of(&eps);
        assert_eq!(
            (
                c.success,
                c.terminated_before_damage,
                c.terminated_after_damage,
                c.timed_out
            ),
            (3, 2, 4, 3)
        );
        // What they were: here every early ending leapt above the band.
        assert_eq!((c.leapt, c.collapsed, c.timed_out_upside_down), (6, 0, 0));
        assert_eq!(c.early_kinds(), "leapt above the band 6");
        // Named endings are counted by kind; an early ending saved before endings were named
        // says so rather than guessing; a timeout upside down is still a timeout.
        let mut eps = eps;
        eps[2].ending = Some(crate::env::Ending::Collapsed);
        eps[3].ending = None;
        eps[8].ending = Some(crate::env::Ending::TimeoutUpsideDown);
        let c = FailureCounts::of(&eps);
        assert_eq!(
            (
                c.terminated_before_damage,
                c.terminated_after_damage,
                c.timed_out
            ),
            (2, 4, 3)
        );
        assert_eq!(
            (
                c.leapt,
                c.collapsed,
                c.early_unrecorded,
                c.timed_out_upside_down
            ),
            (4, 1, 1, 1)
        );
        assert_eq!(
            c.early_kinds(),
            "leapt above the band 4, collapsed below it 1, kind not recorded 1"
        );
        assert_eq!(c.total(), eps.len());
    }

    /// Encoder runs pair with the baseline run of their own training seed, whatever order the
    /// runs were given in, and episodes pair on eval seeds.
    #[test]
    fn encoder_seeds_pair_with_the_baseline_of_the_same_seed() {
        let run = |model: &str, encoder: EncoderKind, train_seed: u64, wins: &[bool]| {
            wins.iter()
                .enumerate()
                .map(|(i, &w)| {
                    let mut e = episode(w, true, if w { 200 } else { 40 }, Onset::Never);
                    (e.model, e.group, e.encoder) = (model.into(), group_of(model), encoder);
                    (e.train_seed, e.seed, e.episode) = (train_seed, 100 + i as u64, i);
                    e
                })
                .collect::<Vec<_>>()
        };
        let (t, f) = (true, false);
        let episodes: Vec<EpisodeRecord> = [
            run("enc-s1", EncoderKind::Lstm, 1, &[t, t, t, f]),
            run("baseline", EncoderKind::None, 0, &[t, f, f, f]),
            run("enc", EncoderKind::Lstm, 0, &[t, t, f, f]),
            run("baseline-s1", EncoderKind::None, 1, &[f, f, t, t]),
            run("aux", EncoderKind::Lstm, 0, &[f, t, t, f]),
            run("aux-s1", EncoderKind::Lstm, 1, &[f, f, t, t]),
        ]
        .concat();
        let report = across_seeds(&episodes, &[Case::Condition(Condition::Severe)]);
        // Each encoder against the baseline, then the two encoders (the later one the reference).
        let pairs: Vec<(&str, &str)> = report
            .comparisons
            .iter()
            .map(|c| (c.model.as_str(), c.reference.as_str()))
            .collect();
        assert_eq!(
            pairs,
            [("enc", "baseline"), ("aux", "baseline"), ("enc", "aux")]
        );
        // enc against aux. Seed 0: aux F T T F vs enc T T F F → b = 1, c = 1, Δ = 0. Seed 1:
        // F F T T vs T T T F → b = 1, c = 2, Δ = ¼.
        let encoders = &report.comparisons[2];
        let counts: Vec<(u64, usize, usize)> = encoders
            .per_seed
            .iter()
            .map(|(s, m)| (*s, m.b, m.c))
            .collect();
        assert_eq!(counts, [(0, 1, 1), (1, 1, 2)]);
        assert!((encoders.mean_difference - 0.125).abs() < 1e-12);
        let cmp = &report.comparisons[0];
        // Seed 0: baseline T F F F vs enc T T F F → b = 0, c = 1. Seed 1: F F T T vs T T T F →
        // b = 1, c = 2. Pooled 1/3; mean Δ = (¼ + ¼)/2.
        let counts: Vec<(u64, usize, usize)> =
            cmp.per_seed.iter().map(|(s, m)| (*s, m.b, m.c)).collect();
        assert_eq!(counts, [(0, 0, 1), (1, 1, 2)]);
        assert_eq!((cmp.pooled.b, cmp.pooled.c), (1, 3));
        assert!((cmp.mean_difference - 0.25).abs() < 1e-12);
        // The group mean is the mean of the seeds' rates: enc (½ + ¾)/2, baseline (¼ + ½)/2.
        let mean = |g: &str| {
            report
                .groups
                .iter()
                .find(|c| c.group == g)
                .map(|c| c.success[&500].mean)
        };
        assert_eq!(mean("enc"), Some(0.625));
        assert_eq!(mean("baseline"), Some(0.375));
        let seeds: Vec<u64> = report.groups[0].runs.iter().map(|r| r.train_seed).collect();
        assert_eq!(seeds, [0, 1]);
    }
}
