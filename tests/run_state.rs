//! The committed training runs (checkpoints/ and checkpoints/seeds/): none ever updated from a
//! buffer below the refill floor. A run's first update comes once the buffer holds a batch (and
//! the warm-up is over), so steps_done − adam_steps is max(batch, learning starts) − 1 in a run
//! that never lost its buffer; a resume that refilled must have refilled at least the floor (or
//! everything the run had seen). Two runs once broke this (an empty-buffer resume: 510).

use serde_json::Value;
use std::path::Path;

fn runs() -> Vec<std::path::PathBuf> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("checkpoints");
    let mut out = Vec::new();
    for dir in [root.clone(), root.join("seeds")] {
        for entry in std::fs::read_dir(&dir).unwrap().flatten() {
            if entry.path().join("train_state.json").exists() {
                out.push(entry.path());
            }
        }
    }
    out.sort();
    out
}

fn json(path: &Path) -> Value {
    serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap()
}

#[test]
fn no_committed_run_updated_from_a_near_empty_buffer() {
    let runs = runs();
    assert!(runs.len() >= 6, "the seed runs are committed: {runs:?}");
    for run in runs {
        let state = json(&run.join("train_state.json"));
        let sac = &json(&run.join("checkpoint.json"))["sac"];
        let steps = state["steps_done"].as_u64().unwrap();
        let actor_updates = state["adam_steps"][0].as_u64().unwrap();
        let first_update = sac["batch_size"]
            .as_u64()
            .unwrap()
            .max(sac["learning_starts"].as_u64().unwrap());
        assert_eq!(
            steps - actor_updates,
            first_update - 1,
            "{}: updates missing or extra against a run that never lost its buffer",
            run.display()
        );
        for resume in state["resumes"].as_array().into_iter().flatten() {
            if resume["buffer"] == "refilled" {
                let refill = resume["refill_transitions"].as_u64().unwrap();
                let at = resume["step"].as_u64().unwrap();
                assert!(
                    refill >= gaitscope::train::MIN_REFILL as u64 || refill >= at,
                    "{}: resumed at {at} with a refill of only {refill}",
                    run.display()
                );
            }
        }
    }
}
