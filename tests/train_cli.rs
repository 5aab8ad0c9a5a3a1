//! `gaitscope train` end to end: a short run per encoder, resume, and bad input.

use gaitscope::policy::{EncoderKind, Policy};
use serde_json::Value;
use std::path::Path;
use std::process::{Command, Output};

fn gaitscope(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_gaitscope"))
        .args(args)
        .output()
        .expect("binary runs")
}

fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

fn steps_done(dir: &Path) -> u64 {
    let meta: Value =
        serde_json::from_slice(&std::fs::read(dir.join("checkpoint.json")).unwrap()).unwrap();
    meta["steps_done"].as_u64().unwrap()
}

const SMALL: [&str; 8] = [
    "--learning-starts",
    "100",
    "--batch-size",
    "32",
    "--buffer-size",
    "2000",
    "--checkpoint-every",
    "150",
];

#[test]
fn short_runs_of_every_encoder_write_loadable_checkpoints_and_resume() {
    for encoder in ["none", "lstm", "mlp-window"] {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join(encoder);
        let dir_s = dir.to_str().unwrap();
        let mut args = vec![
            "train",
            "--encoder",
            encoder,
            "--steps",
            "250",
            "--out",
            dir_s,
            "--quiet",
        ];
        args.extend(SMALL);
        let out = gaitscope(&args);
        assert!(out.status.success(), "{encoder}: {}", stderr(&out));
        assert_eq!(steps_done(&dir), 250);
        let kind: EncoderKind = serde_json::from_value(Value::from(encoder)).unwrap();
        let policy = Policy::load(&dir, Some(kind)).unwrap();
        assert_eq!(policy.net().encoder, kind);
        // Metrics in CleanRL's namespaces: losses after warm-up, episodes if any ended.
        let metrics = std::fs::read_to_string(dir.join("metrics.jsonl")).unwrap();
        for line in metrics.lines() {
            let v: Value = serde_json::from_str(line).unwrap();
            assert!(v["global_step"].as_u64().unwrap() <= 250);
            assert!(
                v.get("charts/episodic_return").is_some() || v.get("losses/qf1").is_some(),
                "{line}"
            );
        }
        assert!(dir.join("replay.bin").exists() && dir.join("train_state.json").exists());

        // Refuses to overwrite; resumes to a higher total without repeating the encoder.
        let out = gaitscope(&args);
        assert!(
            stderr(&out).contains("already holds a checkpoint"),
            "{}",
            stderr(&out)
        );
        let out = gaitscope(&["train", "--resume", dir_s, "--steps", "320", "--quiet"]);
        assert!(out.status.success(), "resume {encoder}: {}", stderr(&out));
        assert_eq!(steps_done(&dir), 320);

        // A fresh checkout has no replay.bin (git-ignored): resume refills the buffer.
        std::fs::remove_file(dir.join("replay.bin")).unwrap();
        let out = gaitscope(&["train", "--resume", dir_s, "--steps", "400", "--quiet"]);
        assert!(
            out.status.success(),
            "resume without replay {encoder}: {}",
            stderr(&out)
        );
        assert!(
            stderr(&out).contains("refilling the replay buffer: 320 transitions"),
            "{}",
            stderr(&out)
        );
        assert_eq!(steps_done(&dir), 400);
        let state: Value =
            serde_json::from_str(&std::fs::read_to_string(dir.join("train_state.json")).unwrap())
                .unwrap();
        let resumes = state["resumes"].as_array().unwrap();
        assert_eq!(resumes.len(), 2, "{resumes:?}");
        assert_eq!(resumes[0]["buffer"], "restored");
        assert_eq!(resumes[1]["buffer"], "refilled");
        assert_eq!(resumes[1]["step"], 320);
        assert_eq!(resumes[1]["refill_transitions"], 320);
        if encoder == "none" {
            // eval names a run whose buffer was refilled (its outputs in the temp folder).
            let eval_out = tmp.path().join("eval");
            let out = gaitscope(&[
                "eval",
                "--checkpoint",
                dir_s,
                "--episodes",
                "1",
                "--max-steps",
                "20",
                "--out",
                eval_out.to_str().unwrap(),
            ]);
            assert!(out.status.success(), "{}", stderr(&out));
            let text = String::from_utf8_lossy(&out.stdout);
            assert!(
                text.contains(
                    "none resumed with a refilled replay buffer at step 320 (320 transitions"
                ),
                "{text}"
            );
        }
    }
}

#[test]
fn the_replay_buffer_can_live_outside_the_run_folder() {
    let tmp = tempfile::tempdir().unwrap();
    let (dir, cache) = (tmp.path().join("run"), tmp.path().join("cache/run"));
    let (dir_s, cache_s) = (dir.to_str().unwrap(), cache.to_str().unwrap());
    let mut args = vec![
        "train",
        "--encoder",
        "none",
        "--steps",
        "250",
        "--out",
        dir_s,
        "--replay-dir",
        cache_s,
        "--quiet",
    ];
    args.extend(SMALL);
    let out = gaitscope(&args);
    assert!(out.status.success(), "{}", stderr(&out));
    assert!(cache.join("replay.bin").exists() && !dir.join("replay.bin").exists());
    // The run remembers where its buffer is, but a plain --resume does not follow a folder the
    // run folder names (issue 49): it says which flag to repeat, and nothing runs.
    let out = gaitscope(&["train", "--resume", dir_s, "--steps", "300", "--quiet"]);
    assert!(!out.status.success());
    assert!(
        stderr(&out).contains(&format!("repeat --replay-dir {cache_s}")),
        "{}",
        stderr(&out)
    );
    assert_eq!(steps_done(&dir), 250);
    // Named again, the resume restores it.
    let out = gaitscope(&[
        "train",
        "--resume",
        dir_s,
        "--steps",
        "300",
        "--replay-dir",
        cache_s,
        "--quiet",
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert!(!stderr(&out).contains("refilling"), "{}", stderr(&out));
    let state: Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("train_state.json")).unwrap())
            .unwrap();
    assert_eq!(state["resumes"][0]["buffer"], "restored");
    assert_eq!(state["resumes"][0]["restored_transitions"], 250);
    // --refill below the floor is refused before anything runs.
    let out = gaitscope(&[
        "train",
        "--resume",
        dir_s,
        "--steps",
        "350",
        "--replay-dir",
        cache_s,
        "--refill",
        "500",
        "--quiet",
    ]);
    assert!(!out.status.success());
    assert!(
        stderr(&out).contains("--refill 500 is below 10000"),
        "{}",
        stderr(&out)
    );
    assert_eq!(steps_done(&dir), 300);
}

#[test]
fn bad_train_input_is_a_clear_error() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("run");
    let dir_s = dir.to_str().unwrap();
    let out = gaitscope(&[
        "train",
        "--encoder",
        "none",
        "--steps",
        "0",
        "--out",
        dir_s,
        "--quiet",
    ]);
    assert!(
        stderr(&out).contains("must be at least 1"),
        "{}",
        stderr(&out)
    );
    let out = gaitscope(&["train", "--resume", "/no/such/run", "--quiet"]);
    assert!(stderr(&out).contains("does not exist"), "{}", stderr(&out));
    let out = gaitscope(&["train", "--encoder", "transformer", "--out", dir_s]);
    assert!(!out.status.success());

    // A run folder whose optimiser state is gone cannot be resumed, and says why.
    let mut args = vec![
        "train",
        "--encoder",
        "none",
        "--steps",
        "120",
        "--out",
        dir_s,
        "--quiet",
        "--no-save-replay",
    ];
    args.extend(SMALL);
    assert!(gaitscope(&args).status.success());
    let out = gaitscope(&["train", "--resume", dir_s, "--encoder", "lstm", "--quiet"]);
    assert!(
        stderr(&out).contains("is a 'none' run; --encoder lstm does not match"),
        "{}",
        stderr(&out)
    );
    std::fs::remove_file(dir.join("train_state.json")).unwrap();
    let out = gaitscope(&["train", "--resume", dir_s, "--steps", "200", "--quiet"]);
    assert!(
        stderr(&out).contains("train_state.json"),
        "{}",
        stderr(&out)
    );
}

#[test]
fn train_check_vets_options_and_config_and_writes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    let good = dir.path().join("good.json");
    std::fs::write(&good, r#"{"damage": {"threshold": 20.0}}"#).unwrap();
    let done = gaitscope(&[
        "train",
        "--check",
        "--config",
        good.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(done.status.success(), "{}", stderr(&done));
    let resolved: Value = serde_json::from_slice(&done.stdout).unwrap();
    assert_eq!(resolved["damage"]["threshold"], 20.0);
    assert_eq!(
        resolved["damage"]["alpha"],
        gaitscope::GaitConfig::default().damage.alpha
    );
    let bad = dir.path().join("bad.json");
    std::fs::write(&bad, r#"{"damage": {"thresh": 20.0}}"#).unwrap();
    let done = gaitscope(&[
        "train",
        "--check",
        "--config",
        bad.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(
        stderr(&done).contains("unknown field `thresh`"),
        "{}",
        stderr(&done)
    );
    let done = gaitscope(&[
        "train",
        "--check",
        "--batch-size",
        "0",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(stderr(&done).contains("batch size"), "{}", stderr(&done));
    // The window length comes from the config and reaches the network; --z-dim sets the latent.
    let window = dir.path().join("window.json");
    std::fs::write(&window, r#"{"context": {"len": 8}}"#).unwrap();
    let done = gaitscope(&[
        "train",
        "--check",
        "--config",
        window.to_str().unwrap(),
        "--z-dim",
        "12",
        "--batch-size",
        "64",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(done.status.success(), "{}", stderr(&done));
    let resolved: Value = serde_json::from_slice(&done.stdout).unwrap();
    assert_eq!(resolved["context"]["len"], 8);
    assert_eq!(resolved["net"]["context_len"], 8);
    assert_eq!(resolved["net"]["z_dim"], 12);
    assert_eq!(resolved["sac"]["batch_size"], 64);
    let done = gaitscope(&[
        "train",
        "--check",
        "--z-dim",
        "0",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(stderr(&done).contains("z size"), "{}", stderr(&done));
    // A warm start's source is vetted too: a paper-world baseline cannot start a dead-legs run.
    let base = dir.path().join("base");
    let made = gaitscope(&[
        "train",
        "--encoder",
        "none",
        "--steps",
        "120",
        "--quiet",
        "--out",
        base.to_str().unwrap(),
    ]);
    assert!(made.status.success(), "{}", stderr(&made));
    let check = |world: &str| {
        gaitscope(&[
            "train",
            "--check",
            "--world",
            world,
            "--init-from",
            base.to_str().unwrap(),
            "--privileged",
            "damage",
            "--out",
            out.to_str().unwrap(),
        ])
    };
    let done = check("dead-legs");
    assert!(
        stderr(&done).contains("trained in world 'paper', this run is in 'dead-legs'"),
        "{}",
        stderr(&done)
    );
    assert!(check("paper").status.success());
    // An encoder model, with the dynamics loss too, starts from it as well.
    let lstm = gaitscope(&[
        "train",
        "--check",
        "--init-from",
        base.to_str().unwrap(),
        "--encoder",
        "lstm",
        "--aux",
        "dynamics",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(lstm.status.success(), "{}", stderr(&lstm));
    assert!(!out.exists(), "--check writes nothing");
}

/// `train --aux dynamics`: a short run and its resume, the heads saved with every checkpoint
/// and tied to it by CRC, `losses/aux` logged, the checkpoint read by every command that acts,
/// and the flags' mistakes refused.
#[test]
fn a_run_with_the_dynamics_loss_saves_resumes_and_is_read_everywhere() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("lstm-aux");
    let d = dir.to_str().unwrap();
    let out = gaitscope(
        &[
            &[
                "train",
                "--encoder",
                "lstm",
                "--aux",
                "dynamics",
                "--aux-weight",
                "0.5",
            ][..],
            // Losses are logged every 1,000 steps.
            &["--steps", "1000", "--seed", "3", "--quiet", "--out", d],
            &SMALL,
        ]
        .concat(),
    );
    assert!(out.status.success(), "{}", stderr(&out));
    assert_eq!(steps_done(&dir), 1000);
    let meta: Value =
        serde_json::from_slice(&std::fs::read(dir.join("checkpoint.json")).unwrap()).unwrap();
    assert_eq!(meta["sac"]["aux"]["kind"], "dynamics");
    assert_eq!(meta["sac"]["aux"]["weight"], 0.5);
    assert!(dir.join("aux.safetensors").exists());
    let state: Value =
        serde_json::from_slice(&std::fs::read(dir.join("train_state.json")).unwrap()).unwrap();
    assert!(state["aux"]["norm"]["count"].as_f64().unwrap() > 900.0);
    let metrics = std::fs::read_to_string(dir.join("metrics.jsonl")).unwrap();
    assert!(metrics.contains("\"losses/aux\"") && metrics.contains("\"losses/aux_critic\""));

    // The flags cannot change on resume; the resume goes on with the heads.
    let e = stderr(&gaitscope(&["train", "--resume", d, "--aux", "none"]));
    assert!(e.contains("cannot change on resume"), "{e}");
    let out = gaitscope(&["train", "--resume", d, "--steps", "1150", "--quiet"]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert_eq!(steps_done(&dir), 1150);

    // Every command that acts reads the checkpoint (the heads are not needed to act).
    let policy = Policy::load(&dir, None).unwrap();
    assert_eq!(policy.net().encoder, EncoderKind::Lstm);
    for args in [
        vec![
            "rollout",
            "--checkpoint",
            d,
            "--episodes",
            "1",
            "--max-steps",
            "20",
        ],
        vec![
            "eval",
            "--checkpoint",
            d,
            "--episodes",
            "1",
            "--max-steps",
            "20",
            "--out",
        ],
    ] {
        let mut args = args;
        let eval_out = tmp.path().join("eval");
        if args[0] == "eval" {
            args.push(eval_out.to_str().unwrap());
        }
        let out = gaitscope(&args);
        assert!(out.status.success(), "{args:?}: {}", stderr(&out));
    }

    // Heads that do not belong to the checkpoint are refused, not trained on.
    let heads = dir.join("aux.safetensors");
    let mut bytes = std::fs::read(&heads).unwrap();
    let last = bytes.len() - 1;
    bytes[last] ^= 0x40;
    std::fs::write(&heads, &bytes).unwrap();
    let e = stderr(&gaitscope(&[
        "train", "--resume", d, "--steps", "1300", "--quiet",
    ]));
    assert!(e.contains("aux.safetensors") && e.contains("CRC-32"), "{e}");
    std::fs::remove_file(&heads).unwrap();
    let e = stderr(&gaitscope(&[
        "train", "--resume", d, "--steps", "1300", "--quiet",
    ]));
    assert!(
        e.contains("aux.safetensors") && e.contains("cannot read"),
        "{e}"
    );
    assert_eq!(steps_done(&dir), 1150, "nothing trained");
}

#[test]
fn aux_flags_are_checked() {
    let check = |extra: &[&str]| {
        let out = gaitscope(
            &[
                &["train", "--check", "--out", "/tmp/never-written"][..],
                extra,
            ]
            .concat(),
        );
        (
            out.status.success(),
            stderr(&out),
            String::from_utf8_lossy(&out.stdout).into_owned(),
        )
    };
    let (ok, e, printed) = check(&["--aux", "dynamics"]);
    assert!(ok, "{e}");
    let resolved: Value = serde_json::from_str(printed.trim()).unwrap();
    assert_eq!(
        resolved["sac"]["aux"],
        serde_json::json!({"kind": "dynamics", "weight": 1.0})
    );
    // Without --aux the resolved config is today's: no aux section at all.
    let (_, _, printed) = check(&[]);
    assert!(!printed.contains("aux"), "{printed}");
    for (extra, message) in [
        (
            vec!["--aux", "dynamics", "--encoder", "none"],
            "not --encoder none",
        ),
        (
            vec!["--aux", "contrastive"],
            "possible values: none, dynamics",
        ),
        (
            vec!["--aux-weight", "2"],
            "--aux-weight needs --aux dynamics",
        ),
        (
            vec!["--aux", "dynamics", "--aux-weight=-1"],
            "must be a number in (0, 1000]",
        ),
        (
            vec!["--aux", "dynamics", "--aux-weight", "NaN"],
            "must be a number in (0, 1000]",
        ),
    ] {
        let (ok, e, _) = check(&extra);
        assert!(!ok && e.contains(message), "{extra:?}: {e}");
    }
    assert!(!Path::new("/tmp/never-written").exists());
}

/// A run folder's numbers are checked on resume as a fresh run's are: a hand-edited
/// checkpoint.json with a discount of −1 or a reset noise of 1e308 (which panicked inside the
/// random-number library) is refused with the range, and the folder is left as it was.
#[test]
fn a_hand_edited_config_out_of_range_is_refused_on_resume() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("run");
    let d = dir.to_str().unwrap();
    let out = gaitscope(
        &[
            &[
                "train",
                "--encoder",
                "none",
                "--steps",
                "200",
                "--quiet",
                "--out",
                d,
            ][..],
            &SMALL,
        ]
        .concat(),
    );
    assert!(out.status.success(), "{}", stderr(&out));
    let meta_path = dir.join("checkpoint.json");
    let good = std::fs::read(&meta_path).unwrap();
    type Edit = fn(&mut Value);
    let cases: [(Edit, &str); 5] = [
        (
            |m| m["sac"]["gamma"] = (-1.0).into(),
            "SAC gamma must lie in [0, 1), got -1",
        ),
        (
            |m| m["sac"]["tau"] = 0.0.into(),
            "SAC tau must lie in (0, 1]",
        ),
        (
            |m| m["sac"]["learning_rate"] = 5.0.into(),
            "SAC learning rate must lie in (0, 1]",
        ),
        (
            |m| m["sac"]["initial_alpha"] = 1e308.into(),
            "SAC initial alpha must lie in (0, 1e6]",
        ),
        (
            |m| m["env"]["env"]["reset_noise_scale"] = 1e308.into(),
            "env.reset_noise_scale must lie in [0, 1]",
        ),
    ];
    for (edit, says) in cases {
        let mut meta: Value = serde_json::from_slice(&good).unwrap();
        edit(&mut meta);
        let text = serde_json::to_vec_pretty(&meta).unwrap();
        std::fs::write(&meta_path, &text).unwrap();
        let out = gaitscope(&["train", "--resume", d, "--steps", "300", "--quiet"]);
        let e = stderr(&out);
        assert!(!out.status.success() && e.contains(says), "{says}: {e}");
        assert!(!e.contains("panicked"), "{e}");
        assert_eq!(
            std::fs::read(&meta_path).unwrap(),
            text,
            "{says}: the file changed"
        );
        assert_eq!(steps_done(&dir), 200);
    }
    // The state's own numbers too: a wall time of −1e308 seconds was taken as it stood.
    std::fs::write(&meta_path, &good).unwrap();
    let state_path = dir.join("train_state.json");
    let mut state: Value = serde_json::from_slice(&std::fs::read(&state_path).unwrap()).unwrap();
    state["wall_time_s"] = (-1e308).into();
    std::fs::write(&state_path, serde_json::to_vec(&state).unwrap()).unwrap();
    let out = gaitscope(&["train", "--resume", d, "--steps", "300", "--quiet"]);
    let e = stderr(&out);
    assert!(
        !out.status.success() && e.contains("wall_time_s -1e308 must lie in [0,"),
        "{e}"
    );
}
