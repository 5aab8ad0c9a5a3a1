//! Evaluation across training seeds: runs of one model (`encoder-lstm`, `encoder-lstm-s1`, …)
//! form a group; a group's success is the mean over its seeds with a stratified bootstrap
//! interval (rliable's protocol: resample seeds, then episodes within each), encoders are paired
//! with the baseline run of the same training seed, and every episode is sorted into a failure
//! mode.

use serde::Serialize;
use std::collections::BTreeMap;

use super::Case;
use super::stats::{
    Interval, McNemar, Rate, improvement_bootstrap, iqm_bootstrap, pooled_mcnemar,
    recovery_fraction, seed_sign_flip_p, sign_flip_floor, stratified_bootstrap,
};
use super::{EpisodeRecord, RecoveryFraction, episodes_of, success_budgets};
use crate::damage::Condition;
use crate::policy::EncoderKind;

/// Bootstrap resamples per interval.
pub const BOOTSTRAP_REPS: usize = 10_000;
/// The bootstrap's RNG seed: the same episodes give the same intervals.
pub const BOOTSTRAP_SEED: u64 = 0x5EED_B007;

/// The model a run belongs to: its folder name without a trailing `-s<seed>`
/// (`encoder-lstm-s2` → `encoder-lstm`; seed 0 lives in `encoder-lstm` itself).
pub fn group_of(label: &str) -> String {
    split_seed(label)
        .map_or(label, |(stem, _)| stem)
        .to_string()
}

/// `MODEL-sN` as (`MODEL`, `N`); `None` for a label without a seed suffix.
pub fn split_seed(label: &str) -> Option<(&str, &str)> {
    label.rsplit_once("-s").filter(|(stem, seed)| {
        !stem.is_empty() && !seed.is_empty() && seed.bytes().all(|b| b.is_ascii_digit())
    })
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
    /// Early endings for turning upside down (worlds with `env.terminate_upside_down`).
    pub flipped: usize,
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
                Some(Ending::Flipped) => c.flipped += 1,
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
            ("flipped", self.flipped),
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

/// One run (training seed) of a group under one condition.
#[derive(Debug, Clone, Serialize)]
pub struct SeedCell {
    pub model: String,
    pub train_seed: u64,
    pub success: BTreeMap<usize, Rate>,
    pub failure_modes: FailureCounts,
    /// Success at the evaluation's budget among the episodes that reached damage
    /// ([`EpisodeRecord::reached_damage`]).
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
    /// rliable's IQM of the seeds' success at the budget (the middle half of the runs), with its 95 %
    /// stratified bootstrap interval.
    pub success_iqm: Interval,
    /// Summed over seeds.
    pub failure_modes: FailureCounts,
    /// Mean over seeds (the seeds where any episode reached damage), with its interval.
    pub success_after_damage: Interval,
}

/// A model group against a reference group under one condition, on success at the evaluation's
/// budget (its step limit: success@500 in the paper's protocol), each run of
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
/// runs' success at the budget.
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
    /// The evaluation's step limit: every success rate here is success within it (also the
    /// report's `max_steps`).
    #[serde(skip)]
    pub budget: usize,
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
/// `budget`: the evaluation's step limit, the success every comparison is made on.
pub fn across_seeds(episodes: &[EpisodeRecord], conditions: &[Case], budget: usize) -> AcrossSeeds {
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
                    success: success_budgets(budget)
                        .into_iter()
                        .map(|b| (b, success_rate(&eps, b)))
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
            let success = success_budgets(budget)
                .into_iter()
                .map(|b| {
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
                &counts(&|c| c.success[&budget]),
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
                    .map(|(x, y)| (x.success_within(budget), y.success_within(budget)))
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
                (!eps.is_empty()).then(|| success_rate(&eps, budget).rate)
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
            let mean_of = |g: &str, c: Case| cell(g, c).map(|x| x.success[&budget].mean);
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
                            .map(|r| (r.success[&budget].successes, r.success[&budget].n))
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
        budget,
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
              the height band, above or below, a flip in a world that ends episodes there, or an \
              unstable simulation — counts as after damage \
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
        let budget = self.budget;
        // The tighter budgets, widest first (350 and 250 in the paper's protocol).
        let tighter: Vec<usize> = success_budgets(budget)
            .into_iter()
            .rev()
            .filter(|&b| b < budget)
            .collect();
        let mut s = format!(
            "**Across training seeds** (success: each seed, then the mean over seeds with its 95 % \
             stratified bootstrap interval: seeds, then episodes within each, {} resamples)\n\n\
             | model | condition | seeds | success@{budget} per seed | success@{budget} | IQM success@{budget} |",
            self.bootstrap_reps
        );
        for b in &tighter {
            s += &format!(" success@{b} |");
        }
        s += "\n|---|---|---|---|---:|---:|";
        s += &"---:|".repeat(tighter.len());
        s += "\n";
        for g in &self.groups {
            let seeds: Vec<String> = g.runs.iter().map(|r| r.train_seed.to_string()).collect();
            let per_seed: Vec<String> = g
                .runs
                .iter()
                .map(|r| pct(r.success[&budget].rate))
                .collect();
            s += &format!(
                "| {} | {} | {} | {} | {} | {} |",
                g.group,
                g.condition,
                seeds.join(", "),
                per_seed.join(", "),
                interval(&g.success[&budget]),
                interval(&g.success_iqm),
            );
            for b in &tighter {
                s += &format!(" {} |", interval(&g.success[b]));
            }
            s += "\n";
        }
        s += &self.failure_modes_markdown();
        if !self.comparisons.is_empty() {
            s += &format!(
                "\n**Paired by training seed**: each encoder against the baseline, and each \
                  pair of encoders (success@{budget} on the same eval seeds; b = reference only, c = \
                  model only; mean Δ = model − reference; pooled: Cochran–Mantel–Haenszel with \
                  pairs as strata, i.e. McNemar on the summed discordant pairs, and its exact sign \
                  test; seed sign-flip: the paired permutation test over seeds' mean differences, \
                  two-sided; with n paired seeds it cannot go below 2/2ⁿ, its floor: 0.25 with \
                  three seeds, 0.031 with six)\n\n\
                  | model | reference | condition | per seed b/c (exact p) | pooled b/c | χ² | \
                  p (χ²) | p (exact) | mean Δ | seed sign-flip p (floor) |\n\
                  |---|---|---|---|---:|---:|---:|---:|---:|---:|\n"
            );
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
            s += &format!(
                "\n**Probability of improvement** (rliable, Agarwal et al. 2021: over every pair of \
                  a run of the first model and a run of the second, the share where the first's \
                  success@{budget} is higher, ties counting ½; 0.5 = no difference; 95 % bootstrap \
                  interval over seeds and episodes. The IQM column above is rliable's interquartile \
                  mean: the mean of the middle half of the runs)\n\n\
                  | model | than | condition | P(improvement) |\n|---|---|---|---:|\n"
            );
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
                 − baseline severe), success@{budget}: of the means over seeds {}",
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
            dead_steps: [None; N_ACTUATORS],
            drawn_deaths: Vec::new(),
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
        // A flip, in a world that ends episodes there, is an early ending of its own kind.
        let last_leap = eps
            .iter()
            .rposition(|e| e.ending == Some(crate::env::Ending::Leapt))
            .unwrap();
        eps[last_leap].ending = Some(crate::env::Ending::Flipped);
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
                c.flipped,
                c.early_unrecorded,
                c.timed_out_upside_down
            ),
            (3, 1, 1, 1, 1)
        );
        assert_eq!(
            c.early_kinds(),
            "leapt above the band 3, collapsed below it 1, flipped 1, kind not recorded 1"
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
        let report = across_seeds(&episodes, &[Case::Condition(Condition::Severe)], 500);
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
