//! Plain Adam (PyTorch's formula, no weight decay) over candle `Var`s, computed on host slices.
//!
//! One fused loop per parameter beats a dozen candle ops per parameter at these sizes, and the
//! moments are plain vectors, so the optimiser state can be saved and resumed exactly.

use candle_core::backprop::GradStore;
use candle_core::{Result, Tensor, Var};

pub const BETA1: f64 = 0.9;
pub const BETA2: f64 = 0.999;
pub const EPS: f64 = 1e-8;

#[derive(Debug, Clone)]
pub struct Adam {
    lr: f64,
    /// Number of steps taken (bias correction uses it).
    pub t: u64,
    slots: Vec<Slot>,
}

#[derive(Debug, Clone)]
struct Slot {
    var: Var,
    m: Vec<f32>,
    v: Vec<f32>,
}

impl Adam {
    pub fn new<'a>(vars: impl Iterator<Item = &'a Var>, lr: f64) -> Self {
        let slots = vars
            .map(|var| Slot {
                var: var.clone(),
                m: vec![0.0; var.elem_count()],
                v: vec![0.0; var.elem_count()],
            })
            .collect();
        Self { lr, t: 0, slots }
    }

    /// One update from the gradients in `grads`; parameters without a gradient are left alone.
    pub fn step(&mut self, grads: &GradStore) -> Result<()> {
        self.t += 1;
        let bc1 = 1.0 - BETA1.powi(self.t as i32);
        let bc2 = 1.0 - BETA2.powi(self.t as i32);
        let step_size = (self.lr / bc1) as f32;
        let bc2_sqrt = bc2.sqrt() as f32;
        let (b1, b2, eps) = (BETA1 as f32, BETA2 as f32, EPS as f32);
        for slot in &mut self.slots {
            let Some(grad) = grads.get(&slot.var) else {
                continue;
            };
            let g = grad.flatten_all()?.to_vec1::<f32>()?;
            let mut theta = slot.var.flatten_all()?.to_vec1::<f32>()?;
            for i in 0..theta.len() {
                slot.m[i] = b1 * slot.m[i] + (1.0 - b1) * g[i];
                slot.v[i] = b2 * slot.v[i] + (1.0 - b2) * g[i] * g[i];
                let denom = slot.v[i].sqrt() / bc2_sqrt + eps;
                theta[i] -= step_size * slot.m[i] / denom;
            }
            slot.var.set(&Tensor::from_vec(
                theta,
                slot.var.shape(),
                slot.var.device(),
            )?)?;
        }
        Ok(())
    }

    /// (m, v) of each parameter, in construction order.
    pub fn moments(&self) -> impl Iterator<Item = (&[f32], &[f32])> {
        self.slots.iter().map(|s| (s.m.as_slice(), s.v.as_slice()))
    }

    /// Restores the moments saved by [`Self::moments`].
    pub fn set_moments(
        &mut self,
        t: u64,
        moments: Vec<(Vec<f32>, Vec<f32>)>,
    ) -> std::result::Result<(), String> {
        if moments.len() != self.slots.len() {
            return Err(format!(
                "{} moment pairs for {} parameters",
                moments.len(),
                self.slots.len()
            ));
        }
        for (i, (slot, (m, v))) in self.slots.iter_mut().zip(moments).enumerate() {
            if m.len() != slot.m.len() || v.len() != slot.v.len() {
                return Err(format!(
                    "parameter {i}: moments of {} values, expected {}",
                    m.len(),
                    slot.m.len()
                ));
            }
            slot.m = m;
            slot.v = v;
        }
        self.t = t;
        Ok(())
    }

    pub fn len(&self) -> usize {
        self.slots.len()
    }

    pub fn is_empty(&self) -> bool {
        self.slots.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    #[test]
    fn first_step_moves_each_weight_by_lr_against_the_gradient_sign() {
        // At t = 1: m̂ = g, v̂ = g², so Δθ = −lr·g/(|g| + ε) ≈ −lr·sign(g).
        let var = Var::new(&[1.0f32, -2.0, 3.0], &Device::Cpu).unwrap();
        let loss = (var.as_tensor() * Tensor::new(&[2.0f32, -0.5, 0.0], &Device::Cpu).unwrap())
            .unwrap()
            .sum_all()
            .unwrap();
        let grads = loss.backward().unwrap();
        let mut adam = Adam::new([&var].into_iter(), 0.1);
        adam.step(&grads).unwrap();
        let after = var.to_vec1::<f32>().unwrap();
        assert!((after[0] - 0.9).abs() < 1e-6);
        assert!((after[1] - -1.9).abs() < 1e-6);
        assert_eq!(after[2], 3.0, "zero gradient, no move");
    }

    #[test]
    fn minimises_a_quadratic() {
        let var = Var::new(&[5.0f32], &Device::Cpu).unwrap();
        let mut adam = Adam::new([&var].into_iter(), 0.1);
        for _ in 0..500 {
            let loss = (var.as_tensor() - 2.0)
                .unwrap()
                .sqr()
                .unwrap()
                .sum_all()
                .unwrap();
            adam.step(&loss.backward().unwrap()).unwrap();
        }
        assert!((var.to_vec1::<f32>().unwrap()[0] - 2.0).abs() < 1e-2);
    }
}
