//! f32 GEMM on host slices through the `gemm` crate (the kernels candle itself uses), with
//! explicit strides so transposed operands cost nothing. One thread unless the calling thread
//! asks for more ([`set_threads`]).

use std::cell::Cell;

thread_local! {
    static THREADS: Cell<usize> = const { Cell::new(1) };
}

/// How many threads the GEMMs called from this thread may use (1: this thread alone, the
/// default). Products large enough for `gemm` to split run their output tiles on rayon's pool;
/// every element's sum keeps its order, so results are the same for any count (tested).
pub fn set_threads(n: usize) {
    THREADS.with(|t| t.set(n.max(1)));
}

/// The calling thread's GEMM thread count.
pub fn threads() -> usize {
    THREADS.with(Cell::get)
}

/// `out (m×n) = [out +] a (m×k) · b (k×n)`, row-major unless strides say otherwise.
#[allow(clippy::too_many_arguments)]
pub(crate) fn matmul(
    out: &mut [f32],
    accumulate: bool,
    (m, n, k): (usize, usize, usize),
    a: &[f32],
    (a_rs, a_cs): (usize, usize),
    b: &[f32],
    (b_rs, b_cs): (usize, usize),
) {
    let last = |rows: usize, cols: usize, rs: usize, cs: usize| (rows - 1) * rs + (cols - 1) * cs;
    assert!(
        out.len() >= m * n && a.len() > last(m, k, a_rs, a_cs) && b.len() > last(k, n, b_rs, b_cs)
    );
    // SAFETY: the assert bounds every index gemm touches: dst m×n row-major, lhs m×k and rhs
    // k×n with the given strides, all within their slices; the slices do not alias.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            out.as_mut_ptr(),
            1,
            n as isize,
            accumulate,
            a.as_ptr(),
            a_cs as isize,
            a_rs as isize,
            b.as_ptr(),
            b_cs as isize,
            b_rs as isize,
            1.0,
            1.0,
            false,
            false,
            false,
            match threads() {
                1 => gemm::Parallelism::None,
                n => gemm::Parallelism::Rayon(n),
            },
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn product(threads: usize, (m, n, k): (usize, usize, usize)) -> Vec<f32> {
        // Values with full mantissas, so a changed summation order would show in the bits.
        let a: Vec<f32> = (0..m * k).map(|i| ((i as f32) * 0.618_034).sin()).collect();
        let b: Vec<f32> = (0..k * n).map(|i| ((i as f32) * 0.414_214).cos()).collect();
        let mut out = vec![0.5f32; m * n];
        set_threads(threads);
        matmul(&mut out, true, (m, n, k), &a, (k, 1), &b, (n, 1));
        set_threads(1);
        out
    }

    #[test]
    fn two_threads_give_the_same_bits_as_one() {
        // The training shapes: batch × hidden × hidden, the LSTM input projection, a head.
        for shape in [
            (256, 256, 256),
            (512, 256, 67),
            (4352, 128, 37),
            (256, 8, 256),
        ] {
            let one = product(1, shape);
            let two = product(2, shape);
            assert!(
                one.iter()
                    .zip(&two)
                    .all(|(x, y)| x.to_bits() == y.to_bits()),
                "{shape:?}"
            );
        }
    }

    #[test]
    fn matmul_matches_a_hand_product() {
        // [[1, 2], [3, 4]] · [[5, 6], [7, 8]] = [[19, 22], [43, 50]], then + 1 accumulated.
        let mut out = vec![1.0f32; 4];
        matmul(
            &mut out,
            true,
            (2, 2, 2),
            &[1., 2., 3., 4.],
            (2, 1),
            &[5., 6., 7., 8.],
            (2, 1),
        );
        assert_eq!(out, [20.0, 23.0, 44.0, 51.0]);
    }
}
