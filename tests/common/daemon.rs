//! A daemon under test: the real binary on a free loopback port, with its store and inbox in
//! a temporary folder, and the real CLI to talk to it.

use serde_json::Value;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

pub const BIN: &str = env!("CARGO_BIN_EXE_patchwork");

pub fn crop(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data")
        .join(name)
}

pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

pub struct Daemon {
    child: Option<Child>,
    pub root: PathBuf,
    pub port: u16,
}

impl Daemon {
    /// Starts a daemon whose store and inbox live under `root`.
    pub fn start(root: &Path) -> Daemon {
        std::fs::create_dir_all(root.join("inbox")).unwrap();
        let port = free_port();
        let log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(root.join("serve.log"))
            .unwrap();
        let child = Command::new(BIN)
            .arg("serve")
            .env("PATCHWORK_DATA_DIR", root.join("data"))
            .env("PATCHWORK_INBOX", root.join("inbox"))
            .env("PATCHWORK_LISTEN", format!("127.0.0.1:{port}"))
            .env("PATCHWORK_SETTLE_MS", "400")
            .env("PATCHWORK_LOG", "info")
            .stdout(Stdio::null())
            .stderr(log)
            .spawn()
            .unwrap();
        let d = Daemon {
            child: Some(child),
            root: root.into(),
            port,
        };
        let t0 = Instant::now();
        while !d.cli(&["stats"]).status.success() {
            assert!(
                t0.elapsed() < Duration::from_secs(30),
                "the daemon did not come up: {}",
                d.log()
            );
            std::thread::sleep(Duration::from_millis(100));
        }
        d
    }

    pub fn inbox(&self) -> PathBuf {
        self.root.join("inbox")
    }

    pub fn log(&self) -> String {
        std::fs::read_to_string(self.root.join("serve.log")).unwrap_or_default()
    }

    pub fn cli(&self, args: &[&str]) -> Output {
        Command::new(BIN)
            .args(args)
            .arg(format!("--server=http://127.0.0.1:{}", self.port))
            .output()
            .unwrap()
    }

    pub fn json(&self, args: &[&str]) -> Value {
        let out = self.cli(args);
        assert!(
            out.status.success(),
            "{args:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        serde_json::from_slice(&out.stdout).unwrap()
    }

    pub fn surveys(&self) -> Vec<Value> {
        self.json(&["surveys", "--json"])
            .as_array()
            .unwrap()
            .clone()
    }

    /// Waits until the survey list satisfies `ok`.
    pub fn wait(&self, what: &str, ok: impl Fn(&[Value]) -> bool) -> Vec<Value> {
        let t0 = Instant::now();
        loop {
            let s = self.surveys();
            if ok(&s) {
                return s;
            }
            assert!(
                t0.elapsed() < Duration::from_secs(60),
                "timed out waiting for {what}: {s:#?}\n{}",
                self.log()
            );
            std::thread::sleep(Duration::from_millis(150));
        }
    }

    pub fn stop(&mut self) {
        if let Some(mut c) = self.child.take() {
            send_signal(c.id(), "TERM");
            let _ = c.wait();
        }
    }

    pub fn kill9(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        self.kill9();
    }
}

pub fn send_signal(pid: u32, sig: &str) {
    let _ = Command::new("kill")
        .arg(format!("-{sig}"))
        .arg(pid.to_string())
        .status();
}

pub fn count(s: &[Value], status: &str) -> usize {
    s.iter().filter(|v| v["status"] == status).count()
}

/// Copies a file in small pieces with pauses shorter than the settle time, as a slow network
/// copy would: the daemon must not take the half-written file.
pub fn copy_slowly(from: &Path, to: &Path) {
    let bytes = std::fs::read(from).unwrap();
    let mut f = std::fs::File::create(to).unwrap();
    for piece in bytes.chunks(bytes.len() / 6 + 1) {
        f.write_all(piece).unwrap();
        f.flush().unwrap();
        std::thread::sleep(Duration::from_millis(150));
    }
}

/// Publishes a file the usual way: write elsewhere, rename into the inbox.
pub fn drop_by_rename(from: &Path, inbox: &Path, name: &str) {
    let tmp = inbox.join(format!("{name}.part"));
    std::fs::copy(from, &tmp).unwrap();
    std::fs::rename(&tmp, inbox.join(name)).unwrap();
}
