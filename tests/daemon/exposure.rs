//! The daemon exposed: tokens guard what they should, a daemon that would be open beyond this
//! machine refuses to start, TLS serves with the configured certificate, SIGTERM stops it
//! quickly whatever is in flight, it starts read-only on a full disk, and odd file names
//! neither break its log nor stay recorded once forgotten, and a client that stops reading a
//! tile frees the daemon at the deadline. docs/RELIABILITY.md points at
//! each test.

use crate::common;

use common::daemon::*;
use std::path::Path;
use std::process::{Command, Output};
use std::time::{Duration, Instant};

const ADMIN: &str = "admin-0123456789abcdef";
const READ: &str = "read-0123456789abcdef";

fn env(pairs: &[(&str, &str)]) -> Vec<(String, String)> {
    pairs
        .iter()
        .map(|(k, v)| (k.to_string(), v.to_string()))
        .collect()
}

/// The CLI against `d` with the given token (or none), whatever the daemon's client uses.
fn cli_as(d: &Daemon, token: Option<&str>, args: &[&str]) -> Output {
    let mut c = Command::new(BIN);
    c.args(args)
        .arg(format!("--server={}", d.url))
        .env_remove("PATCHWORK_TOKEN")
        .env_remove("PATCHWORK_ADMIN_TOKEN")
        .env_remove("PATCHWORK_TOKEN_FILE");
    if let Some(t) = token {
        c.env("PATCHWORK_TOKEN", t);
    }
    c.output().unwrap()
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

#[test]
fn tokens_open_admin_and_reads_as_configured() {
    let tmp = tempfile::tempdir().unwrap();
    let d = Daemon::start_with(
        tmp.path(),
        Setup {
            env: env(&[
                ("PATCHWORK_ADMIN_TOKEN", ADMIN),
                ("PATCHWORK_READ_TOKEN", READ),
            ]),
            client_env: env(&[("PATCHWORK_TOKEN", ADMIN)]),
            ..Setup::default()
        },
    );
    drop_by_rename(&crop("copernicus_n34w119_crop.tif"), &d.inbox(), "a.tif");
    d.wait("the survey", |s| count(s, "active") == 1);
    let query = [
        "query",
        "--roi=-118.99,34.47,-118.93,34.53",
        "--error=5",
        "--json",
    ];

    let o = cli_as(&d, None, &["stats"]);
    assert!(!o.status.success());
    assert!(stderr(&o).contains("need a token"), "{}", stderr(&o));
    let o = cli_as(&d, None, &query);
    assert!(stderr(&o).contains("need a token"), "{}", stderr(&o));
    let o = cli_as(&d, Some("not-the-token-at-all"), &["stats"]);
    assert!(stderr(&o).contains("not valid"), "{}", stderr(&o));

    // The read token opens reads only.
    assert!(cli_as(&d, Some(READ), &query).status.success());
    let o = cli_as(&d, Some(READ), &["retire", "whatever"]);
    assert!(
        stderr(&o).contains("read token does not open Admin"),
        "{}",
        stderr(&o)
    );
    // The admin token opens both; the CLI also reads it from a file.
    assert!(cli_as(&d, Some(ADMIN), &query).status.success());
    let file = tmp.path().join("token");
    std::fs::write(&file, format!("{ADMIN}\n")).unwrap();
    let mut args = vec!["surveys", "--token-file", file.to_str().unwrap()];
    args.push("--json");
    assert!(cli_as(&d, None, &args).status.success());

    let rt = tokio::runtime::Runtime::new().unwrap();
    // Change events name files and their errors: they need the admin token.
    let subscribe = |token: &str| {
        let url = d.url.clone();
        let token = token.to_string();
        rt.block_on(async move {
            let ch = tonic::transport::Channel::from_shared(url)
                .unwrap()
                .connect()
                .await
                .unwrap();
            let mut t = patchwork::serve::proto::terrain_client::TerrainClient::new(ch);
            let mut req = tonic::Request::new(patchwork::serve::proto::SubscribeRequest {});
            req.metadata_mut()
                .insert("authorization", format!("Bearer {token}").parse().unwrap());
            t.subscribe(req).await.map(|_| ()).map_err(|s| s.code())
        })
    };
    assert_eq!(subscribe(READ), Err(tonic::Code::PermissionDenied));
    assert_eq!(subscribe(ADMIN), Ok(()));

    // Health needs no token, so that a load balancer can ask.
    let status = rt.block_on(async {
        let ch = tonic::transport::Channel::from_shared(d.url.clone())
            .unwrap()
            .connect()
            .await
            .unwrap();
        let mut h = tonic_health::pb::health_client::HealthClient::new(ch);
        h.check(tonic_health::pb::HealthCheckRequest {
            service: String::new(),
        })
        .await
        .unwrap()
        .into_inner()
        .status
    });
    assert_eq!(
        status,
        tonic_health::pb::health_check_response::ServingStatus::Serving as i32
    );
}

#[test]
fn a_daemon_open_beyond_this_machine_refuses_to_start_without_a_token() {
    let tmp = tempfile::tempdir().unwrap();
    let port = free_port();
    let setup = Setup {
        env: env(&[("PATCHWORK_LISTEN", &format!("0.0.0.0:{port}"))]),
        ..Setup::default()
    };
    let t0 = Instant::now();
    let status = Daemon::command(tmp.path(), port, &setup).status().unwrap();
    assert!(!status.success());
    assert!(t0.elapsed() < Duration::from_secs(10));
    let log = std::fs::read_to_string(tmp.path().join("serve.log")).unwrap();
    assert!(
        log.contains("PATCHWORK_ADMIN_TOKEN") && log.contains("0.0.0.0"),
        "{log}"
    );
    assert!(!tmp.path().join("data").exists(), "nothing was opened");
    // With a token it serves.
    let mut setup = setup;
    setup
        .env
        .push(("PATCHWORK_ADMIN_TOKEN".into(), ADMIN.into()));
    let mut child = Daemon::command(tmp.path(), port, &setup).spawn().unwrap();
    let d = Daemon::unstarted(tmp.path(), port);
    let t0 = Instant::now();
    while !cli_as(&d, Some(ADMIN), &["stats"]).status.success() {
        assert!(t0.elapsed() < Duration::from_secs(30), "it did not come up");
        std::thread::sleep(Duration::from_millis(100));
    }
    send_signal(child.id(), "TERM");
    child.wait().unwrap();
}

#[test]
fn tls_serves_with_the_configured_certificate() {
    let tmp = tempfile::tempdir().unwrap();
    let d = Daemon::start_with(
        tmp.path(),
        Setup {
            tls: true,
            ..Setup::default()
        },
    );
    assert!(d.url.starts_with("https://"));
    drop_by_rename(&crop("copernicus_n34w119_crop.tif"), &d.inbox(), "a.tif");
    d.wait("the survey over TLS", |s| count(s, "active") == 1);
    // Clear text gets nowhere.
    let o = Command::new(BIN)
        .args(["stats", &format!("--server=http://127.0.0.1:{}", d.port)])
        .output()
        .unwrap();
    assert!(!o.status.success());
}

/// An ESRI grid of `n` × `n` samples in UTM zone 11, large enough to take a while to ingest.
fn big_grid(path: &Path, n: usize) {
    use std::io::Write;
    let mut f = std::io::BufWriter::new(std::fs::File::create(path).unwrap());
    writeln!(
        f,
        "ncols {n}\nnrows {n}\nxllcorner 500000\nyllcorner 3700000\ncellsize 10"
    )
    .unwrap();
    for r in 0..n {
        let row: Vec<String> = (0..n)
            .map(|c| {
                format!(
                    "{:.1}",
                    500.0 + 80.0 * ((r as f64) / 97.0).sin() * ((c as f64) / 61.0).cos()
                )
            })
            .collect();
        writeln!(f, "{}", row.join(" ")).unwrap();
    }
    std::fs::write(
        path.with_extension("prj"),
        r#"PROJCS["WGS 84 / UTM zone 11N",AUTHORITY["EPSG","32611"]]"#,
    )
    .unwrap();
}

#[test]
fn sigterm_stops_the_daemon_within_five_seconds_even_mid_ingest() {
    let tmp = tempfile::tempdir().unwrap();
    let roots = tmp.path().join("roots");
    std::fs::create_dir_all(&roots).unwrap();
    let big = roots.join("big.asc");
    big_grid(&big, 3000);
    let setup = Setup {
        env: env(&[("PATCHWORK_INGEST_ROOTS", roots.to_str().unwrap())]),
        ..Setup::default()
    };
    let mut d = Daemon::start_with(tmp.path(), setup.clone());
    let mut ingest = Command::new(BIN)
        .args(["ingest", big.to_str().unwrap()])
        .arg(format!("--server={}", d.url))
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    // The signal lands while the daemon says the file is being ingested.
    let t0 = Instant::now();
    while d.json(&["stats", "--json"])["ingesting_source"].is_null() {
        assert!(
            t0.elapsed() < Duration::from_secs(60) && ingest.try_wait().unwrap().is_none(),
            "the ingest never showed in stats"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    let busy = ingest.try_wait().unwrap().is_none();
    let took = d.stop_timed();
    assert!(
        busy,
        "the ingest was over before the signal: make the grid bigger"
    );
    assert!(took < Duration::from_secs(5), "SIGTERM took {took:?}");
    eprintln!("SIGTERM during a 9 M-sample ingest: the daemon exited in {took:.2?}");
    let _ = ingest.wait();
    // The store opens and verifies, with or without the survey that was in flight.
    let d = Daemon::start_with(tmp.path(), setup);
    assert!(d.cli(&["verify"]).status.success(), "{}", d.log());
}

#[test]
fn sigterm_under_load_cancels_the_running_work_and_exits_with_margin() {
    let tmp = tempfile::tempdir().unwrap();
    let mut d = Daemon::start(tmp.path());
    drop_by_rename(&crop("copernicus_n34w119_crop.tif"), &d.inbox(), "a.tif");
    d.wait("the survey", |s| count(s, "active") == 1);
    // Sixteen clients asking for large tiles: twice the turns, each tile seconds of work.
    let clients: Vec<_> = (0..16)
        .map(|k| {
            let out = d.root.join(format!("t{k}.npy"));
            Command::new(BIN)
                .args([
                    "tile",
                    "--roi=-119.0,34.46,-118.92,34.54",
                    "--size=3000x3000",
                    "--backend=cpu",
                    "--out",
                    out.to_str().unwrap(),
                ])
                .arg(format!("--server={}", d.url))
                .stdout(std::process::Stdio::null())
                .stderr(std::process::Stdio::null())
                .spawn()
                .unwrap()
        })
        .collect();
    std::thread::sleep(Duration::from_millis(1500));
    let took = d.stop_timed();
    eprintln!("SIGTERM under 16 large tiles: the daemon exited in {took:.2?}");
    assert!(took < Duration::from_secs(5), "SIGTERM took {took:?}");
    for mut c in clients {
        let _ = c.wait();
    }
    assert!(
        !d.log().contains("stopping without them"),
        "the work was cancelled, not waited out: {}",
        d.log()
    );
}

#[test]
fn a_daemon_on_a_full_disk_starts_read_only_and_says_so() {
    let tmp = tempfile::tempdir().unwrap();
    let mut d = Daemon::start(tmp.path());
    drop_by_rename(&crop("copernicus_n34w119_crop.tif"), &d.inbox(), "a.tif");
    d.wait("the survey", |s| count(s, "active") == 1);
    let tile = |d: &Daemon| {
        let out = d.root.join("t.npy");
        let o = d.cli(&[
            "tile",
            "--roi=-118.99,34.47,-118.93,34.53",
            "--size=32x32",
            "--out",
            out.to_str().unwrap(),
        ]);
        assert!(o.status.success(), "{}", stderr(&o));
        let said = String::from_utf8_lossy(&o.stdout);
        assert!(
            !said.contains(" 0 valid samples"),
            "the tile holds data: {said}"
        );
        std::fs::read(out).unwrap()
    };
    let before = tile(&d);
    d.stop();
    // No disk has a petabyte free: to this daemon, the disk is full.
    let config = tmp.path().join("full.toml");
    std::fs::write(&config, "[storage]\nmin_free_mb = 1000000000\n").unwrap();
    let d = Daemon::start_with(
        tmp.path(),
        Setup {
            env: env(&[("PATCHWORK_CONFIG", config.to_str().unwrap())]),
            ..Setup::default()
        },
    );
    assert!(d.log().contains("read-only"), "{}", d.log());
    let stats = String::from_utf8_lossy(&d.cli(&["stats"]).stdout).into_owned();
    assert!(
        stats.contains("read-only: the disk holding the store"),
        "{stats}"
    );
    assert_eq!(tile(&d), before, "reads go on");
    let o = d.cli(&["retire", "whatever"]);
    assert!(!o.status.success());
    let nasa = tmp.path().join("inbox/b.tif");
    std::fs::copy(crop("nasadem_n34w119_crop.tif"), &nasa).unwrap();
    let o = d.cli(&["ingest", nasa.to_str().unwrap()]);
    assert!(stderr(&o).contains("MiB free"), "{}", stderr(&o));
    d.settle_inbox();
    let s = d.surveys();
    assert_eq!(
        (count(&s, "active"), count(&s, "failed")),
        (1, 0),
        "the inbox file waits: it is not the file's fault"
    );
}

#[test]
fn odd_names_keep_the_log_whole_and_failures_can_be_forgotten() {
    let tmp = tempfile::tempdir().unwrap();
    let d = Daemon::start(tmp.path());
    let odd = d.inbox().join("bad\nINJECTED line.tif");
    std::fs::write(tmp.path().join("stage.tif"), b"not a tiff at all").unwrap();
    std::fs::rename(tmp.path().join("stage.tif"), &odd).unwrap();
    let s = d.wait("the bad file", |s| count(s, "failed") == 1);
    assert!(s[0]["source"].as_str().unwrap().contains('\n'));
    assert!(
        !d.log().lines().any(|l| l.starts_with("INJECTED")),
        "{}",
        d.log()
    );
    let listing = String::from_utf8_lossy(&d.cli(&["surveys"]).stdout).into_owned();
    assert_eq!(listing.lines().count(), 1, "{listing}");
    let o = d.cli(&["forget", odd.to_str().unwrap()]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(count(&d.surveys(), "failed"), 0);
    let o = d.cli(&["forget", odd.to_str().unwrap()]);
    assert!(
        stderr(&o).contains("no failure is recorded"),
        "{}",
        stderr(&o)
    );
}

#[test]
fn a_client_that_stops_reading_a_tile_holds_its_work_only_until_the_deadline() {
    use patchwork::config::Config;
    use patchwork::engine::{Engine, Origin};
    use patchwork::serve::proto::terrain_client::TerrainClient;
    use std::sync::Arc;
    let tmp = tempfile::tempdir().unwrap();
    let data = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data");
    // One request at a time: a stalled stream that kept its permit would stall everyone.
    let mut cfg = Config {
        data_dir: tmp.path().join("data"),
        ingest_roots: vec![data.clone()],
        ..Config::default()
    };
    cfg.limits.deadline_ms = 1_000;
    cfg.limits.max_running_requests = 1;
    let engine = Arc::new(Engine::open(cfg).unwrap());
    let done = engine
        .ingest(
            &data.join("copernicus_n34w119_crop.tif"),
            None,
            Origin::Request,
        )
        .unwrap();
    assert!(done.error.is_empty(), "{}", done.error);
    let rt = tokio::runtime::Runtime::new().unwrap();
    rt.block_on(async {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let url = format!("http://{}", listener.local_addr().unwrap());
        tokio::spawn(patchwork::serve::grpc::serve(
            engine,
            listener,
            std::future::pending(),
        ));
        let tile = crop_tile;
        // 64 MB of heights, of which the client takes one band and then nothing more.
        let mut stalled = TerrainClient::connect(url.clone()).await.unwrap();
        let mut s = stalled
            .tile_bands(tile(4000, 4000))
            .await
            .unwrap()
            .into_inner();
        assert!(s.message().await.unwrap().is_some());
        tokio::time::sleep(Duration::from_millis(1_500)).await;
        // Past the deadline the permit is free again, while the stalled stream is still open.
        let mut other = TerrainClient::connect(url).await.unwrap();
        // With one request at a time and a deadline of a second, a permit still held would
        // leave this tile waiting past its deadline: that it is served is the proof, whatever
        // the machine's speed.
        let small = other.tile_bands(tile(64, 64)).await;
        assert!(small.is_ok(), "{:?}", small.err());
        drop(s);
    });
}
