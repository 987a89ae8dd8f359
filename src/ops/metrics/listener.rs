//! The metrics listener's lifecycle (docs/watching.md): started at start on the
//! address bound then, moved or stopped by a reload (`metrics.listen`), the old one
//! running until the new address is bound; its web configuration file
//! (`metrics.web_config`: TLS, users) read again by every reload, new connections
//! served with what it says now. What it serves is `http.rs`.

use super::http::{self, WebState};
use super::web::{WebAccess, WebConfigError};
use super::Board;
use std::net::SocketAddr;
use std::sync::Arc;
use tokio_util::sync::CancellationToken;

/// A new metrics address that could not be bound (the old listener runs on).
#[derive(Debug, thiserror::Error)]
#[error("cannot listen for metrics on {addr}: {source}")]
pub(crate) struct Unbound {
    addr: SocketAddr,
    source: std::io::Error,
}

/// The metrics listener as it runs, moved or stopped by a reload.
pub(crate) struct MetricsListener {
    board: Arc<Board>,
    web: Arc<WebState>,
    running: Option<(SocketAddr, CancellationToken)>,
    shutdown: CancellationToken,
}

impl MetricsListener {
    /// Not listening yet, to serve with `access`; stopped at `shutdown`.
    pub(crate) fn new(board: Arc<Board>, access: WebAccess, shutdown: CancellationToken) -> Self {
        Self {
            board,
            web: Arc::new(WebState::new(access)),
            running: None,
            shutdown,
        }
    }

    /// Serves on `listener` (bound at start, so a bad address fails the start).
    pub(crate) fn start(&mut self, addr: SocketAddr, listener: std::net::TcpListener) {
        let stop = self.shutdown.child_token();
        http::spawn(listener, self.board.clone(), self.web.clone(), stop.clone());
        self.running = Some((addr, stop));
    }

    /// Listens on `want` (none: not at all). A new address that cannot be bound
    /// leaves the old listener running, and says so.
    pub(crate) fn set(&mut self, want: Option<SocketAddr>) -> Result<(), Unbound> {
        if self.running.as_ref().map(|(a, _)| *a) == want {
            return Ok(());
        }
        let bound = match want {
            Some(addr) => match http::bind(addr) {
                Ok(l) => Some((addr, l)),
                Err(source) => return Err(Unbound { addr, source }),
            },
            None => None,
        };
        if let Some((_, stop)) = self.running.take() {
            stop.cancel();
        }
        if let Some((addr, listener)) = bound {
            self.start(addr, listener);
        }
        Ok(())
    }

    /// Does it serve with a web configuration file now?
    pub(crate) fn has_web_file(&self) -> bool {
        self.web.access.read().expect("not poisoned").file.is_some()
    }

    /// Reads the web configuration file `path` again (`metrics.web_config`; empty:
    /// none), its certificates and keys with it: new connections are served with it,
    /// those open finish as they began, the source's login budgets stay. A file that
    /// does not load leaves the one in use, and the error says why. What it serves
    /// with now, in words.
    pub(crate) fn reload_web(&self, path: &str) -> Result<String, WebConfigError> {
        let access = WebAccess::load(path)?;
        let said = access.said();
        *self.web.access.write().expect("not poisoned") = Arc::new(access);
        Ok(said)
    }
}
