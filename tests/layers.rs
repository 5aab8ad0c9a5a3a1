//! The library's layers only depend downward (docs/layout.md): physics → damage → policy →
//! lane → sinks → front-ends. Read from the source: every `crate::module` a module names must
//! sit in a lower layer than the module itself.

use std::collections::BTreeMap;
use std::path::Path;

/// Top-level modules, lowest layer first; a module may name only modules of lower layers.
const LAYERS: &[&[&str]] = &[
    &["damage", "plots", "progress"],
    &["config", "palette"],
    &["env"],
    &["window"],
    &["policy"],
    &["lane", "train"],
    &["rollout", "eval", "explain"],
    &["probe"],
    &["telemetry"],
    &["video", "app"],
    &["bench"],
];

fn layer_of(module: &str) -> Option<usize> {
    LAYERS.iter().position(|l| l.contains(&module))
}

/// Every `crate::name` in the files under `dir`, by the top-level module the file belongs to.
fn references(dir: &Path, top: Option<&str>, out: &mut BTreeMap<String, Vec<(String, String)>>) {
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        let name = path.file_stem().unwrap().to_string_lossy().into_owned();
        let module = top.map_or(name.clone(), str::to_string);
        if path.is_dir() {
            references(&path, Some(&module), out);
        } else if path.extension().is_some_and(|e| e == "rs")
            && !["lib", "main"].contains(&&*module)
        {
            let text = std::fs::read_to_string(&path).unwrap();
            for (i, _) in text.match_indices("crate::") {
                let used: String = text[i + 7..]
                    .chars()
                    .take_while(|c| c.is_ascii_lowercase() || *c == '_')
                    .collect();
                if !used.is_empty() && used != module {
                    out.entry(module.clone())
                        .or_default()
                        .push((used, path.display().to_string()));
                }
            }
        }
    }
}

#[test]
fn modules_only_depend_on_lower_layers() {
    let mut refs = BTreeMap::new();
    references(
        &Path::new(env!("CARGO_MANIFEST_DIR")).join("src"),
        None,
        &mut refs,
    );
    assert!(refs.contains_key("lane") && refs.contains_key("telemetry"));
    let mut wrong = Vec::new();
    for (module, used) in &refs {
        let Some(own) = layer_of(module) else {
            wrong.push(format!("{module} is in no layer (add it to LAYERS)"));
            continue;
        };
        for (target, file) in used {
            match layer_of(target) {
                Some(l) if l < own => {}
                _ => wrong.push(format!("{file}: {module} uses crate::{target}")),
            }
        }
    }
    wrong.dedup();
    assert!(
        wrong.is_empty(),
        "upward or sideways:\n{}",
        wrong.join("\n")
    );
}
