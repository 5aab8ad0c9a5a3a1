//! The SAC pieces against values derived by hand: squashed-Gaussian log-prob, Polyak averaging,
//! the LSTM against a plain reference implementation, and finite-difference gradients.

use candle_core::{Device, Tensor, Var};
use gaitscope::policy::layers::{Grad, Lstm, Mlp, ParamStore};
use gaitscope::policy::{ActorOutput, squashed_sample};
use gaitscope::train::sac::polyak_update;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

fn t2(rows: &[&[f32]]) -> Tensor {
    let cols = rows[0].len();
    let flat: Vec<f32> = rows.iter().flat_map(|r| r.iter().copied()).collect();
    Tensor::from_vec(flat, (rows.len(), cols), &Device::Cpu).unwrap()
}

#[test]
fn squashed_gaussian_log_prob_matches_hand_computation() {
    let mean = [0.3f64, -1.2];
    let log_std = [-0.5f64, 0.1];
    let eps = [0.7f64, -0.4];
    let out = ActorOutput {
        mean: t2(&[&[mean[0] as f32, mean[1] as f32]]),
        log_std: t2(&[&[log_std[0] as f32, log_std[1] as f32]]),
        z: None,
    };
    let (action, log_prob) =
        squashed_sample(&out, &t2(&[&[eps[0] as f32, eps[1] as f32]])).unwrap();
    let action = action.to_vec2::<f32>().unwrap()[0].clone();
    let log_prob = log_prob.to_vec2::<f32>().unwrap()[0][0] as f64;
    let mut expected = 0.0;
    for i in 0..2 {
        let u = mean[i] + log_std[i].exp() * eps[i];
        let a = u.tanh();
        assert!((action[i] as f64 - a).abs() < 1e-6);
        // log N(u; μ, σ) − log(1 − tanh(u)² + 1e-6)
        let normal = -0.5 * ((u - mean[i]) / log_std[i].exp()).powi(2)
            - log_std[i]
            - 0.5 * (2.0 * std::f64::consts::PI).ln();
        expected += normal - (1.0 - a * a + 1e-6).ln();
    }
    assert!(
        (log_prob - expected).abs() < 1e-5,
        "{log_prob} vs {expected}"
    );
}

#[test]
fn polyak_moves_targets_by_exactly_tau() {
    let dev = Device::Cpu;
    let source = Var::new(&[1.0f32, -2.0, 4.0], &dev).unwrap();
    let target = Var::new(&[0.0f32, 2.0, 4.0], &dev).unwrap();
    polyak_update([(&target, &source)].into_iter(), 0.25).unwrap();
    // 0.25·s + 0.75·t: exact in binary floating point for these values.
    assert_eq!(target.to_vec1::<f32>().unwrap(), [0.25, 1.0, 4.0]);
    assert_eq!(
        source.to_vec1::<f32>().unwrap(),
        [1.0, -2.0, 4.0],
        "source untouched"
    );
    let tau = 0.005f32;
    let (s, t) = (0.3f32, -0.7f32);
    let (src, tgt) = (Var::new(&[s], &dev).unwrap(), Var::new(&[t], &dev).unwrap());
    polyak_update([(&tgt, &src)].into_iter(), tau as f64).unwrap();
    assert_eq!(tgt.to_vec1::<f32>().unwrap()[0], tau * s + (1.0 - tau) * t);
}

/// PyTorch's LSTM equations in f64 with plain loops.
fn reference_lstm(
    params: &[Vec<f64>],
    shapes: (usize, usize),
    xs: &[Vec<Vec<f64>>],
) -> Vec<Vec<f64>> {
    let (input, hidden) = shapes;
    let (w_ih, w_hh, b_ih, b_hh) = (&params[0], &params[1], &params[2], &params[3]);
    let sig = |x: f64| 1.0 / (1.0 + (-x).exp());
    xs.iter()
        .map(|seq| {
            let mut h = vec![0.0; hidden];
            let mut c = vec![0.0; hidden];
            for x in seq {
                let gate = |g: usize, j: usize| {
                    let col = g * hidden + j;
                    let mut v = b_ih[col] + b_hh[col];
                    for k in 0..input {
                        v += x[k] * w_ih[k * 4 * hidden + col];
                    }
                    for k in 0..hidden {
                        v += h[k] * w_hh[k * 4 * hidden + col];
                    }
                    v
                };
                let mut h_new = vec![0.0; hidden];
                for j in 0..hidden {
                    let (i, f, g, o) = (
                        sig(gate(0, j)),
                        sig(gate(1, j)),
                        gate(2, j).tanh(),
                        sig(gate(3, j)),
                    );
                    c[j] = f * c[j] + i * g;
                    h_new[j] = o * c[j].tanh();
                }
                h = h_new;
            }
            h
        })
        .collect()
}

fn small_lstm() -> (Lstm, ParamStore) {
    let mut store = ParamStore::new();
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let lstm = Lstm::new(&mut store, "enc", 3, 2, &mut rng, &Device::Cpu).unwrap();
    (lstm, store)
}

fn input_sequences() -> Vec<Vec<Vec<f64>>> {
    (0..2)
        .map(|b| {
            (0..4)
                .map(|t| {
                    (0..3)
                        .map(|k| ((b * 12 + t * 3 + k) as f64 * 0.37).sin())
                        .collect()
                })
                .collect()
        })
        .collect()
}

fn as_tensor(xs: &[Vec<Vec<f64>>]) -> Tensor {
    let flat: Vec<f32> = xs.iter().flatten().flatten().map(|&v| v as f32).collect();
    Tensor::from_vec(flat, (xs.len(), xs[0].len(), xs[0][0].len()), &Device::Cpu).unwrap()
}

#[test]
fn lstm_matches_a_hand_written_reference() {
    let (lstm, store) = small_lstm();
    let names: Vec<&str> = store.iter().map(|(n, _)| n).collect();
    assert_eq!(
        names,
        [
            "enc.weight_ih",
            "enc.weight_hh",
            "enc.bias_ih",
            "enc.bias_hh"
        ]
    );
    let params: Vec<Vec<f64>> = store
        .vars()
        .map(|v| {
            v.flatten_all()
                .unwrap()
                .to_vec1::<f32>()
                .unwrap()
                .into_iter()
                .map(f64::from)
                .collect()
        })
        .collect();
    let xs = input_sequences();
    let ours = lstm
        .forward(&as_tensor(&xs), Grad::Track)
        .unwrap()
        .to_vec2::<f32>()
        .unwrap();
    let reference = reference_lstm(&params, (3, 2), &xs);
    for (o, r) in ours.iter().flatten().zip(reference.iter().flatten()) {
        assert!((*o as f64 - r).abs() < 1e-5, "{o} vs {r}");
    }
}

/// Central differences in f64 through the reference vs autograd through our f32 op.
#[test]
fn lstm_gradients_match_finite_differences() {
    let (lstm, store) = small_lstm();
    let xs = input_sequences();
    let weights = Tensor::new(&[[0.7f32, -1.3], [0.4, 2.0]], &Device::Cpu).unwrap();
    let loss = (lstm.forward(&as_tensor(&xs), Grad::Track).unwrap() * &weights)
        .unwrap()
        .sum_all()
        .unwrap();
    let grads = loss.backward().unwrap();
    let params: Vec<Vec<f64>> = store
        .vars()
        .map(|v| {
            v.flatten_all()
                .unwrap()
                .to_vec1::<f32>()
                .unwrap()
                .into_iter()
                .map(f64::from)
                .collect()
        })
        .collect();
    let ref_loss = |p: &[Vec<f64>]| -> f64 {
        let h = reference_lstm(p, (3, 2), &xs);
        h[0][0] * 0.7 - h[0][1] * 1.3 + h[1][0] * 0.4 + h[1][1] * 2.0
    };
    for (pi, var) in store.vars().enumerate() {
        let auto = grads
            .get(var)
            .expect("every LSTM parameter gets a gradient");
        let auto = auto.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        for k in 0..params[pi].len() {
            let h = 1e-5;
            let mut plus = params.clone();
            plus[pi][k] += h;
            let mut minus = params.clone();
            minus[pi][k] -= h;
            let numeric = (ref_loss(&plus) - ref_loss(&minus)) / (2.0 * h);
            assert!(
                (auto[k] as f64 - numeric).abs() < 1e-4 + 1e-3 * numeric.abs(),
                "param {pi}[{k}]: autograd {} vs numeric {numeric}",
                auto[k]
            );
        }
    }
}

#[test]
fn window_mlp_gradients_match_finite_differences() {
    let dev = Device::Cpu;
    let mut store = ParamStore::new();
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let mlp = Mlp::new(&mut store, "enc", &[6, 5, 3], false, &mut rng, &dev).unwrap();
    let x = Tensor::from_vec(
        (0..12).map(|i| (i as f32 * 0.61).cos()).collect::<Vec<_>>(),
        (2, 6),
        &dev,
    )
    .unwrap();
    let loss_of = |grad: Grad| {
        mlp.forward(&x, grad)
            .unwrap()
            .tanh()
            .unwrap()
            .sqr()
            .unwrap()
            .sum_all()
            .unwrap()
    };
    let grads = loss_of(Grad::Track).backward().unwrap();
    for var in store.vars() {
        let auto = grads
            .get(var)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        let original = var.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        for k in 0..original.len() {
            let eval = |delta: f32| {
                let mut v = original.clone();
                v[k] += delta;
                var.set(&Tensor::from_vec(v, var.shape(), &dev).unwrap())
                    .unwrap();
                let l = loss_of(Grad::Frozen).to_scalar::<f32>().unwrap() as f64;
                var.set(&Tensor::from_vec(original.clone(), var.shape(), &dev).unwrap())
                    .unwrap();
                l
            };
            let h = 1e-2f32;
            let numeric = (eval(h) - eval(-h)) / (2.0 * h as f64);
            assert!(
                (auto[k] as f64 - numeric).abs() < 2e-3 + 2e-2 * numeric.abs(),
                "[{k}] {} vs {numeric}",
                auto[k]
            );
        }
    }
}
