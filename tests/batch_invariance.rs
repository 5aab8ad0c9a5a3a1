//! A decision's bits do not depend on the batch it is in: eval's lockstep (any chunk size, so
//! any --threads) and a lane stepped alone (live, record, rollout) agree exactly. candle's CPU
//! matmul once rounded a lone row differently from a batch, and an episode took 92 steps alone
//! and 95 in a lockstep of eight.

use std::path::Path;

use gaitscope::eval::{Case, run_lockstep};
use gaitscope::lane::{Actor, Lane};
use gaitscope::policy::{ActionMode, Policy};
use gaitscope::{Condition, ConditionChoice, GaitConfig};
use rand::{Rng, SeedableRng};

fn bundled(name: &str) -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("checkpoints")
        .join(name)
}

#[test]
fn every_row_is_the_same_in_every_batch_size() {
    for name in ["encoder-lstm", "encoder-mlp", "baseline"] {
        let policy = Policy::load(&bundled(name), None).unwrap();
        let net = policy.net().clone();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        let n = 200;
        let obs: Vec<f32> = (0..n * net.obs_dim)
            .map(|_| rng.random_range(-1.0..1.0))
            .collect();
        let w = net.context_len * net.entry_dim();
        let window: Vec<f32> = (0..n * w).map(|_| rng.random_range(-1.0..1.0)).collect();
        let uses = net.encoder.uses_window();
        let decide = |b: usize| {
            policy
                .act_batch(
                    &obs[..b * net.obs_dim],
                    uses.then_some(&window[..b * w]),
                    ActionMode::Deterministic,
                    None,
                )
                .unwrap()
        };
        let all = decide(n);
        for b in 1..=n {
            let some = decide(b);
            for i in 0..b {
                assert_eq!(
                    some[i].action, all[i].action,
                    "{name}: row {i} in a batch of {b}"
                );
                assert_eq!(
                    some[i].z, all[i].z,
                    "{name}: z of row {i} in a batch of {b}"
                );
            }
        }
    }
}

#[test]
fn an_episode_alone_is_the_episode_in_a_lockstep() {
    let actor = Actor::load(&bundled("encoder-lstm")).unwrap();
    let mut config = GaitConfig::default();
    config.damage.condition = ConditionChoice::Fixed(Condition::Severe);
    config.env.max_episode_steps = 300;
    let seeds: Vec<u64> = (0..8).collect();
    let together = run_lockstep(
        &actor,
        "lstm",
        &config,
        Case::Condition(Condition::Severe),
        &seeds,
        0,
    )
    .unwrap();
    for r in &together {
        let mut lane = Lane::new(&actor, &config, r.seed).unwrap();
        while !lane.is_done() {
            lane.advance(&actor, ActionMode::Deterministic).unwrap();
        }
        let out = lane.outcome().unwrap();
        assert_eq!(
            (out.step + 1, out.success, out.distance),
            (r.steps, r.success, r.final_distance),
            "seed {}",
            r.seed
        );
    }
}
