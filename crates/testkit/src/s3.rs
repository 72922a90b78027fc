//! An S3 server on loopback for the tests and the bench: s3s-fs, which keeps each bucket as a folder and each
//! object as a file under it, served in this process on a runtime of its own so that a test can
//! stop it and start it again on the same port.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

/// The bucket the server holds.
pub const BUCKET: &str = "terrain";
const KEY: &str = "patchwork-test-key";
const SECRET: &str = "patchwork-test-secret-key";

/// The server: its folder, its port, and the runtime it runs on until stopped.
pub struct S3Server {
    /// The folder its buckets are folders of.
    pub root: PathBuf,
    /// Its loopback port.
    pub port: u16,
    runtime: Option<tokio::runtime::Runtime>,
    /// What the server gets wrong on purpose; shared with the running server.
    pub faults: Arc<Faults>,
}

/// Faults the server plays, as real ones behave: a 503 with S3's `SlowDown` error.
#[derive(Default)]
pub struct Faults {
    /// PUTs of objects whose key contains this are refused while it is set.
    pub refuse_puts: Mutex<Option<String>>,
    /// The next this many requests are refused.
    pub throttle: AtomicU32,
    /// How many requests were refused.
    pub refused: AtomicU32,
    /// The bytes of the objects' contents served by GETs: what clients fetched.
    pub fetched: AtomicU64,
    /// While set, every GET waits, unanswered, until it is cleared: a backend as slow as
    /// one can be.
    pub hold_gets: AtomicBool,
    /// GETs that are waiting on `hold_gets` now.
    pub held: AtomicU32,
}

impl Faults {
    fn refuses(&self, method: &hyper::Method, path: &str) -> bool {
        let put = method == hyper::Method::PUT
            && lock(&self.refuse_puts)
                .as_deref()
                .is_some_and(|k| path.contains(k));
        let throttled = self
            .throttle
            .fetch_update(Ordering::SeqCst, Ordering::SeqCst, |n| n.checked_sub(1))
            .is_ok();
        if put || throttled {
            self.refused.fetch_add(1, Ordering::SeqCst);
        }
        put || throttled
    }
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

const SLOW_DOWN: &str = "<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n<Error><Code>SlowDown</Code>\
<Message>Please reduce your request rate.</Message></Error>";

impl S3Server {
    /// A server over `root` (made, with the bucket's folder, if missing), on a free port.
    pub fn start(root: &Path) -> S3Server {
        std::fs::create_dir_all(root.join(BUCKET)).unwrap();
        let mut s = S3Server {
            root: root.into(),
            port: 0,
            runtime: None,
            faults: Arc::default(),
        };
        s.restart();
        s
    }

    /// Starts the server again on its port (the first time, on a free one).
    pub fn restart(&mut self) {
        assert!(self.runtime.is_none(), "the server is running");
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .enable_all()
            .build()
            .unwrap();
        // The stopped server's threads let go of the port soon, not at once: tried again for
        // a while on a busy machine.
        let t0 = std::time::Instant::now();
        let listener = loop {
            let addr = SocketAddr::from(([127, 0, 0, 1], self.port));
            match rt.block_on(tokio::net::TcpListener::bind(addr)) {
                Ok(l) => break l,
                Err(_) if t0.elapsed() < std::time::Duration::from_secs(10) => {
                    std::thread::sleep(std::time::Duration::from_millis(100));
                }
                Err(e) => panic!("binding {addr}: {e}"),
            }
        };
        self.port = listener.local_addr().unwrap().port();
        let fs = s3s_fs::FileSystem::new(&self.root).unwrap();
        let mut b = s3s::service::S3ServiceBuilder::new(fs);
        b.set_auth(s3s::auth::SimpleAuth::from_single(KEY, SECRET));
        let s3 = b.build();
        let faults = self.faults.clone();
        let service = hyper::service::service_fn(move |req: hyper::Request<_>| {
            let (s3, faults) = (s3.clone(), faults.clone());
            async move {
                if faults.refuses(req.method(), req.uri().path()) {
                    let slow = hyper::Response::builder()
                        .status(hyper::StatusCode::SERVICE_UNAVAILABLE)
                        .header("content-type", "application/xml")
                        .body(s3s::Body::from(SLOW_DOWN.to_string()))
                        .expect("a valid response");
                    return Ok::<_, s3s::HttpError>(slow);
                }
                let get = req.method() == hyper::Method::GET;
                if get && faults.hold_gets.load(Ordering::SeqCst) {
                    faults.held.fetch_add(1, Ordering::SeqCst);
                    while faults.hold_gets.load(Ordering::SeqCst) {
                        tokio::time::sleep(std::time::Duration::from_millis(10)).await;
                    }
                    faults.held.fetch_sub(1, Ordering::SeqCst);
                }
                let resp = hyper::service::Service::call(&s3, req).await?;
                if get && resp.status().is_success() {
                    let len = resp
                        .headers()
                        .get("content-length")
                        .and_then(|v| v.to_str().ok()?.parse::<u64>().ok())
                        .unwrap_or(0);
                    faults.fetched.fetch_add(len, Ordering::Relaxed);
                }
                Ok(resp)
            }
        });
        rt.spawn(async move {
            let http =
                hyper_util::server::conn::auto::Builder::new(hyper_util::rt::TokioExecutor::new());
            loop {
                let Ok((socket, _)) = listener.accept().await else {
                    continue;
                };
                let conn = http
                    .serve_connection(hyper_util::rt::TokioIo::new(socket), service.clone())
                    .into_owned();
                tokio::spawn(async move {
                    let _ = conn.await;
                });
            }
        });
        self.runtime = Some(rt);
    }

    /// Stops the server: its listener and every open connection close.
    pub fn stop(&mut self) {
        if let Some(rt) = self.runtime.take() {
            rt.shutdown_background();
        }
        // The port must be free again before a restart binds it.
        std::thread::sleep(std::time::Duration::from_millis(100));
    }

    /// Its URL, for an S3 client's endpoint.
    pub fn endpoint(&self) -> String {
        format!("http://127.0.0.1:{}", self.port)
    }

    /// The environment of a daemon whose chunks go to `prefix` of the bucket.
    pub fn env(&self, prefix: &str) -> Vec<(String, String)> {
        [
            ("PATCHWORK_STORAGE_BACKEND", "s3".to_string()),
            ("PATCHWORK_S3_ENDPOINT", self.endpoint()),
            ("PATCHWORK_S3_BUCKET", BUCKET.to_string()),
            ("PATCHWORK_S3_PREFIX", prefix.to_string()),
            ("PATCHWORK_S3_ALLOW_HTTP", "true".to_string()),
            ("AWS_ACCESS_KEY_ID", KEY.to_string()),
            ("AWS_SECRET_ACCESS_KEY", SECRET.to_string()),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_string(), v))
        .collect()
    }

    /// The files of the segments under `prefix`, in order.
    pub fn segments(&self, prefix: &str) -> Vec<PathBuf> {
        let dir = self.root.join(BUCKET).join(prefix).join("segments");
        let mut out: Vec<PathBuf> = std::fs::read_dir(&dir)
            .map(|rd| {
                rd.filter_map(Result::ok)
                    .map(|e| e.path())
                    .filter(|p| p.extension().is_some_and(|x| x == "seg"))
                    .collect()
            })
            .unwrap_or_default();
        out.sort();
        out
    }
}

impl Drop for S3Server {
    fn drop(&mut self) {
        self.stop();
    }
}
