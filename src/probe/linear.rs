//! One linear probe: a split by episode, standardised features, a (multi)logistic fit
//! (linfa-logistic), and its test scores next to the majority-class baseline.

use linfa::prelude::*;
use linfa_logistic::{LogisticRegression, MultiLogisticRegression};
use ndarray::{Array1, Array2, Axis};
use rand::SeedableRng;
use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use super::ProbeError;

/// Episode ids for training and testing: a seeded 70/30 split of whole episodes.
pub fn split_by_episode(
    episodes: &[usize],
    train_fraction: f64,
    seed: u64,
) -> (Vec<usize>, Vec<usize>) {
    let mut ids: Vec<usize> = episodes.to_vec();
    ids.sort_unstable();
    ids.dedup();
    ids.shuffle(&mut ChaCha8Rng::seed_from_u64(seed));
    let n_train = ((ids.len() as f64) * train_fraction).round() as usize;
    let (train, test) = ids.split_at(n_train.min(ids.len()));
    (train.to_vec(), test.to_vec())
}

/// Per-feature mean and standard deviation, fitted on training rows.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Standardizer {
    pub mean: Vec<f64>,
    pub std: Vec<f64>,
}

impl Standardizer {
    pub fn fit(x: &Array2<f64>) -> Self {
        let mean = x.mean_axis(Axis(0)).map(|m| m.to_vec()).unwrap_or_default();
        let std = x
            .std_axis(Axis(0), 0.0)
            .iter()
            .map(|&s| if s > 1e-12 { s } else { 1.0 })
            .collect();
        Self { mean, std }
    }
    pub fn apply(&self, x: &Array2<f64>) -> Array2<f64> {
        let mut out = x.clone();
        for mut row in out.rows_mut() {
            for (j, v) in row.iter_mut().enumerate() {
                *v = (*v - self.mean[j]) / self.std[j];
            }
        }
        out
    }
}

/// Accuracy and balanced accuracy (mean per-class recall) of predictions.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Scores {
    pub accuracy: f64,
    pub balanced_accuracy: f64,
}

pub fn scores(truth: &[usize], predicted: &[usize]) -> Scores {
    let n = truth.len().max(1) as f64;
    let accuracy = truth.iter().zip(predicted).filter(|(a, b)| a == b).count() as f64 / n;
    let mut classes: Vec<usize> = truth.to_vec();
    classes.sort_unstable();
    classes.dedup();
    let recalls: Vec<f64> = classes
        .iter()
        .map(|&c| {
            let of_class: Vec<usize> = (0..truth.len()).filter(|&i| truth[i] == c).collect();
            of_class.iter().filter(|&&i| predicted[i] == c).count() as f64 / of_class.len() as f64
        })
        .collect();
    let balanced_accuracy = if recalls.is_empty() {
        0.0
    } else {
        recalls.iter().sum::<f64>() / recalls.len() as f64
    };
    Scores {
        accuracy,
        balanced_accuracy,
    }
}

/// A fitted linear probe: standardise, then softmax (or sigmoid for two classes).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LinearProbe {
    pub classes: Vec<usize>,
    pub standardizer: Standardizer,
    /// One row of weights per class (a single row for a binary probe: P(class 1)).
    pub weights: Vec<Vec<f64>>,
    pub intercepts: Vec<f64>,
}

impl LinearProbe {
    /// Fits on (x, y); one class only gives a constant probe.
    pub fn fit(what: &str, x: &Array2<f64>, y: &[usize]) -> Result<Self, ProbeError> {
        let standardizer = Standardizer::fit(x);
        let xs = standardizer.apply(x);
        let mut classes: Vec<usize> = y.to_vec();
        classes.sort_unstable();
        classes.dedup();
        let fail = |e: &dyn std::fmt::Display| ProbeError::Fit {
            what: what.to_string(),
            reason: e.to_string().into(),
        };
        let (weights, intercepts) = match classes.len() {
            0 => {
                return Err(ProbeError::Fit {
                    what: what.into(),
                    reason: "no samples".into(),
                });
            }
            // One class seen: a constant probe (its weights are never used).
            1 => (vec![vec![0.0; x.ncols()]], vec![0.0]),
            2 => {
                let targets: Array1<usize> =
                    y.iter().map(|&c| usize::from(c == classes[1])).collect();
                let ds = Dataset::new(xs, targets);
                let model = LogisticRegression::default()
                    .max_iterations(200)
                    .fit(&ds)
                    .map_err(|e| fail(&e))?;
                // linfa's positive class is its second label; ours is "== classes[1]" (= 1).
                let sign = if model.labels().pos.class == 1 {
                    1.0
                } else {
                    -1.0
                };
                (
                    vec![model.params().iter().map(|w| sign * w).collect()],
                    vec![sign * model.intercept()],
                )
            }
            _ => {
                let ds = Dataset::new(xs, Array1::from(y.to_vec()));
                let model = MultiLogisticRegression::default()
                    .max_iterations(200)
                    .fit(&ds)
                    .map_err(|e| fail(&e))?;
                let order: Vec<usize> = model.classes().to_vec();
                let params = model.params();
                let mut weights = vec![Vec::new(); classes.len()];
                let mut intercepts = vec![0.0; classes.len()];
                for (k, class) in order.iter().enumerate() {
                    let slot = classes.iter().position(|c| c == class).unwrap_or(k);
                    weights[slot] = params.column(k).to_vec();
                    intercepts[slot] = model.intercept()[k];
                }
                (weights, intercepts)
            }
        };
        Ok(Self {
            classes,
            standardizer,
            weights,
            intercepts,
        })
    }

    /// Class probabilities for one feature vector.
    pub fn probabilities(&self, x: &[f64]) -> Vec<f64> {
        let xs: Vec<f64> = x
            .iter()
            .enumerate()
            .map(|(j, v)| (v - self.standardizer.mean[j]) / self.standardizer.std[j])
            .collect();
        let logit = |k: usize| {
            self.intercepts[k]
                + self.weights[k]
                    .iter()
                    .zip(&xs)
                    .map(|(w, v)| w * v)
                    .sum::<f64>()
        };
        match self.classes.len() {
            1 => vec![1.0],
            2 => {
                let p = 1.0 / (1.0 + (-logit(0)).exp());
                vec![1.0 - p, p]
            }
            n => {
                let logits: Vec<f64> = (0..n).map(logit).collect();
                let max = logits.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
                let exps: Vec<f64> = logits.iter().map(|l| (l - max).exp()).collect();
                let sum: f64 = exps.iter().sum();
                exps.iter().map(|e| e / sum).collect()
            }
        }
    }

    pub fn predict(&self, x: &[f64]) -> usize {
        let p = self.probabilities(x);
        let best = (0..p.len())
            .max_by(|&a, &b| p[a].total_cmp(&p[b]))
            .unwrap_or(0);
        self.classes[best]
    }
}

/// One probe's test result next to its baselines.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ProbeResult {
    pub name: String,
    pub test: Scores,
    /// Always predicting the training set's most common class.
    pub majority: Scores,
}

/// The most common label (the smallest of a tie; 0 for none): the baseline a probe must beat.
pub(super) fn majority_class(labels: &[usize]) -> usize {
    let mut counts = std::collections::BTreeMap::new();
    for &c in labels {
        *counts.entry(c).or_insert(0usize) += 1;
    }
    counts
        .iter()
        .max_by_key(|(_, n)| **n)
        .map_or(0, |(c, _)| *c)
}

pub(super) fn evaluate_probe(
    name: &str,
    train_x: &Array2<f64>,
    train_y: &[usize],
    test_x: &Array2<f64>,
    test_y: &[usize],
) -> Result<(ProbeResult, LinearProbe), ProbeError> {
    let probe = LinearProbe::fit(name, train_x, train_y)?;
    let predicted: Vec<usize> = test_x
        .rows()
        .into_iter()
        .map(|r| probe.predict(r.as_slice().unwrap_or(&r.to_vec())))
        .collect();
    let majority = majority_class(train_y);
    let result = ProbeResult {
        name: name.to_string(),
        test: scores(test_y, &predicted),
        majority: scores(test_y, &vec![majority; test_y.len()]),
    };
    Ok((result, probe))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn split_never_puts_an_episode_on_both_sides() {
        let episodes: Vec<usize> = (0..50).flat_map(|e| std::iter::repeat_n(e, 7)).collect();
        let (train, test) = split_by_episode(&episodes, 0.7, 3);
        assert_eq!((train.len(), test.len()), (35, 15));
        assert!(train.iter().all(|e| !test.contains(e)));
        let mut all: Vec<usize> = train.iter().chain(&test).copied().collect();
        all.sort_unstable();
        assert_eq!(all, (0..50).collect::<Vec<_>>());
    }

    #[test]
    fn balanced_accuracy_averages_per_class_recall() {
        // Class 0: 3 of 4 right; class 1: 0 of 1 right → accuracy 3/5, balanced (0.75 + 0)/2.
        let s = scores(&[0, 0, 0, 0, 1], &[0, 0, 0, 1, 0]);
        assert!((s.accuracy - 0.6).abs() < 1e-12);
        assert!((s.balanced_accuracy - 0.375).abs() < 1e-12);
    }

    fn synthetic(n: usize, shuffle_labels: bool) -> (Array2<f64>, Vec<usize>) {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        use rand::Rng;
        let x = Array2::from_shape_fn((n, 4), |_| rng.random_range(-1.0..1.0));
        // Three classes cut by linear functions of the features.
        let mut y: Vec<usize> = x
            .rows()
            .into_iter()
            .map(|r| {
                if r[0] + 0.5 * r[1] > 0.3 {
                    2
                } else if r[2] - r[3] > 0.0 {
                    1
                } else {
                    0
                }
            })
            .collect();
        if shuffle_labels {
            y.shuffle(&mut rng);
        }
        (x, y)
    }

    #[test]
    fn probe_learns_a_linear_label_and_not_a_shuffled_one() {
        let (x, y) = synthetic(1200, false);
        let (tr, te) = (
            x.slice(ndarray::s![..800, ..]).to_owned(),
            x.slice(ndarray::s![800.., ..]).to_owned(),
        );
        let (result, _) = evaluate_probe("linear", &tr, &y[..800], &te, &y[800..]).unwrap();
        assert!(result.test.accuracy > 0.95, "{:?}", result.test);
        let (x, y) = synthetic(1200, true);
        let (tr, te) = (
            x.slice(ndarray::s![..800, ..]).to_owned(),
            x.slice(ndarray::s![800.., ..]).to_owned(),
        );
        let (result, _) = evaluate_probe("shuffled", &tr, &y[..800], &te, &y[800..]).unwrap();
        // Shuffled labels carry no signal: no better than always guessing the majority class.
        assert!(
            result.test.accuracy < result.majority.accuracy + 0.05,
            "{:?} vs {:?}",
            result.test,
            result.majority
        );
        assert!(result.test.balanced_accuracy < 0.40, "{:?}", result.test);
    }

    #[test]
    fn binary_probe_and_constant_labels() {
        let (x, y) = synthetic(600, false);
        let yb: Vec<usize> = y.iter().map(|&c| usize::from(c == 2)).collect();
        let probe = LinearProbe::fit("binary", &x, &yb).unwrap();
        let acc = x
            .rows()
            .into_iter()
            .zip(&yb)
            .filter(|(r, t)| probe.predict(&r.to_vec()) == **t)
            .count() as f64
            / 600.0;
        assert!(acc > 0.95, "{acc}");
        let constant = LinearProbe::fit("constant", &x, &vec![1; 600]).unwrap();
        assert_eq!(constant.predict(&[0.0; 4]), 1);
    }
}
