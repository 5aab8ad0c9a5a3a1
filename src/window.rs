//! The context window (the paper's "ContextHistoryWrapper"): the last `k` (observation, commanded
//! action) pairs, oldest first, zero-padded at the front until `k` steps exist.
//!
//! Stored as a ring buffer written twice (at slot `p` and `p + k`), so the window is always one
//! contiguous slice: reading it costs nothing and pushing costs two copies of 37 values.

use crate::damage::N_ACTUATORS;
use crate::env::OBS_DIM;

/// Values per window entry for the Ant: observation (29) then action (8).
pub const ENTRY_DIM: usize = OBS_DIM + N_ACTUATORS;

#[derive(Debug, Clone)]
pub struct ContextWindow {
    len: usize,
    obs_dim: usize,
    act_dim: usize,
    /// 2·len entries; entries `[head, head + len)` are the window, oldest first.
    storage: Vec<f32>,
    head: usize,
    filled: usize,
}

impl ContextWindow {
    /// A window of `len` Ant (obs, action) pairs.
    pub fn new(len: usize) -> Self {
        Self::with_dims(len, OBS_DIM, N_ACTUATORS)
    }

    /// A window for any task with `obs_dim` observations and `act_dim` actions.
    pub fn with_dims(len: usize, obs_dim: usize, act_dim: usize) -> Self {
        assert!(len > 0, "context window length must be positive");
        let entry = obs_dim + act_dim;
        Self {
            len,
            obs_dim,
            act_dim,
            storage: vec![0.0; 2 * len * entry],
            head: 0,
            filled: 0,
        }
    }

    /// Values per entry: observation then action.
    pub fn entry_dim(&self) -> usize {
        self.obs_dim + self.act_dim
    }

    /// Number of (obs, action) pairs the window holds.
    pub fn len(&self) -> usize {
        self.len
    }

    /// True until the first push after a clear.
    pub fn is_empty(&self) -> bool {
        self.filled == 0
    }

    /// Number of real (non-padding) entries, at most `len`.
    pub fn filled(&self) -> usize {
        self.filled
    }

    /// Length of [`Self::as_slice`]: `len × 37` for the Ant.
    pub fn flat_dim(&self) -> usize {
        self.len * self.entry_dim()
    }

    /// Length of the encoder input: window then current observation (621 for the Ant, k = 16).
    pub fn encoder_input_dim(&self) -> usize {
        self.flat_dim() + self.obs_dim
    }

    /// Forgets everything (episode reset): the window is all padding again.
    pub fn clear(&mut self) {
        self.storage.fill(0.0);
        self.head = 0;
        self.filled = 0;
    }

    /// Appends the observation the policy saw and the action it commanded.
    pub fn push(&mut self, obs: &[f64], action: &[f64]) {
        assert_eq!(
            (obs.len(), action.len()),
            (self.obs_dim, self.act_dim),
            "window entry dims"
        );
        let slot = self.head;
        let entry_dim = self.entry_dim();
        for copy in [slot, slot + self.len] {
            let entry = &mut self.storage[copy * entry_dim..(copy + 1) * entry_dim];
            for (dst, src) in entry.iter_mut().zip(obs.iter().chain(action)) {
                *dst = *src as f32;
            }
        }
        self.head = (self.head + 1) % self.len;
        self.filled = (self.filled + 1).min(self.len);
    }

    /// The window, `len × 37` values, oldest entry first.
    pub fn as_slice(&self) -> &[f32] {
        let entry_dim = self.entry_dim();
        &self.storage[self.head * entry_dim..(self.head + self.len) * entry_dim]
    }

    /// Writes the encoder input (window then `obs`) into `out`, which must hold
    /// [`Self::encoder_input_dim`] values.
    pub fn write_encoder_input(&self, obs: &[f64], out: &mut [f32]) {
        let (window, current) = out.split_at_mut(self.flat_dim());
        window.copy_from_slice(self.as_slice());
        for (dst, src) in current.iter_mut().zip(obs) {
            *dst = *src as f32;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn obs(v: f64) -> [f64; OBS_DIM] {
        [v; OBS_DIM]
    }
    fn act(v: f64) -> [f64; N_ACTUATORS] {
        [v; N_ACTUATORS]
    }
    /// The first value of each entry, oldest first.
    fn entry_heads(w: &ContextWindow) -> Vec<f32> {
        w.as_slice().chunks(ENTRY_DIM).map(|e| e[0]).collect()
    }

    #[test]
    fn pads_at_front_then_slides_oldest_first() {
        let mut w = ContextWindow::new(4);
        assert_eq!(w.as_slice().len(), 4 * 37);
        assert!(w.as_slice().iter().all(|&v| v == 0.0));
        w.push(&obs(1.0), &act(-1.0));
        w.push(&obs(2.0), &act(-2.0));
        assert_eq!(entry_heads(&w), vec![0.0, 0.0, 1.0, 2.0]);
        // The action sits right after the 29 observation values of its entry.
        let last = &w.as_slice()[3 * ENTRY_DIM..];
        assert_eq!((last[OBS_DIM - 1], last[OBS_DIM]), (2.0, -2.0));
        for v in 3..=6 {
            w.push(&obs(v as f64), &act(0.0));
        }
        assert_eq!(entry_heads(&w), vec![3.0, 4.0, 5.0, 6.0]);
        assert_eq!(w.filled(), 4);
    }

    #[test]
    fn clear_restores_padding() {
        let mut w = ContextWindow::new(3);
        for v in 1..=5 {
            w.push(&obs(v as f64), &act(v as f64));
        }
        w.clear();
        assert!(w.is_empty());
        assert!(w.as_slice().iter().all(|&v| v == 0.0));
        w.push(&obs(9.0), &act(9.0));
        assert_eq!(entry_heads(&w), vec![0.0, 0.0, 9.0]);
    }

    #[test]
    fn encoder_input_is_window_then_obs() {
        let mut w = ContextWindow::new(16);
        assert_eq!(w.encoder_input_dim(), 621);
        w.push(&obs(1.0), &act(0.5));
        let mut out = vec![f32::NAN; 621];
        w.write_encoder_input(&obs(7.0), &mut out);
        assert_eq!(&out[..592], w.as_slice());
        assert!(out[592..].iter().all(|&v| v == 7.0));
    }
}
