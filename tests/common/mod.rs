//! Test helpers: reading recordings back (Rerun chunks, values per `step`) and running the binary.
// Shared by several test crates; each uses a part of it.
#![allow(dead_code)]

use re_chunk::Chunk;

/// The recording's chunks (the blueprint travels in its own store, with random view ids).
pub fn recording_chunks(msgs: impl IntoIterator<Item = rerun::log::LogMsg>) -> Vec<Chunk> {
    msgs.into_iter()
        .filter_map(|m| match m {
            rerun::log::LogMsg::ArrowMsg(store, arrow)
                if store.kind() == rerun::StoreKind::Recording =>
            {
                Some(Chunk::from_arrow_msg(&arrow).expect("a chunk decodes"))
            }
            _ => None,
        })
        .collect()
}

/// The recording chunks of an `.rrd` file, read with Rerun's own decoder; every message must
/// decode.
pub fn read_rrd(path: &std::path::Path) -> Vec<Chunk> {
    let file = std::io::BufReader::new(std::fs::File::open(path).unwrap());
    recording_chunks(
        re_log_encoding::DecoderApp::decode_lazy(file)
            .collect::<Result<Vec<_>, _>>()
            .expect("every message decodes"),
    )
}

/// Rows logged to one entity, over all its chunks (one per step for per-step entities).
pub fn rows(chunks: &[Chunk], entity: &str) -> usize {
    chunks
        .iter()
        // Per-step rows only: a static row (series names, colours) is no step.
        .filter(|c| c.entity_path().to_string() == entity && !c.is_static())
        .map(Chunk::num_rows)
        .sum()
}

/// The stock Rerun CLI/viewer that `make test` unpacks (scripts/setup.sh --test).
pub fn stock_viewer() -> &'static std::path::Path {
    let viewer = std::path::Path::new(gaitscope::app::viewer::BUNDLED_VIEWER);
    assert!(
        viewer.exists(),
        "the stock viewer (`make test` sets it up: scripts/setup.sh --test)"
    );
    viewer
}

/// (step, value) of one entity across chunks: `read` gives one value per row of a chunk.
pub fn per_step<T>(
    chunks: &[Chunk],
    entity: &str,
    read: impl Fn(&Chunk) -> Vec<T>,
) -> Vec<(i64, T)> {
    let mut out = Vec::new();
    for c in chunks
        .iter()
        .filter(|c| c.entity_path().to_string() == entity)
    {
        let Some(steps) = c.timelines().get(&"step".into()) else {
            continue;
        };
        out.extend(steps.times_raw().iter().copied().zip(read(c)));
    }
    out
}

/// (step, text) of every TextLog line on one entity.
pub fn text_log(chunks: &[Chunk], entity: &str) -> Vec<(i64, String)> {
    let text = rerun::TextLog::descriptor_text().component;
    per_step(chunks, entity, |c| {
        c.iter_slices::<String>(text)
            .map(|s| s.iter().map(|v| v.to_string()).collect::<Vec<_>>())
            .collect()
    })
    .into_iter()
    .flat_map(|(t, lines)| lines.into_iter().map(move |l| (t, l)))
    .collect()
}

/// (step, level, text) of every TextLog row of `entity`.
pub fn text_log_levels(chunks: &[Chunk], entity: &str) -> Vec<(i64, String, String)> {
    let text = rerun::TextLog::descriptor_text().component;
    let level = rerun::TextLog::descriptor_level().component;
    per_step(chunks, entity, |c| {
        c.iter_slices::<String>(text)
            .zip(c.iter_slices::<String>(level))
            .map(|(t, l)| {
                t.iter()
                    .zip(l.iter())
                    .map(|(t, l)| (l.to_string(), t.to_string()))
                    .collect::<Vec<_>>()
            })
            .collect()
    })
    .into_iter()
    .flat_map(|(t, rows)| rows.into_iter().map(move |(l, x)| (t, l, x)))
    .collect()
}

/// Runs the gaitscope binary with `args`: its stdout's JSON lines, or its stderr if it failed.
pub fn gaitscope_json_lines<I, S>(args: I) -> Result<Vec<serde_json::Value>, String>
where
    I: IntoIterator<Item = S>,
    S: AsRef<std::ffi::OsStr>,
{
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_gaitscope"))
        .args(args)
        .output()
        .map_err(|e| format!("cannot run gaitscope: {e}"))?;
    if !out.status.success() {
        return Err(String::from_utf8_lossy(&out.stderr).into_owned());
    }
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .map(|l| serde_json::from_str(l).map_err(|e| format!("not a JSON line ({e}): {l}")))
        .collect()
}

/// Rows of an 8-wide scalar batch per `step`, for one entity (actions, fatigue, scales).
pub fn joint_series(chunks: &[Chunk], entity: &str) -> std::collections::BTreeMap<i64, [f64; 8]> {
    let scalars = rerun::Scalars::descriptor_scalars().component;
    per_step(chunks, entity, |c| {
        c.iter_slices::<f64>(scalars)
            .map(|s| <[f64; 8]>::try_from(s).expect("8 joints per row"))
            .collect()
    })
    .into_iter()
    .collect()
}

/// Which leg capsule each actuated joint moves (assets/ant.xml; docs/world.md has the table).
pub const JOINT_GEOMS: [(&str, &str); 8] = [
    ("hip_1", "left_leg_geom"),
    ("ankle_1", "left_ankle_geom"),
    ("hip_2", "right_leg_geom"),
    ("ankle_2", "right_ankle_geom"),
    ("hip_3", "back_leg_geom"),
    ("ankle_3", "third_ankle_geom"),
    ("hip_4", "rightback_leg_geom"),
    ("ankle_4", "fourth_ankle_geom"),
];

/// In Rerun, static data hides every per-step value of the same component on that entity: no
/// (entity, component) may be logged both ways (the legs' colours were, so damage never showed).
pub fn assert_no_static_shadowing(chunks: &[Chunk]) {
    use std::collections::BTreeSet;
    let (mut fixed, mut timed) = (BTreeSet::new(), BTreeSet::new());
    for c in chunks {
        let set = if c.is_static() {
            &mut fixed
        } else {
            &mut timed
        };
        for component in c.components_identifiers() {
            set.insert((c.entity_path().to_string(), component.to_string()));
        }
    }
    let both: Vec<_> = fixed.intersection(&timed).collect();
    assert!(both.is_empty(), "logged both static and per step: {both:?}");
    assert!(
        timed
            .iter()
            .any(|(e, c)| e.ends_with("world/legs") && c.contains("colors")),
        "leg colours are per step"
    );
}

/// (step → RGBA of each leg capsule, by geom name) of the legs under `root` (e.g. "/ant").
pub fn leg_colors(
    chunks: &[Chunk],
    root: &str,
) -> std::collections::BTreeMap<i64, std::collections::BTreeMap<String, [u8; 4]>> {
    let entity = format!("{root}/world/legs");
    let labels_component = rerun::Capsules3D::descriptor_labels().component;
    let labels: Vec<String> = chunks
        .iter()
        .filter(|c| c.is_static() && c.entity_path().to_string() == entity)
        .flat_map(|c| {
            c.iter_slices::<String>(labels_component)
                .collect::<Vec<_>>()
        })
        .flat_map(|s| s.iter().map(|l| l.to_string()).collect::<Vec<_>>())
        .collect();
    assert!(!labels.is_empty(), "{entity} names its capsules");
    let colors = rerun::Capsules3D::descriptor_colors().component;
    per_step(chunks, &entity, |c| {
        c.iter_slices::<u32>(colors)
            .map(|s| {
                labels
                    .iter()
                    .cloned()
                    .zip(s.iter().map(|rgba| rgba.to_be_bytes()))
                    .collect()
            })
            .collect()
    })
    .into_iter()
    .collect()
}

/// The colour a leg segment must have for a joint at torque `scale` (pinned by hand or not),
/// by hand from the key's end points: green at full torque, amber (235, 190, 50) a sliver lost
/// to red (215, 35, 35) nearly all lost, slate at 0, violet when pinned — whatever fatigue says.
pub fn expected_leg_color(scale: f64, pinned: bool) -> [u8; 4] {
    let rgb = if pinned {
        [150, 80, 210]
    } else if scale >= 1.0 {
        [70, 170, 90]
    } else if scale <= 0.0 {
        [55, 60, 75]
    } else {
        let lost = 1.0 - scale;
        let mix = |a: f64, b: f64| (a + (b - a) * lost).round() as u8;
        [mix(235.0, 215.0), mix(190.0, 35.0), mix(50.0, 35.0)]
    };
    [rgb[0], rgb[1], rgb[2], 255]
}

/// Checks every leg colour under `root` against the torque the recording's own scale series
/// says each joint has left at that step (`manual`: joints pinned by hand, by actuator index,
/// from that step on). Returns how many (step, joint) pairs had lost torque.
pub fn check_leg_colors(chunks: &[Chunk], root: &str, manual: &[(i64, usize)]) -> usize {
    let joints: Vec<String> = gaitscope::env::AntEnv::new(gaitscope::GaitConfig::default(), 0)
        .unwrap()
        .actuators()
        .iter()
        .map(|a| a.joint.clone())
        .collect();
    let scale = joint_series(chunks, &format!("{root}/joints/scale"));
    let colors = leg_colors(chunks, root);
    assert!(!colors.is_empty(), "{root}: leg colours per step");
    let mut lost = 0;
    for (step, row) in &colors {
        let Some(s) = scale.get(step) else {
            continue; // a reset frame: no step values yet
        };
        for (i, joint) in joints.iter().enumerate() {
            let geom = JOINT_GEOMS.iter().find(|(j, _)| j == joint).unwrap().1;
            let pinned = manual.iter().any(|&(at, a)| a == i && *step >= at);
            lost += usize::from(!pinned && s[i] < 1.0);
            assert_eq!(
                row[geom],
                expected_leg_color(s[i], pinned),
                "{root}: {geom} ({joint}) at step {step}, scale {}",
                s[i],
            );
        }
    }
    lost
}

/// The static series names of a plotted entity.
pub fn series_names(chunks: &[Chunk], entity: &str) -> Vec<String> {
    let names = rerun::SeriesLines::descriptor_names().component;
    chunks
        .iter()
        .filter(|c| c.is_static() && c.entity_path().to_string() == entity)
        .flat_map(|c| c.iter_slices::<String>(names).collect::<Vec<_>>())
        .flat_map(|s| s.iter().map(|l| l.to_string()).collect::<Vec<_>>())
        .collect()
}

/// The static series colours of a plotted entity (RGBA).
pub fn series_colors(chunks: &[Chunk], entity: &str) -> Vec<[u8; 4]> {
    let colors = rerun::SeriesLines::descriptor_colors().component;
    chunks
        .iter()
        .filter(|c| c.is_static() && c.entity_path().to_string() == entity)
        .flat_map(|c| c.iter_slices::<u32>(colors).collect::<Vec<_>>())
        .flat_map(|s| s.iter().map(|v| v.to_be_bytes()).collect::<Vec<_>>())
        .collect()
}

/// The display names of every view in the blueprint messages (the last layout sent comes last).
pub fn blueprint_view_names(msgs: &[rerun::log::LogMsg]) -> Vec<String> {
    let mut names = Vec::new();
    for msg in msgs {
        let rerun::log::LogMsg::ArrowMsg(store, arrow) = msg else {
            continue;
        };
        if !store.is_blueprint() {
            continue;
        }
        let chunk = Chunk::from_arrow_msg(arrow).expect("a blueprint chunk decodes");
        for component in chunk.components_identifiers() {
            if component.to_string().contains("display_name") {
                for s in chunk.iter_slices::<String>(component) {
                    names.extend(s.iter().map(|n| n.to_string()));
                }
            }
        }
    }
    names
}

/// [`blueprint_view_names`] of the blueprint activated last: the layout a viewer opens with
/// (a recording sends a default one when it opens and its lanes' own once they are known).
pub fn active_blueprint_view_names(msgs: &[rerun::log::LogMsg]) -> Vec<String> {
    let active = msgs
        .iter()
        .rev()
        .find_map(|m| match m {
            rerun::log::LogMsg::BlueprintActivationCommand(cmd) => Some(cmd.blueprint_id.clone()),
            _ => None,
        })
        .expect("a blueprint is activated");
    let ours: Vec<rerun::log::LogMsg> = msgs
        .iter()
        .filter(|m| matches!(m, rerun::log::LogMsg::ArrowMsg(store, _) if *store == active))
        .cloned()
        .collect();
    blueprint_view_names(&ours)
}

/// Saves a small untrained LSTM checkpoint into `dir` as if trained in a world whose joints
/// trigger at fatigue `threshold` and whose window is `context_len` steps.
pub fn save_checkpoint_in_world(dir: &std::path::Path, threshold: f64, context_len: usize) {
    use gaitscope::policy::{EncoderKind, NetConfig};
    let mut trained = gaitscope::GaitConfig::default();
    trained.damage.threshold = threshold;
    trained.context.len = context_len;
    let net = NetConfig {
        hidden: vec![16, 16],
        z_dim: 4,
        context_len,
        ..NetConfig::ant(EncoderKind::Lstm)
    };
    save_untrained(dir, net, &trained);
}

/// Saves an untrained model of shape `net` into `dir`, recorded as trained in `world`.
pub fn save_untrained(
    dir: &std::path::Path,
    net: gaitscope::policy::NetConfig,
    world: &gaitscope::GaitConfig,
) {
    use gaitscope::policy::checkpoint::TrainingRecord;
    use gaitscope::policy::{SacConfig, SacModel};
    let model = SacModel::new(net, 1.0, 3, &candle_core::Device::Cpu).unwrap();
    let record = TrainingRecord {
        env: world.clone(),
        sac: SacConfig::default(),
        seed: 3,
        steps_done: 0,
        episodes_done: 0,
        wall_time_s: 0.0,
        imported_from: None,
    };
    model.save(dir, &record).unwrap();
}

/// A replay buffer filled by `steps` env steps of `act` (given the observation and the window)
/// in the world `config`, reset with `seed`, windows of `net`'s length.
pub fn filled_replay(
    config: gaitscope::GaitConfig,
    net: &gaitscope::policy::NetConfig,
    steps: usize,
    seed: u64,
    mut act: impl FnMut(&[f64], &[f32]) -> Vec<f64>,
) -> gaitscope::train::replay::ReplayBuffer {
    use gaitscope::train::replay::{ReplayBuffer, Transition};
    let window_len = if net.encoder.uses_window() {
        net.context_len
    } else {
        0
    };
    let mut replay = ReplayBuffer::new(steps, net.obs_dim, net.act_dim, window_len);
    let mut env = gaitscope::AntEnv::new(config, seed).unwrap();
    let mut window = gaitscope::ContextWindow::new(net.context_len);
    let mut obs = env.reset_with_seed(seed).to_vec();
    let mut t = 0;
    for _ in 0..steps {
        let action = act(&obs, window.as_slice());
        let out = env.step(&action).unwrap();
        replay.push(Transition {
            obs: &obs,
            action: &action,
            reward: out.reward.total,
            next_obs: &out.obs,
            terminated: out.terminated,
            truncated: out.truncated,
            t_in_episode: t,
        });
        window.push(&obs, &action);
        (obs, t) = if out.done() {
            window.clear();
            (env.reset().to_vec(), 0)
        } else {
            (out.obs.to_vec(), t + 1)
        };
    }
    replay
}

/// Pixels of exactly `rgb` in an RGB(A) PNG, and its size.
pub fn count_colour(png_path: &std::path::Path, rgb: [u8; 3]) -> (usize, (u32, u32)) {
    let decoder = png::Decoder::new(std::io::BufReader::new(
        std::fs::File::open(png_path).unwrap(),
    ));
    let mut reader = decoder.read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size().unwrap()];
    let info = reader.next_frame(&mut buf).unwrap();
    let channels = info.color_type.samples();
    assert!(channels >= 3, "{:?}", info.color_type);
    let n = buf[..info.buffer_size()]
        .chunks_exact(channels)
        .filter(|px| px[..3] == rgb)
        .count();
    (n, (info.width, info.height))
}
