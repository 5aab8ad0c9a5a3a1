//! eval and probe end to end on small saved models: determinism, outputs, clear errors.

mod common;

use candle_core::Device;
use gaitscope::eval::{EvalOptions, evaluate, rescore, write_outputs};
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
        imported_from: None,
    };
    model.save(dir, &record).unwrap();
}

fn options(checkpoints: Vec<std::path::PathBuf>, threads: usize) -> EvalOptions {
    EvalOptions {
        checkpoints,
        told_healthy: Vec::new(),
        episodes: 6,
        seed_base: 77,
        conditions: vec![Condition::Healthy.into(), Condition::Severe.into()],
        scenarios: Vec::new(),
        max_steps: 60,
        threads,
    }
}

/// A baseline (seed 1) and an LSTM encoder (seed 2) saved under `tmp`.
fn baseline_and_encoder(tmp: &Path) -> (std::path::PathBuf, std::path::PathBuf) {
    let (base, enc) = (tmp.join("baseline"), tmp.join("encoder"));
    save_model(&base, EncoderKind::None, 1);
    save_model(&enc, EncoderKind::Lstm, 2);
    (base, enc)
}

#[test]
fn eval_is_deterministic_paired_and_writes_its_outputs() {
    let tmp = tempfile::tempdir().unwrap();
    let (base, enc) = baseline_and_encoder(tmp.path());
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
            .filter(|e| e.model == model && e.condition == Condition::Severe.into())
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
    // One run per model: no across-seed tables or seed-level tests that cannot mean anything.
    assert!(!md.contains("Across training seeds"), "{md}");
    assert!(md.contains("One training seed per model"), "{md}");
    let out = tmp.path().join("eval-out");
    let written = write_outputs(&a, &out).unwrap();
    // eval.json and the two per-run figures; no across-seed figures.
    assert_eq!(written.len(), 3, "{written:?}");
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

#[test]
fn a_saved_evaluation_summarised_again_gives_the_same_tables_and_bad_files_are_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let (base, enc) = baseline_and_encoder(tmp.path());
    let report = evaluate(&options(vec![base, enc], 2)).unwrap();
    let out = tmp.path().join("saved");
    write_outputs(&report, &out).unwrap();
    let saved = out.join("eval.json");
    let again = rescore(&saved).unwrap();
    assert_eq!(again.episodes, report.episodes);
    assert_eq!(again.markdown(), report.markdown());
    // Written again, the file is the same too (its episodes and every summary).
    let out2 = tmp.path().join("again");
    write_outputs(&again, &out2).unwrap();
    assert_eq!(
        std::fs::read(out2.join("eval.json")).unwrap(),
        std::fs::read(&saved).unwrap()
    );
    // Through the CLI, options that choose episodes are refused beside --rescore.
    let path = saved.to_str().unwrap();
    let cli = gaitscope(&["eval", "--rescore", path, "--out", out2.to_str().unwrap()]);
    assert!(
        cli.status.success(),
        "{}",
        String::from_utf8_lossy(&cli.stderr)
    );
    assert_eq!(
        String::from_utf8_lossy(&cli.stdout).trim_end(),
        report.markdown().trim_end()
    );
    let cli = gaitscope(&["eval", "--rescore", path, "--episodes", "5"]);
    assert!(!cli.status.success());
    assert!(String::from_utf8_lossy(&cli.stderr).contains("cannot be used with"));

    // Bad files: clear errors naming the file, nothing written.
    let text = std::fs::read_to_string(&saved).unwrap();
    let json: serde_json::Value = serde_json::from_str(&text).unwrap();
    let write = |name: &str, body: &str| {
        let p = tmp.path().join(name);
        std::fs::write(&p, body).unwrap();
        p
    };
    let mut beyond = json.clone();
    beyond["episodes"][0]["steps"] = serde_json::json!(61);
    let mut stranger = json.clone();
    stranger["episodes"][0]["seed"] = serde_json::json!(5);
    let mut no_limit = json.clone();
    no_limit["max_steps"] = serde_json::json!(0);
    let cases = [
        (
            write("torn.json", &text[..text.len() / 2]),
            "is not an evaluation's eval.json",
        ),
        (
            write("other.json", "{\"episodes\": 3}"),
            "is not an evaluation's eval.json",
        ),
        (
            write("beyond.json", &beyond.to_string()),
            "ran 61 steps, beyond its max_steps 60",
        ),
        (
            write("stranger.json", &stranger.to_string()),
            "seed 5 is not among its seeds",
        ),
        (
            write("no-limit.json", &no_limit.to_string()),
            "max_steps 0 out of range",
        ),
        (tmp.path().to_path_buf(), "cannot read"),
        (tmp.path().join("missing.json"), "cannot read"),
    ];
    for (path, want) in cases {
        let err = rescore(&path).unwrap_err();
        let shown = format!("{err}");
        assert!(shown.contains(want), "{}: {shown}", path.display());
        assert!(shown.contains(&*path.display().to_string()), "{shown}");
    }
    #[cfg(unix)]
    {
        let fifo = tmp.path().join("fifo.json");
        let made = Command::new("mkfifo").arg(&fifo).status().unwrap();
        assert!(made.success());
        let err = rescore(&fifo).unwrap_err();
        assert!(format!("{err}").contains("cannot read"), "{err}");
    }
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
        "--folds",
        "2",
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
        "--folds",
        "2",
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

/// The probe pipeline as a library call: probe.json beside the checkpoint, the figures, the
/// cross-validated report; bad counts refused before anything loads.
#[test]
fn probe_writes_probe_json_and_figures() {
    use gaitscope::probe::pipeline::{ProbeOptions, run};
    let tmp = tempfile::tempdir().unwrap();
    let enc = tmp.path().join("encoder");
    save_model(&enc, EncoderKind::Lstm, 3);
    let figs = tmp.path().join("figs");
    let opts = ProbeOptions {
        checkpoints: vec![enc.clone()],
        baseline: None,
        episodes: 3,
        max_steps: 80,
        seed: 2_000_000_000,
        window_every: 4,
        folds: 5,
        save: true,
        out: figs.clone(),
    };
    for (bad, reason) in [
        (
            ProbeOptions {
                folds: 1,
                ..opts.clone()
            },
            "--folds must be between 2",
        ),
        (
            ProbeOptions {
                folds: 10,
                ..opts.clone()
            },
            "the number of episodes (9)",
        ),
        (
            ProbeOptions {
                episodes: 0,
                ..opts.clone()
            },
            "at least 1",
        ),
    ] {
        let e = run(&bad).unwrap_err().to_string();
        assert!(e.contains(reason), "{e}");
    }
    assert!(
        !enc.join("probe.json").exists(),
        "refused before anything ran"
    );
    let probed = run(&opts).unwrap();
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
        "probe-cv.json",
        "probe-cv.md",
        "probe_latency.png",
    ] {
        assert!(figs.join(name).exists(), "{name}");
        assert!(probed.written.contains(&figs.join(name)), "{name} listed");
    }
    assert!(probed.written.contains(&enc.join("probe.json")));
    let (label, probes) = &probed.probes[0];
    assert_eq!(label, "encoder");
    assert!(
        probes.contains("condition, 3-way") && probes.contains("ankle_1 damaged"),
        "{probes}"
    );
    assert_eq!(probed.report.runs[0].episodes, 9);
    // Where z looks around the first trigger: files, and the four series add up to the shift
    // (the triggered joint + 7 × the others' mean + torso + goal = ‖z − z(0)‖, completeness).
    for path in [
        opts.out.join("onset-attribution.json"),
        opts.out.join("onset-attribution.md"),
        opts.out.join("probe_onset_attribution-encoder.png"),
    ] {
        assert!(path.exists() && probed.written.contains(&path), "{path:?}");
    }
    let onset = &probed.onset[0];
    assert_eq!(onset.offsets.len(), 61);
    assert!(
        onset.episodes > 0,
        "a severe episode of an untrained policy triggers"
    );
    for (i, shift) in onset.shift.iter().enumerate() {
        if !shift.is_finite() {
            continue;
        }
        let m = |g: usize| onset.mean[g][i];
        let sum = m(0) + 7.0 * m(1) + m(2) + m(3);
        assert!(
            (sum - shift).abs() <= 0.01 * shift + 1e-3,
            "offset {}: groups add to {sum}, shift {shift}",
            onset.offsets[i]
        );
    }
}

#[test]
fn eval_groups_seeds_and_pairs_them_by_training_seed() {
    let tmp = tempfile::tempdir().unwrap();
    let dirs: Vec<std::path::PathBuf> = [
        ("encoder-s2", EncoderKind::Lstm, 2),
        ("baseline", EncoderKind::None, 1),
        ("baseline-s2", EncoderKind::None, 2),
        ("encoder", EncoderKind::Lstm, 1),
    ]
    .iter()
    .map(|&(name, kind, seed)| {
        let dir = tmp.path().join(name);
        save_model(&dir, kind, seed);
        dir
    })
    .collect();
    let report = evaluate(&options(dirs, 2)).unwrap();
    // Per run too, each encoder run meets the baseline run of its own training seed.
    let per_run: Vec<(&str, &str)> = report
        .comparisons
        .iter()
        .map(|c| (c.encoder.as_str(), c.baseline.as_str()))
        .collect();
    assert_eq!(
        per_run,
        [
            ("encoder-s2", "baseline-s2"),
            ("encoder-s2", "baseline-s2"),
            ("encoder", "baseline"),
            ("encoder", "baseline"),
        ]
    );
    let seeds = &report.across_seeds;
    // 2 groups × 2 conditions, each with both seeds in training-seed order.
    assert_eq!(seeds.groups.len(), 4);
    for g in &seeds.groups {
        let train: Vec<u64> = g.runs.iter().map(|r| r.train_seed).collect();
        assert_eq!(train, [1, 2], "{}", g.group);
        assert_eq!(g.failure_modes.total(), 12);
        let i = g.success[&report.max_steps];
        assert!(i.low <= i.mean && i.mean <= i.high, "{i:?}");
    }
    assert_eq!(seeds.comparisons.len(), 2);
    for c in &seeds.comparisons {
        assert_eq!(
            (c.model.as_str(), c.reference.as_str()),
            ("encoder", "baseline")
        );
        let paired: Vec<u64> = c.per_seed.iter().map(|(s, _)| *s).collect();
        assert_eq!(paired, [1, 2]);
        let (b, cc) = c
            .per_seed
            .iter()
            .fold((0, 0), |(b, cc), (_, m)| (b + m.b, cc + m.c));
        assert_eq!((c.pooled.b, c.pooled.c), (b, cc));
    }
    // rliable's aggregates: an IQM per group and condition (of two runs: their mean), the
    // probability of improvement of the encoder over the baseline per condition.
    for g in &seeds.groups {
        let rates: Vec<f64> = g
            .runs
            .iter()
            .map(|r| r.success[&report.max_steps].rate)
            .collect();
        let mean = rates.iter().sum::<f64>() / rates.len() as f64;
        assert!((g.success_iqm.mean - mean).abs() < 1e-12, "{}", g.group);
    }
    assert_eq!(seeds.improvements.len(), 2);
    for i in &seeds.improvements {
        assert_eq!(
            (i.better.as_str(), i.than.as_str()),
            ("encoder", "baseline")
        );
        let p = i.probability_of_improvement;
        assert!((0.0..=1.0).contains(&p.mean) && p.low <= p.mean && p.mean <= p.high);
    }
    let md = report.markdown();
    assert!(
        md.contains("Across training seeds")
            && md.contains("Failure modes")
            && md.contains("IQM success@60")
            && md.contains("Probability of improvement"),
        "{md}"
    );
    let json = serde_json::to_value(&report).unwrap();
    assert!(
        json["across_seeds"]["improvements"][0]["probability_of_improvement"]["mean"].is_number()
    );
    assert!(json["across_seeds"]["groups"][0]["success_iqm"]["low"].is_number());
    // The per-run figure: four runs, two models, two colours (baseline blue, the encoder the
    // next free one), never a colour per run.
    let out = tmp.path().join("out");
    write_outputs(&report, &out).unwrap();
    let figure = out.join("success_by_condition.png");
    let (blue, _) = common::count_colour(&figure, [0, 114, 178]);
    let (vermilion, _) = common::count_colour(&figure, [213, 94, 0]);
    let (green, _) = common::count_colour(&figure, [0, 158, 115]);
    assert!(
        blue > 100 && vermilion > 100 && green == 0,
        "{blue} {vermilion} {green}"
    );
}

#[test]
fn two_runs_with_one_training_seed_in_a_group_are_an_error() {
    let tmp = tempfile::tempdir().unwrap();
    let (a, b) = (tmp.path().join("baseline"), tmp.path().join("baseline-s1"));
    save_model(&a, EncoderKind::None, 1);
    save_model(&b, EncoderKind::None, 1);
    let err = evaluate(&options(vec![a, b], 1)).unwrap_err().to_string();
    assert!(err.contains("both training seed 1 of 'baseline'"), "{err}");
}

#[test]
fn probe_cross_validates_several_seeds() {
    let tmp = tempfile::tempdir().unwrap();
    let (a, b) = (
        tmp.path().join("encoder-lstm"),
        tmp.path().join("encoder-lstm-s1"),
    );
    save_model(&a, EncoderKind::Lstm, 3);
    save_model(&b, EncoderKind::Lstm, 4);
    let out_dir = tmp.path().join("probe");
    let out = gaitscope(&[
        "probe",
        "--checkpoint",
        a.to_str().unwrap(),
        b.to_str().unwrap(),
        "--episodes",
        "2",
        "--folds",
        "3",
        "--max-steps",
        "60",
        "--out",
        out_dir.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out_dir.join("probe-cv.json")).unwrap()).unwrap();
    let runs = json["runs"].as_array().unwrap();
    assert_eq!(runs.len(), 2);
    for run in runs {
        assert_eq!(run["episodes"], 6);
        // z, raw obs, raw window × all steps, post-trigger steps.
        assert_eq!(run["condition"].as_array().unwrap().len(), 6);
        assert_eq!(run["joints"].as_array().unwrap().len(), 8);
        // And each joint from the raw observation alone, the control for z's.
        assert_eq!(run["joints_from_obs"].as_array().unwrap().len(), 8);
        for c in run["condition"].as_array().unwrap() {
            assert_eq!(c["folds"].as_array().unwrap().len(), 3, "{c}");
        }
    }
    for name in [
        "probe-cv.md",
        "probe_latency.png",
        "encoder-lstm/pca_z.png",
        "encoder-lstm-s1/pca_z.png",
    ] {
        assert!(out_dir.join(name).exists(), "{name}");
    }
    // The LSTM keeps its colour of every figure (vermilion, beside the baseline's blue) in a
    // figure without the baseline.
    let latency = out_dir.join("probe_latency.png");
    let (vermilion, _) = common::count_colour(&latency, [213, 94, 0]);
    let (blue, _) = common::count_colour(&latency, [0, 114, 178]);
    assert!(vermilion > 100 && blue == 0, "{vermilion} {blue}");
    let e = gaitscope(&[
        "probe",
        "--checkpoint",
        a.to_str().unwrap(),
        "--episodes",
        "1",
        "--folds",
        "5",
    ]);
    assert!(String::from_utf8_lossy(&e.stderr).contains("--folds must be between 2 and"));
}

/// Long work shows a bar with ETA on a terminal (a pty from util-linux's `script`) and stays
/// quiet when its stderr is piped.
#[test]
fn eval_and_probe_show_progress_on_a_terminal_only() {
    let tmp = tempfile::tempdir().unwrap();
    let enc = tmp.path().join("encoder");
    save_model(&enc, EncoderKind::Lstm, 2);
    let enc_s = enc.to_str().unwrap();
    let out_s = tmp.path().join("out");
    let out_s = out_s.to_str().unwrap();
    let exe = env!("CARGO_BIN_EXE_gaitscope");
    for (args, bar) in [
        (
            vec![
                "eval",
                "--checkpoint",
                enc_s,
                "--episodes",
                "3",
                "--max-steps",
                "40",
                "--out",
                out_s,
            ],
            "eval episodes",
        ),
        (
            vec![
                "probe",
                "--checkpoint",
                enc_s,
                "--episodes",
                "3",
                "--max-steps",
                "80",
                "--no-save",
                "--out",
                out_s,
            ],
            "probe episodes",
        ),
    ] {
        let piped = gaitscope(&args);
        assert!(
            piped.status.success(),
            "{}",
            String::from_utf8_lossy(&piped.stderr)
        );
        let stderr = String::from_utf8_lossy(&piped.stderr);
        assert!(!stderr.contains(bar), "piped: no bar: {stderr}");
        let typescript = tmp.path().join("typescript");
        let status = Command::new("script")
            .arg("-qec")
            .arg(format!("{exe} {}", args.join(" ")))
            .arg(&typescript)
            .stdout(std::process::Stdio::null())
            .status()
            .expect("util-linux `script` gives the command a terminal");
        assert!(status.success());
        let shown = std::fs::read_to_string(&typescript).unwrap();
        assert!(
            shown.contains(bar) && shown.contains('<'),
            "on a terminal: {shown}"
        );
    }
}
