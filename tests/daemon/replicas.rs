//! One writer and two read replicas on one bucket of an S3 server (s3s-fs on loopback): the
//! replicas follow three surveys in, one replaced and one retired, and answer tiles and patch
//! sets byte for byte as the writer does; they refuse writes naming the writer; a writer
//! killed between a commit and its log leaves no replica with half of it and publishes it when
//! it restarts; the server stopped for 10 s costs nothing but the time; throttling is retried.

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
