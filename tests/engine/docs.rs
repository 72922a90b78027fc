//! The docs point at files that exist: every relative link of README.md and docs/*.md
//! resolves, so that a file moved or renamed in a refactor cannot leave the architecture
//! described by a path that is gone.

use std::path::{Path, PathBuf};

/// The relative targets of the markdown links `[text](target)` in `text`, anchors dropped.
fn links(text: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut rest = text;
    while let Some(i) = rest.find("](") {
        rest = &rest[i + 2..];
        let Some(end) = rest.find(')') else { break };
        let target = rest[..end].trim();
        let external = target.contains("://") || target.starts_with("mailto:");
        let path = target.split('#').next().unwrap_or("");
        if !external && !path.is_empty() && !path.contains(' ') {
            out.push(path.to_string());
        }
    }
    out
}

#[test]
fn every_relative_link_of_the_docs_resolves() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut files: Vec<PathBuf> = vec![root.join("README.md")];
    for e in std::fs::read_dir(root.join("docs")).unwrap() {
        let p = e.unwrap().path();
        if p.extension().is_some_and(|x| x == "md") {
            files.push(p);
        }
    }
    let mut broken = Vec::new();
    let mut checked = 0;
    for f in &files {
        let text = std::fs::read_to_string(f).unwrap();
        for l in links(&text) {
            checked += 1;
            if !f.parent().unwrap().join(&l).exists() {
                broken.push(format!("{}: {l}", f.strip_prefix(root).unwrap().display()));
            }
        }
    }
    assert!(
        checked > 50,
        "only {checked} links found: is the parser right?"
    );
    assert!(
        broken.is_empty(),
        "links to nothing:\n{}",
        broken.join("\n")
    );
}
