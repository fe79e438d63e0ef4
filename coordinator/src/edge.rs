//! The network edge below HTTP, the same for the gRPC port and the
//! monitor's: who may hold a connection, and for how long, without any
//! token being needed to hold one.
//!
//! Each port accepts in a loop of its own ([`Edge::incoming`]) and hands
//! the server wrapped streams ([`EdgeStream`]). A connection must carry
//! its first request (TLS handshake, HTTP/2 preface and headers all done)
//! within `handshake_timeout`, and may then sit without a request in
//! flight for `idle_timeout`. At most `max_connections` are open per port
//! and `max_per_peer` per peer address: a connection over either cap
//! sheds the open connection idle the longest (one that never sent a
//! request counts as idle since it was accepted), and is refused when
//! every open one is busy. So idle sockets can delay a new client by one
//! accept, never lock it out, and never take the descriptors the store
//! needs (the caps come from RLIMIT_NOFILE, see [`EdgeLimits::for_descriptors`]).
//!
//! Requests are counted by [`TrackLayer`] (a tower layer on both servers),
//! which finds the connection in the request's extensions ([`EdgeInfo`]);
//! a request is in flight until its response body ends or is dropped.

use std::collections::HashMap;
use std::future::Future;
use std::io;
use std::net::{IpAddr, SocketAddr};
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll, Waker};
use std::time::{Duration, Instant};

use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::mpsc;

/// Descriptors kept out of the connection caps: the database, stored
/// films, uploads' temporary files, frames being written, logs.
pub const RESERVED_DESCRIPTORS: u64 = 256;

/// How often timeouts are checked.
const SWEEP_INTERVAL: Duration = Duration::from_millis(250);

/// Bounds on one port's connections.
#[derive(Clone, Copy, Debug)]
pub struct EdgeLimits {
    /// From accept to the first request's headers (TLS handshake and
    /// HTTP/2 preface included).
    pub handshake_timeout: Duration,
    /// Longest time without a request in flight.
    pub idle_timeout: Duration,
    /// Most open connections.
    pub max_connections: usize,
    /// Most open connections from one IP address.
    pub max_per_peer: usize,
}

impl EdgeLimits {
    /// Defaults for a process that may hold `nofile` descriptors shared by
    /// `ports` listening ports: what is left after [`RESERVED_DESCRIPTORS`],
    /// split between the ports (1024 descriptors: 384 connections a port),
    /// and a quarter of that per peer (at least 32).
    pub fn for_descriptors(nofile: u64, ports: usize) -> Self {
        let share = nofile.saturating_sub(RESERVED_DESCRIPTORS) / ports.max(1) as u64;
        let max_connections = share.clamp(16, 16_384) as usize;
        EdgeLimits {
            handshake_timeout: Duration::from_secs(10),
            idle_timeout: Duration::from_secs(300),
            max_connections,
            max_per_peer: (max_connections / 4).max(32).min(max_connections),
        }
    }
}

impl Default for EdgeLimits {
    /// For the common 1024 descriptors and two ports.
    fn default() -> Self {
        EdgeLimits::for_descriptors(1024, 2)
    }
}

/// Why the coordinator closed a connection.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Closed {
    Handshake,
    Idle,
}

/// One accepted connection.
#[derive(Debug)]
pub struct Conn {
    id: u64,
    peer: IpAddr,
    accepted: Instant,
    killed: AtomicBool,
    /// Asset uploads in flight on this connection.
    pub uploads: AtomicU32,
    state: Mutex<ConnState>,
}

#[derive(Debug)]
struct ConnState {
    in_flight: u32,
    requests: u64,
    idle_since: Instant,
    reader: Option<Waker>,
    writer: Option<Waker>,
}

impl Conn {
    fn state(&self) -> std::sync::MutexGuard<'_, ConnState> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn live(&self) -> bool {
        !self.killed.load(Ordering::Relaxed)
    }

    /// Closes the connection: its next read or write fails, and the
    /// server drops it.
    fn kill(&self) {
        if self.killed.swap(true, Ordering::AcqRel) {
            return;
        }
        let (r, w) = {
            let mut s = self.state();
            (s.reader.take(), s.writer.take())
        };
        r.into_iter().chain(w).for_each(Waker::wake);
    }

    /// Marks a request in flight until the guard drops.
    pub fn begin(self: &Arc<Self>) -> Busy {
        let mut s = self.state();
        s.in_flight += 1;
        s.requests += 1;
        Busy(self.clone())
    }

    /// Idle since when, if idle.
    fn idle_since(&self) -> Option<Instant> {
        let s = self.state();
        (s.in_flight == 0).then_some(s.idle_since)
    }
}

/// A request in flight on a connection.
#[derive(Debug)]
pub struct Busy(Arc<Conn>);

impl Drop for Busy {
    fn drop(&mut self) {
        let mut s = self.0.state();
        s.in_flight -= 1;
        if s.in_flight == 0 {
            s.idle_since = Instant::now();
        }
    }
}

/// Counters since start, per port.
#[derive(Debug, Default)]
pub struct EdgeStats {
    pub accepted: AtomicU64,
    /// Closed to make room for a newer one.
    pub shed: AtomicU64,
    /// Refused: every open connection was busy.
    pub refused: AtomicU64,
    /// Closed for sending no request in time.
    pub handshake_timeouts: AtomicU64,
    pub idle_timeouts: AtomicU64,
}

/// One port's connections.
#[derive(Debug)]
pub struct Edge {
    name: &'static str,
    pub limits: EdgeLimits,
    pub stats: EdgeStats,
    conns: Mutex<HashMap<u64, Arc<Conn>>>,
    next_id: AtomicU64,
}

impl Edge {
    pub fn new(name: &'static str, limits: EdgeLimits) -> Arc<Self> {
        Arc::new(Edge {
            name,
            limits,
            stats: EdgeStats::default(),
            conns: Mutex::new(HashMap::new()),
            next_id: AtomicU64::new(0),
        })
    }

    fn conns(&self) -> std::sync::MutexGuard<'_, HashMap<u64, Arc<Conn>>> {
        self.conns.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Open connections (not counting those being closed).
    pub fn open(&self) -> usize {
        self.conns().values().filter(|c| c.live()).count()
    }

    /// Room for a connection from `peer`, shedding idle ones; None when
    /// every connection in the way is busy.
    fn admit(&self, peer: IpAddr) -> Option<Arc<Conn>> {
        let mut conns = self.conns();
        let live = || conns.values().filter(|c| c.live());
        let mut total = live().count();
        let from_peer = live().filter(|c| c.peer == peer).count();
        if from_peer >= self.limits.max_per_peer {
            self.shed(&conns, Some(peer))?;
            total -= 1;
        }
        if total >= self.limits.max_connections {
            self.shed(&conns, None)?;
        }
        let id = self.next_id.fetch_add(1, Ordering::Relaxed);
        let now = Instant::now();
        let conn = Arc::new(Conn {
            id,
            peer,
            accepted: now,
            killed: AtomicBool::new(false),
            uploads: AtomicU32::new(0),
            state: Mutex::new(ConnState {
                in_flight: 0,
                requests: 0,
                idle_since: now,
                reader: None,
                writer: None,
            }),
        });
        conns.insert(id, conn.clone());
        Some(conn)
    }

    /// Closes the connection (of `peer`, or any) idle the longest.
    fn shed(&self, conns: &HashMap<u64, Arc<Conn>>, peer: Option<IpAddr>) -> Option<()> {
        let victim = conns
            .values()
            .filter(|c| c.live() && peer.is_none_or(|p| c.peer == p))
            .filter_map(|c| c.idle_since().map(|t| (t, c)))
            .min_by_key(|(t, c)| (*t, c.id))
            .map(|(_, c)| c);
        match victim {
            Some(c) => {
                c.kill();
                self.stats.shed.fetch_add(1, Ordering::Relaxed);
                Some(())
            }
            None => {
                self.stats.refused.fetch_add(1, Ordering::Relaxed);
                None
            }
        }
    }

    /// Closes the connections past their handshake or idle timeout.
    fn sweep(&self) {
        let conns = self.conns();
        for c in conns.values().filter(|c| c.live()) {
            let why = {
                let s = c.state();
                if s.requests == 0 && c.accepted.elapsed() >= self.limits.handshake_timeout {
                    Some(Closed::Handshake)
                } else if s.in_flight == 0
                    && s.requests > 0
                    && s.idle_since.elapsed() >= self.limits.idle_timeout
                {
                    Some(Closed::Idle)
                } else {
                    None
                }
            };
            match why {
                Some(Closed::Handshake) => {
                    self.stats
                        .handshake_timeouts
                        .fetch_add(1, Ordering::Relaxed);
                }
                Some(Closed::Idle) => {
                    self.stats.idle_timeouts.fetch_add(1, Ordering::Relaxed);
                }
                None => continue,
            }
            c.kill();
        }
    }

    /// Accepts on `listener` in a task of its own until the receiver is
    /// dropped (the server stopped), handing over admitted connections.
    pub fn incoming(
        self: Arc<Self>,
        listener: TcpListener,
    ) -> mpsc::Receiver<io::Result<EdgeStream>> {
        let (tx, rx) = mpsc::channel(16);
        tokio::spawn(async move {
            let mut sweep = tokio::time::interval(SWEEP_INTERVAL);
            sweep.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
            let mut logged = Counts::default();
            loop {
                tokio::select! {
                    _ = tx.closed() => return,
                    _ = sweep.tick() => {
                        self.sweep();
                        logged = self.log_changes(logged);
                    }
                    r = listener.accept() => match r {
                        Ok((tcp, peer)) => {
                            let Some(conn) = self.admit(peer.ip()) else {
                                continue; // dropped: closed at once
                            };
                            self.stats.accepted.fetch_add(1, Ordering::Relaxed);
                            // No 40 ms wait for the ACK of the last small write.
                            let _ = tcp.set_nodelay(true);
                            let stream = EdgeStream { tcp, conn, edge: self.clone(), remote: peer };
                            if tx.send(Ok(stream)).await.is_err() {
                                return;
                            }
                        }
                        Err(e) if out_of_descriptors(&e) => {
                            // Make room, and give the closing a moment.
                            tracing::warn!(port = self.name, error = %e, "accept: out of descriptors; closing the connection idle the longest");
                            {
                                let conns = self.conns();
                                let _ = self.shed(&conns, None);
                            }
                            tokio::time::sleep(Duration::from_millis(20)).await;
                        }
                        // A connection reset before it was accepted.
                        Err(e) => tracing::debug!(port = self.name, error = %e, "accept failed"),
                    }
                }
            }
        });
        rx
    }

    /// One warning a sweep when connections were shed, refused or timed out.
    fn log_changes(&self, last: Counts) -> Counts {
        let s = &self.stats;
        let now = Counts {
            shed: s.shed.load(Ordering::Relaxed),
            refused: s.refused.load(Ordering::Relaxed),
            timeouts: s.handshake_timeouts.load(Ordering::Relaxed)
                + s.idle_timeouts.load(Ordering::Relaxed),
        };
        if now != last {
            tracing::warn!(
                port = self.name,
                open = self.open(),
                max_connections = self.limits.max_connections,
                shed = now.shed - last.shed,
                refused = now.refused - last.refused,
                timed_out = now.timeouts - last.timeouts,
                "connection limits: closed connections"
            );
        }
        now
    }
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
struct Counts {
    shed: u64,
    refused: u64,
    timeouts: u64,
}

fn out_of_descriptors(e: &io::Error) -> bool {
    matches!(e.raw_os_error(), Some(libc::EMFILE | libc::ENFILE))
}

/// Raises the soft RLIMIT_NOFILE to the hard limit; returns the soft
/// limit in force afterwards.
// rlim_t is u64 on Linux, not everywhere.
#[allow(clippy::unnecessary_cast)]
pub fn raise_descriptor_limit() -> io::Result<u64> {
    let mut lim = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: getrlimit/setrlimit write/read only the struct passed.
    if unsafe { libc::getrlimit(libc::RLIMIT_NOFILE, &mut lim) } != 0 {
        return Err(io::Error::last_os_error());
    }
    if lim.rlim_cur < lim.rlim_max {
        let raised = libc::rlimit {
            rlim_cur: lim.rlim_max,
            rlim_max: lim.rlim_max,
        };
        // SAFETY: as above.
        if unsafe { libc::setrlimit(libc::RLIMIT_NOFILE, &raised) } != 0 {
            return Err(io::Error::last_os_error());
        }
        lim = raised;
    }
    Ok(lim.rlim_cur as u64)
}

/// An accepted connection, closed by its [`Edge`] when a limit says so.
#[derive(Debug)]
pub struct EdgeStream {
    tcp: TcpStream,
    conn: Arc<Conn>,
    edge: Arc<Edge>,
    remote: SocketAddr,
}

impl EdgeStream {
    fn closed() -> io::Error {
        io::Error::new(
            io::ErrorKind::ConnectionAborted,
            "closed by the coordinator's connection limits",
        )
    }
}

impl Drop for EdgeStream {
    fn drop(&mut self) {
        self.edge.conns().remove(&self.conn.id);
    }
}

/// Parks the task's waker where [`Conn::kill`] finds it, and says whether
/// the connection was closed meanwhile.
fn park(conn: &Conn, cx: &Context<'_>, writer: bool) -> bool {
    {
        let mut s = conn.state();
        let slot = if writer { &mut s.writer } else { &mut s.reader };
        match slot {
            Some(w) if w.will_wake(cx.waker()) => {}
            _ => *slot = Some(cx.waker().clone()),
        }
    }
    !conn.live()
}

impl EdgeStream {
    /// One read or write of the socket, failing once the connection is
    /// closed, and parking the waker where [`Conn::kill`] finds it.
    fn guarded<T>(
        &mut self,
        cx: &mut Context<'_>,
        writer: bool,
        op: impl FnOnce(Pin<&mut TcpStream>, &mut Context<'_>) -> Poll<io::Result<T>>,
    ) -> Poll<io::Result<T>> {
        if !self.conn.live() {
            return Poll::Ready(Err(Self::closed()));
        }
        match op(Pin::new(&mut self.tcp), cx) {
            Poll::Pending if park(&self.conn, cx, writer) => Poll::Ready(Err(Self::closed())),
            r => r,
        }
    }
}

impl AsyncRead for EdgeStream {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        self.guarded(cx, false, |tcp, cx| tcp.poll_read(cx, buf))
    }
}

impl AsyncWrite for EdgeStream {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        self.guarded(cx, true, |tcp, cx| tcp.poll_write(cx, buf))
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        self.guarded(cx, true, |tcp, cx| tcp.poll_write_vectored(cx, bufs))
    }

    fn is_write_vectored(&self) -> bool {
        self.tcp.is_write_vectored()
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.tcp).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.tcp).poll_shutdown(cx)
    }
}

/// What a request knows of its connection (in its extensions).
#[derive(Clone, Debug)]
pub struct EdgeInfo {
    pub remote: SocketAddr,
    conn: Option<Arc<Conn>>,
}

impl EdgeInfo {
    /// The connection, if the request came through an [`Edge`].
    pub fn conn(&self) -> Option<&Arc<Conn>> {
        self.conn.as_ref()
    }

    /// The connection a request came on (tonic's extensions, or axum's
    /// connect info).
    pub fn of(ext: &axum::http::Extensions) -> Option<&Arc<Conn>> {
        ext.get::<EdgeInfo>()
            .or_else(|| {
                ext.get::<axum::extract::ConnectInfo<EdgeInfo>>()
                    .map(|c| &c.0)
            })
            .and_then(EdgeInfo::conn)
    }
}

impl tonic::transport::server::Connected for EdgeStream {
    type ConnectInfo = EdgeInfo;
    fn connect_info(&self) -> EdgeInfo {
        EdgeInfo {
            remote: self.remote,
            conn: Some(self.conn.clone()),
        }
    }
}

/// The monitor's side: an axum listener over an edge's connections.
pub struct EdgeListener {
    rx: mpsc::Receiver<io::Result<EdgeStream>>,
    local: SocketAddr,
}

impl EdgeListener {
    pub fn new(edge: Arc<Edge>, listener: TcpListener) -> io::Result<Self> {
        let local = listener.local_addr()?;
        Ok(EdgeListener {
            rx: edge.incoming(listener),
            local,
        })
    }
}

impl axum::serve::Listener for EdgeListener {
    type Io = EdgeStream;
    type Addr = EdgeInfo;

    async fn accept(&mut self) -> (EdgeStream, EdgeInfo) {
        loop {
            match self.rx.recv().await {
                Some(Ok(s)) => {
                    let info = tonic::transport::server::Connected::connect_info(&s);
                    return (s, info);
                }
                Some(Err(_)) => continue,
                // The accept task ended: nothing more comes.
                None => std::future::pending::<()>().await,
            }
        }
    }

    fn local_addr(&self) -> io::Result<EdgeInfo> {
        Ok(EdgeInfo {
            remote: self.local,
            conn: None,
        })
    }
}

impl axum::extract::connect_info::Connected<axum::serve::IncomingStream<'_, EdgeListener>>
    for EdgeInfo
{
    fn connect_info(stream: axum::serve::IncomingStream<'_, EdgeListener>) -> Self {
        stream.remote_addr().clone()
    }
}

/// Counts each request as in flight on its connection until its response
/// body ends.
#[derive(Clone, Copy, Debug, Default)]
pub struct TrackLayer;

impl<S> tower::Layer<S> for TrackLayer {
    type Service = Track<S>;
    fn layer(&self, inner: S) -> Track<S> {
        Track(inner)
    }
}

#[derive(Clone, Debug)]
pub struct Track<S>(S);

type BoxFuture<T> = Pin<Box<dyn Future<Output = T> + Send>>;

impl<S, ReqBody, ResBody> tower::Service<axum::http::Request<ReqBody>> for Track<S>
where
    S: tower::Service<axum::http::Request<ReqBody>, Response = axum::http::Response<ResBody>>,
    S::Future: Send + 'static,
    ResBody: Send + 'static,
{
    type Response = axum::http::Response<Tracked<ResBody>>;
    type Error = S::Error;
    type Future = BoxFuture<Result<Self::Response, S::Error>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), S::Error>> {
        self.0.poll_ready(cx)
    }

    fn call(&mut self, req: axum::http::Request<ReqBody>) -> Self::Future {
        let busy = EdgeInfo::of(req.extensions()).map(Conn::begin);
        let fut = self.0.call(req);
        Box::pin(async move {
            let res = fut.await?;
            Ok(res.map(|inner| Tracked { inner, _busy: busy }))
        })
    }
}

/// A response body that holds its request in flight.
#[derive(Debug)]
pub struct Tracked<B> {
    inner: B,
    _busy: Option<Busy>,
}

impl<B> http_body::Body for Tracked<B>
where
    B: http_body::Body + Unpin,
{
    type Data = B::Data;
    type Error = B::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<http_body::Frame<B::Data>, B::Error>>> {
        Pin::new(&mut self.inner).poll_frame(cx)
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> http_body::SizeHint {
        self.inner.size_hint()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn limits_follow_the_descriptor_limit() {
        let l = EdgeLimits::for_descriptors(1024, 2);
        assert_eq!((l.max_connections, l.max_per_peer), (384, 96));
        let l = EdgeLimits::for_descriptors(300, 2);
        assert_eq!((l.max_connections, l.max_per_peer), (22, 22));
        let l = EdgeLimits::for_descriptors(1 << 20, 1);
        assert_eq!((l.max_connections, l.max_per_peer), (16_384, 4096));
    }

    #[test]
    fn the_connection_idle_longest_is_shed_and_busy_ones_never() {
        let edge = Edge::new(
            "test",
            EdgeLimits {
                max_connections: 3,
                max_per_peer: 2,
                ..EdgeLimits::for_descriptors(1024, 1)
            },
        );
        let a: IpAddr = "10.0.0.1".parse().unwrap();
        let b: IpAddr = "10.0.0.2".parse().unwrap();
        let c1 = edge.admit(a).unwrap();
        let c2 = edge.admit(a).unwrap();
        let _busy = c1.begin();
        // A third from `a`: over its peer cap; c1 is busy, so c2 goes.
        let c3 = edge.admit(a).unwrap();
        assert!(c1.live() && !c2.live() && c3.live());
        let c4 = edge.admit(b).unwrap();
        // Total cap (3 live: c1, c3, c4): the idle one accepted first, c3.
        let _c5 = edge.admit(b).unwrap();
        assert!(!c3.live() && c4.live() && c1.live());
        let _b4 = c4.begin();
        let _b5 = _c5.begin();
        assert!(edge.admit(b).is_none(), "all busy: refused");
        assert_eq!(edge.stats.shed.load(Ordering::Relaxed), 2);
        assert_eq!(edge.stats.refused.load(Ordering::Relaxed), 1);
    }
}
