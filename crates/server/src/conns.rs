//! Connections on both ports: held within what the file limit allows, closed when silent or
//! idle, and told apart, so that the turns to run requests go round the clients fairly
//! ([`super::turns`]).
//!
//! hyper bounds how long an HTTP/1 request's headers may take once it has told HTTP/1 from
//! HTTP/2, but not a connection that never sends a byte, nor how many are open, nor how long
//! an idle keep-alive connection keeps its descriptor; tonic bounds none of these. With the
//! common soft limit of 1,024 files, 1,100 idle sockets were enough to make every accept fail
//! and every client wait. So each accepted socket is wrapped in a [`Tracked`], which records
//! when bytes last moved and can be told to end (its reads then see the end of the stream); a
//! reaper closes connections that said nothing or sit idle, and [`Conns::accept`] keeps the
//! count within [`Conns::most`], closing the connection idle longest to make room for a new
//! one, as nginx reuses its idle keep-alive connections when it runs out.

use futures::task::AtomicWaker;
use std::collections::HashMap;
use std::io;
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering::Relaxed};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::{Duration, Instant};
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};

use patchwork_core::sync::lock;

/// Descriptors kept from connections: the store's database and pack, the inbox watcher, the
/// object store's connection pool, the GPU driver, logs.
pub const RESERVED_FDS: u64 = 256;

tokio::task_local! {
    /// The connection a request came on, for the future that serves it.
    pub static CLIENT: Arc<Conn>;
}

/// The connection the request being served came on, if it came on one.
pub fn client() -> Option<Arc<Conn>> {
    CLIENT.try_with(|c| c.clone()).ok()
}

/// The open connections of both ports.
pub struct Conns {
    most: usize,
    header: Duration,
    idle: Duration,
    epoch: Instant,
    /// By the connection's two ends, the daemon's and the client's: one client port can
    /// reach both of the daemon's ports at once (the kernel picks a source port for each
    /// destination apart), and keyed by the client's alone the second connection hid the
    /// first, which then was never closed as silent or idle.
    open: Mutex<HashMap<(SocketAddr, SocketAddr), Arc<Conn>>>,
    /// Accept errors since the last one logged, so that a burst is one line.
    accept_errors: AtomicU64,
    /// Whether the task that closes silent and idle connections runs.
    reaping: AtomicBool,
}

/// One open connection.
pub struct Conn {
    /// The client's address.
    pub peer: SocketAddr,
    /// The daemon's end: its address on the port the connection came to.
    local: SocketAddr,
    /// When bytes last moved (at first, when it was accepted), in ms since [`Conns::epoch`].
    last: AtomicU64,
    /// Whether it has sent anything at all.
    heard: AtomicBool,
    /// When a read first found nothing to read, in ms since [`Conns::epoch`] (0: not yet).
    /// Silence counts from then: a daemon too busy to read a connection for a while must
    /// not take that for the client's silence.
    asked: AtomicU64,
    /// Requests it has running now, and has started in all.
    in_flight: AtomicU64,
    served: AtomicU64,
    closing: AtomicBool,
    waker: AtomicWaker,
}

impl Conn {
    /// What [`Conns`] holds it by: the daemon's end and the client's.
    fn key(&self) -> (SocketAddr, SocketAddr) {
        (self.local, self.peer)
    }

    /// A request started on this connection: running until the guard goes.
    pub fn begin(self: &Arc<Self>) -> InFlight {
        self.in_flight.fetch_add(1, Relaxed);
        self.served.fetch_add(1, Relaxed);
        InFlight(self.clone())
    }

    /// Requests this connection has started, those running included.
    pub fn served(&self) -> u64 {
        self.served.load(Relaxed)
    }

    /// Ends the connection: its next read sees the end of the stream.
    fn close(&self) {
        self.closing.store(true, Relaxed);
        self.waker.wake();
    }

    fn idle(&self) -> bool {
        self.in_flight.load(Relaxed) == 0 && !self.closing.load(Relaxed)
    }
}

/// A request running on a connection, for as long as it lives.
pub struct InFlight(Arc<Conn>);

impl Drop for InFlight {
    fn drop(&mut self) {
        self.0.in_flight.fetch_sub(1, Relaxed);
    }
}

impl Conns {
    /// Connections within `most` (lowered to what the file limit `nofile` leaves after
    /// [`RESERVED_FDS`]), closed when they say nothing for `header` after they open or sit
    /// idle for `idle` (once [`Conns::start`] runs the task that closes them).
    pub fn new(most: u64, nofile: u64, header: Duration, idle: Duration) -> Arc<Conns> {
        let most = most.min(nofile.saturating_sub(RESERVED_FDS)).max(16) as usize;
        Arc::new(Conns {
            most,
            header,
            idle,
            epoch: Instant::now(),
            open: Mutex::new(HashMap::new()),
            accept_errors: AtomicU64::new(0),
            reaping: AtomicBool::new(false),
        })
    }

    /// Starts the task that closes silent and idle connections, once, on the runtime of the
    /// caller; it ends when the last server lets go of these connections.
    pub fn start(self: &Arc<Self>) {
        if self.reaping.swap(true, Relaxed) {
            return;
        }
        // A tick a quarter of the shorter timeout, so that none is overrun by more than that.
        let tick = (self.header.min(self.idle) / 4)
            .clamp(Duration::from_millis(10), Duration::from_secs(1));
        let weak = Arc::downgrade(self);
        tokio::spawn(async move {
            let mut every = tokio::time::interval(tick);
            every.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
            loop {
                every.tick().await;
                match weak.upgrade() {
                    Some(c) => c.reap(),
                    None => return,
                }
            }
        });
    }

    /// How many connections are held at most.
    pub fn most(&self) -> usize {
        self.most
    }

    /// How many are open now.
    fn len(&self) -> usize {
        lock(&self.open).len()
    }

    fn now(&self) -> u64 {
        self.epoch.elapsed().as_millis() as u64
    }

    /// The open connection from `peer` to the daemon's `local` address.
    pub fn get(&self, local: SocketAddr, peer: SocketAddr) -> Option<Arc<Conn>> {
        lock(&self.open).get(&(local, peer)).cloned()
    }

    /// Closes the connections that said nothing within the header timeout of opening, and
    /// those idle (no request running, no byte either way) past the idle timeout.
    fn reap(&self) {
        let now = self.now();
        let (header, idle) = (self.header.as_millis() as u64, self.idle.as_millis() as u64);
        let mut open = lock(&self.open);
        open.retain(|_, c| {
            if !c.idle() {
                return !c.closing.load(Relaxed);
            }
            let asked = c.asked.load(Relaxed);
            let silent = !c.heard.load(Relaxed) && asked > 0 && now.saturating_sub(asked) > header;
            let unused = now.saturating_sub(c.last.load(Relaxed)) > idle;
            if silent || unused {
                tracing::debug!(peer = %c.peer, silent, "closing a connection");
                c.close();
                return false;
            }
            true
        });
    }

    /// The next connection on `listener` that is admitted. Accept errors (out of descriptors,
    /// say) back off from 5 ms to a second rather than spin, and are logged once a burst.
    pub async fn accept(self: &Arc<Self>, listener: &TcpListener) -> Tracked<TcpStream> {
        let mut backoff = Duration::from_millis(5);
        loop {
            match listener.accept().await {
                Ok((tcp, peer)) => {
                    backoff = Duration::from_millis(5);
                    // Replies of more than a segment would otherwise wait out the client's
                    // delayed ACK (Nagle's algorithm): 40 ms on every tile.
                    let _ = tcp.set_nodelay(true);
                    if let Some(t) = self.admit(tcp, peer) {
                        return t;
                    }
                }
                Err(e) => {
                    if self.accept_errors.fetch_add(1, Relaxed) == 0 {
                        tracing::warn!(error = %e, open = self.len(), "cannot accept connections; backing off until some close");
                    }
                    tokio::time::sleep(backoff).await;
                    backoff = (backoff * 2).min(Duration::from_secs(1));
                    continue;
                }
            }
            let missed = self.accept_errors.swap(0, Relaxed);
            if missed > 1 {
                tracing::info!(errors = missed, "accepting connections again");
            }
        }
    }

    /// Takes `tcp` in, closing the connection idle longest if all places are taken; None
    /// (and the socket closed) when none is idle.
    fn admit(self: &Arc<Self>, tcp: TcpStream, peer: SocketAddr) -> Option<Tracked<TcpStream>> {
        let now = self.now();
        let mut open = lock(&self.open);
        if open.len() >= self.most {
            // A connection that sent bytes in the last second and has no request running yet
            // is most likely one whose request is being read: it goes last.
            let victim = open
                .values()
                .filter(|c| c.idle())
                .min_by_key(|c| {
                    let last = c.last.load(Relaxed);
                    let reading = c.heard.load(Relaxed) && now.saturating_sub(last) < 1000;
                    (reading, last)
                })
                .cloned();
            match victim {
                Some(v) => {
                    v.close();
                    open.remove(&v.key());
                }
                None => {
                    tracing::debug!(%peer, "every connection is busy: refused");
                    return None;
                }
            }
        }
        // Without its own address the connection is still held, under the unspecified one.
        let local = tcp
            .local_addr()
            .unwrap_or_else(|_| SocketAddr::from(([0, 0, 0, 0], 0)));
        let conn = Arc::new(Conn {
            peer,
            local,
            last: AtomicU64::new(now),
            heard: AtomicBool::new(false),
            asked: AtomicU64::new(0),
            in_flight: AtomicU64::new(0),
            served: AtomicU64::new(0),
            closing: AtomicBool::new(false),
            waker: AtomicWaker::new(),
        });
        open.insert((local, peer), conn.clone());
        Some(Tracked {
            io: tcp,
            conn,
            conns: self.clone(),
        })
    }
}

/// A connection's socket, which records when bytes move and ends when told to.
pub struct Tracked<S> {
    io: S,
    conn: Arc<Conn>,
    conns: Arc<Conns>,
}

impl<S> Tracked<S> {
    /// The connection this socket carries.
    pub fn conn(&self) -> &Arc<Conn> {
        &self.conn
    }
}

impl<S> Drop for Tracked<S> {
    fn drop(&mut self) {
        let mut open = lock(&self.conns.open);
        if open
            .get(&self.conn.key())
            .is_some_and(|c| Arc::ptr_eq(c, &self.conn))
        {
            open.remove(&self.conn.key());
        }
    }
}

impl<S: AsyncRead + Unpin> AsyncRead for Tracked<S> {
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let me = self.get_mut();
        me.conn.waker.register(cx.waker());
        if me.conn.closing.load(Relaxed) {
            // The end of the stream: hyper and tonic close the connection as a client's.
            return Poll::Ready(Ok(()));
        }
        let before = buf.filled().len();
        let r = Pin::new(&mut me.io).poll_read(cx, buf);
        match r {
            Poll::Ready(Ok(())) if buf.filled().len() > before => {
                me.conn.heard.store(true, Relaxed);
                me.conn.last.store(me.conns.now(), Relaxed);
            }
            Poll::Pending if !me.conn.heard.load(Relaxed) => {
                // The first time there was nothing to read (never 0: a millisecond at least).
                let now = me.conns.now().max(1);
                let _ = me.conn.asked.compare_exchange(0, now, Relaxed, Relaxed);
            }
            _ => {}
        }
        r
    }
}

impl<S: AsyncWrite + Unpin> AsyncWrite for Tracked<S> {
    fn poll_write(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        let me = self.get_mut();
        let r = Pin::new(&mut me.io).poll_write(cx, buf);
        if matches!(r, Poll::Ready(Ok(n)) if n > 0) {
            me.conn.last.store(me.conns.now(), Relaxed);
        }
        r
    }

    fn poll_write_vectored(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        let me = self.get_mut();
        let r = Pin::new(&mut me.io).poll_write_vectored(cx, bufs);
        if matches!(r, Poll::Ready(Ok(n)) if n > 0) {
            me.conn.last.store(me.conns.now(), Relaxed);
        }
        r
    }

    fn is_write_vectored(&self) -> bool {
        self.io.is_write_vectored()
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.get_mut().io).poll_flush(cx)
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.get_mut().io).poll_shutdown(cx)
    }
}

impl tonic::transport::server::Connected for Tracked<TcpStream> {
    type ConnectInfo = tonic::transport::server::TcpConnectInfo;

    fn connect_info(&self) -> Self::ConnectInfo {
        self.io.connect_info()
    }
}

/// The limit on open files in force (the soft one).
pub fn file_limit() -> u64 {
    let mut l = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: getrlimit only writes the struct passed to it.
    if unsafe { libc::getrlimit(libc::RLIMIT_NOFILE, &mut l) } != 0 {
        return 1024;
    }
    l.rlim_cur
}

/// Raises the soft limit on open files to the hard one, and returns the limit in force: the
/// soft limit of 1,024 that many systems start processes with is what a few idle clients
/// exhaust, while the hard limit is usually far above it.
pub fn raise_file_limit() -> u64 {
    // SAFETY: getrlimit and setrlimit only read and write the struct passed to them.
    unsafe {
        let mut l = libc::rlimit {
            rlim_cur: 0,
            rlim_max: 0,
        };
        if libc::getrlimit(libc::RLIMIT_NOFILE, &mut l) != 0 {
            return 1024;
        }
        if l.rlim_cur < l.rlim_max {
            let raised = libc::rlimit {
                rlim_cur: l.rlim_max,
                rlim_max: l.rlim_max,
            };
            if libc::setrlimit(libc::RLIMIT_NOFILE, &raised) == 0 {
                l.rlim_cur = l.rlim_max;
            }
        }
        l.rlim_cur
    }
}

/// A tower layer for the gRPC server: each request runs with its connection known
/// ([`CLIENT`]) and counted as running on it while its response is made.
#[derive(Clone)]
pub struct TrackLayer(pub Arc<Conns>);

impl<S> tower::Layer<S> for TrackLayer {
    type Service = Track<S>;

    fn layer(&self, inner: S) -> Track<S> {
        Track {
            inner,
            conns: self.0.clone(),
        }
    }
}

/// The service [`TrackLayer`] wraps around the server's: it finds each request's connection
/// by its peer address and runs the request under it.
#[derive(Clone)]
pub struct Track<S> {
    inner: S,
    conns: Arc<Conns>,
}

impl<S, B> tower::Service<axum::http::Request<B>> for Track<S>
where
    S: tower::Service<axum::http::Request<B>>,
    S::Future: Send + 'static,
{
    type Response = S::Response;
    type Error = S::Error;
    type Future = Pin<Box<dyn std::future::Future<Output = Result<S::Response, S::Error>> + Send>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), S::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, req: axum::http::Request<B>) -> Self::Future {
        use tonic::transport::server::{TcpConnectInfo, TlsConnectInfo};
        let ext = req.extensions();
        let ends = |i: &TcpConnectInfo| Some((i.local_addr()?, i.remote_addr()?));
        let ends = ext.get::<TcpConnectInfo>().and_then(ends).or_else(|| {
            ext.get::<TlsConnectInfo<TcpConnectInfo>>()
                .and_then(|i| ends(i.get_ref()))
        });
        let conn = ends.and_then(|(local, peer)| self.conns.get(local, peer));
        let fut = self.inner.call(req);
        Box::pin(async move {
            match conn {
                Some(c) => {
                    let _running = c.begin();
                    CLIENT.scope(c, fut).await
                }
                None => fut.await,
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// One client port can reach both of the daemon's ports at once: the two connections are
    /// two, each closed as silent in its turn, not one hiding the other.
    #[tokio::test]
    async fn two_connections_from_one_client_port_to_both_ports_are_both_held() {
        let conns = Conns::new(
            64,
            4096,
            Duration::from_millis(200),
            Duration::from_secs(60),
        );
        let (a, b) = (
            TcpListener::bind("127.0.0.1:0").await.unwrap(),
            TcpListener::bind("127.0.0.1:0").await.unwrap(),
        );
        let client = |to: SocketAddr, from: Option<SocketAddr>| async move {
            let s = tokio::net::TcpSocket::new_v4().unwrap();
            s.set_reuseaddr(true).unwrap();
            s.bind(from.unwrap_or_else(|| SocketAddr::from(([127, 0, 0, 1], 0))))
                .unwrap();
            s.connect(to).await.unwrap()
        };
        let first = client(a.local_addr().unwrap(), None).await;
        let port = first.local_addr().unwrap();
        let second = client(b.local_addr().unwrap(), Some(port)).await;
        assert_eq!(second.local_addr().unwrap(), port, "the same client port");
        let (ta, tb) = (conns.accept(&a).await, conns.accept(&b).await);
        assert_eq!(conns.len(), 2);
        let got = |l: &TcpListener| conns.get(l.local_addr().unwrap(), port).unwrap();
        assert!(Arc::ptr_eq(&got(&a), ta.conn()) && Arc::ptr_eq(&got(&b), tb.conn()));
        // Both silent past the header timeout once read: the reaper closes both.
        let mut buf = [0u8; 8];
        for mut t in [ta, tb] {
            tokio::spawn(async move {
                let _ = tokio::io::AsyncReadExt::read(&mut t, &mut buf).await;
            });
        }
        tokio::time::sleep(Duration::from_millis(400)).await;
        conns.reap();
        assert_eq!(conns.len(), 0, "a silent connection was kept");
        drop((first, second));
    }
}
