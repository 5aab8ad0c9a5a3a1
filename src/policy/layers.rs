//! Small building blocks on candle: named parameters, linear layers, MLPs and an LSTM.
//!
//! Parameters are initialised from our own seeded RNG (candle's CPU RNG cannot be seeded), with
//! PyTorch's defaults: U(−1/√fan_in, 1/√fan_in) for linear layers, U(−1/√H, 1/√H) for the LSTM.
//! Weights are stored as (in, out) so a forward pass is `x · W + b` with no transpose.

use candle_core::{DType, Device, Result, Tensor, Var};
use rand::Rng;
use rand_chacha::ChaCha8Rng;

/// Whether a forward pass records gradients for a module's own parameters.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Grad {
    /// Parameters are leaves of the graph: `backward` produces their gradients.
    Track,
    /// Parameters are treated as constants: gradients flow *through* the module to its input
    /// only (e.g. the critic inside the actor loss), which skips the weight-gradient matmuls.
    Frozen,
}

impl Grad {
    fn param(self, var: &Var) -> Tensor {
        match self {
            Grad::Track => var.as_tensor().clone(),
            Grad::Frozen => var.as_tensor().detach(),
        }
    }
}

/// An ordered list of named parameters: the unit of saving, loading, optimising and Polyak
/// averaging.
#[derive(Debug, Clone, Default)]
pub struct ParamStore {
    params: Vec<(String, Var)>,
}

impl ParamStore {
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds a parameter drawn from U(−bound, bound).
    pub fn uniform(
        &mut self,
        name: String,
        shape: &[usize],
        bound: f64,
        rng: &mut ChaCha8Rng,
        device: &Device,
    ) -> Result<Var> {
        let n = shape.iter().product();
        let bound = bound as f32;
        let values: Vec<f32> = (0..n).map(|_| rng.random_range(-bound..=bound)).collect();
        self.push(name, Tensor::from_vec(values, shape, device)?)
    }

    /// Adds a parameter with a given value.
    pub fn push(&mut self, name: String, value: Tensor) -> Result<Var> {
        let var = Var::from_tensor(&value.to_dtype(DType::F32)?)?;
        self.params.push((name, var.clone()));
        Ok(var)
    }

    /// Moves every parameter of `other` to the end of this store (names as they are).
    pub fn extend(&mut self, other: ParamStore) {
        self.params.extend(other.params);
    }

    pub fn iter(&self) -> impl Iterator<Item = (&str, &Var)> {
        self.params.iter().map(|(n, v)| (n.as_str(), v))
    }

    pub fn vars(&self) -> impl Iterator<Item = &Var> {
        self.params.iter().map(|(_, v)| v)
    }

    pub fn len(&self) -> usize {
        self.params.len()
    }

    pub fn is_empty(&self) -> bool {
        self.params.is_empty()
    }

    /// Total number of scalars.
    pub fn numel(&self) -> usize {
        self.params.iter().map(|(_, v)| v.elem_count()).sum()
    }
}

/// `y = x · W + b`, W stored as (in, out).
#[derive(Debug, Clone)]
pub struct Linear {
    w: Var,
    b: Var,
}

impl Linear {
    pub fn new(
        store: &mut ParamStore,
        name: &str,
        in_dim: usize,
        out_dim: usize,
        rng: &mut ChaCha8Rng,
        device: &Device,
    ) -> Result<Self> {
        let bound = 1.0 / (in_dim as f64).sqrt();
        let w = store.uniform(
            format!("{name}.weight"),
            &[in_dim, out_dim],
            bound,
            rng,
            device,
        )?;
        let b = store.uniform(format!("{name}.bias"), &[1, out_dim], bound, rng, device)?;
        Ok(Self { w, b })
    }

    pub fn forward(&self, x: &Tensor, grad: Grad) -> Result<Tensor> {
        x.matmul(&grad.param(&self.w))?
            .broadcast_add(&grad.param(&self.b))
    }

    pub fn out_dim(&self) -> usize {
        self.w.dims()[1]
    }
}

/// Linear layers with ReLU between them; `relu_out` adds one after the last layer too.
#[derive(Debug, Clone)]
pub struct Mlp {
    layers: Vec<Linear>,
    relu_out: bool,
}

impl Mlp {
    pub fn new(
        store: &mut ParamStore,
        name: &str,
        dims: &[usize],
        relu_out: bool,
        rng: &mut ChaCha8Rng,
        device: &Device,
    ) -> Result<Self> {
        let layers = dims
            .windows(2)
            .enumerate()
            .map(|(i, d)| Linear::new(store, &format!("{name}.{i}"), d[0], d[1], rng, device))
            .collect::<Result<_>>()?;
        Ok(Self { layers, relu_out })
    }

    pub fn forward(&self, x: &Tensor, grad: Grad) -> Result<Tensor> {
        let mut h = x.clone();
        for (i, layer) in self.layers.iter().enumerate() {
            h = layer.forward(&h, grad)?;
            if i + 1 < self.layers.len() || self.relu_out {
                h = h.relu()?;
            }
        }
        Ok(h)
    }
}

/// A single-layer LSTM with PyTorch's gate order (input, forget, cell, output) and two biases.
#[derive(Debug, Clone)]
pub struct Lstm {
    w_ih: Var,
    w_hh: Var,
    b_ih: Var,
    b_hh: Var,
    hidden: usize,
}

impl Lstm {
    pub fn new(
        store: &mut ParamStore,
        name: &str,
        input: usize,
        hidden: usize,
        rng: &mut ChaCha8Rng,
        device: &Device,
    ) -> Result<Self> {
        let bound = 1.0 / (hidden as f64).sqrt();
        let mut param = |suffix: &str, shape: &[usize]| {
            store.uniform(format!("{name}.{suffix}"), shape, bound, rng, device)
        };
        Ok(Self {
            w_ih: param("weight_ih", &[input, 4 * hidden])?,
            w_hh: param("weight_hh", &[hidden, 4 * hidden])?,
            b_ih: param("bias_ih", &[1, 4 * hidden])?,
            b_hh: param("bias_hh", &[1, 4 * hidden])?,
            hidden,
        })
    }

    /// Runs over a batch of sequences `(B, T, input)` from zero state; returns the final hidden
    /// state `(B, hidden)`. The input projection of all T steps is one matmul; the recurrence is
    /// one fused op ([`super::lstm_kernel`]).
    pub fn forward(&self, xs: &Tensor, grad: Grad) -> Result<Tensor> {
        let (b, t, input) = xs.dims3()?;
        let hsz = self.hidden;
        let bias = grad
            .param(&self.b_ih)
            .broadcast_add(&grad.param(&self.b_hh))?;
        // (B·T, in)·W_ih → (B, T, 4H) → time-major (T, B, 4H) so each step is a contiguous slab.
        let projected = xs
            .reshape((b * t, input))?
            .matmul(&grad.param(&self.w_ih))?
            .broadcast_add(&bias)?
            .reshape((b, t, 4 * hsz))?
            .transpose(0, 1)?;
        super::lstm_kernel::lstm_recurrence(&projected, &grad.param(&self.w_hh))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn linear_is_x_w_plus_b_and_init_is_bounded() {
        let dev = Device::Cpu;
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let mut store = ParamStore::new();
        let lin = Linear::new(&mut store, "l", 4, 3, &mut rng, &dev).unwrap();
        let names: Vec<&str> = store.iter().map(|(n, _)| n).collect();
        assert_eq!(names, ["l.weight", "l.bias"]);
        assert_eq!(store.numel(), 4 * 3 + 3);
        for (_, v) in store.iter() {
            let vals = v.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            assert!(vals.iter().all(|x| x.abs() <= 0.5), "U(−1/√4, 1/√4)");
        }
        let x = Tensor::new(&[[1f32, 0., 0., 0.]], &dev).unwrap();
        let y = lin
            .forward(&x, Grad::Track)
            .unwrap()
            .to_vec2::<f32>()
            .unwrap();
        let w = lin.w.to_vec2::<f32>().unwrap();
        let b = lin.b.to_vec2::<f32>().unwrap();
        for j in 0..3 {
            assert_eq!(y[0][j], w[0][j] + b[0][j]);
        }
    }

    #[test]
    fn frozen_parameters_get_no_gradient_but_pass_it_on() {
        let dev = Device::Cpu;
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let mut store = ParamStore::new();
        let lin = Linear::new(&mut store, "l", 2, 1, &mut rng, &dev).unwrap();
        let x = Var::new(&[[1f32, 2.]], &dev).unwrap();
        let y = lin
            .forward(x.as_tensor(), Grad::Frozen)
            .unwrap()
            .sum_all()
            .unwrap();
        let grads = y.backward().unwrap();
        assert!(grads.get(&lin.w).is_none());
        let gx = grads.get(&x).unwrap().to_vec2::<f32>().unwrap();
        let w = lin.w.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        assert_eq!(gx[0], w, "dy/dx = W");
    }
}
