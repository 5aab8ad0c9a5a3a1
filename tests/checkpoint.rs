//! Checkpoints: save → load gives bit-identical actions; every kind of damage is a clear error.

use candle_core::Device;
use gaitscope::GaitConfig;
use gaitscope::policy::checkpoint::{
    CheckpointError, META_FILE, MODEL_FILE, TrainingRecord, safetensors_bytes,
};
use gaitscope::policy::{ActionMode, EncoderKind, NetConfig, Policy, SacConfig, SacModel};
use std::path::Path;

fn small_net(encoder: EncoderKind) -> NetConfig {
    NetConfig {
        hidden: vec![16, 16],
        z_dim: 4,
        window_mlp_hidden: vec![8],
        ..NetConfig::ant(encoder)
    }
}

fn record() -> TrainingRecord {
    TrainingRecord {
        env: GaitConfig::default(),
        sac: SacConfig::default(),
        seed: 5,
        steps_done: 1234,
        episodes_done: 7,
        wall_time_s: 1.5,
        imported_from: None,
    }
}

fn saved(dir: &Path, encoder: EncoderKind) -> SacModel {
    let model = SacModel::new(small_net(encoder), 1.0, 42, &Device::Cpu).unwrap();
    model.save(dir, &record()).unwrap();
    model
}

fn inputs(net: &NetConfig, b: usize) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let obs = (0..b * net.obs_dim)
        .map(|i| (i as f32 * 0.13).sin())
        .collect();
    let window = (0..b * net.context_len * net.entry_dim())
        .map(|i| (i as f32 * 0.07).cos())
        .collect();
    let noise = (0..b * net.act_dim)
        .map(|i| (i as f32 * 0.29).sin())
        .collect();
    (obs, window, noise)
}

#[test]
fn save_then_load_gives_bit_identical_actions_and_z() {
    for encoder in [EncoderKind::None, EncoderKind::Lstm, EncoderKind::MlpWindow] {
        let dir = tempfile::tempdir().unwrap();
        let model = saved(dir.path(), encoder);
        let policy = Policy::load(dir.path(), Some(encoder)).unwrap();
        assert_eq!(policy.meta.steps_done, 1234);
        assert_eq!(policy.meta.seed, 5);
        let net = model.net.clone();
        let (obs, window, noise) = inputs(&net, 3);
        let w = encoder.uses_window().then_some(&window[..]);
        for mode in [ActionMode::Deterministic, ActionMode::Sampled] {
            let before = model
                .actor
                .decide(&net, &Device::Cpu, &obs, w, mode, Some(&noise))
                .unwrap();
            let after = policy.act_batch(&obs, w, mode, Some(&noise)).unwrap();
            assert_eq!(before, after, "{encoder} {mode:?}");
            assert_eq!(
                after[0].z.as_ref().map(Vec::len),
                encoder.uses_window().then_some(4)
            );
        }
        // The full model (critics, targets, log α) round-trips too.
        let (loaded, _) = SacModel::load(dir.path(), None, &Device::Cpu).unwrap();
        for ((n1, v1), (n2, v2)) in model.all_params().zip(loaded.all_params()) {
            assert_eq!(n1, n2);
            assert_eq!(
                v1.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
                v2.flatten_all().unwrap().to_vec1::<f32>().unwrap()
            );
        }
    }
}

fn load_err(dir: &Path, expected: Option<EncoderKind>) -> CheckpointError {
    Policy::load(dir, expected).expect_err("load fails")
}

/// Rewrites model.safetensors with `edit` applied to its tensors, and fixes the CRC in the JSON,
/// so the damage is inside an otherwise well-formed file.
fn rewrite_weights(dir: &Path, edit: impl FnOnce(&mut Vec<(String, candle_core::Tensor)>)) {
    let tensors = candle_core::safetensors::load(dir.join(MODEL_FILE), &Device::Cpu).unwrap();
    let mut list: Vec<(String, candle_core::Tensor)> = tensors.into_iter().collect();
    edit(&mut list);
    let bytes = safetensors_bytes(list.iter().map(|(n, t)| (n.as_str(), t))).unwrap();
    std::fs::write(dir.join(MODEL_FILE), &bytes).unwrap();
    let mut meta: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join(META_FILE)).unwrap()).unwrap();
    meta["model_crc32"] = crc32fast::hash(&bytes).into();
    std::fs::write(dir.join(META_FILE), serde_json::to_vec(&meta).unwrap()).unwrap();
}

#[test]
fn every_damaged_checkpoint_is_a_clear_error() {
    // Missing directory.
    let err = load_err(Path::new("/no/such/checkpoint"), None);
    assert_eq!(
        err.to_string(),
        "checkpoint directory /no/such/checkpoint does not exist"
    );

    // Wrong model kind.
    let dir = tempfile::tempdir().unwrap();
    saved(dir.path(), EncoderKind::None);
    let err = load_err(dir.path(), Some(EncoderKind::Lstm));
    assert!(
        err.to_string()
            .contains("holds a 'none' model, expected 'lstm'"),
        "{err}"
    );

    // Truncated weights.
    let dir = tempfile::tempdir().unwrap();
    saved(dir.path(), EncoderKind::Lstm);
    let bytes = std::fs::read(dir.path().join(MODEL_FILE)).unwrap();
    std::fs::write(dir.path().join(MODEL_FILE), &bytes[..bytes.len() / 2]).unwrap();
    assert!(matches!(
        load_err(dir.path(), None),
        CheckpointError::CrcMismatch { .. }
    ));

    // Missing tensor.
    let dir = tempfile::tempdir().unwrap();
    saved(dir.path(), EncoderKind::Lstm);
    rewrite_weights(dir.path(), |t| {
        t.retain(|(n, _)| n != "actor.encoder.lstm.weight_hh")
    });
    let err = load_err(dir.path(), None);
    assert!(
        err.to_string()
            .contains("'actor.encoder.lstm.weight_hh' is missing"),
        "{err}"
    );

    // Wrong shape.
    let dir = tempfile::tempdir().unwrap();
    saved(dir.path(), EncoderKind::None);
    rewrite_weights(dir.path(), |t| {
        let entry = t.iter_mut().find(|(n, _)| n == "log_alpha").unwrap();
        entry.1 = candle_core::Tensor::zeros(2, candle_core::DType::F32, &Device::Cpu).unwrap();
    });
    let err = load_err(dir.path(), None);
    assert!(
        err.to_string()
            .contains("'log_alpha' has shape [2], the model needs [1]"),
        "{err}"
    );

    // NaN weights.
    let dir = tempfile::tempdir().unwrap();
    saved(dir.path(), EncoderKind::MlpWindow);
    rewrite_weights(dir.path(), |t| {
        let entry = t.iter_mut().find(|(n, _)| n == "actor.mean.bias").unwrap();
        entry.1 = (entry.1.clone() * f64::NAN).unwrap();
    });
    let err = load_err(dir.path(), None);
    assert!(
        err.to_string().contains("'actor.mean.bias' contains NaN"),
        "{err}"
    );

    // Extra tensor (e.g. weights of another model kind).
    let dir = tempfile::tempdir().unwrap();
    saved(dir.path(), EncoderKind::None);
    rewrite_weights(dir.path(), |t| {
        t.push((
            "actor.encoder.lstm.weight_ih".into(),
            candle_core::Tensor::zeros(3, candle_core::DType::F32, &Device::Cpu).unwrap(),
        ))
    });
    assert!(matches!(
        load_err(dir.path(), None),
        CheckpointError::UnexpectedTensor { .. }
    ));

    // checkpoint.json: unparsable, or disagreeing with its own tensor list.
    let dir = tempfile::tempdir().unwrap();
    saved(dir.path(), EncoderKind::None);
    std::fs::write(dir.path().join(META_FILE), "{ not json").unwrap();
    assert!(matches!(
        load_err(dir.path(), None),
        CheckpointError::BadMeta { .. }
    ));
    let dir = tempfile::tempdir().unwrap();
    saved(dir.path(), EncoderKind::None);
    let mut meta: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join(META_FILE)).unwrap()).unwrap();
    meta["net"]["hidden"] = serde_json::json!([16, 32]);
    std::fs::write(
        dir.path().join(META_FILE),
        serde_json::to_vec(&meta).unwrap(),
    )
    .unwrap();
    let err = load_err(dir.path(), None);
    assert!(
        err.to_string().contains("checkpoint.json") && err.to_string().contains("net config"),
        "{err}"
    );

    // Missing weights file.
    let dir = tempfile::tempdir().unwrap();
    saved(dir.path(), EncoderKind::None);
    std::fs::remove_file(dir.path().join(MODEL_FILE)).unwrap();
    assert!(
        load_err(dir.path(), None)
            .to_string()
            .contains("cannot read")
    );
}

#[test]
fn policy_rejects_bad_inputs() {
    let dir = tempfile::tempdir().unwrap();
    saved(dir.path(), EncoderKind::Lstm);
    let policy = Policy::load(dir.path(), None).unwrap();
    let net = policy.net().clone();
    let (mut obs, window, _) = inputs(&net, 1);
    let err = policy
        .act_batch(&obs[..10], Some(&window), ActionMode::Deterministic, None)
        .unwrap_err();
    assert!(err.to_string().contains("not a multiple of 29"), "{err}");
    let err = policy
        .act_batch(&obs, Some(&window[..5]), ActionMode::Deterministic, None)
        .unwrap_err();
    assert!(err.to_string().contains("window has 5 values"), "{err}");
    let err = policy
        .act_batch(&obs, None, ActionMode::Deterministic, None)
        .unwrap_err();
    assert!(err.to_string().contains("needs a context window"), "{err}");
    let err = policy
        .act_batch(&obs, Some(&window), ActionMode::Sampled, None)
        .unwrap_err();
    assert!(err.to_string().contains("need"), "{err}");
    obs[3] = f32::NAN;
    let err = policy
        .act_batch(&obs, Some(&window), ActionMode::Deterministic, None)
        .unwrap_err();
    assert!(
        err.to_string().contains("observation value 3 is NaN"),
        "{err}"
    );
}

/// Issue 49: an atomic write replaces only a regular file or creates a new one. A FIFO (or a
/// device, or a folder) at the destination is refused and left as it was — before, the rename
/// replaced it, and as root `--save-state-at 3 /dev/full` replaced the device node — and a FIFO
/// squatting on the temp name makes the write fail at once instead of blocking.
#[test]
fn an_atomic_write_replaces_only_regular_files() {
    use gaitscope::policy::checkpoint::write_atomic;
    use std::os::unix::fs::FileTypeExt;
    let dir = tempfile::tempdir().unwrap();
    let mkfifo = |p: &std::path::Path| {
        assert!(
            std::process::Command::new("mkfifo")
                .arg(p)
                .status()
                .unwrap()
                .success()
        )
    };
    let fifo = dir.path().join("state.json");
    mkfifo(&fifo);
    let err = write_atomic(&fifo, b"{}").unwrap_err().to_string();
    assert!(err.contains("not a regular file"), "{err}");
    assert!(std::fs::metadata(&fifo).unwrap().file_type().is_fifo());
    let err = write_atomic(dir.path(), b"{}").unwrap_err().to_string();
    assert!(err.contains("not a regular file"), "{err}");

    // A FIFO at the temp name: refused without blocking, the destination untouched.
    let out = dir.path().join("out.json");
    std::fs::write(&out, b"old").unwrap();
    mkfifo(&dir.path().join("out.json.tmp"));
    let started = std::time::Instant::now();
    assert!(write_atomic(&out, b"new").is_err());
    assert!(started.elapsed().as_secs() < 5);
    assert_eq!(std::fs::read(&out).unwrap(), b"old");
    // Once the squatter is gone (the failed write removed it), the write goes through.
    write_atomic(&out, b"new").unwrap();
    assert_eq!(std::fs::read(&out).unwrap(), b"new");
    // A symlink to a regular file is a regular file's name: the link is replaced.
    let target = dir.path().join("target.json");
    std::fs::write(&target, b"t").unwrap();
    let link = dir.path().join("link.json");
    std::os::unix::fs::symlink(&target, &link).unwrap();
    write_atomic(&link, b"via link").unwrap();
    assert_eq!(std::fs::read(&link).unwrap(), b"via link");
}
