//! The library's layers only depend downward (docs/layout.md): physics → damage → policy →
//! lane → sinks → front-ends. Read from the source: every `crate::module` a module names must
//! sit in a lower layer than the module itself.

use std::collections::BTreeMap;
use std::path::Path;

/// Top-level modules, lowest layer first; a module may name only modules of lower layers.
const LAYERS: &[&[&str]] = &[
    // Bounded, regular-file-only reading and writing, under everything that reads a file.
    &["files"],
    &["damage", "plots", "progress"],
    &["config", "palette"],
    &["env"],
    &["window"],
    &["policy"],
    &["lane", "train"],
    &["rollout", "eval", "explain"],
    &["probe"],
    &["telemetry"],
    &["search"],
    &["video", "app"],
    &["bench"],
    // The binary's front door (src/main.rs, src/cli/): it reads the library through
    // `gaitscope::`, and nothing below names it.
    &["cli"],
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

/// The command line sits on top: its files reach the library only as `gaitscope::MODULE`, each
/// a module of [`LAYERS`], and no library file names `cli`.
#[test]
fn the_cli_uses_the_library_from_above() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut files = vec![src.join("main.rs")];
    files.extend(
        std::fs::read_dir(src.join("cli"))
            .unwrap()
            .map(|e| e.unwrap().path()),
    );
    let mut named = 0;
    for file in &files {
        let text = std::fs::read_to_string(file).unwrap();
        for (i, _) in text.match_indices("gaitscope::") {
            let used: String = text[i + 11..]
                .chars()
                .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
                .collect();
            // A re-exported type (`gaitscope::Condition`) starts with a capital.
            if used.starts_with(|c: char| c.is_ascii_lowercase()) {
                named += 1;
                let layer = layer_of(&used);
                assert!(
                    layer.is_some_and(|l| l < layer_of("cli").unwrap()),
                    "{}: gaitscope::{used} is no library module below the CLI",
                    file.display()
                );
            }
        }
    }
    assert!(named > 50, "the CLI names the library's modules ({named})");
    let mut refs = BTreeMap::new();
    references(&src, None, &mut refs);
    for (module, used) in &refs {
        for (target, file) in used {
            assert!(
                target != "cli",
                "{file}: the library's {module} names the CLI"
            );
        }
    }
}

/// A lane changes only through its own methods: nothing hands out its env mutably (the old
/// `Lane::env_mut` back door) and nothing outside src/lane/ asks for one.
#[test]
fn no_back_door_into_a_lane() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut offenders = Vec::new();
    let mut stack = vec![src.clone()];
    while let Some(dir) = stack.pop() {
        for entry in std::fs::read_dir(&dir).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                stack.push(path);
                continue;
            }
            if path.extension().is_none_or(|e| e != "rs") {
                continue;
            }
            let text = std::fs::read_to_string(&path).unwrap();
            let in_lane = path.starts_with(src.join("lane"));
            for (n, line) in text.lines().enumerate() {
                let code = line.split("//").next().unwrap_or("");
                let back_door = code.contains("fn env_mut")
                    || (in_lane && code.contains("pub fn") && code.contains("-> &mut AntEnv"))
                    || (!in_lane && code.contains(".core.env_mut"));
                if back_door {
                    offenders.push(format!("{}:{}: {}", path.display(), n + 1, line.trim()));
                }
            }
        }
    }
    assert!(offenders.is_empty(), "{}", offenders.join("\n"));
}

/// The command line's types and printing stay at the edge: no library file derives clap's
/// traits (the CLI mirrors the library's enums in src/cli/values.rs) or prints with
/// `println!`/`eprintln!` (the library returns what it has, reports progress through bars, and
/// notes through the `log` facade, which the binary prints). Tests beside the code may print.
#[test]
fn the_library_neither_parses_flags_nor_prints() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut offenders = Vec::new();
    let mut checked = 0;
    let mut stack = vec![src.clone()];
    while let Some(dir) = stack.pop() {
        for entry in std::fs::read_dir(&dir).unwrap() {
            let path = entry.unwrap().path();
            if path == src.join("cli") || path == src.join("main.rs") {
                continue;
            }
            if path.is_dir() {
                stack.push(path);
                continue;
            }
            if path.extension().is_none_or(|e| e != "rs") {
                continue;
            }
            checked += 1;
            let text = std::fs::read_to_string(&path).unwrap();
            // Code before the file's test module, if any.
            let code = text.split("#[cfg(test)]").next().unwrap_or("");
            for (n, line) in code.lines().enumerate() {
                let line_code = line.split("//").next().unwrap_or("");
                if line_code.contains("clap::")
                    || line_code.contains("println!(")
                    || line_code.contains("eprintln!(")
                {
                    offenders.push(format!("{}:{}: {}", path.display(), n + 1, line.trim()));
                }
            }
        }
    }
    assert!(checked > 40, "the library's files were read ({checked})");
    assert!(offenders.is_empty(), "{}", offenders.join("\n"));
}
