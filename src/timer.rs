//! Sleeps that end on time. tokio's timer wakes on whole milliseconds (measured here 1.1-1.3 ms
//! late), most of a 1.75 ms t3.5, so the line would idle a millisecond per gap. With precise
//! timing switched on (the daemon does at start; in-process tests on tokio's paused clock leave
//! it off and get tokio's sleeps), the last few milliseconds before a deadline are kept by one
//! timer thread waiting on a condition variable, which wakes the task tens of microseconds late
//! instead. A task that sleeps again and again (the RTU master, once per frame) keeps a
//! `LineTimer` instead: on Linux its own timerfd in the runtime's epoll set, which wakes the
//! runtime thread directly, with no other thread to wake and switch to. Knows nothing of what it
//! times. The one module that reads `std::time::Instant` and tokio's raw `sleep_until`
//! (clippy.toml bans them elsewhere): the rest of the crate chooses a sleep's precision here, by
//! name, and reads the real clock through [`RealInstant`].

// Unsafe blocks, each with its SAFETY comment: the timerfd's calls and its registration.
#![allow(unsafe_code)]
// The clock and the sleeps the rest of the crate is to reach only through this module.
#![allow(clippy::disallowed_types, clippy::disallowed_methods)]

use std::cmp::Reverse;
use std::collections::BinaryHeap;
use std::future::Future;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex, OnceLock, PoisonError};
use std::task::{Context, Poll, Waker};
use std::time::{Duration, Instant};

/// Deadlines further away than this are first waited for with tokio's timer.
const PRECISE_WINDOW: Duration = Duration::from_millis(3);

static PRECISE: AtomicBool = AtomicBool::new(false);

/// Keep every later [`sleep_until`] to sub-millisecond precision. Not for tokio's paused clock.
pub fn use_precise_timer() {
    PRECISE.store(true, Ordering::Relaxed);
}

/// Sleep until `deadline`: tokio's timer, or, with [`use_precise_timer`], tokio's timer to
/// within a few milliseconds and the timer thread for the rest. Cancel-safe.
pub async fn sleep_until(deadline: tokio::time::Instant) {
    if !PRECISE.load(Ordering::Relaxed) {
        return tokio::time::sleep_until(deadline).await;
    }
    let deadline = deadline.into_std();
    if let Some(early) = deadline.checked_sub(PRECISE_WINDOW) {
        if early > Instant::now() {
            tokio::time::sleep_until(early.into()).await;
        }
    }
    precise_sleep_until(deadline).await;
}

/// Sleep until `deadline` on tokio's timer alone, whatever [`use_precise_timer`] says, so up to
/// a millisecond or so late: for deadlines no frame's timing hangs on (a port's reopen, an idle
/// connection, a poll's schedule, a test's wait). Cancel-safe.
pub(crate) fn coarse_sleep_until(deadline: tokio::time::Instant) -> tokio::time::Sleep {
    tokio::time::sleep_until(deadline)
}

/// A moment of the system's monotonic clock, which tokio's paused clock does not hold still:
/// for what is measured in real time whatever clock the runtime keeps (how long since a warning
/// was last logged).
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub(crate) struct RealInstant(Instant);

impl RealInstant {
    pub(crate) fn now() -> RealInstant {
        RealInstant(Instant::now())
    }

    /// The time since this moment.
    pub(crate) fn elapsed(self) -> Duration {
        self.0.elapsed()
    }

    /// The time from `earlier` to this moment; zero if `earlier` is later.
    pub(crate) fn duration_since(self, earlier: RealInstant) -> Duration {
        self.0.saturating_duration_since(earlier.0)
    }
}

impl std::ops::Add<Duration> for RealInstant {
    type Output = RealInstant;

    fn add(self, duration: Duration) -> RealInstant {
        RealInstant(self.0 + duration)
    }
}

/// The sleeps of one task, one at a time. With precise timing on Linux they end on a timerfd of
/// their own, registered once with the runtime's reactor: arming it is one syscall, and its
/// expiry wakes the runtime thread itself. The timer thread's round trip (a futex wake-up, two
/// switches to and from the timer thread, an eventfd write to wake the runtime) cost more CPU
/// per transaction than the rest of the transaction's syscalls together. Without a timerfd (not
/// Linux, no descriptor left, no reactor) the sleeps fall back to [`sleep_until`].
#[derive(Default)]
pub(crate) struct LineTimer {
    #[cfg(target_os = "linux")]
    fd: FdState,
}

#[cfg(target_os = "linux")]
#[derive(Default)]
enum FdState {
    /// Opened at the first precise sleep, inside the runtime that will poll it.
    #[default]
    Unopened,
    Open(timerfd::TimerFd),
    Unavailable,
}

impl LineTimer {
    pub(crate) fn new() -> Self {
        Self::default()
    }

    /// Sleep until `deadline`, like [`sleep_until`]. Cancel-safe: a cancelled sleep leaves the
    /// timerfd armed, and the next sleep re-arms it.
    pub(crate) async fn sleep_until(&mut self, deadline: tokio::time::Instant) {
        if !PRECISE.load(Ordering::Relaxed) {
            return tokio::time::sleep_until(deadline).await;
        }
        #[cfg(target_os = "linux")]
        {
            if let FdState::Unopened = self.fd {
                self.fd = match timerfd::TimerFd::new() {
                    Ok(fd) => FdState::Open(fd),
                    Err(error) => {
                        tracing::debug!(%error, "no timerfd, line sleeps use the timer thread");
                        FdState::Unavailable
                    }
                };
            }
            if let FdState::Open(fd) = &self.fd {
                match fd.sleep_until(deadline.into_std()).await {
                    Ok(()) => return,
                    Err(error) => {
                        tracing::debug!(%error, "timerfd failed, line sleeps use the timer thread");
                        self.fd = FdState::Unavailable;
                    }
                }
            }
        }
        sleep_until(deadline).await;
    }
}

#[cfg(target_os = "linux")]
mod timerfd {
    use std::io;
    use std::os::fd::{AsRawFd, FromRawFd, OwnedFd};
    use std::time::{Duration, Instant};
    use tokio::io::unix::AsyncFd;
    use tokio::io::Interest;

    pub(super) struct TimerFd(AsyncFd<OwnedFd>);

    impl TimerFd {
        pub(super) fn new() -> io::Result<TimerFd> {
            // SAFETY: timerfd_create takes two integers and returns a new descriptor or -1.
            let raw = unsafe {
                libc::timerfd_create(
                    libc::CLOCK_MONOTONIC,
                    libc::TFD_NONBLOCK | libc::TFD_CLOEXEC,
                )
            };
            if raw < 0 {
                return Err(io::Error::last_os_error());
            }
            // SAFETY: `raw` is a descriptor just opened, owned by nobody else.
            let fd = unsafe { OwnedFd::from_raw_fd(raw) };
            // SAFETY: the AsyncFd owns `fd`, so it stays open and the same until it is dropped.
            let fd = unsafe { AsyncFd::register_with_interest(fd, Interest::READABLE) }?;
            Ok(TimerFd(fd))
        }

        /// Arm for `after` from now, replacing any earlier arming and its unread expiry.
        fn arm(&self, after: Duration) -> io::Result<()> {
            // An all-zero value would disarm instead.
            let after = after.max(Duration::from_nanos(1));
            let spec = libc::itimerspec {
                it_interval: libc::timespec {
                    tv_sec: 0,
                    tv_nsec: 0,
                },
                it_value: libc::timespec {
                    tv_sec: libc::time_t::try_from(after.as_secs()).unwrap_or(libc::time_t::MAX),
                    tv_nsec: after.subsec_nanos() as libc::c_long,
                },
            };
            // SAFETY: `spec` is a valid itimerspec; a null old value is allowed.
            let done = unsafe {
                libc::timerfd_settime(self.0.as_raw_fd(), 0, &spec, std::ptr::null_mut())
            };
            if done < 0 {
                return Err(io::Error::last_os_error());
            }
            Ok(())
        }

        pub(super) async fn sleep_until(&self, deadline: Instant) -> io::Result<()> {
            loop {
                let now = Instant::now();
                if now >= deadline {
                    return Ok(());
                }
                // Relative to a `now` taken before arming, so it can only expire late, never
                // early; the loop checks the clock again anyway.
                self.arm(deadline - now)?;
                loop {
                    let mut ready = self.0.readable().await?;
                    let mut expirations = [0u8; 8];
                    let read = ready.try_io(|fd| {
                        // SAFETY: reads at most 8 bytes into an 8-byte buffer.
                        let n = unsafe {
                            libc::read(fd.as_raw_fd(), expirations.as_mut_ptr().cast(), 8)
                        };
                        if n < 0 {
                            Err(io::Error::last_os_error())
                        } else {
                            Ok(())
                        }
                    });
                    match read {
                        Ok(result) => {
                            result?;
                            // Read dry: without this the next sleep would find it readable and
                            // spend a read to learn otherwise.
                            ready.clear_ready();
                            break;
                        }
                        // Readiness left over from an earlier arming.
                        Err(_would_block) => continue,
                    }
                }
            }
        }
    }
}

/// Sleep until `deadline` on the timer thread alone.
pub(crate) fn precise_sleep_until(deadline: Instant) -> PreciseSleep {
    PreciseSleep {
        deadline,
        slot: None,
    }
}

/// What the timer thread and one sleep share.
#[derive(Default)]
struct Slot {
    waker: Mutex<Option<Waker>>,
}

struct Entry {
    deadline: Instant,
    slot: Arc<Slot>,
}

impl PartialEq for Entry {
    fn eq(&self, other: &Self) -> bool {
        self.deadline == other.deadline
    }
}
impl Eq for Entry {}
impl PartialOrd for Entry {
    fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}
impl Ord for Entry {
    fn cmp(&self, other: &Self) -> std::cmp::Ordering {
        self.deadline.cmp(&other.deadline)
    }
}

struct TimerThread {
    due: Mutex<BinaryHeap<Reverse<Entry>>>,
    changed: Condvar,
}

fn timer_thread() -> &'static TimerThread {
    static TIMER: OnceLock<&'static TimerThread> = OnceLock::new();
    TIMER.get_or_init(|| {
        let timer: &'static TimerThread = Box::leak(Box::new(TimerThread {
            due: Mutex::new(BinaryHeap::new()),
            changed: Condvar::new(),
        }));
        std::thread::Builder::new()
            .name("precise-timer".into())
            .spawn(move || {
                set_timer_slack_to_minimum();
                timer.run()
            })
            .expect("the timer thread starts");
        timer
    })
}

/// Linux lets a normal thread's timed waits end up to 50 us late (its "timer slack") so that
/// wake-ups can be batched; this thread exists to be on time.
fn set_timer_slack_to_minimum() {
    #[cfg(target_os = "linux")]
    // SAFETY: PR_SET_TIMERSLACK takes one integer argument and changes only this thread's slack.
    unsafe {
        libc::prctl(libc::PR_SET_TIMERSLACK, 1 as libc::c_ulong);
    }
}

impl TimerThread {
    fn run(&self) {
        let mut due = self.due.lock().unwrap_or_else(PoisonError::into_inner);
        loop {
            let now = Instant::now();
            while due.peek().is_some_and(|e| e.0.deadline <= now) {
                if let Some(Reverse(entry)) = due.pop() {
                    let waker = entry
                        .slot
                        .waker
                        .lock()
                        .unwrap_or_else(PoisonError::into_inner)
                        .take();
                    if let Some(waker) = waker {
                        waker.wake();
                    }
                }
            }
            due = match due.peek().map(|e| e.0.deadline) {
                Some(next) => {
                    let wait = next.saturating_duration_since(now);
                    self.changed
                        .wait_timeout(due, wait)
                        .unwrap_or_else(PoisonError::into_inner)
                        .0
                }
                None => self
                    .changed
                    .wait(due)
                    .unwrap_or_else(PoisonError::into_inner),
            };
        }
    }

    fn add(&self, deadline: Instant, slot: Arc<Slot>) {
        let mut due = self.due.lock().unwrap_or_else(PoisonError::into_inner);
        let earliest = due.peek().is_none_or(|e| deadline < e.0.deadline);
        due.push(Reverse(Entry { deadline, slot }));
        if earliest {
            self.changed.notify_one();
        }
    }
}

/// A sleep kept by the timer thread.
pub(crate) struct PreciseSleep {
    deadline: Instant,
    slot: Option<Arc<Slot>>,
}

impl Future for PreciseSleep {
    type Output = ();

    fn poll(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<()> {
        if Instant::now() >= self.deadline {
            return Poll::Ready(());
        }
        match &self.slot {
            Some(slot) => {
                *slot.waker.lock().unwrap_or_else(PoisonError::into_inner) =
                    Some(cx.waker().clone());
            }
            None => {
                let slot = Arc::new(Slot {
                    waker: Mutex::new(Some(cx.waker().clone())),
                });
                timer_thread().add(self.deadline, slot.clone());
                self.slot = Some(slot);
            }
        }
        // The thread may have fired between the check above and the waker being stored.
        if Instant::now() >= self.deadline {
            return Poll::Ready(());
        }
        Poll::Pending
    }
}

impl Drop for PreciseSleep {
    /// A cancelled sleep wakes nobody; its entry leaves the heap at its deadline.
    fn drop(&mut self) {
        if let Some(slot) = &self.slot {
            slot.waker
                .lock()
                .unwrap_or_else(PoisonError::into_inner)
                .take();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn a_precise_sleep_never_ends_before_its_deadline() {
        for micros in [0, 50, 300, 1_750, 4_000] {
            let deadline = Instant::now() + Duration::from_micros(micros);
            precise_sleep_until(deadline).await;
            assert!(Instant::now() >= deadline, "{micros} us");
        }
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn concurrent_sleeps_end_in_deadline_order() {
        let start = Instant::now();
        let order = Arc::new(Mutex::new(Vec::new()));
        let tasks: Vec<_> = [140u64, 40, 100, 20, 180, 60]
            .into_iter()
            .map(|ms| {
                let order = order.clone();
                tokio::spawn(async move {
                    precise_sleep_until(start + Duration::from_millis(ms)).await;
                    order.lock().unwrap().push(ms);
                })
            })
            .collect();
        for task in tasks {
            task.await.unwrap();
        }
        assert_eq!(*order.lock().unwrap(), [20, 40, 60, 100, 140, 180]);
    }

    #[cfg(target_os = "linux")]
    #[tokio::test]
    async fn a_timerfd_sleep_never_ends_before_its_deadline() {
        let timer = timerfd::TimerFd::new().unwrap();
        for micros in [0, 50, 300, 1_750, 4_000] {
            let deadline = Instant::now() + Duration::from_micros(micros);
            timer.sleep_until(deadline).await.unwrap();
            assert!(Instant::now() >= deadline, "{micros} us");
        }
    }

    #[cfg(target_os = "linux")]
    #[tokio::test]
    async fn an_expiry_of_a_cancelled_timerfd_sleep_does_not_end_the_next() {
        let timer = timerfd::TimerFd::new().unwrap();
        let cancelled = tokio::time::timeout(
            Duration::from_millis(1),
            timer.sleep_until(Instant::now() + Duration::from_millis(20)),
        )
        .await;
        assert!(cancelled.is_err());
        // The cancelled arming expires meanwhile and leaves the descriptor readable.
        tokio::time::sleep(Duration::from_millis(30)).await;
        let deadline = Instant::now() + Duration::from_millis(5);
        timer.sleep_until(deadline).await.unwrap();
        assert!(Instant::now() >= deadline);
    }

    #[tokio::test]
    async fn a_cancelled_sleep_does_not_disturb_the_next() {
        let soon = Instant::now() + Duration::from_millis(2);
        let cancelled = tokio::time::timeout(
            Duration::from_micros(100),
            precise_sleep_until(soon + Duration::from_secs(60)),
        )
        .await;
        assert!(cancelled.is_err());
        precise_sleep_until(soon).await;
        assert!(Instant::now() >= soon);
    }
}
