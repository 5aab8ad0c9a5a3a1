//! Reading recordings back in tests: Rerun's chunks, and values per `step`.

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
#[allow(dead_code)] // not every test crate reads text logs
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
