//! A bounded load test: 32 clients send mixed requests for 20 s while a survey is ingested and
//! retired over and over. Every request must succeed, and every answer must equal the answer
//! of the state before the change or after it: never a mixture, never a half-written survey.
//! It prints the latency percentiles of each kind of request.

use crate::common;

use common::daemon::*;
use patchwork::serve::proto::{
    self as pb, admin_client::AdminClient, terrain_client::TerrainClient,
};
use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tonic::transport::Channel;

const CLIENTS: usize = 32;

fn seconds() -> u64 {
    std::env::var("PATCHWORK_LOAD_SECONDS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(20)
}

/// The region the two surveys share, and a cut through it.
fn cut(error: f64) -> pb::UniformCut {
    pb::UniformCut {
        roi: Some(pb::Rect {
            xmin: -118.96,
            ymin: 34.47,
            xmax: -118.93,
            ymax: 34.50,
        }),
        error,
    }
}

/// One kind of request, and its answer reduced to what must match a state exactly.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
enum Kind {
    Tile,
    Sample,
    Query,
    Stats,
    Surveys,
}

const KINDS: [Kind; 5] = [
    Kind::Tile,
    Kind::Sample,
    Kind::Query,
    Kind::Stats,
    Kind::Surveys,
];

fn points() -> Vec<pb::Point> {
    (0..100)
        .map(|i| pb::Point {
            x: -118.96 + 0.0003 * i as f64,
            y: 34.47 + 0.0003 * ((i * 37) % 100) as f64,
        })
        .collect()
}

/// Sends one request of `kind`; the answer as bytes to compare, for the kinds whose answer
/// is fixed by the state.
async fn ask(
    kind: Kind,
    t: &mut TerrainClient<Channel>,
    a: &mut AdminClient<Channel>,
) -> Result<Option<Vec<u8>>, tonic::Status> {
    let bits = |v: &[f32]| v.iter().flat_map(|h| h.to_bits().to_le_bytes()).collect();
    Ok(match kind {
        Kind::Tile => {
            let r = t
                .resample_tile(pb::TileRequest {
                    crs: String::new(),
                    cut: Some(pb::tile_request::Cut::Uniform(cut(0.0))),
                    width: 48,
                    height: 48,
                    backend: pb::Backend::Cpu as i32,
                    ..Default::default()
                })
                .await?
                .into_inner();
            Some(bits(&r.heights))
        }
        Kind::Sample => {
            let r = t
                .sample_heights(pb::SampleRequest {
                    crs: String::new(),
                    points: points(),
                    error: 2.0,
                    ..Default::default()
                })
                .await?
                .into_inner();
            Some(bits(&r.heights))
        }
        Kind::Query => {
            let mut s = t
                .query_patches(pb::PatchQuery {
                    crs: String::new(),
                    cut: Some(pb::patch_query::Cut::Uniform(cut(5.0))),
                    batch_size: 64,
                })
                .await?
                .into_inner();
            let mut ids = Vec::new();
            while let Some(b) = s.message().await? {
                ids.extend(b.patches.iter().map(|p| p.id));
            }
            ids.sort_unstable();
            Some(ids.iter().flat_map(|i| i.to_le_bytes()).collect())
        }
        Kind::Stats => {
            a.stats(pb::StatsRequest {}).await?;
            None
        }
        Kind::Surveys => {
            a.list_surveys(pb::ListSurveysRequest {}).await?;
            None
        }
    })
}

async fn connect(url: &str) -> (TerrainClient<Channel>, AdminClient<Channel>) {
    let ch = Channel::from_shared(url.to_string())
        .unwrap()
        .connect()
        .await
        .unwrap();
    (
        TerrainClient::new(ch.clone()).max_decoding_message_size(1 << 30),
        AdminClient::new(ch),
    )
}

/// The fixed answers of the current state.
async fn answers(url: &str) -> HashMap<Kind, Vec<u8>> {
    let (mut t, mut a) = connect(url).await;
    let mut out = HashMap::new();
    for k in [Kind::Tile, Kind::Sample, Kind::Query] {
        out.insert(k, ask(k, &mut t, &mut a).await.unwrap().unwrap());
    }
    out
}

fn percentile(sorted: &[Duration], p: f64) -> f64 {
    let i = ((sorted.len() as f64 - 1.0) * p).round() as usize;
    sorted[i].as_secs_f64() * 1e3
}

#[test]
fn thirty_two_clients_during_ingest_and_retire_see_no_error_and_no_mixture() {
    let tmp = tempfile::tempdir().unwrap();
    let roots = tmp.path().join("roots");
    std::fs::create_dir_all(&roots).unwrap();
    let base = roots.join("base.tif");
    let other = roots.join("other.tif");
    // The survey added is the one that takes the overlap (Copernicus holds more of the detail
    // the two share), so that adding it changes every answer.
    std::fs::copy(crop("nasadem_n34w119_crop.tif"), &base).unwrap();
    std::fs::copy(crop("copernicus_n34w119_crop.tif"), &other).unwrap();
    let d = Daemon::start_with(
        tmp.path(),
        Setup {
            env: vec![(
                "PATCHWORK_INGEST_ROOTS".into(),
                roots.to_string_lossy().into_owned(),
            )],
            ..Setup::default()
        },
    );
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .unwrap();
    let url = d.url.clone();
    let ingest = |path: &std::path::Path| pb::IngestRequest {
        paths: vec![path.to_string_lossy().into_owned()],
        accuracy_m: None,
    };
    let retire = pb::RetireRequest {
        id_or_source: other.to_string_lossy().into_owned(),
    };
    let (without, with) = rt.block_on(async {
        let (_, mut admin) = connect(&url).await;
        admin.ingest(ingest(&base)).await.unwrap();
        let without = answers(&url).await;
        admin.ingest(ingest(&other)).await.unwrap();
        let with = answers(&url).await;
        admin.retire(retire.clone()).await.unwrap();
        assert!(
            answers(&url).await == without,
            "retiring gives back the state without it"
        );
        (without, with)
    });
    for k in [Kind::Tile, Kind::Sample, Kind::Query] {
        assert!(without[&k] != with[&k], "{k:?}: the change must be visible");
    }

    let end = Instant::now() + Duration::from_secs(seconds());
    let latencies: Arc<Mutex<HashMap<Kind, Vec<Duration>>>> = Arc::default();
    let errors: Arc<Mutex<Vec<String>>> = Arc::default();
    let (changes, mixtures) = rt.block_on(async {
        let mut tasks = Vec::new();
        for c in 0..CLIENTS {
            let (url, latencies, errors) = (url.clone(), latencies.clone(), errors.clone());
            let (without, with) = (without.clone(), with.clone());
            tasks.push(tokio::spawn(async move {
                let (mut t, mut a) = connect(&url).await;
                let mut mixtures = 0;
                let mut i = c;
                while Instant::now() < end {
                    let kind = KINDS[i % KINDS.len()];
                    i += 1;
                    let t0 = Instant::now();
                    match ask(kind, &mut t, &mut a).await {
                        Ok(answer) => {
                            latencies
                                .lock()
                                .unwrap()
                                .entry(kind)
                                .or_default()
                                .push(t0.elapsed());
                            if let Some(got) = answer {
                                if got != without[&kind] && got != with[&kind] {
                                    mixtures += 1;
                                }
                            }
                        }
                        Err(e) => errors.lock().unwrap().push(format!("{kind:?}: {e}")),
                    }
                }
                mixtures
            }));
        }
        // The writer: the other survey in and out, as fast as it goes.
        let (_, mut admin) = connect(&url).await;
        let mut changes = 0;
        while Instant::now() < end {
            let r = admin.ingest(ingest(&other)).await.unwrap().into_inner();
            assert_eq!(
                r.results[0].outcome(),
                pb::Outcome::Inserted,
                "{:?}",
                r.results[0].error
            );
            admin.retire(retire.clone()).await.unwrap();
            changes += 2;
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        let mut mixtures = 0;
        for t in tasks {
            mixtures += t.await.unwrap();
        }
        (changes, mixtures)
    });

    let errors = errors.lock().unwrap();
    assert!(
        errors.is_empty(),
        "{} errors, first: {:?}",
        errors.len(),
        errors.first()
    );
    assert_eq!(mixtures, 0, "answers that match neither state");
    let mut all = Vec::new();
    let lat = latencies.lock().unwrap();
    for k in KINDS {
        let mut v = lat.get(&k).cloned().unwrap_or_default();
        assert!(!v.is_empty(), "no {k:?} request ran");
        v.sort();
        eprintln!(
            "load {k:?}: {} requests, p50 {:.2} ms, p99 {:.2} ms",
            v.len(),
            percentile(&v, 0.5),
            percentile(&v, 0.99)
        );
        all.extend(v);
    }
    all.sort();
    eprintln!(
        "load: {CLIENTS} clients, {} s, {} requests ({:.0}/s), {changes} changes, 0 errors, p50 {:.2} ms, p99 {:.2} ms",
        seconds(),
        all.len(),
        all.len() as f64 / seconds() as f64,
        percentile(&all, 0.5),
        percentile(&all, 0.99)
    );
    assert!(
        changes >= 4,
        "the survey went in and out only {changes} times"
    );
}
