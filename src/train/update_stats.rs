//! What one SAC update reports (both update paths, [`super::sac`] and [`super::fused`]),
//! under CleanRL's names in metrics.jsonl.

use serde::Serialize;

/// Losses and values of one update, CleanRL's names.
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct UpdateStats {
    #[serde(rename = "losses/qf1")]
    pub qf1_loss: f64,
    #[serde(rename = "losses/qf2")]
    pub qf2_loss: f64,
    #[serde(rename = "losses/qf1_values")]
    pub qf1_values: f64,
    #[serde(rename = "losses/qf2_values")]
    pub qf2_values: f64,
    #[serde(rename = "losses/actor_loss")]
    pub actor_loss: f64,
    #[serde(rename = "losses/alpha")]
    pub alpha: f64,
    #[serde(rename = "losses/alpha_loss")]
    pub alpha_loss: f64,
    /// The actor's auxiliary loss (unweighted), with `--aux`.
    #[serde(rename = "losses/aux", skip_serializing_if = "Option::is_none")]
    pub aux_loss: Option<f64>,
    /// The critic's auxiliary loss (unweighted), with `--aux` and a critic encoder of its own.
    #[serde(rename = "losses/aux_critic", skip_serializing_if = "Option::is_none")]
    pub aux_critic_loss: Option<f64>,
}
