//! The latent's principal axes, saved in `probe.json` for the viewer's PCA panels.

use linfa::prelude::*;
use linfa_reduction::Pca;
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
    /// The first `axes` principal axes of the rows of `z` (linfa-reduction), with each axis'
    /// share of z's total variance.
    pub fn fit(z: &Array2<f64>, axes: usize) -> Result<Self, ProbeError> {
        let pca_model = Pca::params(axes.min(z.ncols()))
            .fit(&DatasetBase::from(z.clone()))
            .map_err(|e| ProbeError::Fit {
                what: "PCA".into(),
                reason: e.to_string(),
            })?;
        let mut pca = PcaBasis {
            mean: pca_model.mean().to_vec(),
            components: pca_model
                .components()
                .rows()
                .into_iter()
                .map(|r| r.to_vec())
                .collect(),
            explained_variance_ratio: Vec::new(),
        };
        // Share of z's total variance along each axis, measured directly: linfa's own ratio is
        // relative to the kept axes only.
        let total: f64 = z.var_axis(Axis(0), 0.0).sum();
        let projected: Vec<Vec<f64>> = z
            .rows()
            .into_iter()
            .map(|r| pca.project(&r.to_vec()))
            .collect();
        pca.explained_variance_ratio = (0..pca.components.len())
            .map(|k| {
                projected.iter().map(|p| p[k] * p[k]).sum::<f64>()
                    / projected.len().max(1) as f64
                    / total.max(1e-12)
            })
            .collect();
        Ok(pca)
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
}
