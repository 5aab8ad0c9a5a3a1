//! `import-sb3` against Stable-Baselines3's own outputs (tests/fixtures/make_sb3_fixtures.py):
//! the imported policies act as SB3's do, and broken archives are refused, leaving nothing.

use gaitscope::policy::sb3::{ImportEncoder, Sb3Error, import_sb3};
use gaitscope::policy::{ActionMode, Policy};
use serde_json::Value;
use std::io::{Read, Write};
use std::path::{Path, PathBuf};

mod common;

const MODELS: [&str; 3] = ["sb3_baseline", "sb3_lstm", "sb3_lstm_shared"];
const WINDOW: usize = 16 * (29 + 8);

fn fixture(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join(format!("tests/fixtures/{name}"))
}

fn reference() -> Value {
    let text = std::fs::read_to_string(fixture("sb3_reference.json")).expect("fixture readable");
    serde_json::from_str(&text).expect("fixture is JSON")
}

fn floats(v: &Value) -> Vec<f64> {
    v.as_array()
        .expect("an array")
        .iter()
        .map(|x| x.as_f64().expect("a number"))
        .collect()
}

fn max_abs_diff(a: &[f64], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max)
}

fn imported(dir: &Path, model: &str) -> PathBuf {
    let out = dir.join(model);
    import_sb3(&fixture(&format!("{model}.zip")), &out, ImportEncoder::Auto)
        .unwrap_or_else(|e| panic!("{model}: {e}"));
    out
}

#[test]
fn imported_policies_act_as_sb3s_do() {
    let reference = reference();
    let tmp = tempfile::tempdir().unwrap();
    for model in MODELS {
        let spec = &reference["models"][model];
        let policy = Policy::load(&imported(tmp.path(), model), None).unwrap();
        assert_eq!(
            policy.net().encoder.name(),
            spec["encoder"].as_str().unwrap()
        );
        assert_eq!(
            policy.net().share_encoder,
            spec["share_features_extractor"] == Value::Bool(true)
        );
        let (mut worst_action, mut worst_h) = (0f64, 0f64);
        let samples = spec["samples"].as_array().unwrap();
        assert_eq!(samples.len(), 50);
        for sample in samples {
            let folded: Vec<f32> = floats(&sample["obs"]).iter().map(|&v| v as f32).collect();
            let (window, obs) = match policy.net().encoder.uses_window() {
                true => (Some(&folded[..WINDOW]), &folded[WINDOW..]),
                false => (None, &folded[..]),
            };
            let decision = policy
                .act_batch(obs, window, ActionMode::Deterministic, None)
                .unwrap()
                .remove(0);
            worst_action =
                worst_action.max(max_abs_diff(&decision.action, &floats(&sample["action"])));
            if let Some(h) = sample.get("h_t") {
                let z: Vec<f64> = decision.z.unwrap().iter().map(|&v| v as f64).collect();
                worst_h = worst_h.max(max_abs_diff(&z, &floats(h)));
            }
        }
        eprintln!("{model}: max |Δaction| {worst_action:.2e}, max |Δh_T| {worst_h:.2e}");
        assert!(
            worst_action < 1e-5,
            "{model}: actions differ by {worst_action}"
        );
        assert!(worst_h < 1e-5, "{model}: h_T differs by {worst_h}");
    }
}

/// Steps from the start until `key` first differs from the Gymnasium rollout by more than `tol`.
fn agreeing_prefix(ours: &[Value], theirs: &[Value], key: &str, tol: f64) -> usize {
    ours.iter()
        .zip(theirs)
        .take_while(|(o, t)| max_abs_diff(&floats(&o[key]), &floats(&t[key])) <= tol)
        .count()
}

fn rollout_jsonl(args: &[&std::ffi::OsStr]) -> Vec<Value> {
    let args = std::iter::once("rollout".as_ref()).chain(args.iter().copied());
    common::gaitscope_json_lines(args).unwrap_or_else(|e| panic!("{e}"))
}

/// The policy-driven rollout from the fixed state follows Gymnasium's. SB3's float32 actions and
/// ours differ in the last bits (summation order), which the contact dynamics amplify in qvel;
/// replaying SB3's own actions shows the physics itself agrees to 1e-9 throughout.
#[test]
fn imported_policies_follow_their_gymnasium_rollouts() {
    let reference = reference();
    let tmp = tempfile::tempdir().unwrap();
    for model in MODELS {
        let rollout = &reference["models"][model]["rollout"];
        let theirs = rollout["steps"].as_array().unwrap();
        let init = tmp.path().join(format!("{model}-init.json"));
        let state = serde_json::json!({"qpos": rollout["init_qpos"], "qvel": rollout["init_qvel"]});
        std::fs::write(&init, state.to_string()).unwrap();
        let checkpoint = imported(tmp.path(), model);
        let condition = rollout["condition"].as_str().unwrap();
        let ours = rollout_jsonl(&[
            "--checkpoint".as_ref(),
            checkpoint.as_os_str(),
            "--init-state".as_ref(),
            init.as_os_str(),
            "--condition".as_ref(),
            condition.as_ref(),
            "--max-steps".as_ref(),
            "100".as_ref(),
            "--jsonl".as_ref(),
        ]);
        assert_eq!(ours.len(), theirs.len(), "{model}: episode lengths");
        let prefix = |key, tol| agreeing_prefix(&ours, theirs, key, tol);
        eprintln!(
            "{model}: {} steps; within 1e-6 / 1e-3 for: action {} / {}, qpos {} / {}, qvel {} / {}",
            ours.len(),
            prefix("action", 1e-6),
            prefix("action", 1e-3),
            prefix("qpos", 1e-6),
            prefix("qpos", 1e-3),
            prefix("qvel", 1e-6),
            prefix("qvel", 1e-3),
        );
        // f32 policies on chaotic contact dynamics part eventually; the start must agree.
        for (key, tol, steps) in [("action", 1e-6, 10), ("qpos", 1e-6, 10)]
            .into_iter()
            .chain(["action", "qpos", "qvel"].map(|k| (k, 1e-3, 50)))
        {
            let n = prefix(key, tol);
            assert!(
                n >= steps,
                "{model}: {key} parts from Gymnasium's by {tol} at step {n}"
            );
        }

        let actions: Vec<Value> = theirs.iter().map(|s| s["action"].clone()).collect();
        let actions_file = tmp.path().join(format!("{model}-actions.json"));
        std::fs::write(&actions_file, Value::Array(actions).to_string()).unwrap();
        let replayed = rollout_jsonl(&[
            "--init-state".as_ref(),
            init.as_os_str(),
            "--actions".as_ref(),
            actions_file.as_os_str(),
            "--condition".as_ref(),
            condition.as_ref(),
            "--jsonl".as_ref(),
        ]);
        assert_eq!(replayed.len(), theirs.len());
        for key in ["qpos", "qvel"] {
            let exact = agreeing_prefix(&replayed, theirs, key, 1e-9);
            assert_eq!(
                exact,
                theirs.len(),
                "{model}: replayed {key} parts at {exact}"
            );
        }
    }
}

/// Rewrites one entry of a zip archive, keeping the others byte for byte.
fn rewrite_entry(zip_bytes: &[u8], name: &str, edit: impl Fn(Vec<u8>) -> Vec<u8>) -> Vec<u8> {
    let mut input = zip::ZipArchive::new(std::io::Cursor::new(zip_bytes)).unwrap();
    let mut output = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    let options =
        zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Stored);
    let mut found = false;
    for i in 0..input.len() {
        let mut file = input.by_index(i).unwrap();
        let entry = file.name().unwrap().to_string();
        let mut bytes = Vec::new();
        file.read_to_end(&mut bytes).unwrap();
        if entry == name || entry.ends_with(&format!("/{name}")) {
            bytes = edit(bytes);
            found = true;
        }
        output.start_file(entry, options).unwrap();
        output.write_all(&bytes).unwrap();
    }
    assert!(found, "no entry {name}");
    output.finish().unwrap().into_inner()
}

fn with_data(zip_bytes: &[u8], edit: impl Fn(&mut Value)) -> Vec<u8> {
    rewrite_entry(zip_bytes, "data", |bytes| {
        let mut data: Value = serde_json::from_slice(&bytes).unwrap();
        edit(&mut data);
        serde_json::to_vec(&data).unwrap()
    })
}

fn replace_bytes(bytes: Vec<u8>, from: &[u8], to: &[u8]) -> Vec<u8> {
    assert_eq!(from.len(), to.len(), "same length keeps the pickle valid");
    let at = bytes
        .windows(from.len())
        .position(|w| w == from)
        .expect("pattern present");
    let mut bytes = bytes;
    bytes[at..at + to.len()].copy_from_slice(to);
    bytes
}

/// Peak memory a refused archive may cost the importer (measured: 11–14 MB for every case; the
/// zip bomb's entry is refused from the archive's directory before inflating, the billion
/// laughs by the pickle guard's dry run before anything is built).
const HOSTILE_PEAK_MB: f64 = 64.0;

/// Runs `cmd` to its end: its exit code and its own peak resident memory (wait4's rusage).
#[expect(
    clippy::zombie_processes,
    reason = "wait4 reaps the child, returning its rusage with it"
)]
fn peak_memory(mut cmd: std::process::Command) -> (i32, f64) {
    let child = cmd.spawn().unwrap();
    let mut status = 0;
    // SAFETY: plain C structs, zeroed, filled by wait4 for the child we just spawned.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    let pid = unsafe { libc::wait4(child.id() as i32, &mut status, 0, &mut usage) };
    assert_eq!(pid, child.id() as i32, "wait4");
    let code = if libc::WIFEXITED(status) {
        libc::WEXITSTATUS(status)
    } else {
        128 + libc::WTERMSIG(status)
    };
    // Linux reports ru_maxrss in KiB.
    (code, usage.ru_maxrss as f64 / 1024.0)
}

#[test]
fn broken_archives_are_refused_with_their_reason_and_leave_nothing() {
    let lstm = std::fs::read(fixture("sb3_lstm.zip")).unwrap();
    let baseline = std::fs::read(fixture("sb3_baseline.zip")).unwrap();
    let nan_weights = |zip: &[u8]| {
        rewrite_entry(zip, "policy.pth", |pth| {
            rewrite_entry(&pth, "data/0", |mut raw| {
                raw[..4].copy_from_slice(&f32::NAN.to_le_bytes());
                raw
            })
        })
    };
    let cases: Vec<(&str, Vec<u8>, ImportEncoder, &str)> = vec![
        (
            "truncated",
            lstm[..lstm.len() / 2].to_vec(),
            ImportEncoder::Auto,
            "not a Stable-Baselines3 archive",
        ),
        (
            "not a zip",
            b"{\"policy_class\": 1}".to_vec(),
            ImportEncoder::Auto,
            "not a readable zip",
        ),
        (
            "another algorithm",
            with_data(&baseline, |d| {
                d["policy_class"]["__module__"] = "stable_baselines3.td3.policies".into()
            }),
            ImportEncoder::Auto,
            "not a SAC model: its policy class comes from stable_baselines3.td3.policies",
        ),
        (
            "observation size",
            with_data(&baseline, |d| {
                d["observation_space"]["_shape"] = serde_json::json!([27])
            }),
            ImportEncoder::Auto,
            "shape [27]",
        ),
        (
            "action size",
            with_data(&baseline, |d| {
                d["action_space"]["_shape"] = serde_json::json!([6])
            }),
            ImportEncoder::Auto,
            "the action space must be 8 values in [-1, 1]: its shape is [6]",
        ),
        (
            "action bounds",
            with_data(&baseline, |d| {
                d["action_space"]["high"] = "[2. 2. 2. 2. 2. 2. 2. 2.]".into()
            }),
            ImportEncoder::Auto,
            "its 'high' bounds are [2.0",
        ),
        (
            "renamed tensor",
            in_policy(&baseline, &|pkl| {
                replace_bytes(pkl, b"actor.mu.weight", b"actor.MU.weight")
            }),
            ImportEncoder::Auto,
            "lacks [\"actor.mu.weight\"]; holds [\"actor.MU.weight\"]",
        ),
        (
            "unmappable extractor",
            in_policy(&lstm, &|pkl| {
                replace_bytes(pkl, b"lstm.weight_ih_l0", b"lstm.weight_ih_l1")
            }),
            ImportEncoder::Auto,
            "cannot map the features extractor",
        ),
        (
            "NaN weights",
            nan_weights(&baseline),
            ImportEncoder::Auto,
            "contains NaN or infinite values",
        ),
        (
            "wrong encoder for the observation",
            lstm.clone(),
            ImportEncoder::None,
            "--encoder none does not fit a 621-d observation",
        ),
        (
            // Bytes where weights should be: refused from the pickle's own record, before any
            // storage is read (it imported as garbage with exit 0 before).
            "byte storage",
            in_policy(&baseline, &|pkl| {
                let (from, to) = (&b"FloatStorage\n"[..], &b"ByteStorage\n"[..]);
                let at = pkl.windows(from.len()).position(|w| w == from).unwrap();
                [&pkl[..at], to, &pkl[at + from.len()..]].concat()
            }),
            ImportEncoder::Auto,
            "has dtype U8; SB3's weights are floats",
        ),
        (
            // A thousand nested tuples ahead of the state dict: refused by the dry run of the
            // pickle (candle's reader recursed on such nesting until the stack overflowed).
            "deep nesting",
            in_policy(&baseline, &|pkl| {
                let mut nested = pkl[..2].to_vec();
                nested.push(b')');
                nested.extend(std::iter::repeat_n(0x85u8, 1_000));
                nested.extend_from_slice(&pkl[2..]);
                nested
            }),
            ImportEncoder::Auto,
            "objects nest deeper than 256",
        ),
        (
            // A memo "billion laughs" ahead of the state dict: a list fetched twice into a
            // tuple, memoised, 40 times over (2⁴⁰ objects if built), then popped.
            "billion laughs",
            in_policy(&baseline, &|pkl| {
                let mut laughs = pkl[..2].to_vec();
                laughs.extend([b']', b'q', 0]);
                for i in 0..40u8 {
                    laughs.extend([b'h', i, b'h', i, 0x86, b'q', i + 1]);
                }
                laughs.push(b'0');
                laughs.extend_from_slice(&pkl[2..]);
                laughs
            }),
            ImportEncoder::Auto,
            "grows past 4000000 parts",
        ),
        (
            // A storage record cut short (its location and size dropped): candle's reader
            // panics on it; the panic is caught and reported in one line (issue 49 #12).
            "short storage tuple",
            short_storage_tuple(&baseline),
            ImportEncoder::Auto,
            "the pickle reader failed on it",
        ),
        (
            // A zip bomb: policy.pth inflates to 300 MB of zeros from a few hundred KB.
            "zip bomb",
            {
                let mut input = zip::ZipArchive::new(std::io::Cursor::new(&baseline[..])).unwrap();
                let mut output = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
                let deflated = zip::write::SimpleFileOptions::default()
                    .compression_method(zip::CompressionMethod::Deflated);
                for i in 0..input.len() {
                    let mut file = input.by_index(i).unwrap();
                    let entry = file.name().unwrap().to_string();
                    output.start_file(entry.clone(), deflated).unwrap();
                    if entry.ends_with("policy.pth") {
                        let zeros = vec![0u8; 1 << 20];
                        for _ in 0..300 {
                            output.write_all(&zeros).unwrap();
                        }
                    } else {
                        let mut bytes = Vec::new();
                        file.read_to_end(&mut bytes).unwrap();
                        output.write_all(&bytes).unwrap();
                    }
                }
                output.finish().unwrap().into_inner()
            },
            ImportEncoder::Auto,
            "inflates to 314572800 bytes (at most 268435456)",
        ),
    ];
    let tmp = tempfile::tempdir().unwrap();
    for (what, bytes, encoder, expected) in cases {
        let zip = tmp.path().join("model.zip");
        std::fs::write(&zip, &bytes).unwrap();
        let out = tmp.path().join("out").join("ckpt");
        let err = import_sb3(&zip, &out, encoder).expect_err(what).to_string();
        assert!(err.contains(expected), "{what}: {err}");
        assert!(!out.exists(), "{what}: a half-written checkpoint");
        let leftovers: Vec<_> = std::fs::read_dir(tmp.path().join("out"))
            .map(|d| d.flatten().map(|e| e.file_name()).collect())
            .unwrap_or_default();
        assert!(leftovers.is_empty(), "{what}: left {leftovers:?}");
        // The same through the CLI, in a process of its own: its peak memory stays under the
        // bound whatever the archive claims.
        let encoder = match encoder {
            ImportEncoder::Auto => "auto",
            ImportEncoder::None => "none",
            ImportEncoder::Lstm => "lstm",
        };
        let mut cli = std::process::Command::new(env!("CARGO_BIN_EXE_gaitscope"));
        cli.args(["import-sb3", "--encoder", encoder, "--out"])
            .arg(&out)
            .arg(&zip)
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null());
        let (code, peak_mb) = peak_memory(cli);
        eprintln!("{what}: exit {code}, peak RSS {peak_mb:.0} MB");
        assert_eq!(code, 1, "{what}: a clean refusal, not a panic or an abort");
        assert!(
            peak_mb < HOSTILE_PEAK_MB,
            "{what}: {peak_mb:.0} MB, the bound is {HOSTILE_PEAK_MB} MB"
        );
        assert!(!out.exists(), "{what}: a half-written checkpoint (CLI)");
    }
    // An existing folder is never overwritten.
    let out = tmp.path().join("taken");
    std::fs::create_dir(&out).unwrap();
    std::fs::write(out.join("keep.txt"), "mine").unwrap();
    let err = import_sb3(&fixture("sb3_baseline.zip"), &out, ImportEncoder::Auto).unwrap_err();
    assert!(matches!(err, Sb3Error::OutputExists(_)), "{err}");
    assert_eq!(
        std::fs::read_to_string(out.join("keep.txt")).unwrap(),
        "mine"
    );
}

/// The archive with policy.pth's pickle edited.
fn in_policy(zip: &[u8], edit: &dyn Fn(Vec<u8>) -> Vec<u8>) -> Vec<u8> {
    rewrite_entry(zip, "policy.pth", |pth| {
        rewrite_entry(&pth, "data.pkl", edit)
    })
}

/// The baseline archive with its first storage record, `('storage', FloatStorage, key, 'cpu',
/// numel)`, cut to its first four items.
fn short_storage_tuple(archive: &[u8]) -> Vec<u8> {
    in_policy(archive, &|pkl| {
        let cpu = &b"X\x03\x00\x00\x00cpu"[..];
        // After 'cpu' and its memo slot (BINPUT n): the size (BININT2), then TUPLE.
        let from = pkl.windows(cpu.len()).position(|w| w == cpu).unwrap() + cpu.len() + 2;
        assert_eq!(pkl[from], b'M', "a BININT2 size");
        [&pkl[..from], &pkl[from + 3..]].concat()
    })
}

/// A panic inside the third-party pickle reader reaches the user as one error line: no panic
/// message, no backtrace, whatever RUST_BACKTRACE says.
#[test]
fn a_parser_panic_is_one_clear_line() {
    let baseline = std::fs::read(fixture("sb3_baseline.zip")).unwrap();
    let tmp = tempfile::tempdir().unwrap();
    let zip = tmp.path().join("model.zip");
    std::fs::write(&zip, short_storage_tuple(&baseline)).unwrap();
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_gaitscope"))
        .args(["import-sb3", "--out"])
        .arg(tmp.path().join("out"))
        .arg(&zip)
        .env("RUST_BACKTRACE", "1")
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("the pickle reader failed on it"), "{err}");
    assert!(
        !err.contains("panicked at") && !err.contains("backtrace"),
        "{err}"
    );
    assert_eq!(err.trim().lines().count(), 1, "{err}");
}

#[test]
fn the_checkpoint_records_where_it_came_from() {
    use sha2::Digest;
    let tmp = tempfile::tempdir().unwrap();
    let dir = imported(tmp.path(), "sb3_lstm_shared");
    let meta = gaitscope::policy::checkpoint::read_meta(&dir).unwrap();
    let origin = meta.imported_from.expect("provenance");
    let bytes = std::fs::read(fixture("sb3_lstm_shared.zip")).unwrap();
    assert_eq!(origin.file, "sb3_lstm_shared.zip");
    assert_eq!(
        origin.version,
        reference()["stable_baselines3"].as_str().unwrap()
    );
    assert_eq!(origin.sha256, format!("{:x}", sha2::Sha256::digest(&bytes)));
    assert_eq!(meta.steps_done, 400);
    assert_eq!(meta.net.hidden, [64, 64]);
}
