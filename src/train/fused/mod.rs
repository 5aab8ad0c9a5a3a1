//! The SAC update of `SacLearner` (train/sac.rs, which picks the path) without autograd: every forward and backward
//! pass written out over preallocated host buffers, on the same `gemm` kernels candle uses.
//!
//! Why: at batch 256 the reference update spends half its time outside GEMM, in candle's
//! op-by-op allocations and elementwise passes. The algorithm, the hyperparameters and SB3's
//! update order are unchanged (α → critic → actor against the updated critic → Polyak), and so
//! are the checkpoint and optimiser formats: [`FusedSac::write_back`] puts weights and moments
//! into the reference learner, which saves them. `tests/fused_update.rs` holds this path to the
//! reference (losses, gradients, updated weights) for every encoder.
//!
//! Deviations in arithmetic, none in the algorithm: the actor's passes over the current and next
//! observations run as one 2B-row batch (the same weights see both); ReLU masks read the output
//! (`y > 0`) where candle reads the input (`x ≥ 0`), which differ only at exactly 0.

mod kernels;

use candle_core::{Result, Tensor, bail};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

use super::adam::{Adam, BETA1, BETA2, EPS};
use super::aux::AuxHeads;
use super::replay::Batch;
use super::update_stats::UpdateStats;
use crate::policy::layers::ParamStore;
use crate::policy::{
    EncoderKind, LOG_STD_MAX, LOG_STD_MIN, NetConfig, SacConfig, SacModel, TANH_EPS,
};
use kernels::{
    DenseRef, InputGrad, LstmRef, LstmScratch, LstmTape, adam_step, both, dense_backward,
    dense_forward, lstm_backward, lstm_forward, lstm_output, relu_backward,
};

/// One owner's parameters (actor, critic, target, α) as flat vectors in the model's order, with
/// their gradients and Adam moments.
struct Group {
    names: Vec<String>,
    values: Vec<Vec<f32>>,
    grads: Vec<Vec<f32>>,
    m: Vec<Vec<f32>>,
    v: Vec<Vec<f32>>,
    shapes: Vec<Vec<usize>>,
    /// Adam steps taken.
    t: u64,
}

impl Group {
    fn new(store: &ParamStore, opt: Option<&Adam>) -> Result<Self> {
        let mut g = Group {
            names: Vec::new(),
            values: Vec::new(),
            grads: Vec::new(),
            m: Vec::new(),
            v: Vec::new(),
            shapes: Vec::new(),
            t: opt.map_or(0, |o| o.t),
        };
        for (name, var) in store.iter() {
            let value = var.flatten_all()?.to_vec1::<f32>()?;
            g.grads.push(vec![0.0; value.len()]);
            g.m.push(vec![0.0; value.len()]);
            g.v.push(vec![0.0; value.len()]);
            g.names.push(name.to_string());
            g.shapes.push(var.dims().to_vec());
            g.values.push(value);
        }
        if let Some(opt) = opt {
            if opt.len() != g.values.len() {
                bail!("{} Adam slots for {} parameters", opt.len(), g.values.len());
            }
            for (i, (m, v)) in opt.moments().enumerate() {
                g.m[i].copy_from_slice(m);
                g.v[i].copy_from_slice(v);
            }
        }
        Ok(g)
    }

    fn index(&self, name: &str) -> Result<usize> {
        match self.names.iter().position(|n| n == name) {
            Some(i) => Ok(i),
            None => bail!("fused update: no parameter named {name}"),
        }
    }

    /// One Adam step on every parameter (the reference steps every parameter too: each one
    /// gets a gradient from its loss).
    fn adam(&mut self, lr: f64) {
        self.t += 1;
        let bc1 = 1.0 - BETA1.powi(self.t as i32);
        let bc2 = 1.0 - BETA2.powi(self.t as i32);
        let step_size = (lr / bc1) as f32;
        let bc2_sqrt = bc2.sqrt() as f32;
        let betas = (BETA1 as f32, BETA2 as f32, EPS as f32);
        for i in 0..self.values.len() {
            adam_step(
                &mut self.values[i],
                &self.grads[i],
                &mut self.m[i],
                &mut self.v[i],
                step_size,
                bc2_sqrt,
                betas,
            );
        }
    }

    /// Writes values into the store's vars (and moments into `opt`).
    fn write_back(&self, store: &ParamStore, opt: Option<&mut Adam>) -> Result<()> {
        for ((_, var), (value, shape)) in store.iter().zip(self.values.iter().zip(&self.shapes)) {
            var.set(&Tensor::from_slice(value, shape.as_slice(), var.device())?)?;
        }
        if let Some(opt) = opt {
            let moments = self.m.iter().cloned().zip(self.v.iter().cloned()).collect();
            opt.set_moments(self.t, moments)
                .map_err(candle_core::Error::Msg)?;
        }
        Ok(())
    }
}

/// Mutable gradients of a layer's weight and bias at once.
fn pair_mut(v: &mut [Vec<f32>], i: usize, j: usize) -> (&mut [f32], &mut [f32]) {
    assert_ne!(i, j);
    if i < j {
        let (a, b) = v.split_at_mut(j);
        (&mut a[i], &mut b[0])
    } else {
        let (a, b) = v.split_at_mut(i);
        (&mut b[0], &mut a[j])
    }
}

/// A linear layer: indices of its weight (in, out) and bias (1, out) in a group.
#[derive(Debug, Clone, Copy)]
struct Dense {
    w: usize,
    b: usize,
    n_in: usize,
    n_out: usize,
}

impl Dense {
    fn find(g: &Group, prefix: &str) -> Result<Self> {
        let w = g.index(&format!("{prefix}.weight"))?;
        let b = g.index(&format!("{prefix}.bias"))?;
        match g.shapes[w].as_slice() {
            &[n_in, n_out] => Ok(Dense { w, b, n_in, n_out }),
            s => bail!("fused update: {prefix}.weight has shape {s:?}"),
        }
    }

    fn get<'a>(&self, values: &'a [Vec<f32>]) -> DenseRef<'a> {
        DenseRef {
            w: &values[self.w],
            b: &values[self.b],
            n_in: self.n_in,
            n_out: self.n_out,
        }
    }
}

/// Linear layers with ReLU between them (and after the last one if `relu_out`).
#[derive(Debug, Clone)]
struct Mlp {
    layers: Vec<Dense>,
    relu_out: bool,
}

impl Mlp {
    fn find(g: &Group, prefix: &str, relu_out: bool) -> Result<Self> {
        let mut layers = Vec::new();
        while g
            .names
            .iter()
            .any(|n| *n == format!("{prefix}.{}.weight", layers.len()))
        {
            layers.push(Dense::find(g, &format!("{prefix}.{}", layers.len()))?);
        }
        if layers.is_empty() {
            bail!("fused update: no layers under {prefix}");
        }
        Ok(Mlp { layers, relu_out })
    }

    fn n_out(&self) -> usize {
        self.layers.last().map_or(0, |l| l.n_out)
    }

    fn widest(&self) -> usize {
        self.layers
            .iter()
            .map(|l| l.n_in.max(l.n_out))
            .max()
            .unwrap_or(0)
    }

    /// Forward over `rows` rows of `x`; every layer's output stays in `tape`.
    fn forward(&self, values: &[Vec<f32>], x: &[f32], rows: usize, tape: &mut MlpTape) {
        self.forward_parts(values, &[x], rows, tape);
    }

    /// Forward over inputs given in parts (stacked rows, `rows` in all), without stacking them.
    fn forward_parts(
        &self,
        values: &[Vec<f32>],
        parts: &[&[f32]],
        rows: usize,
        tape: &mut MlpTape,
    ) {
        tape.outs.resize_with(self.layers.len(), Vec::new);
        for (i, layer) in self.layers.iter().enumerate() {
            let (before, after) = tape.outs.split_at_mut(i);
            let out = &mut after[0];
            out.resize(rows * layer.n_out, 0.0);
            let relu = i + 1 < self.layers.len() || self.relu_out;
            if i == 0 {
                let mut offset = 0;
                for part in parts {
                    let n = part.len() / layer.n_in;
                    let block = &mut out[offset * layer.n_out..(offset + n) * layer.n_out];
                    dense_forward(layer.get(values), part, n, block, relu);
                    offset += n;
                }
            } else {
                dense_forward(layer.get(values), &before[i - 1], rows, out, relu);
            }
        }
    }

    /// Backward from `d_out` (rows × n_out, before the output ReLU if any): weight gradients into
    /// `grads` when given, and the asked columns of the input's gradient.
    #[allow(clippy::too_many_arguments)]
    fn backward(
        &self,
        values: &[Vec<f32>],
        mut grads: Option<&mut [Vec<f32>]>,
        x: &[f32],
        rows: usize,
        tape: &MlpTape,
        d_out: &[f32],
        d_x: Option<InputGrad>,
        scratch: &mut [Vec<f32>; 2],
    ) {
        let n = self.layers.len();
        let width = self.widest();
        for s in scratch.iter_mut() {
            s.resize(rows * width, 0.0);
        }
        let [d, d_prev] = scratch;
        let last = self.n_out();
        d[..rows * last].copy_from_slice(&d_out[..rows * last]);
        if self.relu_out {
            relu_backward(&tape.outs[n - 1], &mut d[..rows * last]);
        }
        let mut d_x = d_x;
        for i in (0..n).rev() {
            let layer = self.layers[i];
            let input = if i == 0 { x } else { &tape.outs[i - 1] };
            let layer_grads = grads.as_deref_mut().map(|g| pair_mut(g, layer.w, layer.b));
            if i > 0 {
                let all = InputGrad {
                    out: &mut d_prev[..],
                    cols: 0..layer.n_in,
                    accumulate: false,
                };
                dense_backward(layer.get(values), input, rows, d, layer_grads, Some(all));
                relu_backward(&tape.outs[i - 1], &mut d_prev[..rows * layer.n_in]);
                std::mem::swap(d, d_prev);
            } else {
                dense_backward(layer.get(values), input, rows, d, layer_grads, d_x.take());
            }
        }
    }
}

#[derive(Default)]
struct MlpTape {
    outs: Vec<Vec<f32>>,
}

impl MlpTape {
    fn output(&self) -> &[f32] {
        self.outs.last().map_or(&[], Vec::as_slice)
    }
}

/// A context encoder's parameters.
#[derive(Debug, Clone)]
enum Encoder {
    None,
    Lstm {
        w_ih: usize,
        w_hh: usize,
        b_ih: usize,
        b_hh: usize,
        input: usize,
        hidden: usize,
    },
    /// MLP over the flattened window, then tanh.
    Window(Mlp),
}

impl Encoder {
    fn find(g: &Group, prefix: &str, kind: EncoderKind) -> Result<Self> {
        Ok(match kind {
            EncoderKind::None => Encoder::None,
            EncoderKind::Lstm => {
                let p = |s: &str| g.index(&format!("{prefix}.lstm.{s}"));
                let w_ih = p("weight_ih")?;
                let w_hh = p("weight_hh")?;
                let (input, g4) = match g.shapes[w_ih].as_slice() {
                    &[i, g4] => (i, g4),
                    s => bail!("fused update: {prefix}.lstm.weight_ih has shape {s:?}"),
                };
                Encoder::Lstm {
                    w_ih,
                    w_hh,
                    b_ih: p("bias_ih")?,
                    b_hh: p("bias_hh")?,
                    input,
                    hidden: g4 / 4,
                }
            }
            EncoderKind::MlpWindow => {
                Encoder::Window(Mlp::find(g, &format!("{prefix}.mlp"), false)?)
            }
        })
    }

    fn lstm<'a>(&self, values: &'a [Vec<f32>]) -> Option<LstmRef<'a>> {
        match *self {
            Encoder::Lstm {
                w_ih,
                w_hh,
                b_ih,
                b_hh,
                input,
                hidden,
            } => Some(LstmRef {
                w_ih: &values[w_ih],
                w_hh: &values[w_hh],
                b_ih: &values[b_ih],
                b_hh: &values[b_hh],
                input,
                hidden,
            }),
            _ => None,
        }
    }

    /// z for windows given in parts (stacked rows); nothing for `None`.
    /// `parallel`: inside the update's pool, an LSTM shares its work between two threads.
    fn forward(
        &self,
        values: &[Vec<f32>],
        parts: &[&[f32]],
        t_len: usize,
        tape: &mut EncoderTape,
        parallel: bool,
    ) {
        match self {
            Encoder::None => {}
            Encoder::Lstm { .. } => {
                if let Some(l) = self.lstm(values) {
                    lstm_forward(l, parts, t_len, &mut tape.lstm, parallel);
                }
            }
            Encoder::Window(mlp) => {
                let width = mlp.layers[0].n_in;
                let rows: usize = parts.iter().map(|p| p.len() / width).sum();
                mlp.forward_parts(values, parts, rows, &mut tape.mlp);
                tape.z.clear();
                tape.z.extend_from_slice(tape.mlp.output());
                kernels::tanh_in_place(&mut tape.z);
            }
        }
    }

    fn z<'a>(&self, tape: &'a EncoderTape, t_len: usize) -> &'a [f32] {
        match self {
            Encoder::None => &[],
            Encoder::Lstm { hidden, .. } => lstm_output(&tape.lstm, t_len, *hidden),
            Encoder::Window(_) => &tape.z,
        }
    }

    /// Gradients of the encoder's parameters from d z of the first `rows` rows, whose windows
    /// are `window` (rows × T × entry).
    #[allow(clippy::too_many_arguments)]
    fn backward(
        &self,
        values: &[Vec<f32>],
        grads: &mut [Vec<f32>],
        window: &[f32],
        rows: usize,
        t_len: usize,
        d_z: &[f32],
        tape: &mut EncoderTape,
        scratch: &mut [Vec<f32>; 2],
        parallel: bool,
    ) {
        match self {
            Encoder::None => {}
            &Encoder::Lstm {
                w_ih,
                w_hh,
                b_ih,
                b_hh,
                ..
            } => {
                let Some(l) = self.lstm(values) else { return };
                let mut taken: Vec<Vec<f32>> = [w_ih, w_hh, b_ih, b_hh]
                    .iter()
                    .map(|&i| std::mem::take(&mut grads[i]))
                    .collect();
                let [a, b, c, d] = taken.as_mut_slice() else {
                    return;
                };
                lstm_backward(
                    l,
                    &tape.lstm,
                    window,
                    rows,
                    t_len,
                    d_z,
                    &mut tape.lstm_scratch,
                    [a, b, c, d],
                    parallel,
                );
                for (&i, g) in [w_ih, w_hh, b_ih, b_hh].iter().zip(taken) {
                    grads[i] = g;
                }
            }
            Encoder::Window(mlp) => {
                // z = tanh(y): dy = dz · (1 − z²).
                let z_dim = mlp.n_out();
                tape.d_pre.clear();
                tape.d_pre.extend(
                    d_z[..rows * z_dim]
                        .iter()
                        .zip(&tape.z)
                        .map(|(d, z)| d * (1.0 - z * z)),
                );
                mlp.backward(
                    values,
                    Some(grads),
                    window,
                    rows,
                    &tape.mlp,
                    &tape.d_pre,
                    None,
                    scratch,
                );
            }
        }
    }
}

#[derive(Default)]
struct EncoderTape {
    lstm: LstmTape,
    lstm_scratch: LstmScratch,
    mlp: MlpTape,
    z: Vec<f32>,
    d_pre: Vec<f32>,
}

/// The actor: encoder, trunk, mean and log-std heads.
struct ActorNet {
    encoder: Encoder,
    /// Widths of z (0 without an encoder) and of the observation in the features [z, obs].
    z_dim: usize,
    obs_dim: usize,
    trunk: Mlp,
    mean: Dense,
    log_std: Dense,
}

/// Twin Q-networks with an optional own encoder.
struct CriticNet {
    encoder: Option<Encoder>,
    q: [Mlp; 2],
}

impl CriticNet {
    fn find(g: &Group, prefix: &str, kind: EncoderKind, own_encoder: bool) -> Result<Self> {
        Ok(CriticNet {
            encoder: if own_encoder {
                Some(Encoder::find(g, &format!("{prefix}.encoder"), kind)?)
            } else {
                None
            },
            q: [
                Mlp::find(g, &format!("{prefix}.q0"), false)?,
                Mlp::find(g, &format!("{prefix}.q1"), false)?,
            ],
        })
    }
}

/// Every buffer one update needs, allocated on first use and reused.
#[derive(Default)]
struct Workspace {
    actor: ActorTape,
    critic_enc: EncoderTape,
    target_enc: EncoderTape,
    noise: Vec<f32>,
    action: Vec<f32>,
    log_prob: Vec<f32>,
    /// Critic input [features, action] (B rows).
    q_input: Vec<f32>,
    /// One per Q-network, so the two can run at once.
    q: [QWork; 2],
    target: Vec<f32>,
    d_action: Vec<f32>,
    d_heads: [Vec<f32>; 2],
    d_h: Vec<f32>,
    d_z: Vec<f32>,
    scratch: [Vec<f32>; 2],
}

/// The actor's forward buffers.
#[derive(Default)]
struct ActorTape {
    enc: EncoderTape,
    /// Features [z, obs] over the current then the next observations (2B rows).
    features: Vec<f32>,
    trunk: MlpTape,
    mean: Vec<f32>,
    log_std_raw: Vec<f32>,
}

/// One Q-network's buffers: its tape, dL/dq, its share of an input gradient, backward scratch.
#[derive(Default)]
struct QWork {
    tape: MlpTape,
    d_q: Vec<f32>,
    d_input: Vec<f32>,
    scratch: [Vec<f32>; 2],
}

/// `a` and `b` at once on the current rayon pool when `parallel`, else one after the other.
/// Either way each computes the same thing, so results do not depend on it.
/// Moves the gradients of `mlp`'s parameters out of `grads` into a vector of the same length
/// (empty elsewhere), so two networks of one group can run their backward passes at once.
fn take_grads(grads: &mut [Vec<f32>], mlp: &Mlp) -> Vec<Vec<f32>> {
    let mut taken = vec![Vec::new(); grads.len()];
    for layer in &mlp.layers {
        for i in [layer.w, layer.b] {
            std::mem::swap(&mut taken[i], &mut grads[i]);
        }
    }
    taken
}

/// Puts back what [`take_grads`] moved out.
fn put_back_grads(grads: &mut [Vec<f32>], taken: Vec<Vec<f32>>, mlp: &Mlp) {
    let mut taken = taken;
    for layer in &mlp.layers {
        for i in [layer.w, layer.b] {
            std::mem::swap(&mut taken[i], &mut grads[i]);
        }
    }
}

/// The fused learner: live weights and optimiser state while training runs.
pub struct FusedSac {
    net: NetConfig,
    config: SacConfig,
    target_entropy: f64,
    actor_p: Group,
    critic_p: Group,
    target_p: Group,
    alpha_p: Group,
    actor: ActorNet,
    critic: CriticNet,
    target: CriticNet,
    /// (target index, source is the actor's, source index) for the Polyak update.
    polyak: Vec<(usize, bool, usize)>,
    ws: Workspace,
    /// The encoders' auxiliary heads (`--aux`), trained with the actor and critic losses.
    aux: Option<AuxFused>,
    /// With more than one thread: the pool the update's GEMMs split their tiles over.
    pool: Option<std::sync::Arc<rayon::ThreadPool>>,
}

/// The auxiliary heads on this path (train/aux.rs has the loss): each head's weights and Adam
/// state as a group, and their buffers.
struct AuxFused {
    weight: f32,
    actor_p: Group,
    actor: Mlp,
    critic: Option<(Group, Mlp)>,
    work: AuxWork,
}

#[derive(Default)]
struct AuxWork {
    /// Head input [z, obs, action] (B rows).
    x: Vec<f32>,
    tape: MlpTape,
    d_pred: Vec<f32>,
    scratch: [Vec<f32>; 2],
}

/// The targets of this batch for the auxiliary heads: the normalised change of each row's
/// observation (B × obs_dim) and 1 for rows that did not terminate (B).
pub struct AuxTargets<'a> {
    pub targets: &'a [f32],
    pub mask: &'a [f32],
}

/// One auxiliary head's forward and backward: the mean squared error over non-terminal rows and
/// observation dimensions (returned unweighted), its weights' gradients into `p.grads`, and
/// weight × dL/dz added into `d_z` (B × z_dim).
#[allow(clippy::too_many_arguments)]
fn aux_step(
    head: &Mlp,
    p: &mut Group,
    z: &[f32],
    z_dim: usize,
    batch: &Batch,
    aux: &AuxTargets,
    weight: f32,
    work: &mut AuxWork,
    d_z: &mut [f32],
) -> f32 {
    let b = batch.size;
    let obs_dim = batch.obs.len() / b;
    let act_dim = batch.actions.len() / b;
    work.x.clear();
    for i in 0..b {
        work.x.extend_from_slice(&z[i * z_dim..(i + 1) * z_dim]);
        work.x
            .extend_from_slice(&batch.obs[i * obs_dim..(i + 1) * obs_dim]);
        work.x
            .extend_from_slice(&batch.actions[i * act_dim..(i + 1) * act_dim]);
    }
    head.forward(&p.values, &work.x, b, &mut work.tape);
    let prediction = work.tape.output();
    let rows = aux.mask.iter().sum::<f32>().max(1.0);
    let denom = rows * obs_dim as f32;
    let mut loss = 0f32;
    work.d_pred.clear();
    for i in 0..b {
        let m = aux.mask[i];
        for j in 0..obs_dim {
            let k = i * obs_dim + j;
            let e = prediction[k] - aux.targets[k];
            loss += m * e * e;
            work.d_pred.push(weight * 2.0 * m * e / denom);
        }
    }
    let d_z = InputGrad {
        out: d_z,
        cols: 0..z_dim,
        accumulate: true,
    };
    head.backward(
        &p.values,
        Some(&mut p.grads),
        &work.x,
        b,
        &work.tape,
        &work.d_pred,
        Some(d_z),
        &mut work.scratch,
    );
    loss / denom
}

impl FusedSac {
    /// Copies the reference learner's weights and Adam state.
    pub fn new(
        model: &SacModel,
        opts: [&Adam; 3],
        config: &SacConfig,
        target_entropy: f64,
        aux: Option<&AuxHeads>,
    ) -> Result<Self> {
        let net = model.net.clone();
        let aux = match aux {
            Some(heads) => {
                let actor_p = Group::new(&heads.actor_params, Some(&heads.actor_opt))?;
                let actor = Mlp::find(&actor_p, "aux.actor", false)?;
                let critic = match &heads.critic_opt {
                    Some(opt) => {
                        let p = Group::new(&heads.critic_params, Some(opt))?;
                        let mlp = Mlp::find(&p, "aux.critic", false)?;
                        Some((p, mlp))
                    }
                    None => None,
                };
                Some(AuxFused {
                    weight: heads.config.weight as f32,
                    actor_p,
                    actor,
                    critic,
                    work: AuxWork::default(),
                })
            }
            None => None,
        };
        let [actor_opt, critic_opt, alpha_opt] = opts;
        let actor_p = Group::new(&model.actor_params, Some(actor_opt))?;
        let critic_p = Group::new(&model.critic_params, Some(critic_opt))?;
        let target_p = Group::new(&model.target_params, None)?;
        let alpha_p = Group::new(&model.alpha_params, Some(alpha_opt))?;
        let own = model.critic.encoder.is_some();
        let actor = ActorNet {
            encoder: Encoder::find(&actor_p, "actor.encoder", net.encoder)?,
            z_dim: if net.encoder.uses_window() {
                net.z_dim
            } else {
                0
            },
            obs_dim: net.obs_dim,
            trunk: Mlp::find(&actor_p, "actor.trunk", true)?,
            mean: Dense::find(&actor_p, "actor.mean")?,
            log_std: Dense::find(&actor_p, "actor.log_std")?,
        };
        let critic = CriticNet::find(&critic_p, "critic", net.encoder, own)?;
        let target = CriticNet::find(&target_p, "critic_target", net.encoder, true)?;
        let mut polyak = Vec::new();
        for (i, name) in target_p.names.iter().enumerate() {
            let rest = name.strip_prefix("critic_target.").unwrap_or(name);
            let shared = !own && rest.starts_with("encoder.");
            let source = if shared {
                actor_p.index(&format!("actor.{rest}"))?
            } else {
                critic_p.index(&format!("critic.{rest}"))?
            };
            polyak.push((i, shared, source));
        }
        Ok(Self {
            net,
            config: config.clone(),
            target_entropy,
            actor_p,
            critic_p,
            target_p,
            alpha_p,
            actor,
            critic,
            target,
            polyak,
            ws: Workspace::default(),
            aux,
            pool: None,
        })
    }

    /// Threads for each update (1: the caller's thread alone). More split every large GEMM's
    /// output tiles over a pool of that size; the arithmetic, and so every result, is the same.
    pub fn set_threads(&mut self, threads: usize) -> Result<()> {
        self.pool = match threads {
            0 | 1 => None,
            n => Some(std::sync::Arc::new(
                rayon::ThreadPoolBuilder::new()
                    .num_threads(n)
                    .thread_name(|i| format!("gaitscope-update-{i}"))
                    .build()
                    .map_err(|e| candle_core::Error::Msg(format!("update thread pool: {e}")))?,
            )),
        };
        Ok(())
    }

    /// Puts the live weights and Adam state back into the model and the reference optimisers
    /// (before saving a checkpoint).
    pub fn write_back(
        &self,
        model: &SacModel,
        opts: [&mut Adam; 3],
        heads: Option<&mut AuxHeads>,
    ) -> Result<()> {
        if let (Some(aux), Some(heads)) = (&self.aux, heads) {
            aux.actor_p
                .write_back(&heads.actor_params, Some(&mut heads.actor_opt))?;
            if let (Some((p, _)), Some(opt)) = (&aux.critic, &mut heads.critic_opt) {
                p.write_back(&heads.critic_params, Some(opt))?;
            }
        }
        let [actor_opt, critic_opt, alpha_opt] = opts;
        self.actor_p
            .write_back(&model.actor_params, Some(actor_opt))?;
        self.critic_p
            .write_back(&model.critic_params, Some(critic_opt))?;
        self.target_p.write_back(&model.target_params, None)?;
        self.alpha_p
            .write_back(&model.alpha_params, Some(alpha_opt))?;
        Ok(())
    }

    /// The last update's gradient of every trained parameter, by name (α, critic, the
    /// critic's auxiliary head, actor, the actor's auxiliary head).
    pub fn gradients(&self) -> Vec<(String, Vec<f32>)> {
        let mut groups = vec![&self.alpha_p, &self.critic_p];
        if let Some((p, _)) = self.aux.as_ref().and_then(|a| a.critic.as_ref()) {
            groups.push(p);
        }
        groups.push(&self.actor_p);
        if let Some(aux) = &self.aux {
            groups.push(&aux.actor_p);
        }
        groups
            .iter()
            .flat_map(|g| g.names.iter().cloned().zip(g.grads.iter().cloned()))
            .collect()
    }

    /// A squashed-Gaussian action for one observation (and window): what the training loop
    /// explores with, from the live weights. `noise` is act_dim standard normals.
    pub fn act(&mut self, obs: &[f32], window: Option<&[f32]>, noise: &[f32]) -> Vec<f64> {
        let t_len = self.net.context_len;
        let parts: Vec<&[f32]> = window.into_iter().collect();
        actor_forward(
            &self.actor,
            &self.actor_p.values,
            &[obs],
            &parts,
            t_len,
            &mut self.ws.actor,
            false,
        );
        let ws = &mut self.ws;
        sample(
            &ws.actor.mean,
            &ws.actor.log_std_raw,
            noise,
            self.net.act_dim,
            &mut ws.action,
            &mut ws.log_prob,
        );
        ws.action.iter().map(|&a| f64::from(a)).collect()
    }

    /// One gradient step on `batch`; `rng` draws the reparameterisation noise exactly as the
    /// reference does (current actions first, then next actions).
    /// `aux`: this batch's targets when the run has auxiliary heads.
    pub fn update(
        &mut self,
        batch: &Batch,
        rng: &mut ChaCha8Rng,
        aux: Option<AuxTargets>,
    ) -> Result<UpdateStats> {
        if self.aux.is_some() != aux.is_some() {
            bail!("fused update: auxiliary targets given without heads, or heads without targets");
        }
        match self.pool.clone() {
            None => self.update_here(batch, rng, aux.as_ref()),
            Some(pool) => pool.install(|| {
                // The GEMM thread count is per thread: set it on the pool's thread that runs this.
                crate::policy::gemm::set_threads(pool.current_num_threads());
                self.update_here(batch, rng, aux.as_ref())
            }),
        }
    }

    fn update_here(
        &mut self,
        batch: &Batch,
        rng: &mut ChaCha8Rng,
        aux_targets: Option<&AuxTargets>,
    ) -> Result<UpdateStats> {
        let b = batch.size;
        let net = self.net.clone();
        let (act, t_len) = (net.act_dim, net.context_len);
        let windows = net.encoder.uses_window();
        let parallel = self.pool.is_some();
        let (win, next_win): (&[f32], &[f32]) = if windows {
            (&batch.window, &batch.next_window)
        } else {
            (&[], &[])
        };
        let ws = &mut self.ws;
        ws.noise.clear();
        ws.noise
            .extend((0..2 * b * act).map(|_| rng.sample::<f32, _>(StandardNormal)));

        // --- forward passes that need nothing from each other ---------------------------------
        // The actor over current and next observations (one 2B batch), beside the target's and
        // the critic's encoders (the critic's weights do not change before its own step).
        let win_parts: Vec<&[f32]> = if windows { vec![win, next_win] } else { vec![] };
        let target_enc = self.target.encoder.as_ref().unwrap_or(&Encoder::None);
        let (actor, actor_p, target_p, critic, critic_p) = (
            &self.actor,
            &self.actor_p,
            &self.target_p,
            &self.critic,
            &self.critic_p,
        );
        let (actor_tape, target_tape, critic_tape) =
            (&mut ws.actor, &mut ws.target_enc, &mut ws.critic_enc);
        both(
            parallel,
            || {
                let obs_parts = [batch.obs.as_slice(), batch.next_obs.as_slice()];
                actor_forward(
                    actor,
                    &actor_p.values,
                    &obs_parts,
                    &win_parts,
                    t_len,
                    actor_tape,
                    parallel,
                );
            },
            || {
                target_enc.forward(&target_p.values, &[next_win], t_len, target_tape, parallel);
                if let Some(enc) = &critic.encoder {
                    enc.forward(&critic_p.values, &[win], t_len, critic_tape, parallel);
                }
            },
        );
        sample(
            &ws.actor.mean,
            &ws.actor.log_std_raw,
            &ws.noise,
            act,
            &mut ws.action,
            &mut ws.log_prob,
        );
        // Rows 0..B: a_pi, log π(a_pi); rows B..2B: the next actions for the target.

        // --- entropy coefficient -------------------------------------------------------------
        let log_alpha = self.alpha_p.values[0][0];
        let alpha = f64::from(log_alpha.exp());
        let te = self.target_entropy as f32;
        let mean_lp_te = ws.log_prob[..b].iter().map(|lp| lp + te).sum::<f32>() / b as f32;
        let alpha_loss = -(log_alpha * mean_lp_te);
        self.alpha_p.grads[0][0] = -mean_lp_te;
        self.alpha_p.adam(self.config.learning_rate);

        // --- critic target ---------------------------------------------------------------------
        q_input(
            &net,
            target_enc.z(&ws.target_enc, t_len),
            &batch.next_obs,
            &ws.action[b * act..2 * b * act],
            b,
            &mut ws.q_input,
        );
        let [w0, w1] = &mut ws.q;
        let [t0, t1] = &self.target.q;
        let (values, input) = (&self.target_p.values, &ws.q_input);
        both(
            parallel,
            || t0.forward(values, input, b, &mut w0.tape),
            || t1.forward(values, input, b, &mut w1.tape),
        );
        ws.target.clear();
        let (gamma, alpha32) = (self.config.gamma as f32, alpha as f32);
        for i in 0..b {
            let q = ws.q[0].tape.output()[i].min(ws.q[1].tape.output()[i]);
            let next_q = q - ws.log_prob[b + i] * alpha32;
            // Bootstrap cut on termination only: a truncated episode still has a future.
            let not_done = 1.0 - batch.terminated[i];
            ws.target
                .push(batch.rewards[i] + (not_done * next_q) * gamma);
        }

        // --- critic ----------------------------------------------------------------------------
        // Features: the critic's own encoder (tracked), or the actor's z (shared, no gradient).
        let z_c = critic_z(
            &self.critic,
            &self.actor,
            &ws.critic_enc,
            &ws.actor.enc,
            t_len,
            b,
        );
        q_input(&net, z_c, &batch.obs, &batch.actions, b, &mut ws.q_input);
        let own_encoder = self.critic.encoder.is_some();
        // z is the first z_dim columns of the critic input; both Q-nets feed it.
        let d_z_cols = (own_encoder && windows).then_some(0..net.z_dim);
        let [q0, q1] = &self.critic.q;
        let mut q1_grads = take_grads(&mut self.critic_p.grads, q1);
        let (values, q0_grads) = (&self.critic_p.values, &mut self.critic_p.grads);
        let [w0, w1] = &mut ws.q;
        let (input, target) = (&ws.q_input, &ws.target);
        let cols = (d_z_cols.clone(), d_z_cols.clone());
        let ((qf1_loss, q1_mean), (qf2_loss, q2_mean)) = both(
            parallel,
            || critic_step(q0, values, q0_grads, input, target, b, cols.0, w0),
            || critic_step(q1, values, &mut q1_grads, input, target, b, cols.1, w1),
        );
        put_back_grads(&mut self.critic_p.grads, q1_grads, q1);
        let mut aux_critic_loss = None;
        if let (Some(enc), Some(_)) = (&self.critic.encoder, d_z_cols) {
            sum_pair(&ws.q[0].d_input, &ws.q[1].d_input, &mut ws.d_z);
            // The critic's auxiliary head reads the same z (its encoder before this step).
            if let (Some(aux), Some(targets)) = (&mut self.aux, aux_targets)
                && let Some((p, head)) = &mut aux.critic
            {
                let z = enc.z(&ws.critic_enc, t_len);
                let loss = aux_step(
                    head,
                    p,
                    z,
                    net.z_dim,
                    batch,
                    targets,
                    aux.weight,
                    &mut aux.work,
                    &mut ws.d_z,
                );
                p.adam(self.config.learning_rate);
                aux_critic_loss = Some(f64::from(loss));
            }
            enc.backward(
                &self.critic_p.values,
                &mut self.critic_p.grads,
                win,
                b,
                t_len,
                &ws.d_z,
                &mut ws.critic_enc,
                &mut ws.scratch,
                parallel,
            );
        }
        self.critic_p.adam(self.config.learning_rate);

        // --- actor -------------------------------------------------------------------------------
        // The critic (just updated) is frozen: gradients reach the action, not its weights.
        if let Some(enc) = &self.critic.encoder {
            enc.forward(
                &self.critic_p.values,
                &[win],
                t_len,
                &mut ws.critic_enc,
                parallel,
            );
        }
        let z_c = critic_z(
            &self.critic,
            &self.actor,
            &ws.critic_enc,
            &ws.actor.enc,
            t_len,
            b,
        );
        q_input(
            &net,
            z_c,
            &batch.obs,
            &ws.action[..b * act],
            b,
            &mut ws.q_input,
        );
        let values = &self.critic_p.values;
        let [w0, w1] = &mut ws.q;
        let input = &ws.q_input;
        both(
            parallel,
            || q0.forward(values, input, b, &mut w0.tape),
            || q1.forward(values, input, b, &mut w1.tape),
        );
        let mut actor_loss = 0f32;
        for w in &mut ws.q {
            w.d_q.clear();
        }
        for i in 0..b {
            let (v1, v2) = (ws.q[0].tape.output()[i], ws.q[1].tape.output()[i]);
            actor_loss += ws.log_prob[i] * alpha32 - v1.min(v2);
            // d/dq_k of −mean(min(q1, q2)): −1/B on the smaller one, half each on a tie
            // (candle's minimum).
            let (s1, s2) = if v1 == v2 {
                (0.5, 0.5)
            } else if v1 < v2 {
                (1.0, 0.0)
            } else {
                (0.0, 1.0)
            };
            for (w, share) in ws.q.iter_mut().zip([s1, s2]) {
                w.d_q.push(-share / b as f32);
            }
        }
        actor_loss /= b as f32;
        // Only the action's columns of the input gradient: the features are detached.
        let f_dim = net.features_dim();
        let [w0, w1] = &mut ws.q;
        both(
            parallel,
            || action_grad(q0, values, input, b, f_dim..f_dim + act, w0),
            || action_grad(q1, values, input, b, f_dim..f_dim + act, w1),
        );
        sum_pair(&ws.q[0].d_input, &ws.q[1].d_input, &mut ws.d_action);
        let aux_loss = self.actor_backward(batch, win, alpha32, aux_targets);
        self.actor_p.adam(self.config.learning_rate);

        // --- target critic -------------------------------------------------------------------
        let tau = self.config.tau as f32;
        for &(t, shared, s) in &self.polyak {
            let src = if shared {
                &self.actor_p.values[s]
            } else {
                &self.critic_p.values[s]
            };
            kernels::polyak(&mut self.target_p.values[t], src, tau);
        }

        Ok(UpdateStats {
            qf1_loss: qf1_loss as f64,
            qf2_loss: qf2_loss as f64,
            qf1_values: q1_mean as f64,
            qf2_values: q2_mean as f64,
            actor_loss: actor_loss as f64,
            alpha,
            alpha_loss: alpha_loss as f64,
            aux_loss,
            aux_critic_loss,
        })
    }

    /// Backward of the actor loss mean(α·log π(a|s) − min Q(s, a)) through the squashing, the
    /// heads, the trunk and the encoder, given dL/da in `ws.d_action`; with auxiliary targets,
    /// the actor's auxiliary head's loss joins at z (returned, unweighted).
    fn actor_backward(
        &mut self,
        batch: &Batch,
        win: &[f32],
        alpha: f32,
        aux_targets: Option<&AuxTargets>,
    ) -> Option<f64> {
        let net = &self.net;
        let (b, act) = (batch.size, net.act_dim);
        let ws = &mut self.ws;
        let inv_b = 1.0 / b as f32;
        for k in 0..2 {
            ws.d_heads[k].clear();
            ws.d_heads[k].resize(b * act, 0.0);
        }
        for i in 0..b * act {
            let a = ws.action[i];
            let raw = ws.actor.log_std_raw[i];
            let log_std = raw.clamp(LOG_STD_MIN as f32, LOG_STD_MAX as f32);
            // log π = Σ −ε²/2 − log σ − ½log 2π − log(1 + ε_tanh − a²), a = tanh(μ + σ·ε).
            let d_logp = alpha * inv_b;
            let d_a = ws.d_action[i] + d_logp * 2.0 * a / (1.0 + TANH_EPS as f32 - a * a);
            let d_u = d_a * (1.0 - a * a);
            ws.d_heads[0][i] = d_u;
            let d_log_std = d_u * log_std.exp() * ws.noise[i] - d_logp;
            // Through the clamp: full gradient inside, half at a bound (candle's max/min), none out.
            let lo = LOG_STD_MIN as f32;
            let hi = LOG_STD_MAX as f32;
            let through = if raw > lo && raw < hi {
                1.0
            } else if raw == lo || raw == hi {
                0.5
            } else {
                0.0
            };
            ws.d_heads[1][i] = d_log_std * through;
        }
        let values = &self.actor_p.values;
        let grads = &mut self.actor_p.grads;
        let h = ws.actor.trunk.output();
        let hidden = self.actor.mean.n_in;
        ws.d_h.resize(b * hidden, 0.0);
        for (k, head) in [self.actor.mean, self.actor.log_std].iter().enumerate() {
            let (gw, gb) = pair_mut(grads, head.w, head.b);
            let d_h = InputGrad {
                out: &mut ws.d_h[..],
                cols: 0..hidden,
                accumulate: k > 0,
            };
            dense_backward(
                head.get(values),
                h,
                b,
                &ws.d_heads[k],
                Some((gw, gb)),
                Some(d_h),
            );
        }
        let windows = net.encoder.uses_window();
        let z_dim = net.z_dim;
        ws.d_z.resize(b * z_dim, 0.0);
        // d/dz only: the observation columns of the features need no gradient.
        let d_z = windows.then(|| InputGrad {
            out: &mut ws.d_z[..],
            cols: 0..z_dim,
            accumulate: false,
        });
        self.actor.trunk.backward(
            values,
            Some(grads),
            &ws.actor.features,
            b,
            &ws.actor.trunk,
            &ws.d_h,
            d_z,
            &mut ws.scratch,
        );
        let mut aux_loss = None;
        if let (Some(aux), Some(targets)) = (&mut self.aux, aux_targets) {
            // z of the current observations: the first B rows of the actor's 2B-row pass.
            let z = &self.actor.encoder.z(&ws.actor.enc, net.context_len)[..b * z_dim];
            let loss = aux_step(
                &aux.actor,
                &mut aux.actor_p,
                z,
                z_dim,
                batch,
                targets,
                aux.weight,
                &mut aux.work,
                &mut ws.d_z,
            );
            aux.actor_p.adam(self.config.learning_rate);
            aux_loss = Some(f64::from(loss));
        }
        if windows {
            self.actor.encoder.backward(
                values,
                grads,
                win,
                b,
                net.context_len,
                &ws.d_z,
                &mut ws.actor.enc,
                &mut ws.scratch,
                self.pool.is_some(),
            );
        }
        aux_loss
    }
}

/// The actor's forward over observation parts (stacked rows) and their windows: encoder, features
/// [z, obs], trunk, heads (`tape.mean`, `tape.log_std_raw`).
fn actor_forward(
    actor: &ActorNet,
    values: &[Vec<f32>],
    obs_parts: &[&[f32]],
    win_parts: &[&[f32]],
    t_len: usize,
    tape: &mut ActorTape,
    parallel: bool,
) {
    actor
        .encoder
        .forward(values, win_parts, t_len, &mut tape.enc, parallel);
    let z = actor.encoder.z(&tape.enc, t_len);
    let (z_dim, obs_dim) = (actor.z_dim, actor.obs_dim);
    tape.features.clear();
    let mut rows = 0;
    for part in obs_parts {
        for o in part.chunks_exact(obs_dim) {
            tape.features
                .extend_from_slice(&z[rows * z_dim..(rows + 1) * z_dim]);
            tape.features.extend_from_slice(o);
            rows += 1;
        }
    }
    actor
        .trunk
        .forward(values, &tape.features, rows, &mut tape.trunk);
    let h = tape.trunk.output();
    tape.mean.resize(rows * actor.mean.n_out, 0.0);
    tape.log_std_raw.resize(rows * actor.log_std.n_out, 0.0);
    dense_forward(actor.mean.get(values), h, rows, &mut tape.mean, false);
    dense_forward(
        actor.log_std.get(values),
        h,
        rows,
        &mut tape.log_std_raw,
        false,
    );
}

/// One Q-network's critic step: forward, ½·mean (q − y)² and mean q, then the backward pass into
/// `grads` and, when asked, the given input columns' gradient into `w.d_input`.
#[allow(clippy::too_many_arguments)]
fn critic_step(
    q: &Mlp,
    values: &[Vec<f32>],
    grads: &mut [Vec<f32>],
    input: &[f32],
    target: &[f32],
    b: usize,
    d_input_cols: Option<std::ops::Range<usize>>,
    w: &mut QWork,
) -> (f32, f32) {
    q.forward(values, input, b, &mut w.tape);
    let out = w.tape.output();
    // critic loss = ½(mean (q1 − y)² + mean (q2 − y)²): d/dq_k = (q_k − y)/B.
    let loss = out
        .iter()
        .zip(target)
        .map(|(q, y)| (q - y) * (q - y))
        .sum::<f32>()
        / b as f32;
    let mean = out.iter().sum::<f32>() / b as f32;
    w.d_q.clear();
    w.d_q
        .extend(out.iter().zip(target).map(|(q, y)| (q - y) / b as f32));
    let d_input = d_input_cols.map(|cols| {
        w.d_input.resize(b * cols.len(), 0.0);
        InputGrad {
            out: &mut w.d_input[..],
            cols,
            accumulate: false,
        }
    });
    q.backward(
        values,
        Some(grads),
        input,
        b,
        &w.tape,
        &w.d_q,
        d_input,
        &mut w.scratch,
    );
    (loss, mean)
}

/// A frozen Q-network's gradient with respect to the given input columns (the action), from
/// `w.d_q`, into `w.d_input`.
fn action_grad(
    q: &Mlp,
    values: &[Vec<f32>],
    input: &[f32],
    b: usize,
    cols: std::ops::Range<usize>,
    w: &mut QWork,
) {
    w.d_input.resize(b * cols.len(), 0.0);
    let d_input = InputGrad {
        out: &mut w.d_input[..],
        cols,
        accumulate: false,
    };
    q.backward(
        values,
        None,
        input,
        b,
        &w.tape,
        &w.d_q,
        Some(d_input),
        &mut w.scratch,
    );
}

/// `out = a + b`, elementwise.
fn sum_pair(a: &[f32], b: &[f32], out: &mut Vec<f32>) {
    out.clear();
    out.extend(a.iter().zip(b).map(|(x, y)| x + y));
}

/// Squashed-Gaussian sample for every row: a = tanh(μ + σ·ε) and log π(a) with the tanh correction.
fn sample(
    mean: &[f32],
    log_std_raw: &[f32],
    noise: &[f32],
    act: usize,
    action: &mut Vec<f32>,
    log_prob: &mut Vec<f32>,
) {
    let rows = mean.len() / act;
    action.resize(rows * act, 0.0);
    log_prob.resize(rows, 0.0);
    let half_log_2pi = (0.5 * (2.0 * std::f64::consts::PI).ln()) as f32;
    for (r, lp_out) in log_prob.iter_mut().enumerate().take(rows) {
        let mut lp = 0f32;
        for j in r * act..(r + 1) * act {
            let log_std = log_std_raw[j].clamp(LOG_STD_MIN as f32, LOG_STD_MAX as f32);
            let a = (mean[j] + log_std.exp() * noise[j]).tanh();
            action[j] = a;
            let gaussian = noise[j] * noise[j] * -0.5 - log_std - half_log_2pi;
            let correction = (-(a * a) + (1.0 + TANH_EPS) as f32).ln();
            lp += gaussian - correction;
        }
        *lp_out = lp;
    }
}

/// The critic's input [features, action] for B rows: features are [z, obs] (or obs alone).
fn q_input(net: &NetConfig, z: &[f32], obs: &[f32], action: &[f32], b: usize, out: &mut Vec<f32>) {
    let (o, a) = (net.obs_dim, net.act_dim);
    let z_dim = if net.encoder.uses_window() {
        net.z_dim
    } else {
        0
    };
    out.clear();
    for i in 0..b {
        out.extend_from_slice(&z[i * z_dim..(i + 1) * z_dim]);
        out.extend_from_slice(&obs[i * o..(i + 1) * o]);
        out.extend_from_slice(&action[i * a..(i + 1) * a]);
    }
}

/// The critic's z for the B rows of the last critic-encoder forward, or with a shared encoder
/// the actor's z of the current observations (read detached).
fn critic_z<'a>(
    critic: &CriticNet,
    actor: &ActorNet,
    critic_tape: &'a EncoderTape,
    actor_tape: &'a EncoderTape,
    t_len: usize,
    b: usize,
) -> &'a [f32] {
    match &critic.encoder {
        Some(enc) => enc.z(critic_tape, t_len),
        None => &actor.encoder.z(actor_tape, t_len)[..b * actor.z_dim],
    }
}
