//! Honest statistics for success rates: Wilson intervals, standard errors, McNemar's paired test
//! (per seed and pooled), the paper's recovery fraction, and across training seeds rliable's
//! stratified bootstrap, the interquartile mean, the probability of improvement and the seed-level
//! sign-flip test.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Binomial, Distribution};
use serde::Serialize;

/// z for a two-sided 95 % interval.
pub const Z95: f64 = 1.959_963_984_540_054;

/// A success count out of n trials, with its uncertainty.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Rate {
    pub successes: usize,
    pub n: usize,
    pub rate: f64,
    /// Binomial standard error √(p(1 − p)/n).
    pub standard_error: f64,
    /// 95 % Wilson score interval.
    pub wilson_low: f64,
    pub wilson_high: f64,
}

impl Rate {
    pub fn new(successes: usize, n: usize) -> Self {
        let p = if n == 0 {
            0.0
        } else {
            successes as f64 / n as f64
        };
        let (wilson_low, wilson_high) = wilson(successes, n, Z95);
        let standard_error = if n == 0 {
            0.0
        } else {
            (p * (1.0 - p) / n as f64).sqrt()
        };
        Self {
            successes,
            n,
            rate: p,
            standard_error,
            wilson_low,
            wilson_high,
        }
    }

    /// "83 % [75, 89]"
    pub fn percent_with_interval(&self) -> String {
        format!(
            "{:.0} % [{:.0}, {:.0}]",
            100.0 * self.rate,
            100.0 * self.wilson_low,
            100.0 * self.wilson_high
        )
    }
}

/// Wilson score interval for k successes in n trials; (0, 1) when n = 0.
pub fn wilson(k: usize, n: usize, z: f64) -> (f64, f64) {
    if n == 0 {
        return (0.0, 1.0);
    }
    let n = n as f64;
    let p = k as f64 / n;
    let z2 = z * z;
    let denom = 1.0 + z2 / n;
    let center = (p + z2 / (2.0 * n)) / denom;
    let half = z / denom * (p * (1.0 - p) / n + z2 / (4.0 * n * n)).sqrt();
    ((center - half).max(0.0), (center + half).min(1.0))
}

/// McNemar's test on paired outcomes (same seeds): only discordant pairs count.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct McNemar {
    /// First succeeded, second failed.
    pub b: usize,
    /// First failed, second succeeded.
    pub c: usize,
    /// (|b − c| − 1)² / (b + c), continuity-corrected; 0 when b + c = 0.
    pub chi2: f64,
    /// p-value of `chi2` on one degree of freedom.
    pub p_chi2: f64,
    /// Exact two-sided binomial p-value (use this when b + c < 25).
    pub p_exact: f64,
}

pub fn mcnemar(pairs: impl IntoIterator<Item = (bool, bool)>) -> McNemar {
    let (mut b, mut c) = (0, 0);
    for (first, second) in pairs {
        match (first, second) {
            (true, false) => b += 1,
            (false, true) => c += 1,
            _ => {}
        }
    }
    mcnemar_counts(b, c)
}

/// McNemar's test from its discordant counts.
pub fn mcnemar_counts(b: usize, c: usize) -> McNemar {
    let n = b + c;
    if n == 0 {
        return McNemar {
            b,
            c,
            chi2: 0.0,
            p_chi2: 1.0,
            p_exact: 1.0,
        };
    }
    let diff = (b as f64 - c as f64).abs() - 1.0;
    let chi2 = diff.max(0.0).powi(2) / n as f64;
    // χ²(1) survival function: P(X > x) = erfc(√(x/2)).
    let p_chi2 = libm::erfc((chi2 / 2.0).sqrt());
    // Two-sided exact: 2·P(Binomial(n, ½) ≤ min(b, c)), summed in log space.
    let k = b.min(c);
    let ln_half_n = n as f64 * 0.5f64.ln();
    let mut ln_choose = 0.0;
    let mut tail = 0.0;
    for i in 0..=k {
        if i > 0 {
            ln_choose += ((n - i + 1) as f64).ln() - (i as f64).ln();
        }
        tail += (ln_choose + ln_half_n).exp();
    }
    McNemar {
        b,
        c,
        chi2,
        p_chi2,
        p_exact: (2.0 * tail).min(1.0),
    }
}

/// RF = (Enc_severe − Base_severe) / (Base_healthy − Base_severe): the share of the baseline's
/// damage-induced loss that the encoder recovers. `None` when the baseline loses nothing: with
/// no loss (or a gain) under severe damage there is nothing to recover, and a negative
/// denominator would turn the ratio's meaning upside down.
pub fn recovery_fraction(
    encoder_severe: f64,
    baseline_severe: f64,
    baseline_healthy: f64,
) -> Option<f64> {
    let loss = baseline_healthy - baseline_severe;
    (loss > 1e-12).then(|| (encoder_severe - baseline_severe) / loss)
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wilson_matches_hand_computation() {
        // 8/10: p = 0.8, z² = 3.8415, denom = 1.38415, center = 0.99208/1.38415 = 0.71674,
        // half = 1.41600·√(0.016 + 0.0096039) = 0.22659 → [0.4902, 0.9433].
        let (lo, hi) = wilson(8, 10, Z95);
        assert!(
            (lo - 0.4902).abs() < 1e-4 && (hi - 0.9433).abs() < 1e-4,
            "{lo} {hi}"
        );
        // 0/20 and 20/20 stay inside [0, 1] and are not degenerate.
        let (lo, hi) = wilson(0, 20, Z95);
        assert_eq!(lo, 0.0);
        assert!((hi - 0.1611).abs() < 1e-4, "{hi}");
        let (lo, hi) = wilson(20, 20, Z95);
        assert!((lo - 0.8389).abs() < 1e-4 && hi == 1.0);
        let r = Rate::new(83, 100);
        assert!((r.standard_error - (0.83f64 * 0.17 / 100.0).sqrt()).abs() < 1e-15);
    }

    #[test]
    fn mcnemar_matches_hand_computation() {
        // b = 10, c = 2: χ² = (8 − 1)²/12 = 4.0833, p = erfc(√2.0417) = 0.04331;
        // exact p = 2·(C(12,0) + C(12,1) + C(12,2))/2¹² = 2·79/4096 = 0.038574.
        let pairs = std::iter::repeat_n((true, false), 10)
            .chain(std::iter::repeat_n((false, true), 2))
            .chain(std::iter::repeat_n((true, true), 30));
        let m = mcnemar(pairs);
        assert_eq!((m.b, m.c), (10, 2));
        assert!((m.chi2 - 49.0 / 12.0).abs() < 1e-12);
        assert!((m.p_chi2 - 0.04331).abs() < 1e-4, "{}", m.p_chi2);
        assert!((m.p_exact - 158.0 / 4096.0).abs() < 1e-12, "{}", m.p_exact);
        let none = mcnemar([(true, true), (false, false)]);
        assert_eq!((none.p_chi2, none.p_exact), (1.0, 1.0));
    }

    #[test]
    fn recovery_fraction_matches_the_paper() {
        // Paper: baseline 83 → 70 % (healthy → severe), encoder 86 % severe: RF = 16/13.
        let rf = recovery_fraction(0.86, 0.70, 0.83).unwrap();
        assert!((rf - 16.0 / 13.0).abs() < 1e-12);
        assert_eq!(recovery_fraction(0.9, 0.8, 0.8), None);
        // A baseline that does better under severe damage (54 → 82 %) has lost nothing:
        // (66 − 82) / (54 − 82) = 0.57 would read as a partial recovery.
        assert_eq!(recovery_fraction(0.66, 0.82, 0.54), None);
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
}
