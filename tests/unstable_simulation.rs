//! A diverging simulation ends the episode as unhealthy instead of silently teleporting the Ant.
//! Own test binary (one test, one thread), so the global MuJoCo log setting is safe to change.

use gaitscope::env::{ACT_DIM, AntEnv, NQ, NV, keep_mujoco_logs_on_console};
use gaitscope::{Condition, GaitConfig};

#[test]
fn diverging_state_terminates_as_unstable() {
    // SAFETY: the only test in this binary; nothing else uses MuJoCo yet.
    unsafe { keep_mujoco_logs_on_console() };
    let mut env = AntEnv::new(GaitConfig::default(), 0).unwrap();
    let mut qpos = [0.0; NQ];
    qpos[..4].copy_from_slice(&[0.0, 0.0, 0.55, 1.0]);
    let mut qvel = [0.0; NV];
    // Above MuJoCo's mjMAXVAL (1e10): mj_step warns and resets the state to qpos0.
    qvel[6] = 1e11;
    env.reset_to_state(&qpos, &qvel, Condition::Healthy)
        .unwrap();
    let out = env.step(&[0.0; ACT_DIM]).unwrap();
    assert!(out.unstable, "MuJoCo's divergence warning is noticed");
    assert!(!out.healthy && out.terminated);
    // The next episode starts clean.
    env.reset_with_seed(1);
    let out = env.step(&[0.0; ACT_DIM]).unwrap();
    assert!(!out.unstable && out.healthy);
    assert!(!std::path::Path::new("MUJOCO_LOG.TXT").exists());
}
