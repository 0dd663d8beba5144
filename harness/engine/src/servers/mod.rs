//! Thin tokio servers around a sans-IO [`Station`]: Modbus/TCP, RTU over TCP, and RTU on a serial line.
//!
//! All endpoints share one station (one drive with one state, as a real drive reachable over several
//! interfaces), each connection keeps its own receive state (`TcpConn` or `RtuPort`). The station's clock is
//! the time since [`start`] was called. The I/O layer only moves bytes, stamps their arrival and honours
//! the delays the station asks for; everything a drive decides is in the station.

mod conn;
mod serial;
mod shutdown;

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use tokio::net::{TcpListener, TcpStream};
use tokio::sync::watch;
use tokio::task::JoinSet;

use codec::framer::RtuTiming;
use drives::Station;

pub use serial::SerialConfig;
use shutdown::Shutdown;

/// How many connections one listener serves at once; further clients wait in the kernel's backlog.
pub const MAX_CONNECTIONS: usize = 1024;

/// The timing of RTU over TCP, where there is no line ([`RtuTiming::tcp_carrier`]): frames are cut by their
/// length and CRC; a silence of 50 ms only ends frames of function codes without a length rule; answers go out
/// at once (no t3.5 to keep).
pub fn rtu_over_tcp_timing() -> RtuTiming {
    RtuTiming::tcp_carrier()
}

/// The endpoints to serve. At least one must be set.
#[derive(Clone, Debug)]
pub struct ServerConfig {
    /// Modbus/TCP listen address (port 0: any free port, read it back from the handle).
    pub tcp: Option<SocketAddr>,
    /// RTU-over-TCP listen address.
    pub rtu_over_tcp: Option<SocketAddr>,
    /// The line timing of RTU over TCP connections.
    pub rtu_over_tcp_timing: RtuTiming,
    /// A serial device (or pty) to serve RTU on.
    pub serial: Option<SerialConfig>,
}

impl Default for ServerConfig {
    fn default() -> Self {
        Self {
            tcp: None,
            rtu_over_tcp: None,
            rtu_over_tcp_timing: rtu_over_tcp_timing(),
            serial: None,
        }
    }
}

/// Why a server could not start.
#[derive(Debug, thiserror::Error)]
pub enum ServerError {
    /// No endpoint was configured.
    #[error("no endpoint to serve: give a TCP, RTU-over-TCP or serial endpoint")]
    NoEndpoint,
    /// A listen address could not be bound.
    #[error("cannot listen for {kind} on {addr}: {source}")]
    Bind {
        kind: &'static str,
        addr: SocketAddr,
        source: std::io::Error,
    },
    /// The serial device could not be opened or configured.
    #[error("cannot open serial device {path}: {source}")]
    Serial {
        path: PathBuf,
        source: tokio_serial::Error,
    },
}

/// The station all endpoints share, with the instant its clock started.
pub struct SharedStation {
    station: Mutex<Station>,
    epoch: Instant,
}

impl SharedStation {
    /// Share `station`; its clock starts now.
    pub fn new(station: Station) -> Self {
        Self {
            station: Mutex::new(station),
            epoch: Instant::now(),
        }
    }

    /// The station's time: how long since the server started.
    pub fn now(&self) -> Duration {
        self.epoch.elapsed()
    }

    /// The wall instant of station time `t`.
    pub fn instant(&self, t: Duration) -> Instant {
        self.epoch + t
    }

    /// Exclusive access to the station. Held only for one sans-IO call, never across an await.
    pub fn lock(&self) -> MutexGuard<'_, Station> {
        // A panic inside the model poisons the lock; the drive keeps serving the other connections with
        // whatever state it had, as the panic already ended (and logged) the connection that caused it.
        self.station.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// A running server: its bound endpoints and the means to stop it. Dropping it signals shutdown too.
pub struct ServerHandle {
    tcp: Option<SocketAddr>,
    rtu_over_tcp: Option<SocketAddr>,
    serial: Option<SerialConfig>,
    station: Arc<SharedStation>,
    stop: watch::Sender<bool>,
    /// One task per endpoint (a listener with its connections, or the serial line).
    tasks: JoinSet<()>,
}

impl ServerHandle {
    /// The bound Modbus/TCP address.
    pub fn tcp_addr(&self) -> Option<SocketAddr> {
        self.tcp
    }

    /// The bound RTU-over-TCP address.
    pub fn rtu_over_tcp_addr(&self) -> Option<SocketAddr> {
        self.rtu_over_tcp
    }

    /// The serial endpoint being served.
    pub fn serial(&self) -> Option<&SerialConfig> {
        self.serial.as_ref()
    }

    /// The shared station (to look at counters or the model's state).
    pub fn station(&self) -> &Arc<SharedStation> {
        &self.station
    }

    /// Ask every listener and connection to stop, without waiting.
    pub fn signal_shutdown(&self) {
        // send_replace: stores the value even when no receiver is left (all tasks already ended).
        self.stop.send_replace(true);
    }

    /// Stop every listener and connection and wait until they have ended.
    pub async fn shutdown(mut self) {
        self.signal_shutdown();
        while let Some(done) = self.tasks.join_next().await {
            if let Err(e) = done {
                eprintln!("server: an endpoint task ended abnormally: {e}");
            }
        }
    }

    /// Resolves when an endpoint stops serving without being asked to (a serial line that failed; the
    /// error was logged). Listeners only stop on shutdown. Cancel-safe.
    pub async fn endpoint_stopped(&mut self) {
        if let Some(Err(e)) = self.tasks.join_next().await {
            eprintln!("server: an endpoint task ended abnormally: {e}");
        }
    }
}

impl Drop for ServerHandle {
    fn drop(&mut self) {
        // The tasks see the signal and end; the JoinSet's drop also aborts them, so nothing outlives the
        // handle for long even without a runtime to finish on.
        self.signal_shutdown();
    }
}

/// Bind every configured endpoint and start serving `station` on them. Returns once all are bound (a
/// client may connect as soon as this returns), or the first error (nothing keeps running then).
pub async fn start(station: Station, config: &ServerConfig) -> Result<ServerHandle, ServerError> {
    if config.tcp.is_none() && config.rtu_over_tcp.is_none() && config.serial.is_none() {
        return Err(ServerError::NoEndpoint);
    }
    // Nobody takes a served drive's decisions: they are dropped request by request.
    let shared = Arc::new(SharedStation::new(station.forgetting_decisions()));
    let (stop, stop_rx) = watch::channel(false);
    let mut handle = ServerHandle {
        tcp: None,
        rtu_over_tcp: None,
        serial: None,
        station: shared.clone(),
        stop,
        tasks: JoinSet::new(),
    };
    // On an error below, `handle` is dropped, which stops the endpoints already started.
    if let Some(addr) = config.tcp {
        let listener = bind("Modbus/TCP", addr).await?;
        handle.tcp = listener.local_addr().ok();
        handle.tasks.spawn(listen(
            listener,
            Speaks::Tcp,
            shared.clone(),
            Shutdown::new(stop_rx.clone()),
        ));
    }
    if let Some(addr) = config.rtu_over_tcp {
        let listener = bind("RTU over TCP", addr).await?;
        handle.rtu_over_tcp = listener.local_addr().ok();
        handle.tasks.spawn(listen(
            listener,
            Speaks::RtuOverTcp(config.rtu_over_tcp_timing),
            shared.clone(),
            Shutdown::new(stop_rx.clone()),
        ));
    }
    if let Some(sc) = &config.serial {
        let port = serial::open(sc).map_err(|source| ServerError::Serial {
            path: sc.path.clone(),
            source,
        })?;
        handle.serial = Some(sc.clone());
        let label = format!("serial {}", sc.path.display());
        let proto = conn::Rtu::new(sc.timing(), true);
        let shutdown = Shutdown::new(stop_rx.clone());
        let shared = shared.clone();
        handle.tasks.spawn(async move {
            conn::drive(port, proto, &shared, shutdown, &label).await;
        });
    }
    Ok(handle)
}

async fn bind(kind: &'static str, addr: SocketAddr) -> Result<TcpListener, ServerError> {
    TcpListener::bind(addr)
        .await
        .map_err(|source| ServerError::Bind { kind, addr, source })
}

/// What a listener's connections speak: Modbus/TCP, or RTU frames cut with this timing.
#[derive(Clone, Copy, Debug)]
enum Speaks {
    Tcp,
    RtuOverTcp(RtuTiming),
}

/// Accept connections until shutdown; each gets its own task and its own receive state.
async fn listen(
    listener: TcpListener,
    speaks: Speaks,
    shared: Arc<SharedStation>,
    mut shutdown: Shutdown,
) {
    let mut conns = JoinSet::new();
    loop {
        tokio::select! {
            _ = shutdown.wait() => break,
            // Reap finished connections so the set stays bounded by the live ones.
            Some(done) = conns.join_next(), if !conns.is_empty() => {
                if let Err(e) = done {
                    eprintln!("server: a connection task ended abnormally: {e}");
                }
            }
            accepted = listener.accept(), if conns.len() < MAX_CONNECTIONS => match accepted {
                Ok((stream, peer)) => {
                    conns.spawn(serve_conn(stream, peer, speaks, shared.clone(), shutdown.clone()));
                }
                Err(e) => {
                    // EMFILE and the like: retrying at once would spin, so back off a little.
                    eprintln!("server: accept failed: {e}");
                    tokio::select! {
                        _ = shutdown.wait() => break,
                        _ = tokio::time::sleep(Duration::from_millis(50)) => {}
                    }
                }
            },
        }
    }
    drop(listener);
    // Every connection watches the same shutdown signal, so this ends promptly.
    while let Some(done) = conns.join_next().await {
        if let Err(e) = done {
            eprintln!("server: a connection task ended abnormally: {e}");
        }
    }
}

async fn serve_conn(
    stream: TcpStream,
    peer: SocketAddr,
    speaks: Speaks,
    shared: Arc<SharedStation>,
    shutdown: Shutdown,
) {
    // Replies are small and a client waits for each one: Nagle's algorithm would hold them back ~40 ms.
    if let Err(e) = stream.set_nodelay(true) {
        eprintln!("server: {peer}: cannot set TCP_NODELAY: {e}");
    }
    match speaks {
        Speaks::Tcp => {
            let label = format!("tcp {peer}");
            conn::drive(stream, conn::Tcp::default(), &shared, shutdown, &label).await
        }
        Speaks::RtuOverTcp(timing) => {
            // No line, so no inter-frame silence to keep before replying.
            let label = format!("rtu-over-tcp {peer}");
            conn::drive(
                stream,
                conn::Rtu::new(timing, false),
                &shared,
                shutdown,
                &label,
            )
            .await
        }
    }
}
