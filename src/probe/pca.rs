//! The latent's principal axes, saved in `probe.json` for the viewer's PCA panels.

use linfa_linalg::eigh::Eigh;
use ndarray::{Array2, Axis};
use serde::{Deserialize, Serialize};

use super::ProbeError;

/// The saved PCA basis: project with (z − mean) · componentsᵀ.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PcaBasis {
    pub mean: Vec<f64>,
    /// Rows are principal axes.
    pub components: Vec<Vec<f64>>,
    /// Share of z's total variance along each axis.
    pub explained_variance_ratio: Vec<f64>,
}

impl PcaBasis {
    /// The first `axes` principal axes of the rows of `z`, with each axis' share of z's total
    /// variance: the eigenvectors of z's covariance by linfa-linalg's dense symmetric
    /// eigendecomposition. (linfa-reduction's PCA, the tests' reference, solves the same problem
    /// iteratively by LOBPCG, which produced NaN and panicked on one run's z — encoder-mlp-s4,
    /// 50 episodes per condition; z is a few dozen wide, so the dense route costs nothing.)
    pub fn fit(z: &Array2<f64>, axes: usize) -> Result<Self, ProbeError> {
        let fit_error = |reason: String| ProbeError::Fit {
            what: "PCA".into(),
            reason: reason.into(),
        };
        let (n, dims) = z.dim();
        if n < 2 || dims == 0 {
            return Err(fit_error(format!(
                "needs at least 2 rows of z, got {n} × {dims}"
            )));
        }
        if let Some(bad) = z.iter().find(|v| !v.is_finite()) {
            return Err(fit_error(format!("z holds a non-finite value ({bad})")));
        }
        let mean = z
            .mean_axis(Axis(0))
            .ok_or_else(|| fit_error("z has no rows".into()))?;
        let centred = z - &mean;
        let covariance = centred.t().dot(&centred) / n as f64;
        let (values, vectors) = covariance.eigh().map_err(|e| fit_error(e.to_string()))?;
        // Largest variance first; total_cmp keeps the order defined whatever the values.
        let mut order: Vec<usize> = (0..dims).collect();
        order.sort_by(|&a, &b| values[b].total_cmp(&values[a]));
        let total = covariance.diag().sum().max(1e-12);
        let kept = &order[..axes.min(dims)];
        let components = kept
            .iter()
            .map(|&k| {
                let mut axis = vectors.column(k).to_vec();
                // An axis' sign is arbitrary; its largest entry positive makes it reproducible.
                let largest = axis
                    .iter()
                    .copied()
                    .fold(0.0f64, |m, v| if v.abs() > m.abs() { v } else { m });
                if largest < 0.0 {
                    axis.iter_mut().for_each(|v| *v = -*v);
                }
                axis
            })
            .collect();
        let explained_variance_ratio = kept.iter().map(|&k| values[k].max(0.0) / total).collect();
        Ok(PcaBasis {
            mean: mean.to_vec(),
            components,
            explained_variance_ratio,
        })
    }

    pub fn project(&self, z: &[f64]) -> Vec<f64> {
        self.components
            .iter()
            .map(|axis| {
                axis.iter()
                    .zip(z)
                    .zip(&self.mean)
                    .map(|((a, v), m)| a * (v - m))
                    .sum()
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pca_projection_is_centered_dot_product() {
        let basis = PcaBasis {
            mean: vec![1.0, 2.0],
            components: vec![vec![0.6, 0.8], vec![-0.8, 0.6]],
            explained_variance_ratio: vec![0.9, 0.1],
        };
        let p = basis.project(&[2.0, 4.0]);
        // (1, 2) · (0.6, 0.8) = 2.2; (1, 2) · (−0.8, 0.6) = 0.4
        assert!((p[0] - 2.2).abs() < 1e-12 && (p[1] - 0.4).abs() < 1e-12);
    }
    fn lcg(state: &mut u64) -> f64 {
        *state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (*state >> 11) as f64 / (1u64 << 53) as f64 - 0.5
    }

    #[test]
    fn points_on_a_line_give_that_line_and_all_the_variance() {
        // z = (1, 2) + t · (0.6, 0.8): one axis, (0.6, 0.8), holding every bit of the variance.
        let z = Array2::from_shape_fn((5, 2), |(i, j)| {
            let t = i as f64 - 2.0;
            [1.0, 2.0][j] + t * [0.6, 0.8][j]
        });
        let pca = PcaBasis::fit(&z, 2).unwrap();
        assert!((pca.mean[0] - 1.0).abs() < 1e-12 && (pca.mean[1] - 2.0).abs() < 1e-12);
        assert!((pca.components[0][0] - 0.6).abs() < 1e-9, "{pca:?}");
        assert!((pca.components[0][1] - 0.8).abs() < 1e-9, "{pca:?}");
        assert!((pca.explained_variance_ratio[0] - 1.0).abs() < 1e-9);
        assert!(pca.explained_variance_ratio[1].abs() < 1e-9);
    }

    #[test]
    fn matches_linfa_reductions_pca_on_well_separated_axes() {
        // Independent columns, three with clearly distinct variances (9, 4, 1.7 times 1/12) and
        // 21 small ones, as wide as a latent: both methods must find the same three axes (up to
        // sign). LOBPCG needs the problem several times wider than the axes asked for; on
        // narrow ones it hands back unconverged vectors without a word.
        let dims = 24;
        let scale = |j: usize| [3.0, 2.0, 1.3].get(j).copied().unwrap_or(0.3);
        let mut state = 7u64;
        let raw = Array2::from_shape_fn((2000, dims), |(_, j)| scale(j) * lcg(&mut state));
        // Rotate so the axes are not the coordinate ones: a Householder reflection.
        let v = ndarray::Array1::from_shape_fn(dims, |j| 1.0 + (j % 5) as f64 - 0.3 * j as f64);
        let v = &v / v.dot(&v).sqrt();
        let h = Array2::<f64>::eye(dims)
            - 2.0
                * &v.view()
                    .insert_axis(Axis(1))
                    .dot(&v.view().insert_axis(Axis(0)));
        let z = raw.dot(&h);
        let ours = PcaBasis::fit(&z, 3).unwrap();
        use linfa::prelude::*;
        let reference = linfa_reduction::Pca::params(3)
            .fit(&linfa::DatasetBase::from(z.clone()))
            .unwrap();
        for (k, axis) in reference.components().rows().into_iter().enumerate() {
            let dot: f64 = axis
                .iter()
                .zip(&ours.components[k])
                .map(|(a, b)| a * b)
                .sum();
            assert!(
                (dot.abs() - 1.0).abs() < 1e-6,
                "axis {k}: |cos| = {}",
                dot.abs()
            );
        }
        for (a, b) in reference.mean().iter().zip(&ours.mean) {
            assert!((a - b).abs() < 1e-12);
        }
        // The shares, checked against the projections' own variance.
        let total: f64 = z.var_axis(Axis(0), 0.0).sum();
        for (k, share) in ours.explained_variance_ratio.iter().enumerate() {
            let var = z
                .rows()
                .into_iter()
                .map(|r| ours.project(&r.to_vec())[k].powi(2))
                .sum::<f64>()
                / z.nrows() as f64;
            assert!((share - var / total).abs() < 1e-9, "axis {k}");
        }
    }

    #[test]
    fn near_constant_dimensions_fit_and_bad_input_is_refused() {
        // Most of z pinned (a saturated tanh), one dimension moving: a rank-one covariance.
        let mut state = 3u64;
        let z = Array2::from_shape_fn((600, 32), |(_, j)| match j {
            0 => lcg(&mut state),
            1 => 1.0 - 1e-13 * lcg(&mut state).abs(),
            _ => -1.0,
        });
        let pca = PcaBasis::fit(&z, 3).unwrap();
        assert!(pca.components[0][0] > 0.999_999, "{:?}", pca.components[0]);
        assert!((pca.explained_variance_ratio[0] - 1.0).abs() < 1e-9);
        assert!(pca.components.iter().flatten().all(|v| v.is_finite()));
        let mut bad = z.clone();
        bad[[5, 4]] = f64::NAN;
        let err = PcaBasis::fit(&bad, 3).unwrap_err().to_string();
        assert!(err.contains("non-finite"), "{err}");
        let err = PcaBasis::fit(&Array2::zeros((1, 4)), 3)
            .unwrap_err()
            .to_string();
        assert!(err.contains("at least 2 rows"), "{err}");
    }
}
