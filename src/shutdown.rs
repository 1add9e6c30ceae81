//! The stop signal a graceful shutdown sends to the bus tasks and the sessions: once given, it
//! carries the deadline by which queued requests must have been served. Buses then serve what is
//! queued until the deadline and answer the rest 0x0A; sessions stop reading and close once their
//! requests are answered. Also how a stopped task's end is logged (`log_end`).

use tokio::sync::watch;
use tokio::task::JoinError;
use tokio::time::Instant;

/// The sending side, held by whoever decides to stop.
pub(crate) struct Stop(watch::Sender<Option<Instant>>);

/// The receiving side, one clone per task.
#[derive(Clone)]
pub struct Stopping(watch::Receiver<Option<Instant>>);

pub(crate) fn channel() -> (Stop, Stopping) {
    let (sender, receiver) = watch::channel(None);
    (Stop(sender), Stopping(receiver))
}

impl Stop {
    /// Ask every task to stop, serving queued work until `deadline`.
    pub(crate) fn stop(&self, deadline: Instant) {
        self.0.send_replace(Some(deadline));
    }
}

impl Stopping {
    #[cfg(any(test, feature = "test-util"))]
    /// A signal that never comes, for tasks run outside a gateway (tests, tools).
    pub fn never() -> Self {
        channel().1
    }

    /// The deadline, if a stop has been asked for.
    pub fn deadline(&self) -> Option<Instant> {
        *self.0.borrow()
    }

    /// Wait until a stop is asked for, and return its deadline. Cancel-safe; returns at once if
    /// the stop came earlier, and never if it cannot come any more.
    pub(crate) async fn requested(&mut self) -> Instant {
        let asked = self
            .0
            .wait_for(Option::is_some)
            .await
            .map(|deadline| *deadline);
        match asked {
            Ok(Some(deadline)) => deadline,
            _ => std::future::pending().await,
        }
    }
}

/// Abort every task of `tasks` and log how each ended ([`log_end`]), naming them `what`.
pub(crate) async fn abort_all(tasks: &mut tokio::task::JoinSet<()>, what: &str) {
    tasks.abort_all();
    while let Some(ended) = tasks.join_next().await {
        log_end(what, ended);
    }
}

/// How `task` ended, in the log: a panic is an error an operator must see (the task's work has
/// stopped); a task cancelled on purpose (the gateway stopping it) is noted at debug.
pub(crate) fn log_end(task: &str, ended: Result<(), JoinError>) {
    match ended {
        Ok(()) => {}
        Err(error) if error.is_panic() => tracing::error!(task, %error, "task panicked"),
        Err(error) => tracing::debug!(task, %error, "task cancelled"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[tokio::test(start_paused = true)]
    async fn every_clone_sees_the_stop_and_its_deadline() {
        let (stop, stopping) = channel();
        let mut a = stopping.clone();
        let mut b = stopping;
        let waiter = tokio::spawn(async move { a.requested().await });
        tokio::task::yield_now().await;
        assert_eq!(b.deadline(), None);
        let deadline = Instant::now() + Duration::from_secs(3);
        stop.stop(deadline);
        assert_eq!(waiter.await.unwrap(), deadline);
        assert_eq!(
            b.requested().await,
            deadline,
            "a late waiter returns at once"
        );
    }

    #[tokio::test(start_paused = true)]
    async fn never_means_never() {
        let mut never = Stopping::never();
        let waited = tokio::time::timeout(Duration::from_secs(3600), never.requested()).await;
        assert!(waited.is_err());
    }
}
