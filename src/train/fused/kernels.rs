//! The arithmetic of the fused update on host slices: dense layers forward and backward, the
//! LSTM and window-MLP encoders, Adam. Row-major everywhere; weights are (in, out) as in the
//! checkpoints, so a forward pass is `x · W + b` with no transpose.

use crate::policy::gemm::matmul;
use crate::policy::lstm_kernel;
use crate::policy::simd::vectorised;

/// `c (m×n) [+]= a (m×k) · b (k×n)`, all row-major and contiguous.
pub fn mm(c: &mut [f32], acc: bool, (m, n, k): (usize, usize, usize), a: &[f32], b: &[f32]) {
    if m * n * k > 0 {
        matmul(c, acc, (m, n, k), a, (k, 1), b, (n, 1));
    }
}

/// `c (m×n) [+]= aᵀ · b` with `a` stored (k×m) and `b` (k×n), row-major.
pub fn mm_tn(c: &mut [f32], acc: bool, (m, n, k): (usize, usize, usize), a: &[f32], b: &[f32]) {
    if m * n * k > 0 {
        matmul(c, acc, (m, n, k), a, (1, m), b, (n, 1));
    }
}

/// `c (m×n) [+]= a · bᵀ` with `a` stored (m×k) and `b` (n×k), row-major.
pub fn mm_nt(c: &mut [f32], acc: bool, (m, n, k): (usize, usize, usize), a: &[f32], b: &[f32]) {
    if m * n * k > 0 {
        matmul(c, acc, (m, n, k), a, (k, 1), b, (1, k));
    }
}

/// One linear layer's parameters, borrowed.
#[derive(Clone, Copy)]
pub struct DenseRef<'a> {
    pub w: &'a [f32],
    pub b: &'a [f32],
    pub n_in: usize,
    pub n_out: usize,
}

/// `y = x · W + b`, then ReLU if asked; `x` is rows × n_in.
pub fn dense_forward(d: DenseRef, x: &[f32], rows: usize, y: &mut [f32], relu: bool) {
    let y = &mut y[..rows * d.n_out];
    for row in y.chunks_exact_mut(d.n_out) {
        row.copy_from_slice(d.b);
    }
    mm(y, true, (rows, d.n_out, d.n_in), &x[..rows * d.n_in], d.w);
    if relu {
        relu_in_place(y);
    }
}

vectorised! {
    /// `y = max(y, 0)` in place.
    pub fn relu_in_place(y: &mut [f32]) {
        for v in y.iter_mut() {
            *v = v.max(0.0);
        }
    }
}

/// Which columns of a layer's input gradient to compute, and where: `out` is rows × cols.len(),
/// overwritten or accumulated into. A critic needs d/d(action) or d/dz only, not d/d(obs).
pub struct InputGrad<'a> {
    pub out: &'a mut [f32],
    pub cols: std::ops::Range<usize>,
    pub accumulate: bool,
}

/// Backward of one linear layer given `dy` (rows × n_out, already through the activation):
/// weight and bias gradients (overwritten) when `grads` is given, and the asked columns of
/// `dx = dy · Wᵀ`.
pub fn dense_backward(
    d: DenseRef,
    x: &[f32],
    rows: usize,
    dy: &[f32],
    grads: Option<(&mut [f32], &mut [f32])>,
    dx: Option<InputGrad>,
) {
    let dy = &dy[..rows * d.n_out];
    if let Some((gw, gb)) = grads {
        mm_tn(gw, false, (d.n_in, d.n_out, rows), &x[..rows * d.n_in], dy);
        column_sums(dy, d.n_out, gb);
    }
    if let Some(InputGrad {
        out,
        cols,
        accumulate,
    }) = dx
    {
        // Columns a..b of dy · Wᵀ are dy · (rows a..b of W)ᵀ, a contiguous block of W.
        let width = cols.len();
        let w = &d.w[cols.start * d.n_out..cols.end * d.n_out];
        mm_nt(
            &mut out[..rows * width],
            accumulate,
            (rows, width, d.n_out),
            dy,
            w,
        );
    }
}

vectorised! {
    /// `tanh` in place with the LSTM gates' exp-based tanh, vectorised (the window-MLP encoder's
    /// z; libm's `tanhf` was 5 % of its update).
    pub fn tanh_in_place(v: &mut [f32]) {
        for x in v.iter_mut() {
            *x = lstm_kernel::tanh(*x);
        }
    }
}

vectorised! {
    /// `out[j] = Σ_rows m[row][j]`.
    pub fn column_sums(m: &[f32], cols: usize, out: &mut [f32]) {
        out.fill(0.0);
        for row in m.chunks_exact(cols) {
            for (o, v) in out.iter_mut().zip(row) {
                *o += v;
            }
        }
    }
}

vectorised! {
    /// Zeroes `d` where the ReLU output `y` is not positive (candle's mask is `x ≥ 0`; the two
    /// differ only where a pre-activation is exactly 0). A select, not a branch: it vectorises.
    pub fn relu_backward(y: &[f32], d: &mut [f32]) {
        for (g, v) in d.iter_mut().zip(y) {
            *g = if *v > 0.0 { *g } else { 0.0 };
        }
    }
}

/// The per-step state an LSTM forward leaves for its backward, time-major, for `rows` rows (the
/// buffers may be longer: a tape keeps its largest size).
#[derive(Default)]
pub struct LstmTape {
    /// Gate pre-activations, then (after the step) activations i, f, g, o: (T, R, 4H).
    pub gates: Vec<f32>,
    /// c_0..c_T: (T + 1, R, H), c_0 = 0.
    pub cells: Vec<f32>,
    /// h_0..h_T: (T + 1, R, H), h_0 = 0; h_T is z.
    pub hidden: Vec<f32>,
    pub rows: usize,
}

/// An LSTM's parameters, borrowed (PyTorch's gate order, weights (in, 4H) and (H, 4H)).
#[derive(Clone, Copy)]
pub struct LstmRef<'a> {
    pub w_ih: &'a [f32],
    pub w_hh: &'a [f32],
    pub b_ih: &'a [f32],
    pub b_hh: &'a [f32],
    pub input: usize,
    pub hidden: usize,
}

/// Runs `a` and `b` on two of the pool's threads when `parallel`, else one after the other.
pub fn both<A: Send, B: Send>(
    parallel: bool,
    a: impl FnOnce() -> A + Send,
    b: impl FnOnce() -> B + Send,
) -> (A, B) {
    if parallel {
        rayon::join(a, b)
    } else {
        (a(), b())
    }
}

/// Each step's block of a time-major buffer (steps × rows × width), cut at row `at`: the first
/// `at` rows of every step, and the rest.
fn split_rows(
    buffer: &mut [f32],
    (steps, rows, width): (usize, usize, usize),
    at: usize,
) -> (Vec<&mut [f32]>, Vec<&mut [f32]>) {
    buffer[..steps * rows * width]
        .chunks_exact_mut(rows * width)
        .map(|step| step.split_at_mut(at * width))
        .unzip()
}

/// Where a pass over `rows` rows is cut between two threads (all rows on one without).
fn row_cut(parallel: bool, rows: usize) -> usize {
    if parallel { rows / 2 } else { rows }
}

/// Runs the LSTM from zero state over windows given in parts (each part rows_i × T × input,
/// batch-major as the replay stores them); the parts' rows are stacked in order. The input
/// projection is one GEMM per step and part, written straight into the time-major gates.
///
/// Given (windows, next windows) — every next window is its window shifted by one step plus the
/// new (obs, action) — the second part's projection of steps 0..T−1 is the first part's of steps
/// 1..T, copied: 17 distinct steps are projected instead of 32.
///
/// `parallel` (inside the update's thread pool): the projection's steps are shared between two
/// threads, then the recurrence's rows (rows are independent at every step). Each element is
/// the same sum in the same order either way, so the bits do not depend on it (tested).
pub fn lstm_forward(
    l: LstmRef,
    parts: &[&[f32]],
    t_len: usize,
    tape: &mut LstmTape,
    parallel: bool,
) {
    let (h, e) = (l.hidden, l.input);
    let g4 = 4 * h;
    let counts: Vec<usize> = parts.iter().map(|p| p.len() / (t_len * e)).collect();
    let rows: usize = counts.iter().sum();
    tape.rows = rows;
    // Grown, never shrunk: one tape serves 512-row and 256-row passes in turn, and growing back
    // zero-filled it each time (3 % of an LSTM update). Every use below is sliced by `rows`.
    for (buffer, len) in [
        (&mut tape.gates, t_len * rows * g4),
        (&mut tape.cells, (t_len + 1) * rows * h),
        (&mut tape.hidden, (t_len + 1) * rows * h),
    ] {
        if buffer.len() < len {
            buffer.resize(len, 0.0);
        }
    }
    tape.cells[..rows * h].fill(0.0);
    tape.hidden[..rows * h].fill(0.0);
    let shifted =
        parts.len() == 2 && counts[0] == counts[1] && is_shift(parts[0], parts[1], t_len, e);
    // Gates start at b_ih + b_hh and the projection accumulates onto them: the same sums, in the
    // same order, as the reference's (x·W_ih) + b.
    let bias: Vec<f32> = l.b_ih.iter().zip(l.b_hh).map(|(a, b)| a + b).collect();
    let project = |t: usize, gates: &mut [f32]| {
        let mut offset = 0;
        for (k, part) in parts.iter().enumerate() {
            let n = counts[k];
            let copied = shifted && k == 1 && t + 1 < t_len;
            if !copied {
                let block = &mut gates[offset * g4..(offset + n) * g4];
                for row in block.chunks_exact_mut(g4) {
                    row.copy_from_slice(&bias);
                }
                // Row b of step t is part[b·T·E + t·E ..]: a strided view, no copy.
                matmul(
                    block,
                    true,
                    (n, g4, e),
                    &part[t * e..],
                    (t_len * e, 1),
                    l.w_ih,
                    (g4, 1),
                );
            }
            offset += n;
        }
    };
    let mut steps: Vec<&mut [f32]> = tape.gates[..t_len * rows * g4]
        .chunks_exact_mut(rows * g4)
        .collect();
    let (early, late) = steps.split_at_mut(if parallel { t_len / 2 } else { t_len });
    both(
        parallel,
        || {
            early
                .iter_mut()
                .enumerate()
                .for_each(|(t, g)| project(t, g))
        },
        || {
            let first = t_len - late.len();
            late.iter_mut()
                .enumerate()
                .for_each(|(t, g)| project(first + t, g))
        },
    );
    if shifted {
        let n = counts[0];
        for t in 0..t_len - 1 {
            // Step t of the next windows = step t + 1 of the windows (its projection, bias in).
            let (now, later) = tape.gates.split_at_mut((t + 1) * rows * g4);
            now[t * rows * g4 + n * g4..(t + 1) * rows * g4].copy_from_slice(&later[..n * g4]);
        }
    }
    let at = row_cut(parallel, rows);
    let (mut gates_a, mut gates_b) = split_rows(&mut tape.gates, (t_len, rows, g4), at);
    let (mut cells_a, mut cells_b) = split_rows(&mut tape.cells, (t_len + 1, rows, h), at);
    let (mut hidden_a, mut hidden_b) = split_rows(&mut tape.hidden, (t_len + 1, rows, h), at);
    both(
        parallel,
        || recur(l, &mut gates_a, &mut cells_a, &mut hidden_a, at),
        || recur(l, &mut gates_b, &mut cells_b, &mut hidden_b, rows - at),
    );
}

/// The recurrence over some rows: `gates` per step (projected inputs in, activations out),
/// `cells` and `hidden` per step from the zero state.
fn recur(
    l: LstmRef,
    gates: &mut [&mut [f32]],
    cells: &mut [&mut [f32]],
    hidden: &mut [&mut [f32]],
    rows: usize,
) {
    let (h, g4) = (l.hidden, 4 * l.hidden);
    for (t, g) in gates.iter_mut().enumerate() {
        if t > 0 {
            mm(g, true, (rows, g4, h), &hidden[t][..], l.w_hh);
        }
        let (c_done, c_next) = cells.split_at_mut(t + 1);
        let h_next = &mut hidden[t + 1];
        lstm_kernel::step_forward(g, &c_done[t][..], &mut c_next[0][..], h_next, h);
    }
}

/// Whether every window of `next` is the same row of `now` moved one step (bit for bit).
fn is_shift(now: &[f32], next: &[f32], t_len: usize, e: usize) -> bool {
    let width = t_len * e;
    now.chunks_exact(width)
        .zip(next.chunks_exact(width))
        .all(|(a, b)| {
            a[e..]
                .iter()
                .zip(&b[..width - e])
                .all(|(x, y)| x.to_bits() == y.to_bits())
        })
}

/// z = h_T of the last forward, rows × H.
pub fn lstm_output(tape: &LstmTape, t_len: usize, h: usize) -> &[f32] {
    &tape.hidden[t_len * tape.rows * h..(t_len + 1) * tape.rows * h]
}

/// Gradients of an LSTM's four parameters (overwritten) from `d_z` for the first
/// `rows` rows of the tape, whose inputs were `window` (rows × T × input).
///
/// First the gates' gradients at every step, back through time (rows are independent, so with
/// `parallel` two threads take half the rows each), then the weights' gradients step by step in
/// the same order as ever (with `parallel`, W_ih's and the bias's beside W_hh's): the same bits
/// on one thread or two.
#[allow(clippy::too_many_arguments)]
pub fn lstm_backward(
    l: LstmRef,
    tape: &LstmTape,
    window: &[f32],
    rows: usize,
    t_len: usize,
    d_z: &[f32],
    scratch: &mut LstmScratch,
    grads: [&mut [f32]; 4],
    parallel: bool,
) {
    let (h, e) = (l.hidden, l.input);
    let g4 = 4 * h;
    let stride = tape.rows;
    let [g_w_ih, g_w_hh, g_b_ih, g_b_hh] = grads;
    scratch.d_h.clear();
    scratch.d_h.extend_from_slice(&d_z[..rows * h]);
    scratch.d_c.clear();
    scratch.d_c.resize(rows * h, 0.0);
    if scratch.d_gates.len() < t_len * rows * g4 {
        scratch.d_gates.resize(t_len * rows * g4, 0.0);
    }
    let at = row_cut(parallel, rows);
    {
        let (mut d_gates_a, mut d_gates_b) =
            split_rows(&mut scratch.d_gates, (t_len, rows, g4), at);
        let (d_h_a, d_h_b) = scratch.d_h.split_at_mut(at * h);
        let (d_c_a, d_c_b) = scratch.d_c.split_at_mut(at * h);
        let through_time =
            |first: usize, d_g: &mut [&mut [f32]], d_h: &mut [f32], d_c: &mut [f32]| {
                let n = d_h.len() / h;
                for t in (0..t_len).rev() {
                    let at_step = |width: usize, step: usize| {
                        let start = (step * stride + first) * width;
                        start..start + n * width
                    };
                    let act = &tape.gates[at_step(g4, t)];
                    let c_prev = &tape.cells[at_step(h, t)];
                    let c = &tape.cells[at_step(h, t + 1)];
                    lstm_kernel::step_backward(act, c_prev, c, d_h, d_c, d_g[t], h);
                    if t > 0 {
                        mm_nt(d_h, false, (n, h, g4), d_g[t], l.w_hh);
                    }
                }
            };
        both(
            parallel,
            || through_time(0, &mut d_gates_a, d_h_a, d_c_a),
            || through_time(at, &mut d_gates_b, d_h_b, d_c_b),
        );
    }
    let d_gates = &scratch.d_gates[..t_len * rows * g4];
    let step = |t: usize| &d_gates[t * rows * g4..(t + 1) * rows * g4];
    both(
        parallel,
        || {
            g_w_ih.fill(0.0);
            g_b_ih.fill(0.0);
            for t in (0..t_len).rev() {
                let d_g = step(t);
                // dW_ih += x_tᵀ · dG (input rows strided by T·E), db += Σ_rows dG.
                matmul(
                    g_w_ih,
                    true,
                    (e, g4, rows),
                    &window[t * e..],
                    (1, t_len * e),
                    d_g,
                    (g4, 1),
                );
                for row in d_g.chunks_exact(g4) {
                    for (o, v) in g_b_ih.iter_mut().zip(row) {
                        *o += v;
                    }
                }
            }
        },
        || {
            g_w_hh.fill(0.0);
            for t in (1..t_len).rev() {
                let h_prev = &tape.hidden[t * stride * h..t * stride * h + rows * h];
                mm_tn(g_w_hh, true, (h, g4, rows), h_prev, step(t));
            }
        },
    );
    // b_ih and b_hh enter as one sum: the same gradient.
    g_b_hh.copy_from_slice(g_b_ih);
}

/// Buffers the LSTM backward reuses between calls.
#[derive(Default)]
pub struct LstmScratch {
    d_h: Vec<f32>,
    d_c: Vec<f32>,
    d_gates: Vec<f32>,
}

vectorised! {
    /// PyTorch's Adam (no weight decay) over one tensor, exactly as [`crate::train::adam::Adam`].
    pub fn adam_step(
        theta: &mut [f32],
        g: &[f32],
        m: &mut [f32],
        v: &mut [f32],
        step_size: f32,
        bc2_sqrt: f32,
        betas: (f32, f32, f32),
    ) {
        let (b1, b2, eps) = betas;
        let n = theta.len();
        let (g, m, v) = (&g[..n], &mut m[..n], &mut v[..n]);
        for i in 0..n {
            m[i] = b1 * m[i] + (1.0 - b1) * g[i];
            v[i] = b2 * v[i] + (1.0 - b2) * g[i] * g[i];
            let denom = v[i].sqrt() / bc2_sqrt + eps;
            theta[i] -= step_size * m[i] / denom;
        }
    }
}

vectorised! {
    /// target ← τ·source + (1 − τ)·target, as sac.rs's `polyak_update` (the reference path).
    pub fn polyak(target: &mut [f32], source: &[f32], tau: f32) {
        for (d, s) in target.iter_mut().zip(source) {
            *d = tau * s + (1.0 - tau) * *d;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn lstm_params(input: usize, hidden: usize) -> [Vec<f32>; 4] {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let mut draw = |n: usize| {
            (0..n)
                .map(|_| rng.random_range(-0.3..0.3))
                .collect::<Vec<f32>>()
        };
        [
            draw(input * 4 * hidden),
            draw(hidden * 4 * hidden),
            draw(4 * hidden),
            draw(4 * hidden),
        ]
    }

    /// Windows and their successors (shifted by one, a new last entry), as the replay builds them.
    fn windows(rows: usize, t_len: usize, e: usize) -> (Vec<f32>, Vec<f32>) {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(4);
        let now: Vec<f32> = (0..rows * t_len * e)
            .map(|_| rng.random_range(-1.0..1.0))
            .collect();
        let mut next = Vec::new();
        for w in now.chunks_exact(t_len * e) {
            next.extend_from_slice(&w[e..]);
            next.extend((0..e).map(|_| rng.random_range(-1.0f32..1.0)));
        }
        (now, next)
    }

    #[test]
    fn shared_projection_of_next_windows_changes_nothing() {
        let (rows, t_len, e, h) = (5, 4, 3, 8);
        let [w_ih, w_hh, b_ih, b_hh] = lstm_params(e, h);
        let l = LstmRef {
            w_ih: &w_ih,
            w_hh: &w_hh,
            b_ih: &b_ih,
            b_hh: &b_hh,
            input: e,
            hidden: h,
        };
        let (now, next) = windows(rows, t_len, e);
        assert!(is_shift(&now, &next, t_len, e));
        let mut broken = next.clone();
        broken[1] += 1.0;
        assert!(
            !is_shift(&now, &broken, t_len, e),
            "a changed entry is no shift"
        );
        let mut both = LstmTape::default();
        lstm_forward(l, &[&now, &next], t_len, &mut both, false);
        let z = lstm_output(&both, t_len, h).to_vec();
        for (k, part) in [&now, &next].iter().enumerate() {
            let mut alone = LstmTape::default();
            lstm_forward(l, &[part], t_len, &mut alone, false);
            let z_alone = lstm_output(&alone, t_len, h);
            let z_part = &z[k * rows * h..(k + 1) * rows * h];
            assert!(
                z_part
                    .iter()
                    .zip(z_alone)
                    .all(|(a, b)| a.to_bits() == b.to_bits()),
                "part {k}: the copied projection must equal the computed one bit for bit"
            );
        }
    }

    #[test]
    fn every_simd_tier_of_the_update_loops_gives_the_same_bits() {
        use crate::policy::simd::{call_tier, tiers};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
        // 1,027 values: whole 16- and 8-lane vectors and a tail; a few exact zeros (the ReLU
        // mask's edge) and large values (tanh saturates).
        let mut draw = |scale: f32| -> Vec<f32> {
            (0..1027)
                .map(|i| match i % 11 {
                    0 => 0.0,
                    1 => scale * 50.0,
                    _ => rng.random_range(-scale..scale),
                })
                .collect()
        };
        let (x, g, m0, v0) = (draw(3.0), draw(1.0), draw(0.1), draw(0.01));
        let v0: Vec<f32> = v0.iter().map(|v| v.abs()).collect();
        let run = |tier: &str| {
            let (mut theta, mut m, mut v) = (x.clone(), m0.clone(), v0.clone());
            call_tier!(
                tier,
                adam_step,
                &mut theta,
                &g,
                &mut m,
                &mut v,
                3e-4,
                0.7,
                (0.9, 0.999, 1e-8)
            );
            let mut target = g.clone();
            call_tier!(tier, polyak, &mut target, &x, 0.005);
            let mut relu = x.clone();
            call_tier!(tier, relu_in_place, &mut relu);
            let mut d = g.clone();
            call_tier!(tier, relu_backward, &x, &mut d);
            let mut t = x.clone();
            call_tier!(tier, tanh_in_place, &mut t);
            let mut sums = vec![0.0; 79];
            call_tier!(tier, column_sums, &x[..79 * 13], 79, &mut sums);
            [theta, m, v, target, relu, d, t, sums]
                .map(|v| v.iter().map(|x| x.to_bits()).collect::<Vec<u32>>())
        };
        let plain = run("plain");
        for tier in tiers() {
            assert!(run(tier) == plain, "{tier} differs from plain");
        }
    }
}
