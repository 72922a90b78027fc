//! The gRPC services: each handler runs the dispatcher on a blocking thread under the request
//! deadline and maps errors in `status`.

use super::auth::Gate;
use super::conns::{self, Conns};
use super::proto::{self as pb, admin_server, terrain_server};
use super::turns::Turns;
use super::{api, convert, door, status};
use patchwork_core::resample::Cancel;
use patchwork_core::sync::lock;
use patchwork_engine::{BadRequest, Engine, EngineError, SampleRequest, TileRequest};
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;
use tokio_stream::{Stream, StreamExt};
use tonic::service::interceptor::InterceptedService;
use tonic::{Request, Response, Status};

/// The Terrain and Admin services over one engine, with the limits both ports share: the turns
/// to run requests, the open streams and the connections. Clones share all of it.
#[derive(Clone)]
pub struct Service {
    engine: Arc<Engine>,
    /// Requests running at once, their turns handed round the clients fairly. A turn goes
    /// with the work, not the call: a request whose caller gave up (past its deadline, or
    /// gone) holds its turn until its work sees its cancel, so clients that ask and hang up
    /// cannot pile up work without bound.
    running: Arc<Turns>,
    load: Arc<Load>,
    /// The view sessions' steps take their turns from this first: at most half the turns, so
    /// that however many sessions wait, one-off requests still find one.
    session_turns: Arc<tokio::sync::Semaphore>,
    /// The admin calls that read what the engine publishes (`stats`, the listing) run beside
    /// the turns, not within them, a few at once: they read counters and the published
    /// catalog, never samples nor the writer, so that an operator's `stats` (and a verify's
    /// progress in it) answers while tiles queue for every turn behind a slow backend.
    /// (`forget` takes the writer, which a verify or an ingest holds for minutes: it takes a
    /// turn, so that it can never hold this lane's permits from `stats`.)
    admin_turns: Arc<tokio::sync::Semaphore>,
    streams: Arc<Streams>,
    /// Subscribe is on the Terrain service but tells what the Admin listing tells.
    admin: Gate,
    /// True once the daemon is told to stop.
    stopping: tokio::sync::watch::Receiver<bool>,
    /// The connections of both ports, within one limit.
    conns: Arc<Conns>,
}

/// Admin reads that run at once, beside the turns (see `Service::admin_turns`).
const ADMIN_TURNS: usize = 2;

/// Where a request's work takes its turn.
enum Lane {
    /// A turn, handed round the clients fairly: tiles, queries, points.
    Requests,
    /// A turn, once the sessions' lane has room.
    Sessions,
    /// The admin lane alone, no turn.
    Admin,
}

fn stopping_status() -> Status {
    Status::unavailable("the daemon is stopping: try again once it is back")
}

/// The long-lived streams (view sessions and subscriptions) open now, in all and by
/// connection, within `limits.max_streams` and `max_streams_per_connection`.
struct Streams {
    open: std::sync::Mutex<(u64, std::collections::HashMap<std::net::SocketAddr, u64>)>,
    most: u64,
    most_per_connection: u64,
}

/// One open stream, counted for as long as it lives.
struct StreamSlot {
    streams: Arc<Streams>,
    peer: Option<std::net::SocketAddr>,
}

impl Streams {
    /// A slot for a stream from `peer`, or RESOURCE_EXHAUSTED naming the limit it is past.
    fn open(self: &Arc<Self>, peer: Option<std::net::SocketAddr>) -> Result<StreamSlot, Status> {
        let mut open = lock(&self.open);
        let (total, by_peer) = &mut *open;
        if *total >= self.most {
            return Err(Status::resource_exhausted(format!(
                "{total} streams are open, the most the daemon keeps (limits.max_streams): close \
                 a view session or subscription first"
            )));
        }
        if let Some(p) = peer {
            let n = by_peer.entry(p).or_default();
            if *n >= self.most_per_connection {
                return Err(Status::resource_exhausted(format!(
                    "{n} streams are open on this connection, the most one may hold \
                     (limits.max_streams_per_connection): use another connection or close one"
                )));
            }
            *n += 1;
        }
        *total += 1;
        Ok(StreamSlot {
            streams: self.clone(),
            peer,
        })
    }
}

impl Drop for StreamSlot {
    fn drop(&mut self) {
        let mut open = lock(&self.streams.open);
        let (total, by_peer) = &mut *open;
        *total -= 1;
        if let Some(p) = self.peer {
            if let Some(n) = by_peer.get_mut(&p) {
                *n -= 1;
                if *n == 0 {
                    by_peer.remove(&p);
                }
            }
        }
    }
}

/// Counts of the requests that wait for a permit and that finished, for `stats`.
#[derive(Default)]
struct Load {
    waiting: AtomicU64,
    served: AtomicU64,
}

/// One request waiting for a permit, for as long as the guard lives: a request whose deadline
/// passes while it waits is dropped there, and must stop counting.
struct Waiting<'a>(&'a Load);

impl<'a> Waiting<'a> {
    fn new(load: &'a Load) -> Self {
        load.waiting.fetch_add(1, Ordering::Relaxed);
        Waiting(load)
    }
}

impl Drop for Waiting<'_> {
    fn drop(&mut self) {
        self.0.waiting.fetch_sub(1, Ordering::Relaxed);
    }
}

/// Sets a [`Cancel`] when dropped: held by a request's future, it stops the request's work
/// on a blocking thread once the future is gone, whether it finished, timed out, or its
/// caller hung up and tonic dropped it. Setting it after the work is done changes nothing.
struct CancelOnDrop(Cancel);

impl Drop for CancelOnDrop {
    fn drop(&mut self) {
        self.0.cancel();
    }
}

impl Service {
    /// A service over `engine` with the limits of its config; `stopping` turns true once the
    /// daemon is told to stop.
    pub fn new(engine: Arc<Engine>, stopping: tokio::sync::watch::Receiver<bool>) -> Self {
        let limits = &engine.config().limits;
        let n = limits.max_running_requests as usize;
        let streams = Arc::new(Streams {
            open: Default::default(),
            most: limits.max_streams,
            most_per_connection: limits.max_streams_per_connection,
        });
        Service {
            admin: Gate::admin(engine.config()),
            running: Turns::new(n),
            session_turns: Arc::new(tokio::sync::Semaphore::new((n / 2).max(1))),
            admin_turns: Arc::new(tokio::sync::Semaphore::new(ADMIN_TURNS)),
            conns: Conns::new(
                limits.max_connections,
                conns::file_limit(),
                Duration::from_millis(limits.header_timeout_ms),
                Duration::from_millis(limits.idle_timeout_ms),
            ),
            streams,
            engine,
            load: Arc::default(),
            stopping,
        }
    }

    /// The connections of both ports.
    pub fn conns(&self) -> &Arc<Conns> {
        &self.conns
    }

    /// The engine the service calls.
    pub fn engine(&self) -> &Arc<Engine> {
        &self.engine
    }

    /// What `stats` says of the requests.
    fn load(&self, r: &mut pb::StatsReply) {
        let limit = self.engine.config().limits.max_running_requests as usize;
        r.requests_limit = limit as u32;
        r.requests_running = self.running.taken().min(limit) as u32;
        r.requests_waiting = self.load.waiting.load(Ordering::Relaxed) as u32;
        r.requests_served = self.load.served.load(Ordering::Relaxed);
    }

    /// Runs `f` off the async threads once a permit is free, within the configured deadline
    /// (the wait for the permit included). Past the deadline the caller gets
    /// DEADLINE_EXCEEDED and `f`'s [`Cancel`] is set, so that work which checks it stops.
    pub(crate) async fn run<T, F>(&self, f: F) -> Result<T, Status>
    where
        T: Send + 'static,
        F: FnOnce(&Engine, &Cancel) -> Result<T, EngineError> + Send + 'static,
    {
        self.run_in(Lane::Requests, f).await
    }

    /// [`Service::run`] in `lane`: a view session's step takes a permit of the sessions'
    /// lane before its turn (within the deadline too), so that sessions hold no more turns
    /// than the lane has; an admin read takes one of the admin lane instead of a turn.
    async fn run_in<T, F>(&self, lane: Lane, f: F) -> Result<T, Status>
    where
        T: Send + 'static,
        F: FnOnce(&Engine, &Cancel) -> Result<T, EngineError> + Send + 'static,
    {
        let engine = self.engine.clone();
        let ms = engine.config().limits.deadline_ms;
        let cancel = Cancel::default();
        let job_cancel = cancel.clone();
        // A caller that hangs up drops this future wherever it is: the work it started stops
        // then too, rather than holding its permit and a core to the end.
        let _cancel_on_drop = CancelOnDrop(cancel.clone());
        let load = self.load.clone();
        let work = async {
            let waiting = Waiting::new(&self.load);
            let (semaphore, turn) = match lane {
                Lane::Requests => (None, true),
                Lane::Sessions => (Some(&self.session_turns), true),
                Lane::Admin => (Some(&self.admin_turns), false),
            };
            let lane = match semaphore {
                Some(l) => Some(
                    l.clone()
                        .acquire_owned()
                        .await
                        .map_err(|_| Status::unavailable("the daemon is stopping"))?,
                ),
                None => None,
            };
            let permit = match turn {
                true => Some(self.running.take(conns::client()).await),
                false => None,
            };
            drop(waiting);
            let job = tokio::task::spawn_blocking(move || {
                let r = f(&engine, &job_cancel);
                drop(permit);
                drop(lane);
                load.served.fetch_add(1, Ordering::Relaxed);
                r
            });
            match job.await {
                Ok(r) => r.map_err(status::to_status),
                Err(e) => Err(Status::internal(format!("the request failed: {e}"))),
            }
        };
        // Once the daemon is told to stop, no new work starts and the work running is
        // cancelled, so that it ends well inside the shutdown's grace.
        let mut stopping = self.stopping.clone();
        if *stopping.borrow() {
            return Err(stopping_status());
        }
        tokio::select! {
            r = tokio::time::timeout(Duration::from_millis(ms), work) => r.unwrap_or_else(|_| {
                cancel.cancel();
                Err(status::deadline(ms))
            }),
            _ = stopping.wait_for(|s| *s) => {
                cancel.cancel();
                Err(stopping_status())
            }
        }
    }

    /// Runs `f` off the async threads with no deadline: ingestion, verification and
    /// compaction take as long as the data needs.
    async fn run_long<T, F>(&self, f: F) -> Result<T, Status>
    where
        T: Send + 'static,
        F: FnOnce(&Engine) -> Result<T, EngineError> + Send + 'static,
    {
        let engine = self.engine.clone();
        tokio::task::spawn_blocking(move || f(&engine))
            .await
            .map_err(|e| Status::internal(format!("the request failed: {e}")))?
            .map_err(status::to_status)
    }
}

/// A request's checked form, or the status that refuses it before it takes a turn.
fn checked<T>(r: Result<T, BadRequest>) -> Result<T, Status> {
    r.map_err(|e| status::to_status(EngineError::from(e)))
}

type BoxStream<T> = Pin<Box<dyn Stream<Item = Result<T, Status>> + Send + 'static>>;

#[tonic::async_trait]
impl terrain_server::Terrain for Service {
    type QueryPatchesStream = BoxStream<pb::PatchBatch>;
    type SubscribeStream = BoxStream<pb::ChangeEvent>;

    async fn query_patches(
        &self,
        r: Request<pb::PatchQuery>,
    ) -> Result<Response<Self::QueryPatchesStream>, Status> {
        let r = r.into_inner();
        let ms = self.engine.config().limits.deadline_ms;
        let deadline = tokio::time::Instant::now() + Duration::from_millis(ms);
        let cut = checked(door::patch_cut(&r))?;
        let size = api::batch_size(r.batch_size);
        let (t, ps) = self.run(move |e, _| e.query(&cut)).await?;
        // Batches are made as the client takes them, two ahead at most: a client that stops
        // reading holds two batches, not the whole cut, and only until the deadline.
        let (tx, rx) = tokio::sync::mpsc::channel(2);
        let running = self.running.clone();
        let client = conns::client();
        // Set when the deadline cut the stream short, so that it ends in an error rather than
        // looking complete.
        let cut_short = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let short = cut_short.clone();
        tokio::spawn(async move {
            for chunk in ps.chunks(size) {
                let permit = running.take(client.clone()).await;
                let (t, chunk) = (t.clone(), chunk.to_vec());
                let batch = tokio::task::spawn_blocking(move || {
                    let b = api::patch_batch(&t, &chunk);
                    drop(permit);
                    b
                })
                .await
                .map_err(|e| Status::internal(format!("the request failed: {e}")))
                .and_then(|b| b.map_err(status::to_status));
                let failed = batch.is_err();
                match tokio::time::timeout_at(deadline, tx.send(batch)).await {
                    Ok(Ok(())) if !failed => {}
                    // The client is gone, or was sent the error.
                    Ok(_) => return,
                    Err(_) => {
                        short.store(true, std::sync::atomic::Ordering::SeqCst);
                        return;
                    }
                }
            }
        });
        let end = tokio_stream::once(()).filter_map(move |()| {
            cut_short
                .load(std::sync::atomic::Ordering::SeqCst)
                .then(|| Err(status::deadline(ms)))
        });
        Ok(Response::new(Box::pin(
            tokio_stream::wrappers::ReceiverStream::new(rx).chain(end),
        )))
    }

    type ViewSessionStream = BoxStream<pb::ViewDelta>;

    async fn view_session(
        &self,
        r: Request<tonic::Streaming<pb::ViewCut>>,
    ) -> Result<Response<Self::ViewSessionStream>, Status> {
        let slot = self.streams.open(r.remote_addr())?;
        let mut cameras = r.into_inner();
        let ms = self.engine.config().limits.deadline_ms;
        // One message ahead at most, and each made only once there is room for it: a client
        // that stops reading holds that message and what the connection buffers, and only
        // until the step's deadline, not its whole cut (whose samples, on a large store, are
        // tens of megabytes a session).
        let (tx, rx) = tokio::sync::mpsc::channel(1);
        let svc = self.clone();
        tokio::spawn(async move {
            // The session counts against the limits until this task ends.
            let _slot = slot;
            let session = Arc::new(std::sync::Mutex::new(api::ViewSession::default()));
            while let Ok(Some(camera)) = cameras.message().await {
                let deadline = tokio::time::Instant::now() + Duration::from_millis(ms);
                let s = session.clone();
                let begun = svc
                    .run_in(Lane::Sessions, move |e, _| lock(&s).begin(e, &camera))
                    .await;
                let mut step = match begun {
                    Ok(step) => step,
                    Err(status) => {
                        let _ = tokio::time::timeout_at(deadline, tx.send(Err(status))).await;
                        return;
                    }
                };
                while !step.done() {
                    // Room first, then the message: nothing is read or made for a client
                    // that does not take it.
                    let permit = match tokio::time::timeout_at(deadline, tx.reserve()).await {
                        Ok(Ok(p)) => p,
                        // The client is gone.
                        Ok(Err(_)) => return,
                        // It stopped reading: end with an error, should it read again, so
                        // that it does not take a partial step for a whole one.
                        Err(_) => {
                            let _ = tokio::time::timeout(
                                Duration::from_secs(1),
                                tx.send(Err(status::deadline(ms))),
                            )
                            .await;
                            return;
                        }
                    };
                    let made = svc.run_in(Lane::Sessions, move |e, _| {
                        let d = step.next(e)?;
                        Ok((step, d))
                    });
                    match tokio::time::timeout_at(deadline, made).await {
                        Ok(Ok((s, Some(d)))) => {
                            step = s;
                            permit.send(Ok(d));
                        }
                        Ok(Ok((s, None))) => step = s,
                        Ok(Err(status)) => {
                            permit.send(Err(status));
                            return;
                        }
                        Err(_) => {
                            permit.send(Err(status::deadline(ms)));
                            return;
                        }
                    }
                }
                lock(&session).finish(step);
            }
        });
        Ok(Response::new(Box::pin(
            tokio_stream::wrappers::ReceiverStream::new(rx),
        )))
    }

    async fn resample_tile(
        &self,
        r: Request<pb::TileRequest>,
    ) -> Result<Response<pb::Tile>, Status> {
        let r = checked(TileRequest::try_from(&r.into_inner()))?;
        self.run(move |e, c| api::resample_tile(e, &r, c))
            .await
            .map(Response::new)
    }

    async fn mesh_tile(&self, r: Request<pb::MeshRequest>) -> Result<Response<pb::Mesh>, Status> {
        let r = checked(door::MeshAsk::try_from(&r.into_inner()))?;
        self.run(move |e, c| api::mesh_tile(e, &r, c))
            .await
            .map(Response::new)
    }

    type TileBandsStream = BoxStream<pb::TileBand>;

    async fn tile_bands(
        &self,
        r: Request<pb::TileRequest>,
    ) -> Result<Response<Self::TileBandsStream>, Status> {
        let r = checked(TileRequest::try_from(&r.into_inner()))?;
        let ms = self.engine.config().limits.deadline_ms;
        let deadline = tokio::time::Instant::now() + Duration::from_millis(ms);
        // Bands go out as the resampler finishes them, two ahead at most: sending overlaps
        // resampling, and a client that stops reading holds the work only until the deadline.
        let (tx, mut rx) = tokio::sync::mpsc::channel(2);
        let last = tx.clone();
        let svc = self.clone();
        let rt = tokio::runtime::Handle::current();
        tokio::spawn(async move {
            let done = svc
                .run(move |e, c| {
                    api::tile_bands(e, &r, c, &mut |band| {
                        let sent =
                            rt.block_on(tokio::time::timeout_at(deadline, tx.send(Ok(band))));
                        matches!(sent, Ok(Ok(())))
                    })
                })
                .await;
            if let Err(s) = done {
                // The answer when no band went out; otherwise it ends the stream.
                let _ = tokio::time::timeout(Duration::from_secs(1), last.send(Err(s))).await;
            }
        });
        match rx.recv().await {
            Some(Ok(first)) => Ok(Response::new(Box::pin(
                tokio_stream::once(Ok(first))
                    .chain(tokio_stream::wrappers::ReceiverStream::new(rx)),
            ))),
            Some(Err(s)) => Err(s),
            None => Err(Status::internal("the tile ended before its first band")),
        }
    }

    async fn sample_heights(
        &self,
        r: Request<pb::SampleRequest>,
    ) -> Result<Response<pb::Samples>, Status> {
        let r = checked(SampleRequest::try_from(&r.into_inner()))?;
        self.run(move |e, c| api::sample_heights(e, &r, c))
            .await
            .map(Response::new)
    }

    async fn tile_sources(
        &self,
        r: Request<pb::TileRequest>,
    ) -> Result<Response<pb::TileSourceList>, Status> {
        let r = checked(TileRequest::try_from(&r.into_inner()))?;
        self.run(move |e, c| api::tile_sources(e, &r, c))
            .await
            .map(Response::new)
    }

    async fn subscribe(
        &self,
        r: Request<pb::SubscribeRequest>,
    ) -> Result<Response<Self::SubscribeStream>, Status> {
        self.admin.admit(&r)?;
        let slot = self.streams.open(r.remote_addr())?;
        let rx = self.engine.subscribe();
        let engine = self.engine.clone();
        // A subscriber that does not read loses the events past the channel's bound, never
        // holds more; the slot goes when the client does.
        let s = tokio_stream::wrappers::BroadcastStream::new(rx).filter_map(move |e| {
            let _slot = &slot;
            e.ok().map(|e| {
                let changed = super::web::pyramid::Changed::of(&engine, &e);
                Ok(convert::event(&e, changed.as_ref()))
            })
        });
        Ok(Response::new(Box::pin(s)))
    }
}

#[tonic::async_trait]
impl admin_server::Admin for Service {
    async fn ingest(
        &self,
        r: Request<pb::IngestRequest>,
    ) -> Result<Response<pb::IngestReply>, Status> {
        let r = r.into_inner();
        self.run_long(move |e| api::ingest(e, &r))
            .await
            .map(Response::new)
    }

    async fn list_surveys(
        &self,
        _: Request<pb::ListSurveysRequest>,
    ) -> Result<Response<pb::SurveyList>, Status> {
        self.run_in(Lane::Admin, |e, _| api::list_surveys(e))
            .await
            .map(Response::new)
    }

    async fn retire(
        &self,
        r: Request<pb::RetireRequest>,
    ) -> Result<Response<pb::RetireReply>, Status> {
        let r = r.into_inner();
        // Retiring hashes the survey's file to decide whether to pin it: no read deadline.
        self.run_long(move |e| api::retire(e, &r))
            .await
            .map(Response::new)
    }

    async fn forget(
        &self,
        r: Request<pb::ForgetRequest>,
    ) -> Result<Response<pb::ForgetReply>, Status> {
        let r = r.into_inner();
        self.run(move |e, _| api::forget(e, &r))
            .await
            .map(Response::new)
    }

    async fn stats(
        &self,
        _: Request<pb::StatsRequest>,
    ) -> Result<Response<pb::StatsReply>, Status> {
        let mut r = self.run_in(Lane::Admin, |e, _| api::stats(e)).await?;
        self.load(&mut r);
        Ok(Response::new(r))
    }

    async fn verify(
        &self,
        _: Request<pb::VerifyRequest>,
    ) -> Result<Response<pb::VerifyReply>, Status> {
        self.run_long(api::verify).await.map(Response::new)
    }

    async fn repair(
        &self,
        _: Request<pb::RepairRequest>,
    ) -> Result<Response<pb::RepairReply>, Status> {
        self.run_long(api::repair).await.map(Response::new)
    }

    async fn compact(
        &self,
        _: Request<pb::CompactRequest>,
    ) -> Result<Response<pb::CompactReply>, Status> {
        self.run_long(api::compact).await.map(Response::new)
    }
}

/// Serves the API, health (`grpc.health.v1`) and reflection (v1 and v1alpha) until `shutdown`,
/// behind the configured tokens, over TLS when the config names a certificate and key.
pub async fn serve(
    engine: Arc<Engine>,
    listener: tokio::net::TcpListener,
    shutdown: impl std::future::Future<Output = ()> + Send + 'static,
) -> Result<(), Box<dyn std::error::Error + Send + Sync>> {
    // The sender is kept until the server is done: a dropped one reads as a stop too.
    let (stop, stopping) = tokio::sync::watch::channel(false);
    let stop = Arc::new(stop);
    let signal = stop.clone();
    let shutdown = async move {
        shutdown.await;
        let _ = signal.send(true);
    };
    let r = serve_service(Service::new(engine, stopping), listener, shutdown).await;
    drop(stop);
    r
}

/// Serves `svc`, whose stop signal its maker holds, until `shutdown`: the daemon shares one
/// service, and so one set of limits, between gRPC and HTTP.
pub async fn serve_service(
    svc: Service,
    listener: tokio::net::TcpListener,
    shutdown: impl std::future::Future<Output = ()> + Send + 'static,
) -> Result<(), Box<dyn std::error::Error + Send + Sync>> {
    let cfg = svc.engine.config().clone();
    let (health, health_svc) = tonic_health::server::health_reporter();
    health
        .set_serving::<terrain_server::TerrainServer<Service>>()
        .await;
    health
        .set_serving::<admin_server::AdminServer<Service>>()
        .await;
    health
        .set_service_status("", tonic_health::ServingStatus::Serving)
        .await;
    let reflection_v1 = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(pb::DESCRIPTOR)
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        .build_v1()?;
    let reflection_v1alpha = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(pb::DESCRIPTOR)
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        .build_v1alpha()?;
    // Connections within the daemon's limit, closed when silent or idle (see `conns`).
    let conns = svc.conns.clone();
    conns.start();
    let incoming = futures::stream::unfold((conns.clone(), listener), |(c, l)| async move {
        let t = c.accept(&l).await;
        Some((Ok::<_, std::io::Error>(t), (c, l)))
    });
    // Flow control sized by measuring the connection (BDP) rather than HTTP/2's 64 KiB
    // default window, which a multi-megabyte tile would otherwise wait on, window by window.
    //
    // A connection may open the streams its sessions may hold and 64 requests more at once;
    // a client past that waits for a stream rather than being refused. Keepalive pings find
    // connections whose client is gone, so that their sessions end and give their slots back.
    let per_connection = cfg
        .limits
        .max_streams_per_connection
        .min(u32::MAX as u64 - 64) as u32;
    let mut server = tonic::transport::Server::builder()
        .http2_adaptive_window(Some(true))
        .max_concurrent_streams(Some(per_connection + 64))
        .http2_keepalive_interval(Some(Duration::from_secs(30)))
        .http2_keepalive_timeout(Some(Duration::from_secs(10)));
    if let (Some(cert), Some(key)) = (&cfg.tls_cert, &cfg.tls_key) {
        let identity = super::tls::load(cert, key)?;
        server = server
            .tls_config(tonic::transport::ServerTlsConfig::new().identity(identity))
            .map_err(|e| format!("TLS: {e}"))?;
    }
    server
        .layer(conns::TrackLayer(conns))
        .add_service(health_svc)
        .add_service(reflection_v1)
        .add_service(reflection_v1alpha)
        .add_service(InterceptedService::new(
            terrain_server::TerrainServer::new(svc.clone())
                .max_decoding_message_size(64 << 20)
                .max_encoding_message_size(256 << 20),
            Gate::terrain(&cfg),
        ))
        .add_service(InterceptedService::new(
            admin_server::AdminServer::new(svc),
            Gate::admin(&cfg),
        ))
        .serve_with_incoming_shutdown(incoming, shutdown)
        .await?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use patchwork_engine::config::Config;
    use std::time::Instant;

    /// A request whose caller hangs up stops its work at once, not at its deadline: tonic
    /// drops the handler's future, and the work on the blocking thread must see that.
    #[test]
    fn work_whose_caller_is_gone_is_cancelled() {
        let tmp = tempfile::tempdir().unwrap();
        let mut cfg = Config {
            data_dir: tmp.path().join("data"),
            inbox: Vec::new(),
            ..Config::default()
        };
        // Far past the test's wait: only the hang-up can stop the work in time.
        cfg.limits.deadline_ms = 600_000;
        let engine = Arc::new(Engine::open(cfg).unwrap());
        let (_stop, stopping) = tokio::sync::watch::channel(false);
        let svc = Service::new(engine, stopping);
        let rt = tokio::runtime::Builder::new_multi_thread()
            .enable_all()
            .build()
            .unwrap();
        let (started_tx, started) = std::sync::mpsc::channel();
        let (ended_tx, ended) = std::sync::mpsc::channel();
        rt.block_on(async move {
            let work = async move {
                svc.run(move |_, cancel| {
                    started_tx.send(()).unwrap();
                    let t0 = Instant::now();
                    // The work of a long mesh: it checks its cancel as it goes.
                    while !cancel.is_cancelled() && t0.elapsed() < Duration::from_secs(60) {
                        std::thread::sleep(Duration::from_millis(5));
                    }
                    ended_tx.send(cancel.is_cancelled()).unwrap();
                    Ok(())
                })
                .await
            };
            // The caller goes away while the work runs.
            let caller = tokio::spawn(work);
            tokio::task::spawn_blocking(move || started.recv().unwrap())
                .await
                .unwrap();
            caller.abort();
        });
        let cancelled = ended
            .recv_timeout(Duration::from_secs(20))
            .expect("the work of a request whose caller hung up was still running 20 s later");
        assert!(cancelled);
    }
}
