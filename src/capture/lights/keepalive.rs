//! Keeping the firmware's host-silence timeout from switching an LED off during a long
//! exposure or download, without defeating it when the host hangs.
//!
//! A thread pings the controller, but only while the sequencer holds a [`Lease`], and a lease
//! has a budget: the longest the step it covers may take (a camera's shot time, a settle
//! time). If the step overruns its budget (a hung camera, a stuck host), the pings stop and
//! the firmware switches the LED off by itself one timeout later. The same thread watches the
//! operator's interrupt and switches the LEDs off at once, even while the sequencer is blocked
//! inside a camera call.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use super::SharedLights;
use crate::capture::interrupt::Interrupt;

/// How often the thread looks at the interrupt flag.
const POLL: Duration = Duration::from_millis(20);

struct Control {
    lease_until: Option<Instant>,
    next_ping: Instant,
    stop: bool,
}

struct Inner {
    lights: SharedLights,
    interrupt: Interrupt,
    interval: Duration,
    control: Mutex<Control>,
    wake: Condvar,
    failure: Mutex<Option<String>>,
    pings: std::sync::atomic::AtomicU64,
    off_for_interrupt: AtomicBool,
}

/// The keepalive thread; stops when dropped.
pub struct Keepalive {
    inner: Arc<Inner>,
    thread: Option<JoinHandle<()>>,
}

/// Pings run while this lives, for at most its budget.
pub struct Lease<'a> {
    keepalive: &'a Keepalive,
}

impl Keepalive {
    /// Starts the thread; `interval` should be at most a third of the firmware's timeout.
    pub fn start(lights: SharedLights, interval: Duration, interrupt: Interrupt) -> Keepalive {
        let inner = Arc::new(Inner {
            lights,
            interrupt,
            interval,
            control: Mutex::new(Control {
                lease_until: None,
                next_ping: Instant::now(),
                stop: false,
            }),
            wake: Condvar::new(),
            failure: Mutex::new(None),
            pings: 0.into(),
            off_for_interrupt: AtomicBool::new(false),
        });
        let worker = inner.clone();
        let thread = std::thread::Builder::new()
            .name("psscan-led-keepalive".into())
            .spawn(move || worker.run())
            .expect("a thread can be started");
        Keepalive {
            inner,
            thread: Some(thread),
        }
    }

    /// Keeps the controller alive for at most `budget` or until the lease is dropped
    /// (`Duration::MAX`: until dropped, for an operator holding an LED on the bench).
    pub fn lease(&self, budget: Duration) -> Lease<'_> {
        let mut control = self.inner.lock_control();
        let now = Instant::now();
        // A budget past what an Instant can hold means "no limit": a century will do.
        let forever = Duration::from_secs(100 * 365 * 24 * 3600);
        control.lease_until = Some(
            now.checked_add(budget)
                .unwrap_or_else(|| now + forever.min(budget)),
        );
        control.next_ping = now + self.inner.interval;
        self.inner.wake.notify_all();
        Lease { keepalive: self }
    }

    /// The last ping that failed, if any (the sequencer reports it).
    pub fn failure(&self) -> Option<String> {
        self.inner
            .failure
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
    }

    /// Pings sent so far.
    pub fn pings(&self) -> u64 {
        self.inner.pings.load(Ordering::Relaxed)
    }

    /// Whether the thread switched the LEDs off because of the interrupt.
    pub fn switched_off_for_interrupt(&self) -> bool {
        self.inner.off_for_interrupt.load(Ordering::SeqCst)
    }
}

impl Drop for Lease<'_> {
    fn drop(&mut self) {
        self.keepalive.inner.lock_control().lease_until = None;
    }
}

impl Drop for Keepalive {
    fn drop(&mut self) {
        self.inner.lock_control().stop = true;
        self.inner.wake.notify_all();
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

impl Inner {
    fn lock_control(&self) -> std::sync::MutexGuard<'_, Control> {
        self.control.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn run(&self) {
        loop {
            let mut control = self.lock_control();
            if control.stop {
                return;
            }
            if self.interrupt.is_set() && !self.off_for_interrupt.load(Ordering::SeqCst) {
                drop(control);
                // Whatever the sequencer is blocked in, the LEDs go off now.
                let _ = self.lights.lock().off();
                self.off_for_interrupt.store(true, Ordering::SeqCst);
                continue;
            }
            let now = Instant::now();
            let leased = control.lease_until.is_some_and(|until| now < until);
            if leased && now >= control.next_ping {
                control.next_ping = now + self.interval;
                drop(control);
                self.ping();
                continue;
            }
            let wait = if leased {
                (control.next_ping - now).min(POLL)
            } else {
                POLL
            };
            let _ = self
                .wake
                .wait_timeout(control, wait)
                .unwrap_or_else(|p| p.into_inner());
        }
    }

    fn ping(&self) {
        let result = self.lights.lock().keepalive();
        self.pings.fetch_add(1, Ordering::Relaxed);
        if let Err(e) = result {
            *self.failure.lock().unwrap_or_else(|p| p.into_inner()) = Some(e.to_string());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::capture::lights::{LightController, MockLights};

    #[test]
    fn a_lease_keeps_the_led_on_past_the_timeout_and_its_budget_does_not() {
        let mut mock = MockLights::new(10);
        let probe = mock.probe();
        mock.set_timeout(100).unwrap();
        mock.on(4).unwrap();
        let lights = SharedLights::new(Box::new(mock));
        let keepalive =
            Keepalive::start(lights.clone(), Duration::from_millis(30), Interrupt::new());
        {
            let _lease = keepalive.lease(Duration::from_secs(10));
            std::thread::sleep(Duration::from_millis(300));
            assert_eq!(probe.lit(), vec![4], "kept alive through 3 timeouts");
        }
        assert!(keepalive.pings() >= 5, "{}", keepalive.pings());
        // A step that overruns its budget: pings stop, the controller times out.
        lights.lock().on(4).unwrap();
        let _lease = keepalive.lease(Duration::from_millis(50));
        std::thread::sleep(Duration::from_millis(300));
        assert!(probe.lit().is_empty());
        assert!(lights.lock().state().unwrap().tripped);
    }

    #[test]
    fn an_interrupt_switches_the_leds_off_at_once() {
        let mut mock = MockLights::new(10);
        let probe = mock.probe();
        mock.on(7).unwrap();
        let lights = SharedLights::new(Box::new(mock));
        let stop = Interrupt::new();
        let keepalive = Keepalive::start(lights, Duration::from_millis(500), stop.clone());
        stop.set();
        let start = Instant::now();
        while !keepalive.switched_off_for_interrupt() {
            assert!(start.elapsed() < Duration::from_secs(5));
            std::thread::sleep(Duration::from_millis(5));
        }
        assert!(probe.lit().is_empty());
    }
}
