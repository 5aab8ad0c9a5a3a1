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
