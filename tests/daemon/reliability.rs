//! What the engine and the inbox promise under bad requests and faults: ingest stays inside
//! its folders and says nothing about the rest of the disk, failure records stay bounded, a
//! full disk refuses writes while reads go on, a retirement by hand sticks, and an inbox
//! folder that goes away retires nothing. docs/RELIABILITY.md points at each test.

use crate::common;

use common::daemon::crop;
use patchwork::config::{Config, OnDelete};
use patchwork::engine::{
    Ctx, Cut, Engine, EngineError, Origin, Outcome, TileRequest, REFUSED_PATH,
};
use patchwork::serve::status::to_status;
use patchwork::store::{DiskSpace, Status, StoreError};
use patchwork::watch::Reconciler;
use patchwork_core::geom::Aabb;
use patchwork_core::resample::Backend;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

const COP: &str = "copernicus_n34w119_crop.tif";
const NASA: &str = "nasadem_n34w119_crop.tif";
const SRTM: &str = "srtm_n44e005_voids_crop.tif";

struct Setup {
    tmp: tempfile::TempDir,
    cfg: Config,
}

impl Setup {
    fn new() -> Setup {
        let tmp = tempfile::tempdir().unwrap();
        let root = tmp.path().canonicalize().unwrap();
        for d in ["inbox", "roots", "outside"] {
            std::fs::create_dir_all(root.join(d)).unwrap();
        }
        let cfg = Config {
            data_dir: root.join("data"),
            inbox: vec![root.join("inbox")],
            ingest_roots: vec![root.join("roots")],
            settle_ms: 0,
            ..Config::default()
        };
        Setup { tmp, cfg }
    }

    fn root(&self) -> PathBuf {
        self.tmp.path().canonicalize().unwrap()
    }

    fn at(&self, rel: &str) -> PathBuf {
        self.root().join(rel)
    }

    fn put(&self, crop_name: &str, rel: &str) -> PathBuf {
        let p = self.at(rel);
        std::fs::copy(crop(crop_name), &p).unwrap();
        p
    }

    fn engine(&self) -> Arc<Engine> {
        Arc::new(Engine::open(self.cfg.clone()).unwrap())
    }
}

fn ingest(e: &Engine, p: &Path) -> patchwork::engine::Ingested {
    e.ingest(p, None, Origin::Request).unwrap()
}

#[test]
fn ingest_stays_inside_its_folders_and_says_nothing_about_the_rest() {
    let s = Setup::new();
    let e = s.engine();
    let outside = s.put(COP, "outside/good.tif");
    std::fs::create_dir(s.at("outside/folder.tif")).unwrap();
    std::os::unix::fs::symlink(&outside, s.at("inbox/link.tif")).unwrap();
    std::os::unix::fs::symlink(s.at("outside/none.tif"), s.at("inbox/dangling.tif")).unwrap();
    let asc = s.at("roots/grid.asc");
    std::fs::write(
        &asc,
        "ncols 2\nnrows 2\nxllcorner 0\nyllcorner 0\ncellsize 1\n1 2\n3 4\n",
    )
    .unwrap();
    // A sidecar that leads outside gives the file away as surely as the file itself.
    std::fs::write(s.at("outside/secret.prj"), "root:x:0:0").unwrap();
    std::os::unix::fs::symlink(s.at("outside/secret.prj"), s.at("roots/grid.prj")).unwrap();
    let refused = [
        outside.clone(),
        s.at("outside/missing.tif"),
        s.at("outside/folder.tif"),
        s.at("inbox/link.tif"),
        s.at("inbox/dangling.tif"),
        s.at("inbox/../outside/good.tif"),
        PathBuf::from("/etc/passwd"),
        PathBuf::from("/"),
        asc.clone(),
    ];
    for p in &refused {
        let r = ingest(&e, p);
        assert_eq!(r.outcome, Outcome::Failed, "{}", p.display());
        assert_eq!(r.error, REFUSED_PATH, "{}", p.display());
        assert_eq!(
            r.reason,
            Some(patchwork::engine::Reason::OutsideIngestFolders),
            "{}",
            p.display()
        );
    }
    assert!(
        e.catalog().failures.is_empty(),
        "a client's paths are not remembered"
    );
    std::fs::remove_file(s.at("roots/grid.prj")).unwrap();
    // Inside, the errors say what is wrong; the ASCII grid has no CRS.
    let r = ingest(&e, &asc);
    assert!(r.error.contains("no CRS"), "{}", r.error);
    assert_eq!(r.reason, Some(patchwork::engine::Reason::Crs));
    let good = s.put(COP, "roots/good.tif");
    assert_eq!(ingest(&e, &good).outcome, Outcome::Inserted);
    let inbox = s.put(NASA, "inbox/nasa.tif");
    assert_eq!(ingest(&e, &inbox).outcome, Outcome::Inserted);

    // A FIFO, as the file or as its sidecar, is refused at once: opening one to read would
    // wait for a writer that never comes, and hold up every ingest after it.
    let fifo = |p: &Path| {
        let ok = std::process::Command::new("mkfifo")
            .arg(p)
            .status()
            .unwrap();
        assert!(ok.success());
    };
    fifo(&s.at("roots/pipe.tif"));
    let other = s.put(SRTM, "roots/other.tif");
    fifo(&s.at("roots/other.tif.toml"));
    let (tx, rx) = std::sync::mpsc::channel();
    let (e2, pipe) = (e.clone(), s.at("roots/pipe.tif"));
    std::thread::spawn(move || {
        let a = ingest(&e2, &pipe).error;
        let b = ingest(&e2, &other).error;
        tx.send((a, b)).unwrap();
    });
    let (a, b) = rx
        .recv_timeout(Duration::from_secs(20))
        .expect("a FIFO held the ingest up");
    assert!(a.contains("not a regular file"), "{a}");
    assert!(
        b.contains("sidecar") && b.contains("not a regular file"),
        "{b}"
    );
}

#[test]
fn failure_records_are_bounded_and_batches_limited() {
    let mut s = Setup::new();
    s.cfg.limits.max_failures = 20;
    let e = s.engine();
    for i in 0..60 {
        let p = s.at(&format!("roots/bad{i:02}.tif"));
        std::fs::write(&p, b"not a tiff").unwrap();
        assert_eq!(ingest(&e, &p).outcome, Outcome::Failed);
        // Asking again for the same file keeps one record.
        assert_eq!(ingest(&e, &p).outcome, Outcome::Failed);
        // Names with nothing behind them are not remembered at all.
        ingest(&e, &s.at(&format!("roots/missing{i}.tif")));
    }
    let failures = &e.catalog().failures;
    assert_eq!(failures.len(), 20);
    assert!(failures.iter().all(|f| f.source.contains("/roots/bad")));
    let last = s.at("roots/bad59.tif");
    assert!(e.forget(last.to_str().unwrap()).unwrap());
    assert!(!e.forget(last.to_str().unwrap()).unwrap());
    assert_eq!(e.catalog().failures.len(), 19);

    let r = patchwork::serve::proto::IngestRequest {
        paths: vec!["/x.tif".into(); 257],
        accuracy_m: None,
    };
    let err = patchwork::serve::api::ingest(&e, &r).unwrap_err();
    assert_eq!(to_status(err).code(), tonic::Code::ResourceExhausted);
    let r = patchwork::serve::proto::RetireRequest {
        id_or_source: "x".repeat(1 << 20),
    };
    let st = to_status(patchwork::serve::api::retire(&e, &r).unwrap_err());
    assert_eq!(st.code(), tonic::Code::InvalidArgument);
    assert!(st.message().len() < 200, "{}", st.message());
    let r = patchwork::serve::proto::RetireRequest {
        id_or_source: "y".repeat(4000),
    };
    let st = to_status(patchwork::serve::api::retire(&e, &r).unwrap_err());
    assert_eq!(st.code(), tonic::Code::NotFound);
    assert!(st.message().len() < 300, "{}", st.message());
}

/// A disk whose free space the test sets.
struct FakeDisk(AtomicU64);

impl DiskSpace for FakeDisk {
    fn available(&self, _: &Path) -> std::io::Result<u64> {
        Ok(self.0.load(Ordering::SeqCst))
    }
}

fn tile(e: &Engine, roi: Aabb) -> Vec<u32> {
    let cut = Cut::new(None, roi, 0.0).unwrap();
    let (t, _, _) = e
        .tile(
            &TileRequest::new(cut.clone(), 64, 64, Backend::Cpu).unwrap(),
            Ctx::default(),
        )
        .unwrap();
    t.heights.iter().map(|h| h.to_bits()).collect()
}

#[test]
fn a_full_disk_refuses_writes_keeps_reads_and_writes_resume_with_space() {
    let s = Setup::new();
    let disk = Arc::new(FakeDisk(AtomicU64::new(u64::MAX)));
    let e = Engine::open_on(s.cfg.clone(), disk.clone()).unwrap();
    let a = s.put(COP, "roots/a.tif");
    let b = s.put(NASA, "roots/b.tif");
    assert_eq!(ingest(&e, &a).outcome, Outcome::Inserted);
    let roi = e.snapshot().index().bounds().unwrap();
    let before = tile(&e, roi);
    assert!(e.read_only().is_none());

    disk.0.store(1 << 20, Ordering::SeqCst);
    let err = e.ingest(&b, None, Origin::Request).unwrap_err();
    assert!(
        matches!(err, EngineError::Store(StoreError::Full { .. })),
        "{err}"
    );
    assert_eq!(to_status(err).code(), tonic::Code::ResourceExhausted);
    let err = e.retire(a.to_str().unwrap()).unwrap_err();
    assert_eq!(to_status(err).code(), tonic::Code::ResourceExhausted);
    assert!(e.compact().is_err());
    assert!(
        e.catalog().failures.is_empty(),
        "the disk is not the file's fault"
    );
    // Reads go on as before.
    assert_eq!(tile(&e, roi), before);
    assert_eq!(e.stats().surveys, 1);
    assert!(e.stats().read_only.unwrap().contains("MiB free"));
    assert!(e.verify().unwrap().is_ok());

    disk.0.store(u64::MAX, Ordering::SeqCst);
    assert_eq!(ingest(&e, &b).outcome, Outcome::Inserted);
    assert!(e.read_only().is_none());
    drop(e);

    // A daemon that starts on a full disk serves what it has, read-only.
    disk.0.store(0, Ordering::SeqCst);
    let e = Engine::open_on(s.cfg.clone(), disk.clone()).unwrap();
    assert_eq!(e.stats().surveys, 2);
    assert!(e.read_only().is_some());
    assert_eq!(tile(&e, roi).len(), before.len());
    disk.0.store(u64::MAX, Ordering::SeqCst);
    assert!(e.retire(b.to_str().unwrap()).is_ok());
}

fn reconciler(e: &Arc<Engine>, s: &Setup) -> Reconciler<Engine> {
    let mut r = Reconciler::new(e.clone(), &s.cfg.inbox, Duration::ZERO, OnDelete::Retire);
    r.startup();
    r
}

fn active(e: &Engine) -> Vec<String> {
    let mut v: Vec<String> = e.catalog().active().map(|r| r.source.clone()).collect();
    v.sort();
    v
}

#[test]
fn a_retirement_by_hand_sticks_until_the_file_changes() {
    let s = Setup::new();
    let e = s.engine();
    let a = s.put(COP, "inbox/a.tif");
    let mut rec = reconciler(&e, &s);
    rec.pass();
    assert_eq!(active(&e).len(), 1);
    e.retire(a.to_str().unwrap()).unwrap();
    rec.pass();
    assert!(active(&e).is_empty(), "the next pass leaves it retired");
    // Nor does a restart bring it back.
    drop(rec);
    let e = {
        drop(e);
        s.engine()
    };
    let mut rec = reconciler(&e, &s);
    rec.pass();
    assert!(active(&e).is_empty(), "a restart leaves it retired");
    // New content at the same path is a new survey.
    std::fs::copy(crop(NASA), &a).unwrap();
    rec.pass();
    assert_eq!(active(&e), vec![a.to_string_lossy().into_owned()]);
    // A client that names the file brings it back at once.
    e.retire(a.to_str().unwrap()).unwrap();
    assert!(active(&e).is_empty());
    assert_eq!(ingest(&e, &a).outcome, Outcome::Inserted);
    assert!(e.catalog().pins.is_empty());
    // Deleting a retired file drops its pin: the same file dropped in again comes back.
    e.retire(a.to_str().unwrap()).unwrap();
    assert_eq!(e.catalog().pins.len(), 1);
    std::fs::remove_file(&a).unwrap();
    rec.pass();
    assert!(e.catalog().pins.is_empty());
    std::fs::copy(crop(NASA), &a).unwrap();
    rec.pass();
    assert_eq!(active(&e).len(), 1);
}

#[test]
fn an_inbox_folder_that_goes_away_retires_nothing() {
    let s = Setup::new();
    let e = s.engine();
    s.put(COP, "inbox/a.tif");
    s.put(SRTM, "inbox/b.tif");
    let mut rec = reconciler(&e, &s);
    rec.pass();
    assert_eq!(active(&e).len(), 2);
    let inbox = s.at("inbox");
    let away = s.at("away");

    // Deleted (moved away) while the daemon runs: nothing is retired.
    std::fs::rename(&inbox, &away).unwrap();
    let (_, back) = rec.pass();
    assert!(back.is_empty());
    assert!(!rec.all_present());
    assert_eq!(active(&e).len(), 2);
    // An empty folder in its place (a share's mount point before the share) is no better.
    std::fs::create_dir(&inbox).unwrap();
    rec.pass();
    assert_eq!(active(&e).len(), 2);
    std::fs::remove_dir(&inbox).unwrap();
    // Missing at start-up: nothing is retired either.
    drop(rec);
    let mut rec = reconciler(&e, &s);
    rec.pass();
    assert_eq!(active(&e).len(), 2);
    // Back again: the watcher is told to watch it, and still nothing is retired.
    std::fs::rename(&away, &inbox).unwrap();
    let (_, back) = rec.pass();
    assert_eq!(back, vec![inbox.clone()]);
    assert!(rec.all_present());
    assert_eq!(active(&e).len(), 2);
    // A file seen deleted from a folder that is there retires its survey.
    std::fs::remove_file(inbox.join("b.tif")).unwrap();
    rec.pass();
    assert_eq!(
        active(&e),
        vec![inbox.join("a.tif").to_string_lossy().into_owned()]
    );
    assert_eq!(
        e.catalog()
            .records
            .values()
            .filter(|r| r.status == Status::Retired)
            .count(),
        1
    );
    // So does the last one: the folder, the very one seen holding files, is now empty.
    std::fs::remove_file(inbox.join("a.tif")).unwrap();
    rec.pass();
    assert!(active(&e).is_empty());
}

/// An ESRI grid of 40² samples in UTM zone 31 at `base` metres, every height written with
/// the same number of characters: grids of different bases are files of the same size.
fn fixed_width_grid(base: f64) -> Vec<u8> {
    let mut s =
        String::from("ncols 40\nnrows 40\nxllcorner 650000\nyllcorner 4900000\ncellsize 30\n");
    for r in 0..40 {
        let row: Vec<String> = (0..40)
            .map(|c| format!("{:07.1}", base + (r * 3 + c * 2) as f64 * 0.5))
            .collect();
        s.push_str(&row.join(" "));
        s.push('\n');
    }
    s.into_bytes()
}

/// Writes `bytes` over the file at `p` in place (same inode), then puts its mtime back to
/// `mtime`, as `cp -p`, `rsync -a` and tar do.
fn rewrite_keeping_mtime(p: &Path, bytes: &[u8], mtime: std::time::SystemTime) {
    use std::io::Write;
    let mut f = std::fs::OpenOptions::new().write(true).open(p).unwrap();
    f.write_all(bytes).unwrap();
    f.set_modified(mtime).unwrap();
}

fn height_at_centre(e: &Engine) -> f64 {
    let roi = Aabb::new(650_000.0, 4_900_000.0, 651_200.0, 4_901_200.0);
    let t = e
        .tile(
            &TileRequest::new(Cut::new(None, roi, 0.0).unwrap(), 1, 1, Backend::Cpu).unwrap(),
            Ctx::default(),
        )
        .unwrap();
    t.0.heights[0] as f64
}

#[test]
fn a_file_rewritten_with_its_size_and_mtime_kept_is_seen_in_place_and_by_rename() {
    let mut s = Setup::new();
    // A store of the grid's own UTM zone, whose tiles the checks ask in metres.
    s.cfg.crs = Some("EPSG:32631".into());
    let prj = r#"PROJCS["WGS 84 / UTM zone 31N",AUTHORITY["EPSG","32631"]]"#;
    let a = s.at("inbox/a.asc");
    std::fs::write(&a, fixed_width_grid(1000.0)).unwrap();
    std::fs::write(a.with_extension("prj"), prj).unwrap();
    let mtime = std::fs::metadata(&a).unwrap().modified().unwrap();
    let e = s.engine();
    let mut rec = reconciler(&e, &s);
    rec.pass();
    assert_eq!(active(&e).len(), 1);
    let before = height_at_centre(&e);
    assert!((before - 1000.0).abs() < 100.0, "{before}");

    // In place: same size, same mtime, new heights.
    let len = std::fs::metadata(&a).unwrap().len();
    rewrite_keeping_mtime(&a, &fixed_width_grid(1050.0), mtime);
    assert_eq!(std::fs::metadata(&a).unwrap().len(), len);
    assert_eq!(std::fs::metadata(&a).unwrap().modified().unwrap(), mtime);
    rec.pass();
    let after = height_at_centre(&e);
    assert!((after - before - 50.0).abs() < 1e-3, "{before} → {after}");
    assert_eq!(active(&e).len(), 1, "replaced, not added");

    // By rename: a new file of the same size and mtime moved over the old one.
    let staged = s.at("outside/a.asc");
    std::fs::write(&staged, fixed_width_grid(1100.0)).unwrap();
    std::fs::File::options()
        .write(true)
        .open(&staged)
        .unwrap()
        .set_modified(mtime)
        .unwrap();
    std::fs::rename(&staged, &a).unwrap();
    rec.pass();
    let renamed = height_at_centre(&e);
    assert!(
        (renamed - before - 100.0).abs() < 1e-3,
        "{before} → {renamed}"
    );

    // While the daemon is down, the same again: the restart sees it too.
    drop(rec);
    drop(e);
    rewrite_keeping_mtime(&a, &fixed_width_grid(1150.0), mtime);
    let e = s.engine();
    let mut rec = reconciler(&e, &s);
    rec.pass();
    assert!((height_at_centre(&e) - before - 150.0).abs() < 1e-3);

    // A pass with nothing changed ingests nothing: the unchanged file keeps its survey.
    let id = e.catalog().active().next().unwrap().id;
    rec.pass();
    assert_eq!(e.catalog().active().next().unwrap().id, id);
}

#[test]
fn a_failed_file_rewritten_with_its_size_and_mtime_kept_is_tried_again() {
    let s = Setup::new();
    let prj = r#"PROJCS["WGS 84 / UTM zone 31N",AUTHORITY["EPSG","32631"]]"#;
    let a = s.at("inbox/a.asc");
    let good = fixed_width_grid(1000.0);
    // As long as the good grid, but heights no terrain has.
    let bad = fixed_width_grid(99000.0);
    let bad = &bad[..good.len()];
    std::fs::write(&a, bad).unwrap();
    std::fs::write(a.with_extension("prj"), prj).unwrap();
    let mtime = std::fs::metadata(&a).unwrap().modified().unwrap();
    let e = s.engine();
    let mut rec = reconciler(&e, &s);
    rec.pass();
    assert!(active(&e).is_empty());
    assert_eq!(e.catalog().failures.len(), 1);
    assert!(!e.catalog().failures[0].content_id.is_empty());
    // Down, the file is fixed with its size and mtime kept; the restart tries it again.
    drop(rec);
    drop(e);
    rewrite_keeping_mtime(&a, &good, mtime);
    let e = s.engine();
    let mut rec = reconciler(&e, &s);
    rec.pass();
    assert_eq!(active(&e).len(), 1, "{:?}", e.catalog().failures);
    assert!(e.catalog().failures.is_empty());
    // And while it runs: another file fails, and is fixed in place the same way.
    let b = s.at("inbox/b.asc");
    std::fs::write(&b, bad).unwrap();
    std::fs::write(b.with_extension("prj"), prj).unwrap();
    let mtime = std::fs::metadata(&b).unwrap().modified().unwrap();
    rec.pass();
    assert_eq!(active(&e).len(), 1);
    assert_eq!(e.catalog().failures.len(), 1);
    let other = fixed_width_grid(2000.0);
    rewrite_keeping_mtime(&b, &other[..good.len()], mtime);
    rec.pass();
    assert_eq!(active(&e).len(), 2, "{:?}", e.catalog().failures);
}

#[test]
fn a_name_that_is_not_utf8_is_recorded_as_failed_under_an_escaped_name() {
    use std::os::unix::ffi::OsStrExt;
    let s = Setup::new();
    let name = std::ffi::OsStr::from_bytes(b"caf\xe9.tif");
    let p = s.at("inbox").join(name);
    std::fs::copy(crop(COP), &p).unwrap();
    let e = s.engine();
    let mut rec = reconciler(&e, &s);
    rec.pass();
    let failures = e.catalog().failures.clone();
    assert_eq!(failures.len(), 1, "{failures:?}");
    assert!(failures[0].source.ends_with("caf\\xe9.tif"), "{failures:?}");
    assert!(
        failures[0].error.contains("not valid UTF-8"),
        "{failures:?}"
    );
    // Recorded once: later passes leave it, and nothing is retired or added.
    rec.pass();
    rec.pass();
    assert_eq!(e.catalog().failures.len(), 1);
    assert!(active(&e).is_empty());
    // Renamed, it is ingested.
    std::fs::rename(&p, s.at("inbox/cafe.tif")).unwrap();
    rec.pass();
    assert_eq!(active(&e).len(), 1);
}

#[test]
fn a_damaged_survey_is_left_out_and_its_inbox_file_ingested_again_at_start() {
    let s = Setup::new();
    s.put(COP, "inbox/a.tif");
    s.put(SRTM, "inbox/b.tif");
    let e = s.engine();
    let mut rec = reconciler(&e, &s);
    rec.pass();
    assert_eq!(active(&e).len(), 2);
    let cop = Aabb::new(-119.0, 34.46, -118.92, 34.54);
    let srtm = {
        let r = e
            .catalog()
            .active()
            .find(|r| r.source.ends_with("b.tif"))
            .unwrap()
            .clone();
        let g = r.georef;
        let (w, h) = (r.cols as f64, r.rows as f64);
        let (x0, y0) = (g.origin[0], g.origin[1]);
        let (x1, y1) = (x0 + g.step[0] * w * 0.8, y0 + g.step[1] * h * 0.8);
        Aabb::new(x0.min(x1), y0.min(y1), x0.max(x1), y0.max(y1))
    };
    let before = (tile(&e, cop), tile(&e, srtm));
    drop(rec);
    drop(e);
    // One byte of the last survey committed, in its chunks at the end of the pack.
    let pack = s.cfg.data_dir.join(patchwork::store::pack::PACK_FILE);
    let mut bytes = std::fs::read(&pack).unwrap();
    let at = bytes.len() - 100;
    bytes[at] ^= 0x5a;
    std::fs::write(&pack, bytes).unwrap();
    let e = s.engine();
    let damaged = e.catalog().damaged.clone();
    assert_eq!(damaged.len(), 1, "{damaged:?}");
    assert_eq!(active(&e).len(), 1, "the other survey is served");
    let listing = patchwork::serve::api::list_surveys(&e).unwrap();
    let d = listing
        .surveys
        .iter()
        .find(|i| i.status() == patchwork::serve::proto::SurveyStatus::Damaged)
        .expect("listed as damaged");
    assert!(d.error.contains("checksum"), "{}", d.error);
    let intact_is_cop = damaged.values().next().unwrap().source.ends_with("b.tif");
    if intact_is_cop {
        assert_eq!(tile(&e, cop), before.0);
    } else {
        assert_eq!(tile(&e, srtm), before.1);
    }
    assert_eq!(e.stats().damaged, 1);
    // The inbox sees that its file is not served, and ingests it again at start.
    let mut rec = reconciler(&e, &s);
    rec.pass();
    assert!(e.catalog().damaged.is_empty());
    assert_eq!(active(&e).len(), 2);
    assert_eq!((tile(&e, cop), tile(&e, srtm)), before);
    assert!(e.verify().unwrap().problems.is_empty());
}

/// The engine as the watcher's sink, counting the files it is asked to take.
struct Counting {
    e: Arc<Engine>,
    asked: AtomicU64,
}

impl patchwork::watch::Sink for Counting {
    fn catalog(&self) -> Arc<patchwork::store::Catalog> {
        self.e.catalog()
    }

    fn ingest(&self, path: &Path) -> Result<patchwork::engine::Ingested, EngineError> {
        self.asked.fetch_add(1, Ordering::SeqCst);
        patchwork::watch::Sink::ingest(&*self.e, path)
    }

    fn retire_deleted(&self, source: &str) -> Result<(), EngineError> {
        self.e.retire_deleted(source)
    }

    fn hold(&self, source: &str, why: Option<patchwork::engine::Held>) {
        self.e.hold(source, why)
    }

    fn free_bytes(&self) -> u64 {
        self.e.free_bytes()
    }
}

#[test]
fn a_file_deferred_for_lack_of_space_waits_for_room_and_files_not_dems_are_listed() {
    use patchwork::engine::Held;
    let s = Setup::new();
    let disk = Arc::new(FakeDisk(AtomicU64::new(1 << 20)));
    let e = Arc::new(Engine::open_on(s.cfg.clone(), disk.clone()).unwrap());
    let sink = Arc::new(Counting {
        e: e.clone(),
        asked: AtomicU64::new(0),
    });
    let mut r = Reconciler::new(sink.clone(), &s.cfg.inbox, Duration::ZERO, OnDelete::Retire);
    r.startup();
    let cop = s.put(COP, "inbox/cop.tif");
    std::fs::write(s.at("inbox/notes.json"), "{}").unwrap();
    std::fs::write(s.at("inbox/cop.tif.aux.xml"), "<PAMDataset/>").unwrap();
    let held = |e: &Engine| e.surveys().1.held;

    // The disk is full: the file is tried once, then waits, listed with the reason.
    r.pass();
    assert_eq!(sink.asked.load(Ordering::SeqCst), 1);
    for _ in 0..5 {
        r.pass();
    }
    assert_eq!(
        sink.asked.load(Ordering::SeqCst),
        1,
        "a deferred file was read again with nothing changed"
    );
    let listed = held(&e);
    let cop_source = cop.to_string_lossy().into_owned();
    assert!(
        matches!(listed.get(&cop_source), Some(Held::Deferred(why)) if why.contains("MiB")),
        "{listed:?}"
    );
    // A file that is not a DEM is listed as skipped, saying why; a DEM's companion is not.
    let json = s.at("inbox/notes.json").to_string_lossy().into_owned();
    assert!(
        matches!(listed.get(&json), Some(Held::Skipped(why)) if why.contains(".json")),
        "{listed:?}"
    );
    assert_eq!(listed.len(), 2, "{listed:?}");

    // Space comes back: the next pass takes the file, and nothing is held but the JSON.
    disk.0.store(u64::MAX, Ordering::SeqCst);
    r.pass();
    assert_eq!(sink.asked.load(Ordering::SeqCst), 2);
    assert_eq!(active(&e), vec![cop_source]);
    let listed = held(&e);
    assert_eq!(listed.keys().collect::<Vec<_>>(), vec![&json]);
    std::fs::remove_file(s.at("inbox/notes.json")).unwrap();
    r.pass();
    assert!(held(&e).is_empty());
}
