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

/// A free loopback port whose next one is free too, for a daemon's gRPC and HTTP servers.
///
/// Drawn below the kernel's ephemeral range (32768 and up on Linux), where the CLI's own
/// outgoing connections take their ports: a port from `bind(0)` could be taken by one of
/// those between this check and the daemon's bind. Tests running side by side can still race
/// for one, so [`Daemon::start_with`] starts again on another port if the bind fails.
pub fn free_port() -> u16 {
    use std::sync::atomic::{AtomicU64, Ordering};
    static STATE: AtomicU64 = AtomicU64::new(0);
    let seed = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_nanos() as u64
        ^ (u64::from(std::process::id()) << 32);
    let _ = STATE.compare_exchange(0, seed | 1, Ordering::Relaxed, Ordering::Relaxed);
    loop {
        let x = STATE
            .fetch_add(0x9E37_79B9_7F4A_7C15, Ordering::Relaxed)
            .wrapping_mul(0xBF58_476D_1CE4_E5B9);
        let port = 20_000 + ((x >> 33) % 12_000) as u16;
        if std::net::TcpListener::bind(("127.0.0.1", port)).is_ok()
            && std::net::TcpListener::bind(("127.0.0.1", port + 1)).is_ok()
        {
            return port;
        }
    }
}

/// The HTTP port of a daemon under test whose gRPC port is `port`.
pub fn http_port(port: u16) -> u16 {
    port + 1
}

pub struct Daemon {
    child: Option<Child>,
    pub root: PathBuf,
    pub port: u16,
    /// How the CLI reaches the daemon: environment (token, CA) and server URL.
    pub client_env: Vec<(String, String)>,
    pub url: String,
    /// The base URL of its HTTP server for web map clients.
    pub http: String,
}

/// How a daemon under test is set up beyond the defaults.
#[derive(Clone, Default)]
pub struct Setup {
    /// Environment of the daemon.
    pub env: Vec<(String, String)>,
    /// Variables taken out of the daemon's environment.
    pub unset: Vec<String>,
    /// Environment of the CLI that talks to it.
    pub client_env: Vec<(String, String)>,
    /// Serve TLS with the test certificate in tests/data/tls.
    pub tls: bool,
}

pub fn tls_file(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/tls")
        .join(name)
}

impl Daemon {
    /// Starts a daemon whose store and inbox live under `root`.
    pub fn start(root: &Path) -> Daemon {
        Self::start_with(root, Setup::default())
    }

    /// The command that starts a daemon under `root` on `port`, with `setup`'s environment;
    /// its HTTP server listens on the port after it (see [`http_port`]) unless `setup` says
    /// otherwise.
    pub fn command(root: &Path, port: u16, setup: &Setup) -> Command {
        std::fs::create_dir_all(root.join("inbox")).unwrap();
        let log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(root.join("serve.log"))
            .unwrap();
        let mut cmd = Command::new(BIN);
        cmd.arg("serve")
            .env("PATCHWORK_DATA_DIR", root.join("data"))
            .env("PATCHWORK_INBOX", root.join("inbox"))
            .env("PATCHWORK_LISTEN", format!("127.0.0.1:{port}"))
            .env(
                "PATCHWORK_HTTP_LISTEN",
                format!("127.0.0.1:{}", http_port(port)),
            )
            .env("PATCHWORK_SETTLE_MS", "400")
            .env("PATCHWORK_LOG", "info")
            .env_remove("PATCHWORK_ADMIN_TOKEN")
            .env_remove("PATCHWORK_READ_TOKEN")
            .stdout(Stdio::null())
            .stderr(log);
        if setup.tls {
            cmd.env("PATCHWORK_TLS_CERT", tls_file("server.pem"))
                .env("PATCHWORK_TLS_KEY", tls_file("server.key"));
        }
        cmd.envs(setup.env.iter().map(|(k, v)| (k, v)));
        for k in &setup.unset {
            cmd.env_remove(k);
        }
        cmd
    }

    /// A handle for a daemon the caller runs itself: only the CLI helpers work.
    pub fn unstarted(root: &Path, port: u16) -> Daemon {
        Daemon {
            child: None,
            root: root.into(),
            port,
            client_env: Vec::new(),
            url: format!("http://127.0.0.1:{port}"),
            http: format!("http://127.0.0.1:{}", http_port(port)),
        }
    }

    /// Starts a daemon under `root` as `setup` says, and waits until it answers.
    pub fn start_with(root: &Path, setup: Setup) -> Daemon {
        let mut client_env = setup.client_env.clone();
        if setup.tls {
            client_env.push((
                "PATCHWORK_CA".into(),
                tls_file("ca.pem").to_string_lossy().into_owned(),
            ));
        }
        let scheme = if setup.tls {
            "https://localhost"
        } else {
            "http://127.0.0.1"
        };
        // Tests running side by side can race for a port between `free_port` and the
        // daemon's bind; a daemon that lost the race exits saying so and starts again on
        // another port.
        for _ in 0..8 {
            let port = free_port();
            let log_len = std::fs::metadata(root.join("serve.log")).map_or(0, |m| m.len());
            let child = Self::command(root, port, &setup).spawn().unwrap();
            let mut d = Daemon {
                child: Some(child),
                root: root.into(),
                port,
                client_env: client_env.clone(),
                url: format!("{scheme}:{port}"),
                http: format!("http://127.0.0.1:{}", http_port(port)),
            };
            let t0 = Instant::now();
            loop {
                if d.cli(&["stats"]).status.success() {
                    return d;
                }
                let exited = d.child.as_mut().unwrap().try_wait().unwrap().is_some();
                let log = std::fs::read(root.join("serve.log")).unwrap_or_default();
                let since =
                    String::from_utf8_lossy(&log[(log_len as usize).min(log.len())..]).into_owned();
                if exited && since.contains("Address already in use") {
                    d.child = None;
                    break;
                }
                assert!(
                    !exited && t0.elapsed() < Duration::from_secs(30),
                    "the daemon did not come up: {}",
                    d.log()
                );
                std::thread::sleep(Duration::from_millis(100));
            }
        }
        panic!("no free port for a daemon after 8 tries");
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
            .arg(format!("--server={}", self.url))
            .env_remove("PATCHWORK_TOKEN")
            .env_remove("PATCHWORK_ADMIN_TOKEN")
            .envs(self.client_env.iter().map(|(k, v)| (k, v)))
            .output()
            .unwrap()
    }

    /// The daemon's process id, while it runs.
    pub fn pid(&self) -> Option<u32> {
        self.child.as_ref().map(|c| c.id())
    }

    /// Sends SIGTERM and returns how long the daemon took to exit.
    pub fn stop_timed(&mut self) -> Duration {
        let mut c = self.child.take().expect("running");
        let t0 = Instant::now();
        send_signal(c.id(), "TERM");
        let _ = c.wait();
        t0.elapsed()
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

    /// The passes the daemon's inbox watcher has finished (`stats`).
    pub fn inbox_passes(&self) -> u64 {
        self.json(&["stats", "--json"])["inbox_passes"]
            .as_u64()
            .expect("stats' inbox_passes")
    }

    /// Waits until the daemon has seen its inbox as it is now, and done what it does with it:
    /// two more passes than now have finished (the first may have begun before the change).
    /// Meanwhile a file the watcher leaves alone by its name (a dot file) is made and removed
    /// in the inbox, so that a pass comes at once rather than at the idle one. For a test that
    /// expects nothing to happen: after this, nothing will.
    pub fn settle_inbox(&self) {
        let start = self.inbox_passes();
        let t0 = Instant::now();
        for k in 0.. {
            let now = self.inbox_passes();
            if now >= start + 2 {
                return;
            }
            assert!(
                t0.elapsed() < Duration::from_secs(60),
                "the inbox watcher finished {} passes in 60 s\n{}",
                now - start,
                self.log()
            );
            let nudge = self.inbox().join(format!(".nudge-{k}"));
            std::fs::write(&nudge, b"").unwrap();
            std::thread::sleep(Duration::from_millis(100));
            let _ = std::fs::remove_file(&nudge);
        }
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

/// A north-up tile of `w × h` samples over the middle of the Copernicus crop, on the CPU.
pub fn crop_tile(w: u32, h: u32) -> patchwork::serve::proto::TileRequest {
    use patchwork::serve::proto as pb;
    pb::TileRequest {
        crs: String::new(),
        cut: Some(pb::tile_request::Cut::Uniform(pb::UniformCut {
            roi: Some(pb::Rect {
                xmin: -119.0,
                ymin: 34.46,
                xmax: -118.92,
                ymax: 34.54,
            }),
            error: 0.0,
        })),
        width: w,
        height: h,
        backend: pb::Backend::Cpu as i32,
        ..Default::default()
    }
}
