//! The docs point at files that exist: every relative link of README.md and docs/*.md
//! resolves, so that a file moved or renamed in a refactor cannot leave the architecture
//! described by a path that is gone. And the README's install of the viewer's libraries
//! names the versions the viewer page and the browser test use.

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

/// The version a text pins `name` at: what follows `name` and `sep` up to a quote, a space or
/// the end of the line.
fn pinned<'a>(text: &'a str, name: &str, sep: &str) -> Vec<&'a str> {
    let key = format!("{name}{sep}");
    text.match_indices(&key)
        .map(|(i, _)| {
            let rest = &text[i + key.len()..];
            let end = rest
                .find(|c: char| c == '"' || c == '\'' || c.is_whitespace() || c == ',')
                .unwrap_or(rest.len());
            &rest[..end]
        })
        .collect()
}

#[test]
fn the_readme_installs_the_viewer_libraries_the_page_and_the_browser_test_use() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let read = |p: &str| std::fs::read_to_string(root.join(p)).unwrap();
    let readme = read("README.md");
    let package = read("tests/web/package.json");
    let page = read("crates/server/src/web/viewer.html");
    let command = readme
        .lines()
        .find(|l| l.starts_with("npm install") && l.contains("maplibre-gl"))
        .expect("the README's npm install of the viewer's libraries");
    for (name, constant) in [("maplibre-gl", "MAPLIBRE = '"), ("cesium", "CESIUM = '")] {
        let readme_v = pinned(command, name, "@");
        let test_v = pinned(&package, &format!("\"{name}\""), ": \"");
        let page_v = pinned(&page, constant.trim_end_matches('\''), "'");
        assert_eq!(
            readme_v.len(),
            1,
            "{name}: the README's command {command:?}"
        );
        assert_eq!(
            readme_v, test_v,
            "{name}: README against tests/web/package.json"
        );
        assert_eq!(readme_v, page_v, "{name}: README against viewer.html");
    }
}
