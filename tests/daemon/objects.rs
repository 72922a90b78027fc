//! A store whose chunks live on an S3 server (s3s-fs on loopback): it serves what a store on
//! the local pack serves, to the sample; cached reads go on while the server is down, cold ones
//! fail as UNAVAILABLE and succeed once it is back; a crashed commit's segment is deleted at
//! the next open; a second store is refused the place, and a second writer the lease; a lost
//! segment is named as damage.

use crate::common::copy_dir;
use crate::common::daemon::*;
use crate::common::s3::S3Server;
use std::path::Path;
use std::process::Output;
use std::time::{Duration, Instant};

const FILE: &str = "copernicus_n34w119_crop.tif";
/// Two corners of the crop that lie in different chunks of its finest level (chunks are 256
/// samples a side; the crop is 300).
const WEST: &str = "-118.995,34.50,-118.975,34.53";
const EAST: &str = "-118.925,34.47,-118.918,34.53";

/// On the CPU: the heights are compared bit for bit between stores, and `auto` may send
/// two requests to different backends, which agree only to the GPU's tolerance.
fn tile(d: &Daemon, roi: &str, out: &Path) -> Output {
    d.cli(&[
        "tile",
        "--backend=cpu",
        "--roi",
        roi,
        "--size",
        "40x60",
        "--error",
        "0",
        "--out",
        out.to_str().unwrap(),
    ])
}

fn heights(d: &Daemon, roi: &str, out: &Path) -> Vec<f32> {
    let done = tile(d, roi, out);
    assert!(
        done.status.success(),
        "{}\n{}",
        String::from_utf8_lossy(&done.stderr),
        d.log()
    );
    patchwork_read::read_raster(out, &Default::default())
        .unwrap()
        .samples
}

/// The east tile over gRPC, which must fail: its status.
fn cold_tile(d: &Daemon) -> tonic::Status {
    use patchwork::serve::proto::{self as pb, terrain_client::TerrainClient};
    let [xmin, ymin, xmax, ymax]: [f64; 4] = EAST
        .split(',')
        .map(|v| v.parse().unwrap())
        .collect::<Vec<_>>()
        .try_into()
        .unwrap();
    let mut req = crop_tile(40, 60);
    req.cut = Some(pb::tile_request::Cut::Uniform(pb::UniformCut {
        roi: Some(pb::Rect {
            xmin,
            ymin,
            xmax,
            ymax,
        }),
        error: 0.0,
    }));
    let rt = tokio::runtime::Runtime::new().unwrap();
    rt.block_on(async {
        let mut t = TerrainClient::connect(d.url.clone()).await.unwrap();
        t.resample_tile(req)
            .await
            .expect_err("a cold read with the server down")
    })
}

fn active(d: &Daemon) {
    d.wait("the survey active", |s| count(s, "active") == 1);
}

#[test]
fn a_store_on_s3_serves_as_a_local_one_and_rides_out_the_server_going_away() {
    let tmp = tempfile::tempdir().unwrap();
    let out = |name: &str| tmp.path().join(name);
    let mut s3 = S3Server::start(&tmp.path().join("s3"));
    let setup = Setup {
        env: s3.env("store1"),
        ..Setup::default()
    };
    let local = Daemon::start(&tmp.path().join("local"));
    let mut d = Daemon::start_with(&tmp.path().join("remote"), setup.clone());
    drop_by_rename(&crop(FILE), &local.inbox(), FILE);
    drop_by_rename(&crop(FILE), &d.inbox(), FILE);
    active(&local);
    active(&d);
    // The chunks went to the bucket, one segment a commit; none to the data folder.
    assert!(!tmp.path().join("remote/data/chunks.pack").exists());
    let segments = s3.segments("store1");
    assert_eq!(segments.len(), 1, "{segments:?}");

    // A fresh start, so that every sample comes from the bucket, not from the ingest's memory.
    d.stop();
    let mut d = Daemon::start_with(&d.root.clone(), setup.clone());
    let west = heights(&d, WEST, &out("w.tif"));
    assert!(west.iter().all(|h| h.is_finite()));
    assert_eq!(west, heights(&local, WEST, &out("lw.tif")));

    // The server goes: what is cached is served, what is not is UNAVAILABLE, soon.
    s3.stop();
    assert_eq!(heights(&d, WEST, &out("w2.tif")), west);
    let t0 = Instant::now();
    let cold = cold_tile(&d);
    assert_eq!(cold.code(), tonic::Code::Unavailable, "{cold:?}");
    assert!(cold.message().contains("store1/segments/"), "{cold:?}");
    assert!(t0.elapsed() < Duration::from_secs(20), "{:?}", t0.elapsed());
    // It comes back, and so does everything it holds.
    s3.restart();
    let east = heights(&d, EAST, &out("e.tif"));
    assert_eq!(east, heights(&local, EAST, &out("le.tif")));
    let v = d.cli(&["verify"]);
    assert!(v.status.success(), "{}", String::from_utf8_lossy(&v.stdout));

    // A commit that crashed after its segment went up leaves one past the committed end: the
    // next open deletes it, and the store verifies.
    d.stop();
    let orphan = segments[0].with_file_name(format!("{:020}.seg", 1u64 << 40));
    std::fs::write(&orphan, b"a commit that never reached the database").unwrap();
    let mut d = Daemon::start_with(&d.root.clone(), setup.clone());
    assert!(!orphan.exists());
    assert_eq!(s3.segments("store1"), segments);
    let v = d.cli(&["verify"]);
    assert!(v.status.success(), "{}", String::from_utf8_lossy(&v.stdout));

    // Another store may not take a place that holds this one's segments.
    let other = tmp.path().join("other");
    let mut child = Daemon::command(&other, free_port(), &setup)
        .spawn()
        .unwrap();
    let t0 = Instant::now();
    let code = loop {
        if let Some(c) = child.try_wait().unwrap() {
            break c;
        }
        assert!(
            t0.elapsed() < Duration::from_secs(30),
            "the second store opened"
        );
        std::thread::sleep(Duration::from_millis(100));
    };
    assert!(!code.success());
    let log = std::fs::read_to_string(other.join("serve.log")).unwrap();
    assert!(log.contains("another store's"), "{log}");
    assert_eq!(s3.segments("store1"), segments);

    // A second writer, on a copy of the database, is refused while the lease lives, and says
    // who holds it.
    d.stop();
    let copy = tmp.path().join("copy");
    copy_dir(&d.root.join("data"), &copy.join("data"));
    let mut d = Daemon::start_with(&d.root.clone(), setup.clone());
    let mut child = Daemon::command(&copy, free_port(), &setup).spawn().unwrap();
    let t0 = Instant::now();
    while child.try_wait().unwrap().is_none() {
        assert!(
            t0.elapsed() < Duration::from_secs(30),
            "the second writer opened"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    let log = std::fs::read_to_string(copy.join("serve.log")).unwrap();
    assert!(log.contains("holds the store's lease"), "{log}");
    assert!(d.cli(&["stats"]).status.success());

    // A segment lost from the bucket: the survey is damaged, and verify names what is gone.
    d.stop();
    std::fs::remove_file(&segments[0]).unwrap();
    let d = Daemon::start_with(&d.root.clone(), setup);
    let v = d.cli(&["verify"]);
    let said = String::from_utf8_lossy(&v.stdout);
    assert!(!v.status.success(), "{said}");
    assert!(said.contains("s3://terrain/store1"), "{said}");
}

/// An operator's `stats` and listing answer while every turn to run a request waits on a
/// backend that answers nothing: 16 clients' cold tiles hold the turns and queue for more.
/// The admin reads run beside the turns, so they neither wait for one nor take one.
#[test]
fn stats_and_the_listing_answer_while_tiles_queue_behind_a_stalled_backend() {
    use patchwork::serve::proto::terrain_client::TerrainClient;
    use patchwork::serve::proto::{self as pb, admin_client::AdminClient};
    use std::sync::atomic::Ordering;
    const CLIENTS: usize = 16;
    let tmp = tempfile::tempdir().unwrap();
    let s3 = S3Server::start(&tmp.path().join("s3"));
    // A GET held for the whole test must not time out in the store's client meanwhile.
    let config = tmp.path().join("patchwork.toml");
    std::fs::write(&config, "[storage]\ntimeout_ms = 120000\n").unwrap();
    let mut env = s3.env("stalled");
    env.push(("PATCHWORK_CONFIG".into(), config.to_string_lossy().into()));
    let setup = Setup {
        env,
        ..Setup::default()
    };
    let d = Daemon::start_with(&tmp.path().join("d"), setup.clone());
    drop_by_rename(&crop(FILE), &d.inbox(), FILE);
    active(&d);
    // A fresh start: every sample is read from the bucket.
    let mut d = d;
    d.stop();
    let d = Daemon::start_with(&d.root.clone(), setup);
    s3.faults.hold_gets.store(true, Ordering::SeqCst);
    let rt = tokio::runtime::Runtime::new().unwrap();
    let limit = rt.block_on(async {
        let mut tiles = Vec::new();
        for k in 0..CLIENTS {
            let url = d.url.clone();
            tiles.push(tokio::spawn(async move {
                let mut t = TerrainClient::connect(url).await.unwrap();
                let mut req = crop_tile(16 + k as u32, 16);
                req.backend = pb::Backend::Cpu as i32;
                t.resample_tile(req).await
            }));
        }
        let mut admin = AdminClient::connect(d.url.clone()).await.unwrap();
        let stats = || {
            let mut r = tonic::Request::new(pb::StatsRequest {});
            // Far past what an answer that waits for no turn takes; far short of the held
            // GETs, so that an answer queued behind them fails here.
            r.set_timeout(Duration::from_secs(5));
            let mut a = admin.clone();
            async move { a.stats(r).await.map(|r| r.into_inner()) }
        };
        // Until every turn is held by a tile whose read hangs, and tiles wait for more. A
        // tile takes its turn before it reads: on a loaded machine every turn can be taken
        // while no read has reached the bucket yet.
        let t0 = Instant::now();
        let limit = loop {
            let s = stats().await.expect("stats while tiles hold the turns");
            if s.requests_running == s.requests_limit
                && s.requests_waiting > 0
                && s3.faults.held.load(Ordering::SeqCst) > 0
            {
                break s.requests_limit;
            }
            assert!(
                t0.elapsed() < Duration::from_secs(30),
                "the tiles never held every turn: {s:?}"
            );
            tokio::time::sleep(Duration::from_millis(50)).await;
        };
        let mut took = Vec::new();
        for _ in 0..10 {
            let t0 = Instant::now();
            let s = stats().await.expect("stats while tiles queue");
            took.push(t0.elapsed().as_secs_f64() * 1e3);
            assert_eq!(s.requests_running, s.requests_limit);
            assert_eq!(s.surveys, 1);
        }
        let mut r = tonic::Request::new(pb::ListSurveysRequest {});
        r.set_timeout(Duration::from_secs(5));
        let listed = admin
            .list_surveys(r)
            .await
            .expect("the listing while tiles queue");
        assert_eq!(listed.into_inner().surveys.len(), 1);
        took.sort_by(f64::total_cmp);
        eprintln!(
            "stats beside {CLIENTS} tiles held on the backend: median {:.1} ms, worst {:.1} ms",
            took[took.len() / 2],
            took[took.len() - 1]
        );
        // The backend answers again: every tile is served.
        s3.faults.hold_gets.store(false, Ordering::SeqCst);
        for t in tiles {
            let tile = t.await.unwrap();
            assert!(tile.is_ok(), "{tile:?}");
        }
        limit
    });
    assert_eq!(limit, 8);
}
