//! Accepting connections with bounds a hostile client cannot hold open (issue 51).
//!
//! `axum::serve` gave every connection all the time it wanted: 300 half-open sockets sending
//! nothing were never closed, and against a server with 256 file descriptors `accept` then failed
//! and healthz, uploads and the synchronous path all timed out, no token needed. Here each
//! connection is served by hyper's HTTP/1 server directly, with:
//!
//! * a **header read timeout** ([`ConnLimits::header`]): the request's headers must arrive within
//!   it, for the first request and for each next one on a kept-alive connection (an idle
//!   keep-alive connection is closed after it too);
//! * a **body read timeout** ([`ConnLimits::body`]): a request body may not stall longer between
//!   two chunks (a slow but steady upload is fine; a stalled one ends with an error);
//! * a **cap per client address** ([`ConnLimits::per_address`]): connections beyond it are
//!   closed as soon as they are accepted, so one address cannot hold every descriptor.
//!
//! `accept` errors (out of descriptors) are logged and retried after a short pause rather than
//! ending the server. Shutdown stops accepting and lets open connections finish their requests
//! (`hyper_util`'s graceful shutdown); the caller bounds how long.

use std::collections::HashMap;
use std::convert::Infallible;
use std::future::Future;
use std::net::IpAddr;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use axum::Router;
use axum::body::Body;
use hyper::body::Incoming;
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::server::graceful::GracefulShutdown;
use hyper_util::service::TowerToHyperService;
use tokio::net::TcpListener;
use tower::ServiceExt;
use tower_http::timeout::TimeoutBody;
use tracing::{debug, warn};

/// The bounds every connection is held to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ConnLimits {
    /// Time a connection has to send a request's headers (`header_read_timeout`).
    pub header: Duration,
    /// Longest stall of a request body between chunks (`body_read_timeout`).
    pub body: Duration,
    /// Connections open at once from one client address (`max_connections_per_address`).
    pub per_address: usize,
}

/// Connections open per client address.
#[derive(Debug, Default)]
struct Open(Mutex<HashMap<IpAddr, usize>>);

/// One connection's place in [`Open`], given back when dropped.
struct Slot {
    open: Arc<Open>,
    ip: IpAddr,
}

impl Open {
    /// A slot for a connection from `ip`, unless `ip` holds `cap` already.
    fn take(self: &Arc<Self>, ip: IpAddr, cap: usize) -> Option<Slot> {
        let mut m = self.0.lock().unwrap_or_else(|e| e.into_inner());
        let n = m.entry(ip).or_default();
        if *n >= cap {
            return None;
        }
        *n += 1;
        Some(Slot {
            open: self.clone(),
            ip,
        })
    }
}

impl Drop for Slot {
    fn drop(&mut self) {
        let mut m = self.open.0.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(n) = m.get_mut(&self.ip) {
            *n -= 1;
            if *n == 0 {
                m.remove(&self.ip);
            }
        }
    }
}

/// Serves `app` on `listener` with `limits` until `stop` completes; then stops accepting and
/// waits for the open connections to finish their requests.
///
/// # Errors
/// None so far: `accept` failures are retried.
pub async fn serve(
    listener: TcpListener,
    app: Router,
    limits: ConnLimits,
    stop: impl Future<Output = ()> + Send,
) -> std::io::Result<()> {
    let open = Arc::new(Open::default());
    let graceful = GracefulShutdown::new();
    let mut stop = std::pin::pin!(stop);
    loop {
        let (stream, addr) = tokio::select! {
            accepted = listener.accept() => match accepted {
                Ok(a) => a,
                Err(e) => {
                    // Out of descriptors (EMFILE) or a connection reset before it was accepted:
                    // the timeouts free descriptors, so wait a little and go on.
                    warn!(error = %e, "accept failed; retrying");
                    tokio::time::sleep(Duration::from_millis(100)).await;
                    continue;
                }
            },
            () = &mut stop => break,
        };
        let Some(slot) = open.take(addr.ip(), limits.per_address) else {
            debug!(%addr, "over max_connections_per_address; closed");
            continue;
        };
        let body = limits.body;
        let service = app
            .clone()
            .map_request(move |r: axum::http::Request<Incoming>| {
                r.map(|b| Body::new(TimeoutBody::new(body, b)))
            })
            .map_err(|e: Infallible| match e {});
        let conn = hyper::server::conn::http1::Builder::new()
            .timer(TokioTimer::new())
            .header_read_timeout(limits.header)
            .serve_connection(TokioIo::new(stream), TowerToHyperService::new(service));
        let conn = graceful.watch(conn);
        tokio::spawn(async move {
            if let Err(e) = conn.await {
                debug!(%addr, error = %e, "connection ended");
            }
            drop(slot);
        });
    }
    drop(listener);
    graceful.shutdown().await;
    Ok(())
}
