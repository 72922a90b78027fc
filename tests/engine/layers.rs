//! The daemon's modules keep their layers: each imports only modules listed before it in
//! docs/ARCHITECTURE.md. Between crates the compiler keeps the layers; inside this one crate,
//! this test does, so that a cycle fails here rather than growing unnoticed.

use std::path::{Path, PathBuf};

/// The daemon's modules, lowest first.
const LAYERS: [&str; 10] = [
    "sync", "paths", "config", "store", "restore", "gpu", "ingest", "engine", "watch", "serve",
];

/// The source files of a module: `src/<m>.rs`, or every file under `src/<m>/`.
fn files_of(module: &str) -> Vec<PathBuf> {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let file = src.join(format!("{module}.rs"));
    if file.exists() {
        return vec![file];
    }
    let mut out = Vec::new();
    let mut dirs = vec![src.join(module)];
    while let Some(d) = dirs.pop() {
        for e in std::fs::read_dir(&d).unwrap_or_else(|e| panic!("{}: {e}", d.display())) {
            let p = e.unwrap().path();
            if p.is_dir() {
                dirs.push(p);
            } else if p.extension().is_some_and(|x| x == "rs") {
                out.push(p);
            }
        }
    }
    out
}

/// The modules of this crate a file's code (its tests and comments left out) names as
/// `crate::<m>`. A doc comment may point up to where a thing is used; only code depends.
fn imports(text: &str) -> Vec<String> {
    let code = match text.find("#[cfg(test)]\nmod tests") {
        Some(i) => &text[..i],
        None => text,
    };
    let code: String = code
        .lines()
        .map(|l| match l.find("//") {
            Some(i) => &l[..i],
            None => l,
        })
        .collect::<Vec<_>>()
        .join("\n");
    let mut out = Vec::new();
    for (i, _) in code.match_indices("crate::") {
        let rest = &code[i + "crate::".len()..];
        let name: String = rest
            .chars()
            .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
            .collect();
        // `crate::{a, b}` names several.
        if name.is_empty() && rest.starts_with('{') {
            let inner = &rest[1..rest.find('}').unwrap_or(rest.len())];
            out.extend(
                inner
                    .split(',')
                    .map(|s| s.trim().split("::").next().unwrap_or("").to_string()),
            );
        } else {
            out.push(name);
        }
    }
    out
}

#[test]
fn no_module_imports_one_of_a_higher_layer() {
    let mut bad = Vec::new();
    for (k, module) in LAYERS.iter().enumerate() {
        for file in files_of(module) {
            let text = std::fs::read_to_string(&file).unwrap();
            for used in imports(&text) {
                match LAYERS.iter().position(|m| *m == used) {
                    Some(j) if j > k => bad.push(format!(
                        "{} imports crate::{used}, a higher layer than {module}",
                        file.display()
                    )),
                    Some(_) => {}
                    None if used.is_empty() || used == "self" => {}
                    None => bad.push(format!(
                        "{} imports crate::{used}, which is in no layer: add it to LAYERS \
                         and docs/ARCHITECTURE.md",
                        file.display()
                    )),
                }
            }
        }
    }
    assert!(bad.is_empty(), "{}", bad.join("\n"));
}

#[test]
fn every_module_of_the_crate_has_a_layer() {
    let lib =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("src/lib.rs")).unwrap();
    for line in lib.lines() {
        if let Some(m) = line
            .strip_prefix("pub mod ")
            .and_then(|l| l.strip_suffix(';'))
        {
            assert!(LAYERS.contains(&m), "module {m} has no layer in LAYERS");
        }
    }
}

#[test]
fn the_import_reader_sees_grouped_and_nested_paths() {
    let found = imports(
        "use crate::{store::X, sync::lock};\n/// Built by [`crate::watch`].\nfn f() { crate::engine::g(); } // crate::serve",
    );
    assert_eq!(found, ["store", "sync", "engine"]);
}
