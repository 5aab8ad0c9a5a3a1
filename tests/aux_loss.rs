//! `train --aux dynamics` (train/aux.rs): the normalisation against a two-pass computation, the
//! loss purely additive (weight 0 trains the same bits as no auxiliary loss), its gradient
//! reaching the encoder, and the head's sanity on the Ant: trained on transitions from two
//! damage conditions, its loss falls, and a z that carries the condition predicts better than
//! one that does not — the pressure that should teach an encoder to detect damage.

use candle_core::{Device, Tensor};
use gaitscope::GaitConfig;
use gaitscope::damage::{Condition, ConditionChoice};
use gaitscope::policy::{AuxConfig, AuxKind, EncoderKind, NetConfig, SacConfig, SacModel};
use gaitscope::train::aux::{AuxHeads, DeltaNorm};
use gaitscope::train::replay::{Batch, ReplayBuffer};
use gaitscope::train::sac::{SacLearner, UpdatePath};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

mod common;

const DYNAMICS: AuxConfig = AuxConfig {
    kind: AuxKind::Dynamics,
    weight: 1.0,
};

fn small_net() -> NetConfig {
    NetConfig {
        hidden: vec![32, 32],
        z_dim: 8,
        ..NetConfig::ant(EncoderKind::Lstm)
    }
}

/// `steps` random-action transitions of the Ant under `condition` (joints trigger at fatigue
/// 2, so severe damage sets in within a few steps), with their windows.
fn transitions(condition: Condition, steps: usize, seed: u64, net: &NetConfig) -> ReplayBuffer {
    let mut config = GaitConfig::default();
    config.damage.condition = ConditionChoice::Fixed(condition);
    config.damage.threshold = 2.0;
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    common::filled_replay(config, net, steps, seed, |_, _| {
        (0..8).map(|_| rng.random_range(-1.0..=1.0)).collect()
    })
}

#[test]
fn the_normalisation_matches_a_two_pass_mean_and_std() {
    let pairs: Vec<([f64; 2], [f64; 2])> = vec![
        ([0.0, 1.0], [1.0, 1.5]),
        ([2.0, -1.0], [2.5, 0.0]),
        ([1.0, 0.0], [4.0, 0.25]),
        ([-3.0, 2.0], [-3.0, 2.0]),
    ];
    let mut norm = DeltaNorm::new(2);
    for (o, n) in &pairs {
        norm.observe(o, n);
    }
    // Changes: (1, 0.5), (0.5, 1), (3, 0.25), (0, 0): means 1.125 and 0.4375.
    assert!((norm.mean[0] - 1.125).abs() < 1e-12 && (norm.mean[1] - 0.4375).abs() < 1e-12);
    let var0 = [1.0f64, 0.5, 3.0, 0.0]
        .iter()
        .map(|d| (d - 1.125).powi(2))
        .sum::<f64>()
        / 4.0;
    assert!((norm.std()[0] - var0.sqrt()).abs() < 1e-12);
    // A dimension that never changes is divided by the floor, not by zero.
    let mut still = DeltaNorm::new(1);
    still.observe(&[1.0], &[1.0]);
    still.observe(&[2.0], &[2.0]);
    assert_eq!(still.std(), vec![gaitscope::train::aux::MIN_STD]);
}

fn learner(aux: Option<f64>) -> SacLearner {
    let net = small_net();
    let model = SacModel::new(net, 1.0, 7, &Device::Cpu).unwrap();
    let config = SacConfig {
        aux: if aux.is_some() {
            DYNAMICS
        } else {
            AuxConfig::default()
        },
        ..SacConfig::default()
    };
    let mut learner = SacLearner::new(model, config, Device::Cpu);
    learner.init_aux(7).unwrap();
    if let (Some(w), Some(heads)) = (aux, &mut learner.aux) {
        heads.config.weight = w;
    }
    learner.set_update_path(UpdatePath::Reference).unwrap();
    learner
}

fn weights(l: &SacLearner) -> Vec<(String, Vec<f32>)> {
    l.model
        .all_params()
        .map(|(n, v)| (n.to_string(), v.flatten_all().unwrap().to_vec1().unwrap()))
        .collect()
}

#[test]
fn the_loss_is_additive_and_reaches_the_encoder() {
    let net = small_net();
    let replay = transitions(Condition::Severe, 600, 3, &net);
    let run = |mut l: SacLearner| {
        let (mut sampler, mut rng) = (ChaCha8Rng::seed_from_u64(1), ChaCha8Rng::seed_from_u64(2));
        let mut batch = Batch::default();
        let mut stats = Vec::new();
        for _ in 0..3 {
            replay.sample(64, &mut sampler, &mut batch);
            for k in 0..batch.size {
                let o = &batch.obs[k * net.obs_dim..(k + 1) * net.obs_dim];
                let n = &batch.next_obs[k * net.obs_dim..(k + 1) * net.obs_dim];
                let (o, n): (Vec<f64>, Vec<f64>) = (
                    o.iter().map(|&v| v.into()).collect(),
                    n.iter().map(|&v| v.into()).collect(),
                );
                l.observe(&o, &n, batch.terminated[k] > 0.5);
            }
            stats.push(l.update(&batch, &mut rng).unwrap());
        }
        (weights(&l), stats)
    };
    let (plain, plain_stats) = run(learner(None));
    let (zero, zero_stats) = run(learner(Some(0.0)));
    let (on, on_stats) = run(learner(Some(1.0)));
    // Weight 0: every policy weight, bit for bit, as without the loss.
    assert_eq!(plain, zero);
    assert_eq!(plain_stats[2].actor_loss, zero_stats[2].actor_loss);
    assert!(plain_stats[0].aux_loss.is_none() && zero_stats[0].aux_loss.is_some());
    // Weight 1: the encoders move differently (the loss reaches them), the heads' losses are
    // logged for actor and critic.
    let differs = |prefix: &str| {
        plain
            .iter()
            .zip(&on)
            .filter(|((n, _), _)| n.starts_with(prefix))
            .any(|((_, a), (_, b))| a != b)
    };
    assert!(
        differs("actor.encoder"),
        "the actor's encoder feels the loss"
    );
    assert!(
        differs("critic.encoder"),
        "the critic's encoder feels the loss"
    );
    assert!(
        on_stats
            .iter()
            .all(|s| s.aux_loss.is_some() && s.aux_critic_loss.is_some())
    );
}

#[test]
fn a_z_that_carries_the_condition_predicts_the_dynamics_better() {
    let net = NetConfig {
        z_dim: 2,
        ..small_net()
    };
    let healthy = transitions(Condition::Healthy, 1_500, 11, &net);
    let severe = transitions(Condition::Severe, 1_500, 11, &net);
    // One batch per condition at a time, z = 0 (z-free) or the condition one-hot.
    let train = |one_hot: bool| -> (f64, f64) {
        let mut heads = AuxHeads::new(DYNAMICS, &net, 5, 1e-3, &Device::Cpu).unwrap();
        let mut sampler = ChaCha8Rng::seed_from_u64(4);
        let mut batch = Batch::default();
        // The normalisation from both conditions' changes.
        for replay in [&healthy, &severe] {
            replay.sample(1_500, &mut ChaCha8Rng::seed_from_u64(9), &mut batch);
            for k in 0..batch.size {
                let slice = |v: &[f32]| -> Vec<f64> {
                    v[k * net.obs_dim..(k + 1) * net.obs_dim]
                        .iter()
                        .map(|&x| x.into())
                        .collect()
                };
                if batch.terminated[k] < 0.5 {
                    heads
                        .norm
                        .observe(&slice(&batch.obs), &slice(&batch.next_obs));
                }
            }
        }
        let z_for = |condition: usize, b: usize| {
            let mut z = vec![0f32; b * 2];
            if one_hot {
                for k in 0..b {
                    z[k * 2 + condition] = 1.0;
                }
            }
            Tensor::from_vec(z, (b, 2), &Device::Cpu).unwrap()
        };
        let (mut first, mut last) = (0.0, 0.0);
        for step in 0..400 {
            let mut total = 0.0;
            for (c, replay) in [&healthy, &severe].into_iter().enumerate() {
                replay.sample(128, &mut sampler, &mut batch);
                let (loss, value) = heads
                    .loss(&heads.actor, &z_for(c, batch.size), &batch, &Device::Cpu)
                    .unwrap();
                let grads = loss.backward().unwrap();
                heads.actor_opt.step(&grads).unwrap();
                total += value / 2.0;
            }
            if step < 20 {
                first += total / 20.0;
            }
            if step >= 380 {
                last += total / 20.0;
            }
        }
        (first, last)
    };
    let (free_first, free_last) = train(false);
    let (labelled_first, labelled_last) = train(true);
    eprintln!(
        "aux loss: z-free {free_first:.3} → {free_last:.3}, condition in z {labelled_first:.3} → {labelled_last:.3}"
    );
    assert!(free_last < 0.8 * free_first, "the head learns the dynamics");
    assert!(
        labelled_last < free_last,
        "knowing the condition predicts the change better"
    );
}
