//! One writer and two read replicas on one bucket of an S3 server (s3s-fs on loopback): the
//! replicas follow three surveys in, one replaced and one retired, and answer tiles and patch
//! sets byte for byte as the writer does; they refuse writes naming the writer; a writer
//! killed between a commit and its log leaves no replica with half of it and publishes it when
//! it restarts; the server stopped for 10 s costs nothing but the time; throttling is retried.

use crate::common;
use crate::common::daemon::*;
use crate::common::s3::S3Server;
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

/// How often the replicas ask for new commits, in ms.
const POLL_MS: u64 = 400;

/// The three regions the surveys cover: the N34W119 crops, the Ventoux voids, Ventoux's west.
const ROIS: [&str; 3] = [
    "-118.99,34.46,-118.90,34.53",
    "5.5,44.65,6.0,45.0",
    "5.2,44.09,5.36,44.24",
];

fn real(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/real")
        .join(name)
}

fn stats(d: &Daemon) -> Value {
    d.json(&["stats", "--json"])
}

fn commit(d: &Daemon) -> u64 {
    stats(d)["commit"].as_u64().unwrap()
}

/// What a server answers, as bytes: a tile of each region as GeoTIFF, and its patch sets.
fn answers(d: &Daemon, tag: &str) -> Vec<Vec<u8>> {
    let mut out = Vec::new();
    for (i, roi) in ROIS.iter().enumerate() {
        let file = d.root.join(format!("{tag}{i}.tif"));
        // On the CPU: compared bit for bit, where `auto` may pick either backend.
        let t = d.cli(&[
            "tile",
            "--backend=cpu",
            "--roi",
            roi,
            "--size",
            "64x48",
            "--error",
            "0",
            "--out",
            file.to_str().unwrap(),
        ]);
        assert!(t.status.success(), "{}", String::from_utf8_lossy(&t.stderr));
        out.push(std::fs::read(&file).unwrap());
        for error in ["0", "10"] {
            let q = d.cli(&["query", "--roi", roi, "--error", error, "--json"]);
            assert!(q.status.success(), "{}", String::from_utf8_lossy(&q.stderr));
            out.push(q.stdout);
        }
    }
    out
}

/// Waits until every replica has applied the writer's newest commit, and checks that they
/// then answer as it does. Returns how long the slowest took.
fn converge(w: &Daemon, replicas: &[&Daemon], step: &str) -> Duration {
    let want = commit(w);
    let t0 = Instant::now();
    for r in replicas {
        loop {
            let s = stats(r);
            if s["commit"].as_u64() == Some(want) {
                assert_eq!(s["published_commit"].as_u64(), Some(want), "{s}");
                assert_eq!(s["lag_seconds"].as_f64(), Some(0.0), "{s}");
                break;
            }
            // Two rounds, and room for a busy machine to schedule them.
            assert!(
                t0.elapsed() < Duration::from_millis(2 * POLL_MS) + Duration::from_secs(8),
                "{step}: a replica stays at commit {} of {want}: {s}\n{}",
                s["commit"],
                r.log()
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }
    let took = t0.elapsed();
    let theirs = answers(w, "w");
    for (i, r) in replicas.iter().enumerate() {
        assert!(
            answers(r, "r") == theirs,
            "{step}: replica {i} answers otherwise at commit {want}"
        );
    }
    took
}

fn surveys_of(d: &Daemon, status: &str) -> usize {
    count(&d.surveys(), status)
}

/// What Admin.Retire answers, which must be an error.
fn retire_over_grpc(d: &Daemon, source: &str) -> tonic::Status {
    use patchwork::serve::proto::{self as pb, admin_client::AdminClient};
    let rt = tokio::runtime::Runtime::new().unwrap();
    rt.block_on(async {
        let mut a = AdminClient::connect(d.url.clone()).await.unwrap();
        a.retire(pb::RetireRequest {
            id_or_source: source.into(),
        })
        .await
        .expect_err("a replica refuses a retirement")
    })
}

/// What Admin.Ingest answers for `path`.
fn ingest_over_grpc(d: &Daemon, path: &Path) -> Result<(), tonic::Status> {
    use patchwork::serve::proto::{self as pb, admin_client::AdminClient};
    let rt = tokio::runtime::Runtime::new().unwrap();
    rt.block_on(async {
        let mut a = AdminClient::connect(d.url.clone()).await.unwrap();
        a.ingest(pb::IngestRequest {
            paths: vec![path.to_string_lossy().into_owned()],
            accuracy_m: None,
        })
        .await
        .map(|_| ())
    })
}

/// The source name of the active survey of the inbox file `name`.
fn source(d: &Daemon, name: &str) -> String {
    d.surveys()
        .iter()
        .find(|s| s["status"] == "active" && s["source"].as_str().unwrap().ends_with(name))
        .unwrap_or_else(|| panic!("no active survey of {name}: {:#?}", d.surveys()))["source"]
        .as_str()
        .unwrap()
        .to_string()
}

#[test]
fn replicas_answer_as_the_writer_through_its_commits_its_crash_and_the_servers_outage() {
    let tmp = tempfile::tempdir().unwrap();
    let mut s3 = S3Server::start(&tmp.path().join("s3"));
    let mut env = s3.env("store1");
    env.extend([
        ("PATCHWORK_STORAGE_POLL_MS".into(), POLL_MS.to_string()),
        ("PATCHWORK_STORAGE_SNAPSHOT_EVERY".into(), "3".into()),
        (
            "PATCHWORK_INGEST_ROOTS".into(),
            real("").to_string_lossy().into_owned(),
        ),
    ]);
    let writer = Setup {
        env: env.clone(),
        ..Setup::default()
    };
    let mut follow = env.clone();
    follow.push(("PATCHWORK_FOLLOW".into(), "s3://terrain/store1".into()));
    let replica = Setup {
        env: follow,
        ..Setup::default()
    };
    let mut w = Daemon::start_with(&tmp.path().join("writer"), writer.clone());
    let r1 = Daemon::start_with(&tmp.path().join("r1"), replica.clone());
    let r2 = Daemon::start_with(&tmp.path().join("r2"), replica.clone());
    assert_eq!(stats(&r1)["follows"], "s3://terrain/store1");

    // Three surveys in, one replaced by new content under its name, one retired.
    drop_by_rename(&crop("copernicus_n34w119_crop.tif"), &w.inbox(), "a.tif");
    drop_by_rename(&crop("nasadem_n34w119_crop.tif"), &w.inbox(), "b.tif");
    drop_by_rename(&crop("srtm_n44e005_voids_crop.tif"), &w.inbox(), "c.tif");
    w.wait("three surveys", |s| count(s, "active") == 3);
    let mut lags = vec![converge(&w, &[&r1, &r2], "three surveys")];
    drop_by_rename(&crop("srtm_n44e005_big_hole_crop.tif"), &w.inbox(), "c.tif");
    w.wait("c.tif replaced", |s| count(s, "retired") == 1);
    lags.push(converge(&w, &[&r1, &r2], "a replacement"));
    let out = w.cli(&["retire", &source(&w, "a.tif")]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    lags.push(converge(&w, &[&r1, &r2], "a retirement"));
    assert_eq!(surveys_of(&r1, "active"), 2);

    // A replica refuses writes, naming the writer.
    let out = r1.cli(&["retire", &source(&r1, "b.tif")]);
    let said = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{said}");
    assert!(said.contains("read replica"), "{said}");
    assert!(said.contains(&format!(":{}:", w.pid().unwrap())), "{said}");
    let refused = retire_over_grpc(&r1, &source(&r1, "b.tif"));
    assert_eq!(
        refused.code(),
        tonic::Code::FailedPrecondition,
        "{refused:?}"
    );

    // The writer killed between a commit and its log: the log's PUT is refused until then.
    let before = commit(&r1);
    *s3.faults.refuse_puts.lock().unwrap() = Some("/store1/log/".into());
    drop_by_rename(&real("ventoux_geographic.tif"), &w.inbox(), "d.tif");
    w.wait("d.tif", |s| count(s, "active") == 3);
    std::thread::sleep(Duration::from_millis(3 * POLL_MS));
    // The segment is up and the writer's database has the commit; no replica has any of it.
    for r in [&r1, &r2] {
        assert_eq!(commit(r), before);
        assert_eq!(surveys_of(r, "active"), 2);
    }
    w.kill9();
    *s3.faults.refuse_puts.lock().unwrap() = None;
    let mut w = Daemon::start_with(&w.root.clone(), writer.clone());
    assert_eq!(
        commit(&w),
        before + 1,
        "the restarted writer is at the commit it crashed in"
    );
    lags.push(converge(&w, &[&r1, &r2], "the crashed commit"));
    assert_eq!(surveys_of(&r2, "active"), 3);

    // Throttling: a burst of 503s is retried with backoff, and the commit goes through.
    s3.faults.throttle.store(3, Ordering::SeqCst);
    let out = w.cli(&["retire", &source(&w, "d.tif")]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    lags.push(converge(&w, &[&r1, &r2], "throttled"));
    assert!(s3.faults.refused.load(Ordering::SeqCst) >= 3);

    // The server stopped for 10 s: the replicas keep serving what they hold, an ingest that
    // needs the server is refused as UNAVAILABLE, and once it is back the ingest goes through
    // and reaches the replicas. Nothing is lost.
    let held = answers(&r1, "held");
    s3.stop();
    let down = Instant::now();
    assert!(answers(&r1, "down") == held);
    let asc = real("ventoux.asc");
    let refused = ingest_over_grpc(&w, &asc).expect_err("no ingest with the server down");
    assert_eq!(refused.code(), tonic::Code::Unavailable, "{refused:?}");
    assert!(
        refused.message().contains("store1/segments/"),
        "{refused:?}"
    );
    assert!(answers(&r2, "down") == held);
    std::thread::sleep(Duration::from_secs(10).saturating_sub(down.elapsed()));
    s3.restart();
    let out = w.cli(&["ingest", asc.to_str().unwrap()]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    lags.push(converge(&w, &[&r1, &r2], "after the outage"));
    for d in [&w, &r1, &r2] {
        let v = d.cli(&["verify"]);
        assert!(v.status.success(), "{}", String::from_utf8_lossy(&v.stdout));
    }
    w.stop();
    eprintln!("replicas converged after {lags:?} (poll {POLL_MS} ms)");
}

/// The box of the store's plane (EPSG:4326 here) each region replica holds: the border runs
/// through the N34W119 crops, so that both hold tiles that meet there.
const WEST: [f64; 4] = [-180.0, -90.0, -118.95, 90.0];
const EAST: [f64; 4] = [-118.95, -90.0, 180.0, 90.0];

fn region_arg(b: [f64; 4]) -> String {
    format!("{},{},{},{}", b[0], b[1], b[2], b[3])
}

fn inside(t: &patchwork::serve::proto::Rect, b: [f64; 4]) -> bool {
    t.xmin >= b[0] && t.ymin >= b[1] && t.xmax <= b[2] && t.ymax <= b[3]
}

/// Waits until `d` has applied commit `want`.
fn at_commit(d: &Daemon, want: u64) {
    let t0 = Instant::now();
    while commit(d) != want || stats(d)["published_commit"].as_u64() != Some(want) {
        assert!(
            t0.elapsed() < Duration::from_secs(30),
            "a replica stays behind commit {want}: {}",
            d.log()
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// A pyramid of web tiles: its tiles over an area in degrees, a tile's bounds, its path and
/// its tiles' extension.
type Pyramid = (
    fn(u32, &patchwork_core::geom::Aabb) -> patchwork_core::geom::tiles::TileRange,
    fn(u32, u32, u32) -> patchwork_core::geom::Aabb,
    &'static str,
    &'static str,
);

/// The web tiles of levels 11 to 14 over the N34W119 crops and of level 11 over the Ventoux
/// crop, each with its bounds in degrees: raster-DEM (PNG) and quantized-mesh paths.
fn tiles() -> Vec<(String, patchwork::serve::proto::Rect)> {
    use patchwork_core::geom::tiles::{geographic, mercator};
    use patchwork_core::geom::Aabb;
    let rect = |b: Aabb| patchwork::serve::proto::Rect {
        xmin: b.min[0],
        ymin: b.min[1],
        xmax: b.max[0],
        ymax: b.max[1],
    };
    let mut out = Vec::new();
    for (area, levels) in [
        (Aabb::new(-118.99, 34.46, -118.90, 34.53), 11..=14),
        (Aabb::new(5.5, 44.65, 6.0, 45.0), 11..=11),
    ] {
        for z in levels {
            let pyramids: [Pyramid; 2] = [
                (mercator::over, mercator::lonlat_bounds, "tiles", "png"),
                (geographic::over, geographic::bounds, "terrain", "terrain"),
            ];
            for (over, bounds, path, ext) in pyramids {
                let r = over(z, &area);
                for x in r.x0..=r.x1 {
                    for y in r.y0..=r.y1 {
                        out.push((format!("/{path}/{z}/{x}/{y}.{ext}"), rect(bounds(z, x, y))));
                    }
                }
            }
        }
    }
    out
}

/// nginx, where installed: its path, or why not.
fn nginx() -> Result<PathBuf, String> {
    let found = std::env::var_os("NGINX")
        .map(PathBuf::from)
        .into_iter()
        .chain(["/usr/sbin/nginx", "/usr/bin/nginx", "/usr/local/sbin/nginx"].map(PathBuf::from))
        .find(|p| p.is_file());
    found.ok_or_else(|| "no nginx (Debian's nginx-light; or NGINX=path)".into())
}

#[test]
fn region_replicas_answer_inside_their_regions_as_the_whole_store_behind_a_proxy() {
    let tmp = tempfile::tempdir().unwrap();
    let s3 = S3Server::start(&tmp.path().join("s3"));
    let mut env = s3.env("regions");
    env.push(("PATCHWORK_STORAGE_POLL_MS".into(), POLL_MS.to_string()));
    // Tiles are compared bit for bit, and `auto` picks the GPU or the CPU by their load, which
    // agree only to a rounding: these daemons take no emulated GPU.
    let cpu = vec!["PATCHWORK_ALLOW_EMULATED_GPU".to_string()];
    let writer = Setup {
        env: env.clone(),
        unset: cpu.clone(),
        ..Setup::default()
    };
    let replica = |region: Option<[f64; 4]>| {
        let mut e = env.clone();
        e.push(("PATCHWORK_FOLLOW".into(), "s3://terrain/regions".into()));
        if let Some(b) = region {
            e.push(("PATCHWORK_REGION".into(), region_arg(b)));
        }
        Setup {
            env: e,
            unset: cpu.clone(),
            ..Setup::default()
        }
    };
    let w = Daemon::start_with(&tmp.path().join("writer"), writer);
    let whole = Daemon::start_with(&tmp.path().join("whole"), replica(None));
    let west = Daemon::start_with(&tmp.path().join("west"), replica(Some(WEST)));
    let east = Daemon::start_with(&tmp.path().join("east"), replica(Some(EAST)));
    drop_by_rename(&crop("copernicus_n34w119_crop.tif"), &w.inbox(), "a.tif");
    drop_by_rename(&crop("nasadem_n34w119_crop.tif"), &w.inbox(), "b.tif");
    drop_by_rename(&crop("srtm_n44e005_voids_crop.tif"), &w.inbox(), "c.tif");
    w.wait("three surveys", |s| count(s, "active") == 3);
    let want = commit(&w);
    for d in [&whole, &west, &east] {
        at_commit(d, want);
    }
    // The west holds the crops that reach its border, not the Alps.
    let boxes = |d: &Daemon| stats(d)["active_boxes"].as_u64().unwrap();
    assert!(
        boxes(&west) < boxes(&whole),
        "the west replica holds {} boxes, the whole store {}",
        boxes(&west),
        boxes(&whole)
    );

    // Every tile inside a region comes from its replica byte for byte as from the whole
    // store's; one across the border, or beyond, is refused as misdirected.
    let get = |d: &Daemon, path: &str| common::http::get(&format!("{}{path}", d.http), &[]);
    let tiles = tiles();
    let (mut same, mut refused) = (0, 0);
    for (path, b) in &tiles {
        let want = get(&whole, path);
        assert_eq!(want.status, 200, "{path}: {}", want.text());
        for (d, region) in [(&west, WEST), (&east, EAST)] {
            let got = get(d, path);
            if inside(b, region) {
                assert_eq!(got.status, 200, "{path}: {}", got.text());
                assert!(
                    got.body == want.body,
                    "{path} differs from the whole store's"
                );
                same += 1;
            } else {
                assert_eq!(got.status, 421, "{path}: {}", got.text());
                assert_eq!(got.json()["reason"], "OUTSIDE_REGION", "{path}");
                refused += 1;
            }
        }
    }
    assert!(
        same > 20 && refused > 20,
        "{same} tiles alike, {refused} refused"
    );
    // Heights at points inside a region, and a view-dependent cut nowhere.
    let points = "/heights?points=-118.97,34.5,-118.96,34.51";
    let (here, there) = (get(&west, points), get(&whole, points));
    assert_eq!(there.status, 200, "{}", there.text());
    assert_eq!(here.body, there.body);
    assert_eq!(get(&east, points).status, 421);

    // Behind nginx, with the config the daemon prints: every tile as the whole store's, each
    // served by the replica its region holds it in, or by the whole store's.
    let nginx = match nginx() {
        Ok(p) => p,
        Err(why) => {
            let msg = format!("proxy part NOT RUN: {why}");
            if std::env::var("PATCHWORK_REQUIRE_PROXY").as_deref() == Ok("1") {
                panic!("{msg} (PATCHWORK_REQUIRE_PROXY=1)");
            }
            println!("{msg}");
            return;
        }
    };
    let dir = tmp.path().join("nginx");
    std::fs::create_dir_all(dir.join("tmp")).unwrap();
    let port = free_port();
    let printed = std::process::Command::new(BIN)
        .args([
            "proxy-config",
            &format!("--listen=127.0.0.1:{port}"),
            &format!("--whole={}", whole.http),
            &format!("--replica=west={}@{}", west.http, region_arg(WEST)),
            &format!("--replica=east={}@{}", east.http, region_arg(EAST)),
        ])
        .output()
        .unwrap();
    assert!(
        printed.status.success(),
        "{}",
        String::from_utf8_lossy(&printed.stderr)
    );
    std::fs::write(dir.join("patchwork.conf"), &printed.stdout).unwrap();
    let d = dir.display();
    std::fs::write(
        dir.join("nginx.conf"),
        format!(
            "worker_processes 1;\npid {d}/nginx.pid;\nerror_log {d}/error.log;\n\
             events {{ worker_connections 64; }}\n\
             http {{\n    log_format route '$uri $upstream_addr $status';\n    \
             access_log {d}/access.log route;\n    \
             client_body_temp_path {d}/tmp;\n    proxy_temp_path {d}/tmp;\n    \
             fastcgi_temp_path {d}/tmp;\n    uwsgi_temp_path {d}/tmp;\n    \
             scgi_temp_path {d}/tmp;\n    include {d}/patchwork.conf;\n}}\n"
        ),
    )
    .unwrap();
    let mut proxy = std::process::Command::new(&nginx)
        .args([
            "-p",
            &d.to_string(),
            "-c",
            &format!("{d}/nginx.conf"),
            "-g",
            "daemon off;",
        ])
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let base = format!("http://127.0.0.1:{port}");
    let t0 = Instant::now();
    while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
        if let Some(status) = proxy.try_wait().unwrap() {
            let mut err = String::new();
            std::io::Read::read_to_string(proxy.stderr.as_mut().unwrap(), &mut err).unwrap();
            panic!("nginx exited ({status}): {err}");
        }
        assert!(
            t0.elapsed() < Duration::from_secs(10),
            "nginx did not listen"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    for (path, _) in &tiles {
        let via = common::http::get(&format!("{base}{path}"), &[]);
        assert_eq!(via.status, 200, "{path} through nginx: {}", via.text());
        assert!(via.body == get(&whole, path).body, "{path} through nginx");
    }
    let _ = proxy.kill();
    let _ = proxy.wait();
    // Where each went, from nginx's log.
    let addr = |d: &Daemon| d.http.trim_start_matches("http://").to_string();
    let log = std::fs::read_to_string(dir.join("access.log")).unwrap();
    let mut routed = [0usize; 3];
    for (path, b) in &tiles {
        let line = log
            .lines()
            .find(|l| l.split(' ').next() == Some(path.as_str()))
            .unwrap_or_else(|| panic!("{path} is not in nginx's log"));
        let to = line.split(' ').nth(1).unwrap();
        let (want, k) = if inside(b, WEST) {
            (addr(&west), 0)
        } else if inside(b, EAST) {
            (addr(&east), 1)
        } else {
            (addr(&whole), 2)
        };
        assert_eq!(to, want, "{path} went to {to}");
        routed[k] += 1;
    }
    assert!(routed.iter().all(|&n| n > 0), "routed {routed:?}");
    eprintln!(
        "boxes: west {}, east {}, whole {}; {same} tiles alike and {refused} refused; through \
         nginx west {} east {} whole {}",
        boxes(&west),
        boxes(&east),
        boxes(&whole),
        routed[0],
        routed[1],
        routed[2]
    );
}
