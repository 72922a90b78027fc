//! Paths as the daemon names them: a survey's source is its absolute path as text, with the
//! bytes of a name that is not UTF-8 escaped; and a client's string cut short for a message.

use std::path::{Path, PathBuf};

/// A client's string for an error message: quoted, control characters escaped, and cut short,
/// so that a megabyte of input does not come back in the reply.
pub fn quote_short(s: &str) -> String {
    const MOST: usize = 120;
    match s.char_indices().nth(MOST) {
        Some((cut, _)) => format!("{:?}… ({} bytes)", &s[..cut], s.len()),
        None => format!("{s:?}"),
    }
}

/// The absolute path a survey is known by.
pub fn source_name(path: &Path) -> String {
    let abs: PathBuf = match (path.parent(), path.file_name()) {
        (Some(dir), Some(name)) if !dir.as_os_str().is_empty() => dir
            .canonicalize()
            .map(|d| d.join(name))
            .unwrap_or_else(|_| path.to_path_buf()),
        _ => std::env::current_dir()
            .map(|d| d.join(path))
            .unwrap_or_else(|_| path.to_path_buf()),
    };
    escaped(&abs)
}

/// A path as text: itself when it is UTF-8, else with each byte that is not written `\xNN`
/// (U+FFFD would make different names one).
pub fn escaped(path: &Path) -> String {
    use std::os::unix::ffi::OsStrExt;
    let bytes = path.as_os_str().as_bytes();
    let mut out = String::with_capacity(bytes.len());
    for chunk in bytes.utf8_chunks() {
        out.push_str(chunk.valid());
        for b in chunk.invalid() {
            out.push_str(&format!("\\x{b:02x}"));
        }
    }
    out
}

/// The size of the file at `path` and its mtime in seconds since the epoch; `None` when it cannot
/// be read. A failed file's record keeps them, to tell when the file has changed.
pub fn size_mtime(path: &Path) -> Option<(u64, u64)> {
    let m = std::fs::metadata(path).ok()?;
    let mtime = m
        .modified()
        .ok()?
        .duration_since(std::time::UNIX_EPOCH)
        .ok()?
        .as_secs();
    Some((m.len(), mtime))
}
