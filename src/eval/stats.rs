//! Honest statistics for success rates: Wilson intervals, standard errors, McNemar's paired test
//! and the paper's recovery fraction.

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
}
