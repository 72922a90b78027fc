//! View sessions (§6.4): along a flight, the patches a client holds after applying each step's
//! delta are exactly the view cut for that camera, patch for patch, also when a survey
//! arrives mid-flight; a camera that has not moved costs an empty step; a wrong camera ends
//! the session with INVALID_ARGUMENT.

use crate::common;

use patchwork::config::Config;
use patchwork::engine::{Engine, Origin};
use patchwork::serve::proto::{self as pb, terrain_client::TerrainClient};
use prost::Message;
use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Arc;

fn camera(k: usize, frames: usize) -> pb::ViewCut {
    // Low over the Copernicus crop, flying north-east and looking ahead.
    let s = k as f64 / frames as f64;
    camera_at(-119.03 + 0.1 * s, 34.43 + 0.1 * s)
}

/// Serves `engine` on a loopback port for as long as the runtime runs; its URL.
async fn serve(engine: &Arc<Engine>) -> String {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let url = format!("http://{}", listener.local_addr().unwrap());
    tokio::spawn(patchwork::serve::grpc::serve(
        engine.clone(),
        listener,
        std::future::pending(),
    ));
    url
}

/// The whole cut for a camera, by id, as QueryPatches sends it.
async fn full_cut(
    t: &mut TerrainClient<tonic::transport::Channel>,
    v: &pb::ViewCut,
) -> BTreeMap<u64, Vec<u8>> {
    let mut s = t
        .query_patches(pb::PatchQuery {
            crs: String::new(),
            cut: Some(pb::patch_query::Cut::View(*v)),
            batch_size: 0,
        })
        .await
        .unwrap()
        .into_inner();
    let mut all = BTreeMap::new();
    while let Some(b) = s.message().await.unwrap() {
        for p in b.patches {
            all.insert(p.id, p.encode_to_vec());
        }
    }
    all
}

/// Applies one step's messages to what the client holds; returns the step's messages.
async fn apply(
    deltas: &mut tonic::Streaming<pb::ViewDelta>,
    held: &mut BTreeMap<u64, Vec<u8>>,
    frame: u64,
) -> Vec<pb::ViewDelta> {
    let mut step = Vec::new();
    loop {
        let d = deltas.message().await.unwrap().expect("a whole step");
        assert_eq!(d.frame, frame);
        assert!(d.added.len() <= 256);
        // About 256 KB at most: the patch that crosses it ends the message.
        let sizes: Vec<usize> = d.added.iter().map(|p| p.encoded_len()).collect();
        let before_last: usize = sizes.iter().rev().skip(1).sum();
        assert!(
            before_last < 256 << 10,
            "{before_last} B before a message's last patch"
        );
        if step.is_empty() {
            for id in &d.removed {
                assert!(held.remove(id).is_some(), "removed {id:016x}, never held");
            }
        } else {
            assert!(d.removed.is_empty(), "removals come first");
        }
        for p in &d.added {
            held.insert(p.id, p.encode_to_vec());
        }
        let last = d.last;
        step.push(d);
        if last {
            return step;
        }
    }
}

/// The committed crops' folder.
fn crops() -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data")
}

/// An empty store under `root`, open to the crops.
fn store(root: &Path) -> Arc<Engine> {
    let cfg = Config {
        data_dir: root.join("data"),
        ingest_roots: vec![crops()],
        ..Config::default()
    };
    Arc::new(Engine::open(cfg).unwrap())
}

/// Ingests the crop `name`, which must succeed.
fn ingest(engine: &Engine, name: &str) {
    let done = engine
        .ingest(&crops().join(name), None, Origin::Request)
        .unwrap();
    assert!(done.error.is_empty(), "{}", done.error);
}

#[test]
fn a_client_applying_the_deltas_holds_every_view_cut_along_a_flight() {
    let tmp = tempfile::tempdir().unwrap();
    let engine = store(tmp.path());
    let ingest = |name: &str| ingest(&engine, name);
    ingest("copernicus_n34w119_crop.tif");
    let rt = tokio::runtime::Runtime::new().unwrap();
    rt.block_on(async {
        let url = serve(&engine).await;
        let mut t = TerrainClient::connect(url).await.unwrap();
        let (tx, rx) = tokio::sync::mpsc::channel(4);
        let mut deltas = t
            .view_session(tokio_stream::wrappers::ReceiverStream::new(rx))
            .await
            .unwrap()
            .into_inner();

        const FRAMES: usize = 40;
        let mut held = BTreeMap::new();
        let (mut sent_delta, mut sent_full) = (0usize, 0usize);
        for k in 0..FRAMES {
            if k == FRAMES / 2 {
                // New data mid-flight: the next step brings its patches and drops those it
                // outranks.
                ingest("nasadem_n34w119_crop.tif");
            }
            let v = camera(k, FRAMES);
            tx.send(v).await.unwrap();
            let step = apply(&mut deltas, &mut held, k as u64).await;
            let full = full_cut(&mut t, &v).await;
            assert_eq!(
                held.keys().collect::<Vec<_>>(),
                full.keys().collect::<Vec<_>>(),
                "frame {k}"
            );
            assert!(
                held == full,
                "frame {k}: a patch held differs from the cut's"
            );
            assert_eq!(step.last().unwrap().patches as usize, full.len());
            sent_delta += step.iter().map(|d| d.encoded_len()).sum::<usize>();
            sent_full += full.values().map(|p| p.len()).sum::<usize>();
        }
        // Flying slowly, most of each cut is already held.
        assert!(
            sent_delta * 3 < sent_full,
            "deltas {sent_delta} B against full cuts {sent_full} B"
        );

        // The same camera again: nothing to change.
        tx.send(camera(FRAMES - 1, FRAMES)).await.unwrap();
        let step = apply(&mut deltas, &mut held, FRAMES as u64).await;
        assert_eq!(step.len(), 1);
        assert!(step[0].added.is_empty() && step[0].removed.is_empty());

        // A camera that cannot be: the session ends with what is wrong.
        let mut bad = camera(0, FRAMES);
        bad.fov_deg = 200.0;
        tx.send(bad).await.unwrap();
        let err = deltas.message().await.unwrap_err();
        assert_eq!(err.code(), tonic::Code::InvalidArgument, "{err:?}");
    });
}

/// A survey as large as a full 1° tile's view cut: 2,400 × 2,400 samples of one arc-second
/// from the crop's place north-east, with tens of metres of relief between samples, so that a view session's
/// step from 3 km up at 0.5 px takes its finest patches over tens of kilometres (as the full
/// Copernicus N34W119 does: 2,146 patches, 8.8 MB).
fn large_survey(path: &Path) {
    const N: usize = 2400;
    let step = 1.0 / 3600.0;
    let mut samples = Vec::with_capacity(N * N);
    for r in 0..N {
        for c in 0..N {
            let (x, y) = (c as f64 * 0.02, r as f64 * 0.02);
            // Hills, and a hash of the sample for the detail every level drops.
            let hills = 400.0 + 150.0 * (x / 3.0).sin() * (y / 2.0).cos();
            let h = (c as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
                ^ (r as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F);
            let h = h ^ (h >> 29);
            let detail = (h % 1000) as f64 / 1000.0 * 40.0;
            samples.push((hills + detail) as f32);
        }
    }
    let crs = patchwork_core::crs::Crs::epsg(4326).unwrap();
    patchwork_read::write_tiff::write_geotiff_f32(
        path,
        N,
        N,
        &samples,
        [-119.1, step, 0.0, 35.07, 0.0, -step],
        Some(&crs),
        None,
    )
    .unwrap();
}

/// 3 km up over the large survey, a 4,096-pixel viewport at 0.5 px: the probe's camera.
fn high_camera(k: usize) -> pb::ViewCut {
    let s = (k % 40) as f64 / 40.0;
    let (x, y) = (-119.05 + 0.1 * s, 34.45 + 0.1 * s);
    pb::ViewCut {
        eye_z: 3000.0,
        viewport_px: 4096,
        pixel_error: 0.5,
        ..camera_at(x, y)
    }
}

/// The daemon's resident memory, in bytes.
fn resident() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .unwrap()
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok())
        .expect("VmRSS in /proc/self/status")
        * 1024
}

#[test]
fn unread_sessions_past_the_limits_are_refused_and_never_stall_a_tile() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("in");
    std::fs::create_dir_all(&data).unwrap();
    let file = data.join("large.tif");
    large_survey(&file);
    let mut cfg = Config {
        data_dir: tmp.path().join("data"),
        ingest_roots: vec![data.clone()],
        ..Config::default()
    };
    // The defaults but the deadline: a tile that waited behind the sessions' steps would miss
    // it and fail.
    cfg.limits.deadline_ms = 2000;
    let (most, per_connection) = (
        cfg.limits.max_streams,
        cfg.limits.max_streams_per_connection,
    );
    let engine = Arc::new(Engine::open(cfg).unwrap());
    let done = engine.ingest(&file, None, Origin::Request).unwrap();
    assert!(done.error.is_empty(), "{}", done.error);
    let rt = tokio::runtime::Runtime::new().unwrap();
    rt.block_on(async {
        let url = serve(&engine).await;
        // One step read whole: each session's cut is as large as the full tile's.
        let mut t = TerrainClient::connect(url.clone()).await.unwrap();
        let (tx, rx) = tokio::sync::mpsc::channel(4);
        tx.send(high_camera(20)).await.unwrap();
        let mut s = t
            .view_session(tokio_stream::wrappers::ReceiverStream::new(rx))
            .await
            .unwrap()
            .into_inner();
        let mut ids = BTreeMap::new();
        let step = apply(&mut s, &mut ids, 0).await;
        let step_bytes: usize = step.iter().map(|d| d.encoded_len()).sum();
        eprintln!(
            "one step: {} patches, {:.1} MB in {} messages",
            ids.len(),
            step_bytes as f64 / 1e6,
            step.len()
        );
        assert!(
            ids.len() >= 2000 && step_bytes >= 8_000_000,
            "{} patches, {step_bytes} B",
            ids.len()
        );
        drop((tx, s));

        // 500 sessions over 10 connections, each sent a camera and never read.
        const CONNECTIONS: usize = 10;
        const SESSIONS: usize = 500;
        let before = resident();
        let mut clients = Vec::new();
        for _ in 0..CONNECTIONS {
            clients.push(TerrainClient::connect(url.clone()).await.unwrap());
        }
        let (mut held, mut refused) = (Vec::new(), 0usize);
        for k in 0..SESSIONS {
            let mut t = clients[k % CONNECTIONS].clone();
            let (tx, rx) = tokio::sync::mpsc::channel(4);
            tx.send(high_camera(k)).await.unwrap();
            match t
                .view_session(tokio_stream::wrappers::ReceiverStream::new(rx))
                .await
            {
                Ok(stream) => held.push((tx, stream.into_inner())),
                Err(s) => {
                    assert_eq!(s.code(), tonic::Code::ResourceExhausted, "{s:?}");
                    refused += 1;
                }
            }
        }
        let expected = (most as usize).min(CONNECTIONS * per_connection as usize);
        assert_eq!(held.len(), expected);
        assert_eq!(refused, SESSIONS - expected);
        // Tiles on a connection of their own answer within the deadline while the sessions
        // make what they can of their steps.
        let mut t = TerrainClient::connect(url.clone()).await.unwrap();
        let mut worst: f64 = 0.0;
        for _ in 0..5 {
            let t0 = std::time::Instant::now();
            let tile = t.resample_tile(common::daemon::crop_tile(64, 64)).await;
            assert!(tile.is_ok(), "{tile:?}");
            worst = worst.max(t0.elapsed().as_secs_f64());
            tokio::time::sleep(std::time::Duration::from_millis(300)).await;
        }
        // What the unread sessions hold: the messages they made ahead, not their steps.
        let grown = resident().saturating_sub(before);
        eprintln!(
            "64² tiles beside {} unread sessions ({refused} refused): worst {:.1} ms; \
             the sessions hold {:.0} MB, their steps {:.0} MB",
            held.len(),
            worst * 1e3,
            grown as f64 / 1e6,
            (held.len() * step_bytes) as f64 / 1e6
        );
        assert!(
            (grown as usize) < held.len() * step_bytes / 3,
            "{grown} B resident for {} unread steps of {step_bytes} B",
            held.len()
        );
        // Sessions whose clients go give their slots back, and a new one's step is read whole.
        // (Not one of those held: past the deadline they end in an error, and their
        // connections' windows are full of their neighbours' unread messages.)
        drop(held);
        let t0 = std::time::Instant::now();
        let mut deltas = loop {
            let (tx, rx) = tokio::sync::mpsc::channel(4);
            tx.send(camera(0, 40)).await.unwrap();
            match clients[0]
                .view_session(tokio_stream::wrappers::ReceiverStream::new(rx))
                .await
            {
                Ok(s) => break (tx, s.into_inner()),
                Err(s) if t0.elapsed().as_secs() < 10 => {
                    assert_eq!(s.code(), tonic::Code::ResourceExhausted);
                    tokio::time::sleep(std::time::Duration::from_millis(50)).await;
                }
                Err(s) => panic!("the slots did not come back: {s:?}"),
            }
        };
        let mut ids = BTreeMap::new();
        let step = apply(&mut deltas.1, &mut ids, 0).await;
        assert!(!step.is_empty() && !ids.is_empty());
    });
}

/// A camera flying out and back over the crop, then turning on the spot: patches leave the
/// cut and come back into it.
fn out_and_back(k: usize, frames: usize) -> pb::ViewCut {
    let third = frames / 3;
    if k >= 2 * third {
        // Turning on the spot, 6° a frame.
        let a = (k - 2 * third) as f64 * 6f64.to_radians();
        let (x, y) = (-118.98, 34.48);
        return pb::ViewCut {
            look_x: x + 0.06 * a.cos(),
            look_y: y + 0.06 * a.sin(),
            ..camera_at(x, y)
        };
    }
    let s = if k < third { k } else { 2 * third - k } as f64 / third as f64;
    camera_at(-119.03 + 0.1 * s, 34.43 + 0.1 * s)
}

/// At (x, y), 1,500 m up, looking north-east and down.
fn camera_at(x: f64, y: f64) -> pb::ViewCut {
    pb::ViewCut {
        eye_x: x,
        eye_y: y,
        eye_z: 1500.0,
        look_x: x + 0.05,
        look_y: y + 0.06,
        look_z: 400.0,
        fov_deg: 60.0,
        viewport_px: 800,
        pixel_error: 2.0,
        ..Default::default()
    }
}

#[test]
fn a_client_cache_and_prefetch_keep_every_cut_exact_and_send_less() {
    let tmp = tempfile::tempdir().unwrap();
    let engine = store(tmp.path());
    for name in ["copernicus_n34w119_crop.tif", "nasadem_n34w119_crop.tif"] {
        ingest(&engine, name);
    }
    const FRAMES: usize = 60;
    let rt = tokio::runtime::Runtime::new().unwrap();
    rt.block_on(async {
        let url = serve(&engine).await;
        let mut t = TerrainClient::connect(url).await.unwrap();
        // (cache, prefetch) → (bytes sent, patches restored, frames complete before asked)
        let mut runs = Vec::new();
        for (cache, prefetch) in [(0u64, 0u64), (4 << 20, 0), (4 << 20, 96 << 10), (48 << 10, 32 << 10)] {
            let (tx, rx) = tokio::sync::mpsc::channel(4);
            let mut deltas = t
                .view_session(tokio_stream::wrappers::ReceiverStream::new(rx))
                .await
                .unwrap()
                .into_inner();
            let mut client = patchwork::serve::api::ViewClient::new(cache);
            let (mut bytes, mut restored, mut complete) = (0usize, 0usize, 0usize);
            for k in 0..FRAMES {
                let v = pb::ViewCut {
                    cache_bytes: cache,
                    prefetch_bytes: prefetch,
                    ..out_and_back(k, FRAMES)
                };
                let full = full_cut(&mut t, &v).await;
                let ahead = k > 0 && full.keys().all(|id| client.has(*id));
                tx.send(v).await.unwrap();
                let mut first = true;
                let mut added = 0;
                loop {
                    let d = deltas.message().await.unwrap().expect("a whole step");
                    assert_eq!(d.frame, k as u64);
                    bytes += d.encoded_len();
                    restored += d.restored.len();
                    added += d.added.len();
                    client.apply(&d, first).unwrap_or_else(|e| panic!("frame {k}: {e}"));
                    first = false;
                    if d.last {
                        assert_eq!(d.patches as usize, full.len());
                        break;
                    }
                }
                // The cut is exact, patch for patch, and the cache within its bytes.
                let held: BTreeMap<u64, Vec<u8>> = client
                    .cut
                    .iter()
                    .map(|(id, p)| (*id, p.encode_to_vec()))
                    .collect();
                assert!(held == full, "frame {k} with cache {cache}, prefetch {prefetch}");
                // A step that adds nothing finds every patch already here.
                assert!(added > 0 || k == 0 || ahead, "frame {k}: nothing sent, yet a patch lacked");
                if ahead {
                    complete += 1;
                }
                assert!(client.cached_bytes() <= cache);
            }
            eprintln!(
                "cache {cache} B, prefetch {prefetch} B a frame: {:.1} kB a frame, {restored} patches restored, {complete} of {} frames complete before asked",
                bytes as f64 / FRAMES as f64 / 1e3,
                FRAMES - 1
            );
            runs.push((bytes, restored, complete));
        }
        let [none, cached, ahead, small] = runs[..] else { unreachable!() };
        // Coming back over the same ground, the cache saves sending it again.
        assert_eq!(none.1, 0);
        assert!(cached.1 > 0 && cached.0 < none.0, "{runs:?}");
        // Prefetching makes more frames whole before they are asked for.
        assert!(ahead.2 > cached.2, "{runs:?}");
        // A small cache evicts, and stays exact.
        assert!(small.0 > 0);
    });
}
