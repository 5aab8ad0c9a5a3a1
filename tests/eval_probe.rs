//! eval and probe end to end on small saved models: determinism, outputs, clear errors.

use candle_core::Device;
use gaitscope::eval::{EvalOptions, evaluate, write_outputs};
use gaitscope::policy::checkpoint::TrainingRecord;
use gaitscope::policy::{EncoderKind, NetConfig, SacConfig, SacModel};
use gaitscope::{Condition, GaitConfig};
use std::path::Path;
use std::process::Command;

fn save_model(dir: &Path, encoder: EncoderKind, seed: u64) {
    let net = NetConfig {
        hidden: vec![32, 32],
        ..NetConfig::ant(encoder)
    };
    let model = SacModel::new(net, 1.0, seed, &Device::Cpu).unwrap();
    let record = TrainingRecord {
        env: GaitConfig::default(),
        sac: SacConfig::default(),
        seed,
        steps_done: 0,
        episodes_done: 0,
        wall_time_s: 0.0,
    };
    model.save(dir, &record).unwrap();
}

fn options(checkpoints: Vec<std::path::PathBuf>, threads: usize) -> EvalOptions {
    EvalOptions {
        checkpoints,
        episodes: 6,
        seed_base: 77,
        conditions: vec![Condition::Healthy, Condition::Severe],
        max_steps: 60,
        threads,
    }
}

#[test]
fn eval_is_deterministic_paired_and_writes_its_outputs() {
    let tmp = tempfile::tempdir().unwrap();
    let (base, enc) = (tmp.path().join("baseline"), tmp.path().join("encoder"));
    save_model(&base, EncoderKind::None, 1);
    save_model(&enc, EncoderKind::Lstm, 2);
    let a = evaluate(&options(vec![base.clone(), enc.clone()], 2)).unwrap();
    let b = evaluate(&options(vec![base.clone(), enc.clone()], 2)).unwrap();
    assert_eq!(a.episodes, b.episodes, "same seed, same episodes");
    let c = evaluate(&options(vec![base.clone(), enc.clone()], 1)).unwrap();
    assert_eq!(a.episodes.len(), c.episodes.len());
    // 2 models × 2 conditions × 6 episodes, every model on the same seeds.
    assert_eq!(a.episodes.len(), 24);
    for model in ["baseline", "encoder"] {
        let seeds: Vec<u64> = a
            .episodes
            .iter()
            .filter(|e| e.model == model && e.condition == Condition::Severe)
            .map(|e| e.seed)
            .collect();
        let mut sorted = seeds.clone();
        sorted.sort_unstable();
        assert_eq!(sorted, (77..83).collect::<Vec<_>>());
    }
    assert_eq!(a.comparisons.len(), 2, "encoder vs baseline per condition");
    assert!(a.recovery_fraction.contains_key("encoder"));
    for e in &a.episodes {
        assert!(e.steps <= 60);
        assert_eq!(e.success_within(500), e.success);
    }
    let md = a.markdown();
    assert!(
        md.contains("| baseline |") && md.contains("McNemar"),
        "{md}"
    );
    let out = tmp.path().join("eval-out");
    let written = write_outputs(&a, &out).unwrap();
    assert_eq!(written.len(), 3);
    for path in written {
        assert!(
            std::fs::metadata(&path).unwrap().len() > 1000,
            "{}",
            path.display()
        );
    }
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("eval.json")).unwrap()).unwrap();
    assert_eq!(json["episodes"].as_array().unwrap().len(), 24);
    // Nothing half-written is left behind.
    let leftovers: Vec<_> = std::fs::read_dir(&out)
        .unwrap()
        .flatten()
        .filter(|e| e.file_name().to_string_lossy().contains("tmp"))
        .collect();
    assert!(leftovers.is_empty());
}

fn gaitscope(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_gaitscope"))
        .args(args)
        .output()
        .unwrap()
}

#[test]
fn bad_checkpoints_and_kinds_are_clear_errors() {
    let tmp = tempfile::tempdir().unwrap();
    let base = tmp.path().join("baseline");
    let enc = tmp.path().join("encoder");
    save_model(&base, EncoderKind::None, 1);
    save_model(&enc, EncoderKind::MlpWindow, 2);
    let err = |out: std::process::Output| {
        assert!(!out.status.success());
        String::from_utf8_lossy(&out.stderr).into_owned()
    };
    let e = err(gaitscope(&[
        "eval",
        "--checkpoint",
        "/no/such/dir",
        "--episodes",
        "2",
    ]));
    assert!(
        e.contains("checkpoint directory /no/such/dir does not exist"),
        "{e}"
    );
    let e = err(gaitscope(&[
        "probe",
        "--checkpoint",
        base.to_str().unwrap(),
        "--episodes",
        "1",
    ]));
    assert!(e.contains("has no context encoder"), "{e}");
    let e = err(gaitscope(&[
        "probe",
        "--checkpoint",
        enc.to_str().unwrap(),
        "--baseline",
        enc.to_str().unwrap(),
        "--episodes",
        "1",
    ]));
    assert!(
        e.contains("holds a 'mlp-window' model, expected 'none'"),
        "{e}"
    );
    let e = err(gaitscope(&[
        "eval",
        "--checkpoint",
        base.to_str().unwrap(),
        "--episodes",
        "0",
    ]));
    assert!(e.contains("at least one"), "{e}");
}

#[test]
fn probe_writes_probe_json_and_figures() {
    let tmp = tempfile::tempdir().unwrap();
    let enc = tmp.path().join("encoder");
    save_model(&enc, EncoderKind::Lstm, 3);
    let figs = tmp.path().join("figs");
    let out = gaitscope(&[
        "probe",
        "--checkpoint",
        enc.to_str().unwrap(),
        "--episodes",
        "3",
        "--max-steps",
        "80",
        "--out",
        figs.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let file = gaitscope::probe::ProbeFile::load(&enc).unwrap();
    assert_eq!(file.joints.len(), 8);
    assert_eq!(file.pca.components.len(), 3);
    assert!(file.pca.explained_variance_ratio.iter().sum::<f64>() <= 1.0 + 1e-9);
    assert!(
        file.train_episodes
            .iter()
            .all(|e| !file.test_episodes.contains(e))
    );
    for name in [
        "pca_z.png",
        "onset_latent_shift.png",
        "onset_progress.png",
        "fatigue_episode.png",
        "trigger_step_by_joint.png",
    ] {
        assert!(figs.join(name).exists(), "{name}");
    }
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        stdout.contains("condition, 3-way") && stdout.contains("ankle_1 damaged"),
        "{stdout}"
    );
}
