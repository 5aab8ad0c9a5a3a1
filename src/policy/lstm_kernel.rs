//! The LSTM recurrence as one fused candle op, forward and backward (BPTT).
//!
//! Why: built from candle's generic ops, one 16-step LSTM is ~230 graph nodes; each `narrow`
//! backward pads to the full sequence (O(T²) memory traffic) and glibc's scalar `tanhf` alone
//! took a quarter of the update time. Here the input projection stays one batched matmul (done
//! by the caller in candle), and this op runs the recurrence with the same `gemm` kernels candle
//! uses plus fused gate arithmetic. The backward recomputes the forward (cheaper than keeping
//! activations alive in the graph) and returns gradients for the projected inputs and W_hh.

use candle_core::{CpuStorage, CustomOp2, Layout, Result, Shape, Tensor, bail};

use super::gemm::matmul;
use super::simd::vectorised;

/// Gate order (PyTorch's): input, forget, cell, output.
#[derive(Debug, Clone, Copy)]
pub struct LstmRecurrence;

/// Applies the fused recurrence with gradient tracking.
pub fn lstm_recurrence(projected: &Tensor, w_hh: &Tensor) -> Result<Tensor> {
    projected
        .contiguous()?
        .apply_op2(&w_hh.contiguous()?, LstmRecurrence)
}

/// exp(x) as 2ⁿ·p(r), r = x − n·ln 2, with Cephes' expf polynomial (relative error ~1e-7).
/// Unlike libm's `expf` it inlines, so the gate loops below vectorise (16 or 8 lanes wide,
/// [`super::simd`]).
#[inline(always)]
fn exp(x: f32) -> f32 {
    let x = x.clamp(-87.0, 88.0);
    // Round to nearest by adding and removing 1.5·2²³ (no libm call, so it vectorises); the
    // sum's low mantissa bits then hold n as an integer.
    const ROUND: f32 = 12_582_912.0;
    let shifted = x * std::f32::consts::LOG2_E + ROUND;
    let n = shifted - ROUND;
    // Separate multiplies and adds, no FMA: a checkpoint's actions stay bit-identical across
    // CPUs and across versions of this kernel.
    let r = x - n * 0.693_359_4 + n * 2.121_944_4e-4;
    let mut p = 1.987_569_1e-4_f32;
    p = p * r + 1.398_199_9e-3;
    p = p * r + 8.333_452e-3;
    p = p * r + 4.166_579_6e-2;
    p = p * r + 1.666_666_5e-1;
    p = p * r + 0.5;
    let e = p * r * r + r + 1.0;
    // 2ⁿ from n's bits with integer arithmetic: `n as i32` is a saturating cast that does not
    // vectorise, and n ∈ [−126, 127] needs no saturation.
    let n_int = shifted.to_bits().wrapping_sub(ROUND.to_bits());
    e * f32::from_bits(n_int.wrapping_add(127) << 23)
}

#[inline(always)]
fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + exp(-x))
}

/// tanh through exp: glibc's `tanhf` goes through `expm1f` and is several times slower.
#[inline(always)]
pub(crate) fn tanh(x: f32) -> f32 {
    1.0 - 2.0 / (exp(2.0 * x) + 1.0)
}

/// One batch row of gate pre-activations (i, f, g, o, each H wide) → activations in place, new
/// cell and hidden state.
#[inline(always)]
fn cell_forward_row(gates: &mut [f32], c_prev: &[f32], c_next: &mut [f32], h_next: &mut [f32]) {
    let h = c_prev.len();
    // Every slice re-cut to exactly H (or 4H): the compiler then drops the bounds checks and
    // vectorises the loop.
    let (gi, rest) = gates[..4 * h].split_at_mut(h);
    let (gf, rest) = rest.split_at_mut(h);
    let (gg, go) = rest.split_at_mut(h);
    let (c_next, h_next) = (&mut c_next[..h], &mut h_next[..h]);
    for j in 0..h {
        let i = sigmoid(gi[j]);
        let f = sigmoid(gf[j]);
        let g = tanh(gg[j]);
        let o = sigmoid(go[j]);
        let c = f * c_prev[j] + i * g;
        c_next[j] = c;
        h_next[j] = o * tanh(c);
        (gi[j], gf[j], gg[j], go[j]) = (i, f, g, o);
    }
}

/// Backward of [`cell_forward_row`]: writes d(pre-activations) and updates d_c to d c_prev.
#[inline(always)]
fn cell_backward_row(
    act: &[f32],
    c_prev: &[f32],
    c: &[f32],
    d_h: &[f32],
    d_c: &mut [f32],
    d_gates: &mut [f32],
) {
    let h = c.len();
    let (c_prev, d_h, d_c) = (&c_prev[..h], &d_h[..h], &mut d_c[..h]);
    let (ai, rest) = act[..4 * h].split_at(h);
    let (af, rest) = rest.split_at(h);
    let (ag, ao) = rest.split_at(h);
    let (di, rest) = d_gates[..4 * h].split_at_mut(h);
    let (df, rest) = rest.split_at_mut(h);
    let (dg, d_o) = rest.split_at_mut(h);
    for j in 0..h {
        let (i, f, g, o) = (ai[j], af[j], ag[j], ao[j]);
        let tc = tanh(c[j]);
        let dc = d_c[j] + d_h[j] * o * (1.0 - tc * tc);
        di[j] = dc * g * i * (1.0 - i);
        df[j] = dc * c_prev[j] * f * (1.0 - f);
        dg[j] = dc * i * (1.0 - g * g);
        d_o[j] = d_h[j] * tc * o * (1.0 - o);
        d_c[j] = dc * f;
    }
}

vectorised! {
    /// One time step's cell update for all rows: gates (B, 4H) hold the pre-activations and
    /// become the activations; c_next and h_next are (B, H).
    pub(crate) fn step_forward(
        gates: &mut [f32],
        c_prev: &[f32],
        c_next: &mut [f32],
        h_next: &mut [f32],
        h: usize,
    ) {
        for (r, g) in gates.chunks_exact_mut(4 * h).enumerate() {
            let rows = r * h..(r + 1) * h;
            cell_forward_row(
                g,
                &c_prev[rows.clone()],
                &mut c_next[rows.clone()],
                &mut h_next[rows],
            );
        }
    }
}

vectorised! {
    /// Backward of [`step_forward`] for all rows: d(pre-activations) into d_gates, d_c updated
    /// to d c_prev.
    pub(crate) fn step_backward(
        act: &[f32],
        c_prev: &[f32],
        c: &[f32],
        d_h: &[f32],
        d_c: &mut [f32],
        d_gates: &mut [f32],
        h: usize,
    ) {
        for (r, dg) in d_gates.chunks_exact_mut(4 * h).enumerate() {
            let rows = r * h..(r + 1) * h;
            let a = &act[r * 4 * h..(r + 1) * 4 * h];
            cell_backward_row(
                a,
                &c_prev[rows.clone()],
                &c[rows.clone()],
                &d_h[rows.clone()],
                &mut d_c[rows],
                dg,
            );
        }
    }
}

/// Everything the forward produced, per step, for the backward.
struct Trace {
    /// Activated gates per step: (T, B, 4H) as i, f, g, o.
    gates: Vec<f32>,
    /// Cell states c_0..c_T: (T + 1, B, H), c_0 = 0.
    cells: Vec<f32>,
    /// Hidden states h_0..h_T: (T + 1, B, H), h_0 = 0.
    hidden: Vec<f32>,
}

fn forward(projected: &[f32], w_hh: &[f32], t_len: usize, b: usize, h: usize) -> Trace {
    let g4 = 4 * h;
    let mut gates = projected.to_vec();
    let mut cells = vec![0f32; (t_len + 1) * b * h];
    let mut hidden = vec![0f32; (t_len + 1) * b * h];
    for t in 0..t_len {
        let g = &mut gates[t * b * g4..(t + 1) * b * g4];
        if t > 0 {
            // gates += h_t · W_hh (h_0 = 0 makes the first step's product zero).
            matmul(
                g,
                true,
                (b, g4, h),
                &hidden[t * b * h..(t + 1) * b * h],
                (h, 1),
                w_hh,
                (g4, 1),
            );
        }
        let (c_prev, c_next) = cells[t * b * h..(t + 2) * b * h].split_at_mut(b * h);
        let h_next = &mut hidden[(t + 1) * b * h..(t + 2) * b * h];
        step_forward(g, c_prev, c_next, h_next, h);
    }
    Trace {
        gates,
        cells,
        hidden,
    }
}

/// Returns (d projected (T, B, 4H), d W_hh (H, 4H)) for upstream gradient `d_h_last` (B, H).
fn backward(
    projected: &[f32],
    w_hh: &[f32],
    d_h_last: &[f32],
    t_len: usize,
    b: usize,
    h: usize,
) -> (Vec<f32>, Vec<f32>) {
    let g4 = 4 * h;
    let trace = forward(projected, w_hh, t_len, b, h);
    let mut d_projected = vec![0f32; t_len * b * g4];
    let mut d_w_hh = vec![0f32; h * g4];
    let mut d_h = d_h_last.to_vec();
    let mut d_c = vec![0f32; b * h];
    for t in (0..t_len).rev() {
        let act = &trace.gates[t * b * g4..(t + 1) * b * g4];
        let c_prev = &trace.cells[t * b * h..(t + 1) * b * h];
        let c = &trace.cells[(t + 1) * b * h..(t + 2) * b * h];
        let d_g = &mut d_projected[t * b * g4..(t + 1) * b * g4];
        step_backward(act, c_prev, c, &d_h, &mut d_c, d_g, h);
        if t > 0 {
            let h_prev = &trace.hidden[t * b * h..(t + 1) * b * h];
            // dW_hh += h_{t}ᵀ · dG  (H×B · B×4H)
            matmul(&mut d_w_hh, true, (h, g4, b), h_prev, (1, h), d_g, (g4, 1));
            // dh_{t} = dG · W_hhᵀ  (B×4H · 4H×H)
            matmul(&mut d_h, false, (b, h, g4), d_g, (g4, 1), w_hh, (1, g4));
        }
    }
    (d_projected, d_w_hh)
}

fn dims(l1: &Layout, l2: &Layout) -> Result<(usize, usize, usize)> {
    let (t_len, b, g4) = l1.shape().dims3()?;
    let (h, g4_w) = l2.shape().dims2()?;
    if g4 != 4 * h || g4_w != g4 {
        bail!(
            "lstm recurrence: projected {:?} and W_hh {:?} disagree",
            l1.shape(),
            l2.shape()
        );
    }
    Ok((t_len, b, h))
}

fn contiguous_f32<'a>(s: &'a CpuStorage, l: &Layout) -> Result<&'a [f32]> {
    let CpuStorage::F32(v) = s else {
        bail!("lstm recurrence: only f32 is supported")
    };
    match l.contiguous_offsets() {
        Some((start, end)) => Ok(&v[start..end]),
        None => bail!("lstm recurrence: inputs must be contiguous"),
    }
}

impl CustomOp2 for LstmRecurrence {
    fn name(&self) -> &'static str {
        "lstm-recurrence"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (t_len, b, h) = dims(l1, l2)?;
        let trace = forward(
            contiguous_f32(s1, l1)?,
            contiguous_f32(s2, l2)?,
            t_len,
            b,
            h,
        );
        let last = trace.hidden[t_len * b * h..].to_vec();
        Ok((CpuStorage::F32(last), Shape::from((b, h))))
    }

    fn bwd(
        &self,
        arg1: &Tensor,
        arg2: &Tensor,
        _res: &Tensor,
        grad_res: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let (t_len, b, g4) = arg1.dims3()?;
        let h = g4 / 4;
        let projected = arg1.flatten_all()?.to_vec1::<f32>()?;
        let w_hh = arg2.flatten_all()?.to_vec1::<f32>()?;
        let d_h = grad_res.flatten_all()?.to_vec1::<f32>()?;
        let (d_projected, d_w_hh) = backward(&projected, &w_hh, &d_h, t_len, b, h);
        Ok((
            Some(Tensor::from_vec(
                d_projected,
                (t_len, b, g4),
                arg1.device(),
            )?),
            Some(Tensor::from_vec(d_w_hh, (h, g4), arg2.device())?),
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn polynomial_exp_matches_std() {
        for i in -870..=880 {
            let x = i as f32 * 0.1;
            let rel = (exp(x) - x.exp()).abs() / x.exp();
            assert!(rel < 3e-7, "x = {x}: {} vs {}", exp(x), x.exp());
        }
    }

    #[test]
    fn exp_based_tanh_matches_std() {
        for i in -400..=400 {
            let x = i as f32 * 0.05;
            assert!((tanh(x) - x.tanh()).abs() < 2e-7, "x = {x}");
        }
        assert_eq!(tanh(100.0), 1.0);
        assert_eq!(tanh(-100.0), -1.0);
    }

    /// Pre-activations and states across the gates' whole range: ordinary values, the
    /// saturated tails, the exp clamp's edges, zeros of both signs.
    fn awkward_values(n: usize, seed: u64) -> Vec<f32> {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let edges = [
            0.0, -0.0, 1e-30, -1e-30, 40.0, -40.0, 87.5, -87.5, 200.0, -200.0,
        ];
        (0..n)
            .map(|i| match i % 7 {
                0 => edges[(i / 7) % edges.len()],
                1 => rng.random_range(-30.0..30.0),
                _ => rng.random_range(-4.0..4.0),
            })
            .collect()
    }

    #[test]
    fn every_simd_tier_gives_the_same_bits() {
        use crate::policy::simd::{call_tier, tiers};
        // H = 32 as the encoders use, 257 rows (an odd tail), and H = 5 (no full vector).
        for (b, h) in [(257, 32), (3, 5)] {
            let gates = awkward_values(b * 4 * h, 1);
            let c_prev = awkward_values(b * h, 2);
            let d_h = awkward_values(b * h, 3);
            let d_c = awkward_values(b * h, 4);
            let run = |tier: &str| {
                let (mut g, mut c, mut hn) = (gates.clone(), vec![0.0; b * h], vec![0.0; b * h]);
                call_tier!(tier, step_forward, &mut g, &c_prev, &mut c, &mut hn, h);
                let (mut dc, mut dg) = (d_c.clone(), vec![0.0; b * 4 * h]);
                call_tier!(
                    tier,
                    step_backward,
                    &g,
                    &c_prev,
                    &c,
                    &d_h,
                    &mut dc,
                    &mut dg,
                    h
                );
                [g, c, hn, dc, dg].map(|v| v.iter().map(|x| x.to_bits()).collect::<Vec<u32>>())
            };
            let plain = run("plain");
            assert!(plain[2].iter().all(|&x| f32::from_bits(x).is_finite()));
            for tier in tiers() {
                assert!(
                    run(tier) == plain,
                    "{tier} differs from plain (B = {b}, H = {h})"
                );
            }
        }
    }
}
