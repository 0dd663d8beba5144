//! The shutdown signal every listener and connection loop waits on.

use tokio::sync::watch;

/// A receiver of the server's shutdown signal. Cheap to clone: one per task.
#[derive(Clone, Debug)]
pub(crate) struct Shutdown(watch::Receiver<bool>);

impl Shutdown {
    pub(crate) fn new(rx: watch::Receiver<bool>) -> Self {
        Self(rx)
    }

    /// Resolves once shutdown was asked for, or once the handle is gone (nobody could ask any more).
    pub(crate) async fn wait(&mut self) {
        let _ = self.0.wait_for(|stop| *stop).await;
    }
}
