//! The fused SAC update against the reference (candle's autograd): from the same weights,
//! optimiser state, batch and noise, the same losses, gradients and updated weights to 1e-5
//! relative (‖a − b‖ / ‖b‖ per tensor), for every encoder, fresh and from the shipped
//! checkpoints with batches of real transitions.
//!
//! Updated weights are compared once Adam has moments: at its first step Adam moves every
//! weight by ≈ lr·sign(g), so a gradient that is 0 up to rounding may step either way on either
//! path (2·lr apart) although both gradients agree to 1e-6. For the same reason a single weight
//! whose gradient is near Adam's ε can differ by ~1 % of a step; the per-tensor norm absorbs it,
//! an element-wise bound would not (the largest element-wise errors are printed).

use candle_core::Device;
use gaitscope::policy::{EncoderKind, NetConfig, SacConfig, SacModel};
use gaitscope::train::replay::{Batch, ReplayBuffer};
use gaitscope::train::sac::{SacLearner, UpdatePath, UpdateStats};
use gaitscope::{ConditionChoice, GaitConfig};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use std::path::PathBuf;

mod common;

const TOL: f64 = 1e-5;

/// ‖a − b‖₂ / ‖b‖₂.
fn rel_err(a: &[f32], b: &[f32]) -> f64 {
    assert_eq!(a.len(), b.len());
    let norm = |it: &mut dyn Iterator<Item = f64>| it.map(|v| v * v).sum::<f64>().sqrt();
    let diff = norm(&mut a.iter().zip(b).map(|(x, y)| f64::from(x - y)));
    diff / norm(&mut b.iter().map(|&y| f64::from(y))).max(1e-30)
}

/// max |a − b| / max |b|, for the record.
fn max_rel_err(a: &[f32], b: &[f32]) -> f64 {
    let scale = b.iter().fold(0f64, |m, v| m.max(f64::from(v.abs())));
    let err = a
        .iter()
        .zip(b)
        .fold(0f64, |m, (x, y)| m.max(f64::from((x - y).abs())));
    err / scale.max(1e-30)
}

/// A replay buffer filled by `steps` env steps of `act`, under random damage.
fn filled_replay(
    net: &NetConfig,
    steps: usize,
    seed: u64,
    act: impl FnMut(&[f64], &[f32]) -> Vec<f64>,
) -> ReplayBuffer {
    let mut config = GaitConfig::default();
    config.damage.condition = ConditionChoice::Random;
    common::filled_replay(config, net, steps, seed, act)
}

fn random_replay(net: &NetConfig) -> ReplayBuffer {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    filled_replay(net, 1_500, 5, |_, _| {
        (0..8).map(|_| rng.random_range(-1.0..=1.0)).collect()
    })
}

fn check_stats(what: &str, fused: &UpdateStats, reference: &UpdateStats) {
    for (name, a, b) in [
        ("qf1", fused.qf1_loss, reference.qf1_loss),
        ("qf2", fused.qf2_loss, reference.qf2_loss),
        ("qf1_values", fused.qf1_values, reference.qf1_values),
        ("qf2_values", fused.qf2_values, reference.qf2_values),
        ("actor_loss", fused.actor_loss, reference.actor_loss),
        ("alpha", fused.alpha, reference.alpha),
        ("alpha_loss", fused.alpha_loss, reference.alpha_loss),
        (
            "aux",
            fused.aux_loss.unwrap_or(0.0),
            reference.aux_loss.unwrap_or(0.0),
        ),
        (
            "aux_critic",
            fused.aux_critic_loss.unwrap_or(0.0),
            reference.aux_critic_loss.unwrap_or(0.0),
        ),
    ] {
        let err = (a - b).abs() / b.abs().max(1e-6);
        assert!(
            err <= TOL,
            "{what}: {name} fused {a} vs reference {b} (rel {err:e})"
        );
    }
}

/// One update on each path from identical learners; compares losses, gradients and (when
/// `weights`) the updated weights.
fn compare_one_update(
    what: &str,
    reference: &mut SacLearner,
    fused: &mut SacLearner,
    batch: &Batch,
    weights: bool,
) {
    let mut rng_ref = ChaCha8Rng::seed_from_u64(11);
    let mut rng_fused = rng_ref.clone();
    let (ref_stats, ref_grads) = reference.reference_update(batch, &mut rng_ref).unwrap();
    let fused_stats = fused.update(batch, &mut rng_fused).unwrap();
    check_stats(what, &fused_stats, &ref_stats);
    let fused_grads = fused.fused_gradients().expect("the fused path is on");
    assert_eq!(
        fused_grads.len(),
        ref_grads.len(),
        "{what}: every parameter has a gradient on both paths"
    );
    let (mut worst, mut worst_max) = ((0.0, String::new()), 0f64);
    for (name, g_ref) in &ref_grads {
        let (_, g_fused) = fused_grads
            .iter()
            .find(|(n, _)| n == name)
            .unwrap_or_else(|| panic!("{what}: no fused gradient for {name}"));
        let err = rel_err(g_fused, g_ref);
        assert!(err <= TOL, "{what}: gradient of {name} off by {err:e}");
        worst_max = worst_max.max(max_rel_err(g_fused, g_ref));
        if err > worst.0 {
            worst = (err, name.clone());
        }
    }
    eprintln!(
        "{what}: gradients within {:.1e} ({}), element-wise {worst_max:.1e}",
        worst.0, worst.1
    );
    if !weights {
        return;
    }
    let mut weights_max = 0f64;
    fused.sync_model().unwrap();
    for ((name, a), (_, b)) in fused.model.all_params().zip(reference.model.all_params()) {
        let a = a.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let b = b.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let err = rel_err(&a, &b);
        assert!(err <= TOL, "{what}: updated {name} off by {err:e}");
        weights_max = weights_max.max(max_rel_err(&a, &b));
    }
    if let (Some(a), Some(b)) = (&fused.aux, &reference.aux) {
        // The auxiliary heads too, and the normalisation both read.
        assert_eq!(a.norm, b.norm);
        for ((name, a), (_, b)) in a.params().zip(b.params()) {
            let a = a.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            let b = b.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            let err = rel_err(&a, &b);
            assert!(err <= TOL, "{what}: updated {name} off by {err:e}");
            weights_max = weights_max.max(max_rel_err(&a, &b));
        }
    }
    eprintln!("{what}: updated weights element-wise within {weights_max:.1e}");
}

/// Makes `to` an exact copy of `from` (weights, Adam moments and steps), on the fused path.
fn copy_learner(from: &SacLearner, to: &mut SacLearner) {
    for ((_, src), (_, dst)) in from.model.all_params().zip(to.model.all_params()) {
        dst.set(src.as_tensor()).unwrap();
    }
    for (src, dst) in [
        (&from.actor_opt, &mut to.actor_opt),
        (&from.critic_opt, &mut to.critic_opt),
        (&from.alpha_opt, &mut to.alpha_opt),
    ] {
        let moments = src
            .moments()
            .map(|(m, v)| (m.to_vec(), v.to_vec()))
            .collect();
        dst.set_moments(src.t, moments).unwrap();
    }
    if let (Some(src), Some(dst)) = (&from.aux, &mut to.aux) {
        for ((_, s), (_, d)) in src.params().zip(dst.params()) {
            d.set(s.as_tensor()).unwrap();
        }
        let copy = |src: &gaitscope::train::adam::Adam, dst: &mut gaitscope::train::adam::Adam| {
            let moments = src
                .moments()
                .map(|(m, v)| (m.to_vec(), v.to_vec()))
                .collect();
            dst.set_moments(src.t, moments).unwrap();
        };
        copy(&src.actor_opt, &mut dst.actor_opt);
        if let (Some(s), Some(d)) = (&src.critic_opt, &mut dst.critic_opt) {
            copy(s, d);
        }
        dst.norm = src.norm.clone();
    }
    to.set_update_path(UpdatePath::Fused).unwrap();
}

fn fresh_learner(net: &NetConfig) -> SacLearner {
    let model = SacModel::new(net.clone(), 1.0, 7, &Device::Cpu).unwrap();
    SacLearner::new(model, SacConfig::default(), Device::Cpu)
}

fn fresh_pair(net: &NetConfig) {
    let replay = random_replay(net);
    let mut reference = fresh_learner(net);
    let mut fused = fresh_learner(net);
    fused.set_update_path(UpdatePath::Fused).unwrap();
    // Three updates: the first from Adam's zero moments (losses and gradients), the next two
    // from the reference's state after it (weights too).
    let mut sampler = ChaCha8Rng::seed_from_u64(2);
    let mut batch = Batch::default();
    for k in 0..3 {
        replay.sample(256, &mut sampler, &mut batch);
        let what = format!("{} fresh, update {k}", net.encoder);
        compare_one_update(&what, &mut reference, &mut fused, &batch, k > 0);
        copy_learner(&reference, &mut fused);
    }
}

/// A learner with `--aux dynamics` (weight 0.5), its normalisation taken from `replay`.
fn fresh_aux_learner(net: &NetConfig, replay: &ReplayBuffer) -> SacLearner {
    let model = SacModel::new(net.clone(), 1.0, 7, &Device::Cpu).unwrap();
    let config = SacConfig {
        aux: gaitscope::policy::AuxConfig {
            kind: gaitscope::policy::AuxKind::Dynamics,
            weight: 0.5,
        },
        ..SacConfig::default()
    };
    let mut learner = SacLearner::new(model, config, Device::Cpu);
    learner.init_aux(7).unwrap();
    let mut batch = Batch::default();
    replay.sample(1_000, &mut ChaCha8Rng::seed_from_u64(8), &mut batch);
    let d = net.obs_dim;
    for k in 0..batch.size {
        let row =
            |v: &[f32]| -> Vec<f64> { v[k * d..(k + 1) * d].iter().map(|&x| x.into()).collect() };
        learner.observe(
            &row(&batch.obs),
            &row(&batch.next_obs),
            batch.terminated[k] > 0.5,
        );
    }
    learner
}

/// With the auxiliary dynamics loss: the same losses (aux ones included), gradients (the
/// heads' and, through z, the encoders') and updated weights (the heads' too) on both paths.
fn fresh_aux_pair(net: &NetConfig) {
    let replay = random_replay(net);
    let mut reference = fresh_aux_learner(net, &replay);
    let mut fused = fresh_aux_learner(net, &replay);
    fused.set_update_path(UpdatePath::Fused).unwrap();
    let mut sampler = ChaCha8Rng::seed_from_u64(2);
    let mut batch = Batch::default();
    for k in 0..3 {
        replay.sample(256, &mut sampler, &mut batch);
        let what = format!("{} with --aux dynamics, update {k}", net.encoder);
        compare_one_update(&what, &mut reference, &mut fused, &batch, k > 0);
        copy_learner(&reference, &mut fused);
    }
}

#[test]
fn fused_matches_reference_with_the_dynamics_loss() {
    fresh_aux_pair(&NetConfig::ant(EncoderKind::Lstm));
    fresh_aux_pair(&NetConfig::ant(EncoderKind::MlpWindow));
    let mut shared = NetConfig::ant(EncoderKind::Lstm);
    shared.share_encoder = true;
    fresh_aux_pair(&shared);
}

#[test]
fn fused_matches_reference_for_the_baseline() {
    fresh_pair(&NetConfig::ant(EncoderKind::None));
}

#[test]
fn fused_matches_reference_for_the_lstm_encoder() {
    fresh_pair(&NetConfig::ant(EncoderKind::Lstm));
}

#[test]
fn fused_matches_reference_for_the_window_mlp_encoder() {
    fresh_pair(&NetConfig::ant(EncoderKind::MlpWindow));
}

#[test]
fn fused_matches_reference_with_a_shared_encoder() {
    let mut net = NetConfig::ant(EncoderKind::Lstm);
    net.share_encoder = true;
    fresh_pair(&net);
}

/// The shipped checkpoints with their saved Adam moments, on batches of transitions their own
/// policy produced (severe and mild damage, sampled actions).
#[test]
fn fused_matches_reference_from_the_shipped_checkpoints() {
    for name in ["baseline", "encoder-lstm", "encoder-mlp"] {
        let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
            .join("checkpoints")
            .join(name);
        let mut reference = gaitscope::train::load_learner(&dir, &Device::Cpu).unwrap();
        let mut fused = gaitscope::train::load_learner(&dir, &Device::Cpu).unwrap();
        fused.set_update_path(UpdatePath::Fused).unwrap();
        let net = reference.model.net.clone();
        let policy = gaitscope::policy::Policy::new(
            gaitscope::policy::checkpoint::read_meta(&dir).unwrap(),
            reference.model.actor.clone(),
            Device::Cpu,
        );
        let mut noise_rng = ChaCha8Rng::seed_from_u64(9);
        let replay = filled_replay(&net, 1_200, 21, |obs, window| {
            let obs32: Vec<f32> = obs.iter().map(|&v| v as f32).collect();
            let noise: Vec<f32> = (0..8)
                .map(|_| noise_rng.sample::<f32, _>(StandardNormal))
                .collect();
            policy
                .act_batch(
                    &obs32,
                    net.encoder.uses_window().then_some(window),
                    gaitscope::policy::ActionMode::Sampled,
                    Some(&noise),
                )
                .unwrap()
                .remove(0)
                .action
        });
        let mut batch = Batch::default();
        replay.sample(256, &mut ChaCha8Rng::seed_from_u64(4), &mut batch);
        compare_one_update(
            &format!("{name} checkpoint"),
            &mut reference,
            &mut fused,
            &batch,
            true,
        );
    }
}

/// Two threads per update only share the GEMMs' output tiles out: three updates on each encoder
/// give the same losses and the same weight bits as one thread.
#[test]
fn two_threads_train_the_same_bits_as_one() {
    for encoder in [EncoderKind::None, EncoderKind::Lstm, EncoderKind::MlpWindow] {
        let net = NetConfig::ant(encoder);
        let replay = random_replay(&net);
        let mut learners = [fresh_learner(&net), fresh_learner(&net)];
        for (learner, threads) in learners.iter_mut().zip([1, 2]) {
            learner.set_update_path(UpdatePath::Fused).unwrap();
            learner.set_threads(threads).unwrap();
        }
        let (mut sampler, mut noise) = (
            [ChaCha8Rng::seed_from_u64(5), ChaCha8Rng::seed_from_u64(5)],
            [ChaCha8Rng::seed_from_u64(6), ChaCha8Rng::seed_from_u64(6)],
        );
        let mut batch = Batch::default();
        for k in 0..3 {
            let mut stats = Vec::new();
            for i in 0..2 {
                replay.sample(256, &mut sampler[i], &mut batch);
                stats.push(learners[i].update(&batch, &mut noise[i]).unwrap());
            }
            assert_eq!(
                format!("{:?}", stats[0]),
                format!("{:?}", stats[1]),
                "{encoder}, update {k}"
            );
        }
        for learner in &mut learners {
            learner.sync_model().unwrap();
        }
        for ((name, one), (_, two)) in learners[0]
            .model
            .all_params()
            .zip(learners[1].model.all_params())
        {
            let bits = |v: &candle_core::Var| -> Vec<u32> {
                v.as_tensor()
                    .flatten_all()
                    .unwrap()
                    .to_vec1::<f32>()
                    .unwrap()
                    .into_iter()
                    .map(f32::to_bits)
                    .collect()
            };
            assert_eq!(bits(one), bits(two), "{encoder}: {name}");
        }
    }
}
