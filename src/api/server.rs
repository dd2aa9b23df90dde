//! Running the service: bind, serve, shut down gracefully.
//!
//! Shutdown (SIGTERM or Ctrl-C): the listener stops accepting, readiness turns false, running
//! jobs are cancelled at their next batch or tile (finished tiles stay as checkpoints and the jobs
//! go back to `accepted`, to resume at the next start), in-flight requests get
//! [`ServeOptions::grace`] to finish, and the process exits.

use std::future::Future;
use std::net::SocketAddr;
use std::time::Duration;

use thiserror::Error;
use tokio::net::TcpListener;
use tracing::{info, warn};

use super::{ApiError, ApiSettings, AppState, router};
use crate::jobs::{Jobs, JobsError, Settings};

/// Errors of starting or running the server.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum ServeError {
    /// The address cannot be bound.
    #[error("cannot listen on {addr}: {source}")]
    Bind {
        /// The configured address.
        addr: String,
        /// The OS error.
        source: std::io::Error,
    },
    /// The job service cannot start.
    #[error("job service: {0}")]
    Jobs(#[from] JobsError),
    /// The API cannot start.
    #[error("api: {0}")]
    Api(#[from] ApiError),
    /// Serving failed.
    #[error("serving: {0}")]
    Io(#[from] std::io::Error),
}

/// Everything `qemd serve` needs.
#[derive(Debug, Clone)]
pub struct ServeOptions {
    /// `host:port` to listen on.
    pub listen: String,
    /// The job service.
    pub jobs: Settings,
    /// The API.
    pub api: ApiSettings,
    /// How long in-flight requests and stopping jobs get at shutdown.
    pub grace: Duration,
    /// The bounds every connection is held to.
    pub connections: super::conn::ConnLimits,
}

/// A bound server, ready to run.
#[derive(Debug)]
pub struct Server {
    listener: TcpListener,
    state: AppState,
    grace: Duration,
    connections: super::conn::ConnLimits,
}

impl Server {
    /// Starts the job service (recovering interrupted jobs) and binds the listener.
    ///
    /// # Errors
    /// [`ServeError::Bind`], [`ServeError::Jobs`].
    pub async fn bind(opts: ServeOptions) -> Result<Server, ServeError> {
        let listener =
            TcpListener::bind(&opts.listen)
                .await
                .map_err(|source| ServeError::Bind {
                    addr: opts.listen.clone(),
                    source,
                })?;
        let jobs = Jobs::open(opts.jobs).await?;
        let state = AppState::new(jobs, opts.api)?;
        Ok(Server {
            listener,
            state,
            grace: opts.grace,
            connections: opts.connections,
        })
    }

    /// The address actually bound (port 0 resolved).
    ///
    /// # Errors
    /// The socket has no address.
    pub fn local_addr(&self) -> Result<SocketAddr, ServeError> {
        Ok(self.listener.local_addr()?)
    }

    /// Serves until `signal` completes, then shuts down gracefully.
    ///
    /// # Errors
    /// [`ServeError::Io`].
    pub async fn run(
        self,
        signal: impl Future<Output = ()> + Send + 'static,
    ) -> Result<(), ServeError> {
        let jobs = self.state.jobs.clone();
        let app = router(self.state);
        let (tx, rx) = tokio::sync::watch::channel(false);
        let stopping = jobs.clone();
        tokio::spawn(async move {
            signal.await;
            info!("shutting down: no new connections, running jobs checkpoint and stop");
            stopping.begin_shutdown();
            let _ = tx.send(true);
        });
        let wait = |mut rx: tokio::sync::watch::Receiver<bool>| async move {
            let _ = rx.wait_for(|s| *s).await;
        };
        let serve = super::conn::serve(self.listener, app, self.connections, wait(rx.clone()));
        let deadline = {
            let grace = self.grace;
            let w = wait(rx);
            async move {
                w.await;
                tokio::time::sleep(grace).await;
            }
        };
        tokio::select! {
            r = serve => r?,
            () = deadline => warn!("requests still open after the grace period; closing them"),
        }
        jobs.shutdown(self.grace).await;
        info!("stopped");
        Ok(())
    }
}

/// Completes on Ctrl-C or SIGTERM.
pub async fn shutdown_signal() {
    let ctrl_c = async {
        if tokio::signal::ctrl_c().await.is_err() {
            std::future::pending::<()>().await;
        }
    };
    #[cfg(unix)]
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                let _ = s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! {
        () = ctrl_c => {},
        () = term => {},
    }
}
