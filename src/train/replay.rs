//! Replay buffer in flat vectors. Each transition is stored once; the 16-step context windows
//! are rebuilt at sampling time from the transitions before it in the same episode, so a
//! 300k-transition buffer needs ~80 MB instead of the ~1.5 GB of stored 621-d windows.

use rand::Rng;
use std::io::{Read, Write};

/// One transition as the trainer hands it over.
#[derive(Debug, Clone, Copy)]
pub struct Transition<'a> {
    pub obs: &'a [f64],
    pub action: &'a [f64],
    pub reward: f64,
    pub next_obs: &'a [f64],
    /// Cuts the bootstrap (success or fall); truncation does not.
    pub terminated: bool,
    pub truncated: bool,
    /// Index of this step in its episode (0 for the first step after a reset).
    pub t_in_episode: usize,
}

/// A sampled minibatch, flat and batch-major.
#[derive(Debug, Clone, Default)]
pub struct Batch {
    pub size: usize,
    pub obs: Vec<f32>,
    pub actions: Vec<f32>,
    pub rewards: Vec<f32>,
    /// 1.0 where the transition terminated.
    pub terminated: Vec<f32>,
    pub next_obs: Vec<f32>,
    /// B × k × (obs+act): the window the policy saw with `obs` (empty if k = 0).
    pub window: Vec<f32>,
    /// B × k × (obs+act): the window that goes with `next_obs`.
    pub next_window: Vec<f32>,
}

#[derive(Debug, Clone)]
pub struct ReplayBuffer {
    capacity: usize,
    obs_dim: usize,
    act_dim: usize,
    /// Window length to rebuild (0: no windows).
    context_len: usize,
    obs: Vec<f32>,
    actions: Vec<f32>,
    rewards: Vec<f32>,
    terminated: Vec<bool>,
    truncated: Vec<bool>,
    next_obs: Vec<f32>,
    t_in_episode: Vec<u32>,
    len: usize,
    /// Next slot to write.
    pos: usize,
}

impl ReplayBuffer {
    pub fn new(capacity: usize, obs_dim: usize, act_dim: usize, context_len: usize) -> Self {
        assert!(capacity > 0, "replay capacity must be positive");
        Self {
            capacity,
            obs_dim,
            act_dim,
            context_len,
            obs: vec![0.0; capacity * obs_dim],
            actions: vec![0.0; capacity * act_dim],
            rewards: vec![0.0; capacity],
            terminated: vec![false; capacity],
            truncated: vec![false; capacity],
            next_obs: vec![0.0; capacity * obs_dim],
            t_in_episode: vec![0; capacity],
            len: 0,
            pos: 0,
        }
    }

    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    pub fn capacity(&self) -> usize {
        self.capacity
    }

    pub fn push(&mut self, t: Transition<'_>) {
        let i = self.pos;
        copy_f32(
            &mut self.obs[i * self.obs_dim..(i + 1) * self.obs_dim],
            t.obs,
        );
        copy_f32(
            &mut self.actions[i * self.act_dim..(i + 1) * self.act_dim],
            t.action,
        );
        copy_f32(
            &mut self.next_obs[i * self.obs_dim..(i + 1) * self.obs_dim],
            t.next_obs,
        );
        self.rewards[i] = t.reward as f32;
        self.terminated[i] = t.terminated;
        self.truncated[i] = t.truncated;
        self.t_in_episode[i] = t.t_in_episode as u32;
        self.pos = (self.pos + 1) % self.capacity;
        self.len = (self.len + 1).min(self.capacity);
    }

    /// Slot of the oldest stored transition.
    fn oldest(&self) -> usize {
        if self.len < self.capacity {
            0
        } else {
            self.pos
        }
    }

    /// Whether the history slot `i`'s window needs is still in the buffer (not overwritten).
    pub fn has_history(&self, slot: usize) -> bool {
        let age = (slot + self.capacity - self.oldest()) % self.capacity;
        slot < self.len && age >= (self.t_in_episode[slot] as usize).min(self.context_len)
    }

    /// Writes the window of `slot` (its `k` predecessors in the episode, zero-padded in front)
    /// into `out`; with `include_self` the window ends with `slot` itself (the next-obs window).
    pub fn write_window(&self, slot: usize, include_self: bool, out: &mut [f32]) {
        let k = self.context_len;
        let entry = self.obs_dim + self.act_dim;
        let t = self.t_in_episode[slot] as usize + usize::from(include_self);
        let real = t.min(k);
        out[..(k - real) * entry].fill(0.0);
        let last = if include_self {
            slot
        } else {
            (slot + self.capacity - 1) % self.capacity
        };
        for n in 0..real {
            // Entry (k − real + n) holds the transition `real − 1 − n` steps before `last`.
            let j = (last + self.capacity - (real - 1 - n)) % self.capacity;
            let dst = &mut out[(k - real + n) * entry..(k - real + n + 1) * entry];
            dst[..self.obs_dim]
                .copy_from_slice(&self.obs[j * self.obs_dim..(j + 1) * self.obs_dim]);
            dst[self.obs_dim..]
                .copy_from_slice(&self.actions[j * self.act_dim..(j + 1) * self.act_dim]);
        }
    }

    /// Samples `size` transitions uniformly (among those whose history is intact) into `batch`.
    pub fn sample(&self, size: usize, rng: &mut impl Rng, batch: &mut Batch) {
        assert!(self.len > 0, "sampling an empty replay buffer");
        let (od, ad, k) = (self.obs_dim, self.act_dim, self.context_len);
        let wdim = k * (od + ad);
        batch.size = size;
        batch.obs.resize(size * od, 0.0);
        batch.next_obs.resize(size * od, 0.0);
        batch.actions.resize(size * ad, 0.0);
        batch.rewards.resize(size, 0.0);
        batch.terminated.resize(size, 0.0);
        batch.window.resize(size * wdim, 0.0);
        batch.next_window.resize(size * wdim, 0.0);
        for b in 0..size {
            let i = loop {
                let i = rng.random_range(0..self.len);
                if self.has_history(i) {
                    break i;
                }
            };
            batch.obs[b * od..(b + 1) * od].copy_from_slice(&self.obs[i * od..(i + 1) * od]);
            batch.next_obs[b * od..(b + 1) * od]
                .copy_from_slice(&self.next_obs[i * od..(i + 1) * od]);
            batch.actions[b * ad..(b + 1) * ad]
                .copy_from_slice(&self.actions[i * ad..(i + 1) * ad]);
            batch.rewards[b] = self.rewards[i];
            batch.terminated[b] = if self.terminated[i] { 1.0 } else { 0.0 };
            if k > 0 {
                self.write_window(i, false, &mut batch.window[b * wdim..(b + 1) * wdim]);
                self.write_window(i, true, &mut batch.next_window[b * wdim..(b + 1) * wdim]);
            }
        }
    }

    /// Saves the buffer (little-endian, with a header) so `--resume` continues with it.
    pub fn write_to(&self, w: &mut impl Write) -> std::io::Result<()> {
        w.write_all(REPLAY_MAGIC)?;
        for v in [
            self.capacity,
            self.obs_dim,
            self.act_dim,
            self.context_len,
            self.len,
            self.pos,
        ] {
            w.write_all(&(v as u64).to_le_bytes())?;
        }
        for vec in [&self.obs, &self.actions, &self.rewards, &self.next_obs] {
            for v in vec.iter() {
                w.write_all(&v.to_le_bytes())?;
            }
        }
        for flags in [&self.terminated, &self.truncated] {
            w.write_all(&flags.iter().map(|&f| u8::from(f)).collect::<Vec<_>>())?;
        }
        for v in &self.t_in_episode {
            w.write_all(&v.to_le_bytes())?;
        }
        Ok(())
    }

    /// The exact size in bytes of this buffer as [`Self::write_to`] saves it: the header, then
    /// every slot whether filled or not. A resume reads no file of another size.
    pub fn file_len(&self) -> u64 {
        let floats = 2 * self.obs.len() + self.actions.len() + self.rewards.len();
        (REPLAY_MAGIC.len() + 6 * 8 + 4 * floats + 2 * self.capacity + 4 * self.t_in_episode.len())
            as u64
    }

    /// Reads a buffer saved by [`Self::write_to`]; its shape must match `self`'s.
    pub fn read_from(&mut self, r: &mut impl Read) -> Result<(), String> {
        let mut magic = [0u8; 8];
        r.read_exact(&mut magic)
            .map_err(|e| format!("header: {e}"))?;
        if &magic != REPLAY_MAGIC {
            return Err("not a gaitscope replay file".into());
        }
        let mut header = [0usize; 6];
        for h in &mut header {
            let mut b = [0u8; 8];
            r.read_exact(&mut b).map_err(|e| format!("header: {e}"))?;
            *h = u64::from_le_bytes(b) as usize;
        }
        let [capacity, obs_dim, act_dim, context_len, len, pos] = header;
        if (capacity, obs_dim, act_dim, context_len)
            != (self.capacity, self.obs_dim, self.act_dim, self.context_len)
        {
            return Err(format!(
                "saved buffer has capacity {capacity}, dims {obs_dim}/{act_dim}, window {context_len}; this run needs {}, {}/{}, {}",
                self.capacity, self.obs_dim, self.act_dim, self.context_len
            ));
        }
        if len > capacity || pos >= capacity {
            return Err(format!(
                "corrupt header: len {len}, pos {pos}, capacity {capacity}"
            ));
        }
        let truncated = |e: std::io::Error| format!("truncated body: {e}");
        for vec in [
            &mut self.obs,
            &mut self.actions,
            &mut self.rewards,
            &mut self.next_obs,
        ] {
            let mut bytes = vec![0u8; vec.len() * 4];
            r.read_exact(&mut bytes).map_err(truncated)?;
            for (v, b) in vec.iter_mut().zip(bytes.as_chunks::<4>().0) {
                *v = f32::from_le_bytes(*b);
            }
        }
        for flags in [&mut self.terminated, &mut self.truncated] {
            let mut bytes = vec![0u8; flags.len()];
            r.read_exact(&mut bytes).map_err(truncated)?;
            for (f, b) in flags.iter_mut().zip(bytes) {
                *f = b != 0;
            }
        }
        let mut bytes = vec![0u8; self.t_in_episode.len() * 4];
        r.read_exact(&mut bytes).map_err(truncated)?;
        for (v, b) in self.t_in_episode.iter_mut().zip(bytes.as_chunks::<4>().0) {
            *v = u32::from_le_bytes(*b);
        }
        let non_finite = |v: &[f32]| v.iter().any(|x| !x.is_finite());
        if non_finite(&self.obs)
            || non_finite(&self.actions)
            || non_finite(&self.rewards)
            || non_finite(&self.next_obs)
        {
            return Err("holds a NaN or infinite value".into());
        }
        self.len = len;
        self.pos = pos;
        Ok(())
    }
}

const REPLAY_MAGIC: &[u8; 8] = b"GSREPLY1";

fn copy_f32(dst: &mut [f32], src: &[f64]) {
    for (d, s) in dst.iter_mut().zip(src) {
        *d = *s as f32;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::window::ContextWindow;
    use rand::SeedableRng;
    use std::collections::HashMap;

    /// Drives a buffer with short episodes, records the window the "env" had online for each
    /// transition, then checks every stored slot rebuilds exactly that window — including the
    /// steps right after resets and after the ring wrapped around.
    #[test]
    fn sampled_windows_equal_the_online_windows() {
        let (obs_dim, act_dim, k, capacity) = (3, 2, 4, 37);
        let mut buffer = ReplayBuffer::new(capacity, obs_dim, act_dim, k);
        let mut window = ContextWindow::with_dims(k, obs_dim, act_dim);
        let mut online: HashMap<usize, (Vec<f32>, Vec<f32>)> = HashMap::new();
        let mut slot_of_step = HashMap::new();
        let mut obs = vec![0.0; obs_dim];
        let mut t_in_episode = 0;
        for global in 0..200usize {
            let action: Vec<f64> = (0..act_dim)
                .map(|a| (global * 10 + a) as f64 + 0.5)
                .collect();
            let next_obs: Vec<f64> = (0..obs_dim).map(|o| (global * 100 + o) as f64).collect();
            let before = window.as_slice().to_vec();
            window.push(&obs, &action);
            let after = window.as_slice().to_vec();
            online.insert(global, (before, after));
            let episode_len = 3 + global % 7; // varied lengths, some shorter than k
            let done = t_in_episode + 1 >= episode_len;
            slot_of_step.insert(global, buffer.pos);
            buffer.push(Transition {
                obs: &obs,
                action: &action,
                reward: 0.0,
                next_obs: &next_obs,
                terminated: done,
                truncated: false,
                t_in_episode,
            });
            if done {
                window.clear();
                obs = vec![-(global as f64); obs_dim]; // the reset observation
                t_in_episode = 0;
            } else {
                obs = next_obs;
                t_in_episode += 1;
            }
        }
        let wdim = k * (obs_dim + act_dim);
        let mut checked = 0;
        for global in 200 - capacity..200 {
            let slot = slot_of_step[&global];
            if !buffer.has_history(slot) {
                continue;
            }
            let mut w = vec![f32::NAN; wdim];
            let mut nw = vec![f32::NAN; wdim];
            buffer.write_window(slot, false, &mut w);
            buffer.write_window(slot, true, &mut nw);
            assert_eq!(w, online[&global].0, "window of step {global}");
            assert_eq!(nw, online[&global].1, "next window of step {global}");
            checked += 1;
        }
        // Only the k slots right after the oldest can lack their history.
        assert!(checked >= capacity - k, "checked {checked}");
        // The sampler uses the same windows.
        let mut batch = Batch::default();
        buffer.sample(
            64,
            &mut rand_chacha::ChaCha8Rng::seed_from_u64(0),
            &mut batch,
        );
        assert_eq!(batch.window.len(), 64 * wdim);
        for b in 0..64 {
            let obs0 = batch.obs[b * obs_dim];
            let step = (0..200).rev().find(|&g| {
                let s = slot_of_step[&g];
                buffer.obs[s * obs_dim] == obs0 && g >= 200 - capacity
            });
            let step = step.expect("sampled transition is stored");
            assert_eq!(
                &batch.window[b * wdim..(b + 1) * wdim],
                online[&step].0.as_slice()
            );
            // The next window is the window moved one step (the fused LSTM reuses its
            // projection on that promise, and checks it per batch).
            let entry = obs_dim + act_dim;
            assert_eq!(
                &batch.next_window[b * wdim..(b + 1) * wdim - entry],
                &batch.window[b * wdim + entry..(b + 1) * wdim]
            );
        }
    }

    #[test]
    fn save_and_restore_round_trip() {
        let mut buffer = ReplayBuffer::new(5, 2, 1, 2);
        for i in 0..7 {
            let v = i as f64;
            buffer.push(Transition {
                obs: &[v, v],
                action: &[v],
                reward: v,
                next_obs: &[v + 1.0, v],
                terminated: i % 3 == 0,
                truncated: false,
                t_in_episode: i % 3,
            });
        }
        let mut bytes = Vec::new();
        buffer.write_to(&mut bytes).unwrap();
        let mut restored = ReplayBuffer::new(5, 2, 1, 2);
        restored.read_from(&mut bytes.as_slice()).unwrap();
        assert_eq!((restored.len, restored.pos), (5, 2));
        assert_eq!(restored.obs, buffer.obs);
        assert_eq!(restored.t_in_episode, buffer.t_in_episode);
        let mut wrong = ReplayBuffer::new(6, 2, 1, 2);
        assert!(
            wrong
                .read_from(&mut bytes.as_slice())
                .unwrap_err()
                .contains("capacity 5")
        );
        // 56 header bytes (magic + six u64): cut inside it, then inside the body.
        assert!(
            restored
                .read_from(&mut &bytes[..40])
                .unwrap_err()
                .contains("header")
        );
        assert!(
            restored
                .read_from(&mut &bytes[..100])
                .unwrap_err()
                .contains("truncated")
        );
    }
}
