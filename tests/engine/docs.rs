//! The docs point at files that exist: every relative link of README.md, CONTRIBUTING.md and
//! docs/*.md resolves, so that a file moved or renamed in a refactor cannot leave the
//! architecture described by a path that is gone. The operations guide's install of the
//! viewer's libraries names the versions the viewer page and the browser test use. The
//! configuration reference is made from the commented config file. (The README's quick start
//! is run as written by the daemon tests.)

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
    let mut files: Vec<PathBuf> = vec![root.join("README.md"), root.join("CONTRIBUTING.md")];
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
fn the_guide_installs_the_viewer_libraries_the_page_and_the_browser_test_use() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let read = |p: &str| std::fs::read_to_string(root.join(p)).unwrap();
    let readme = read("docs/OPERATIONS.md");
    let package = read("tests/web/package.json");
    let page = read("crates/server/src/web/viewer.html");
    let command = readme
        .lines()
        .map(str::trim_start)
        .find(|l| l.starts_with("npm install") && l.contains("maplibre-gl"))
        .expect("the guide's npm install of the viewer's libraries");
    for (name, constant) in [("maplibre-gl", "MAPLIBRE = '"), ("cesium", "CESIUM = '")] {
        let readme_v = pinned(command, name, "@");
        let test_v = pinned(&package, &format!("\"{name}\""), ": \"");
        let page_v = pinned(&page, constant.trim_end_matches('\''), "'");
        assert_eq!(readme_v.len(), 1, "{name}: the guide's command {command:?}");
        assert_eq!(
            readme_v, test_v,
            "{name}: docs/OPERATIONS.md against tests/web/package.json"
        );
        assert_eq!(
            readme_v, page_v,
            "{name}: docs/OPERATIONS.md against viewer.html"
        );
    }
}

/// One key of `config/patchwork.toml`: its section, name, value as the file gives it (None
/// where the file only shows an example, commented out: the key is unset by default), and the
/// comment above it.
struct Key {
    section: String,
    name: String,
    default: Option<String>,
    example: Option<String>,
    meaning: String,
}

/// The keys of the commented config file, in order, and each section's own comment. A comment
/// block belongs to the keys that follow it up to the next blank line or comment; a commented
/// `key = value` line is a key unset by default, with that value as its example.
fn config_keys(text: &str) -> (Vec<Key>, Vec<(String, String)>) {
    let key_line = |l: &str| -> Option<(String, String)> {
        let (k, v) = l.split_once(" = ")?;
        let k = k.trim();
        (!k.is_empty()
            && k.chars()
                .all(|c| c.is_ascii_alphanumeric() || "_\":.".contains(c)))
        .then(|| (k.trim_matches('"').to_string(), v.trim().to_string()))
    };
    let (mut keys, mut sections) = (Vec::new(), Vec::new());
    let (mut section, mut block, mut used) = (String::new(), Vec::<String>::new(), false);
    // The file's own header is not any key's meaning.
    let body = text.split_once("\n\n").map_or(text, |(_, b)| b);
    for line in body.lines() {
        let line = line.trim_end();
        if line.is_empty() {
            block.clear();
            used = false;
        } else if let Some(name) = line.strip_prefix('[').and_then(|l| l.strip_suffix(']')) {
            section = name.to_string();
            sections.push((section.clone(), block.join(" ")));
            block.clear();
            used = false;
        } else if let Some(c) = line.strip_prefix('#') {
            let c = c.trim();
            if let Some((k, v)) = key_line(c) {
                keys.push(Key {
                    section: section.clone(),
                    name: k,
                    default: None,
                    example: Some(v),
                    meaning: block.join(" "),
                });
                used = true;
            } else {
                if used {
                    block.clear();
                    used = false;
                }
                block.push(c.to_string());
            }
        } else if let Some((k, v)) = key_line(line) {
            keys.push(Key {
                section: section.clone(),
                name: k,
                default: Some(v),
                example: None,
                meaning: block.join(" "),
            });
            used = true;
        }
    }
    (keys, sections)
}

/// docs/CONFIG.md's tables, as the commented config file makes them.
fn config_tables(text: &str) -> String {
    let (keys, sections) = config_keys(text);
    // A table cell: a bar would end it, and `<token>` would be read as an HTML tag.
    let cell = |s: &str| {
        s.replace('|', "\\|")
            .replace('<', "&lt;")
            .replace('>', "&gt;")
    };
    let mut out = String::new();
    let mut names: Vec<String> = vec![String::new()];
    names.extend(sections.iter().map(|(s, _)| s.clone()));
    for name in names {
        let of: Vec<&Key> = keys.iter().filter(|k| k.section == name).collect();
        let about = sections
            .iter()
            .find(|(s, _)| *s == name)
            .map(|(_, a)| a.as_str());
        if name.is_empty() {
            out.push_str("### Top level\n\n");
        } else {
            out.push_str(&format!("### `[{name}]`\n\n"));
        }
        if let Some(a) = about.filter(|a| !a.is_empty()) {
            out.push_str(&format!("{}\n\n", a));
        }
        if name == "vertical.geoids" {
            // Its keys are the user's: vertical CRSs, each naming a grid.
            out.push_str("| vertical CRS | grid, for example |\n|---|---|\n");
            for k in &of {
                out.push_str(&format!(
                    "| `{}` | `{}` |\n",
                    k.name,
                    cell(k.example.as_deref().unwrap_or(""))
                ));
            }
            out.push('\n');
            continue;
        }
        out.push_str("| key | default | meaning |\n|---|---|---|\n");
        for k in of {
            let default = match (&k.default, &k.example) {
                (Some(d), _) => format!("`{}`", cell(d)),
                (None, Some(e)) => format!("unset (for example `{}`)", cell(e)),
                (None, None) => "unset".into(),
            };
            out.push_str(&format!(
                "| `{}` | {default} | {} |\n",
                k.name,
                cell(&k.meaning)
            ));
        }
        out.push('\n');
    }
    out
}

/// The tables of docs/CONFIG.md are made from config/patchwork.toml, whose values the engine's
/// own test holds to the compiled-in defaults: so every key is documented, with its default,
/// and none that the code lacks. `PATCHWORK_BLESS=1` writes the tables afresh.
#[test]
fn the_configuration_reference_is_the_commented_config_file() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let toml = std::fs::read_to_string(root.join("config/patchwork.toml")).unwrap();
    let path = root.join("docs/CONFIG.md");
    let doc = std::fs::read_to_string(&path).unwrap();
    const BEGIN: &str = "<!-- tables made from config/patchwork.toml -->\n";
    let start = doc
        .find(BEGIN)
        .expect("the tables' marker in docs/CONFIG.md")
        + BEGIN.len();
    let want = config_tables(&toml);
    if std::env::var("PATCHWORK_BLESS").is_ok_and(|v| v == "1") {
        std::fs::write(&path, format!("{}{want}", &doc[..start])).unwrap();
        return;
    }
    let (keys, _) = config_keys(&toml);
    assert!(
        keys.len() > 60,
        "only {} keys read: is the parser right?",
        keys.len()
    );
    assert!(
        doc[start..] == want,
        "docs/CONFIG.md's tables differ from config/patchwork.toml: run this test with \
         PATCHWORK_BLESS=1 to write them again"
    );
}
