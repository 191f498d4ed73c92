//! A gate that `os.fork()` closes: the fork waits until no thread is inside a call of a
//! `DescriptorIndex`, and calls that begin meanwhile wait until the fork is done.
//!
//! Why: a forked child holds one thread, and a copy of every lock as it was at the fork. An
//! index whose lock another thread held at that moment (a query, or an `add` half done) would
//! be locked for ever in the child, or torn. With the gate no index lock is held or waited
//! for when the process forks, so the child gets every index whole and free.
//!
//! The gate is one atomic word (no lock of its own, which a fork could copy held): the low bits
//! count the threads inside, the top bit says a fork is waiting. Python calls
//! [`_before_fork`], [`_after_fork_in_parent`] and [`_after_fork_in_child`] through
//! `os.register_at_fork` (`vvloc/__init__.py`).

use pyo3::prelude::*;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Duration;

const FORKING: usize = 1 << (usize::BITS - 1);

static GATE: AtomicUsize = AtomicUsize::new(0);

/// Waits with short, growing sleeps: the waits last as long as one fork or one index call.
fn pause(step: &mut u64) {
    std::thread::sleep(Duration::from_micros(*step));
    *step = (*step * 2).min(1_000);
}

/// A thread inside the gate; it leaves when this is dropped.
pub struct Inside(());

impl Drop for Inside {
    fn drop(&mut self) {
        GATE.fetch_sub(1, Ordering::Release);
    }
}

/// Enters the gate, waiting while a fork is under way. Call with the GIL released (the fork's
/// thread holds the GIL while it waits for the threads inside to leave).
pub fn enter() -> Inside {
    let mut step = 10;
    loop {
        let state = GATE.load(Ordering::Relaxed);
        if state & FORKING == 0
            && GATE
                .compare_exchange_weak(state, state + 1, Ordering::Acquire, Ordering::Relaxed)
                .is_ok()
        {
            return Inside(());
        }
        if state & FORKING != 0 {
            pause(&mut step);
        }
    }
}

/// Closes the gate and waits until every thread inside has left (called before `os.fork()`).
#[pyfunction]
pub fn _before_fork(py: Python<'_>) {
    py.detach(|| {
        // One fork at a time: a second thread forking waits for the first to reopen the gate.
        let mut step = 10;
        while GATE.fetch_or(FORKING, Ordering::AcqRel) & FORKING != 0 {
            pause(&mut step);
        }
        let mut step = 10;
        while GATE.load(Ordering::Acquire) & !FORKING != 0 {
            pause(&mut step);
        }
    });
}

/// Opens the gate again in the parent (also after a fork that failed).
#[pyfunction]
pub fn _after_fork_in_parent() {
    GATE.fetch_and(!FORKING, Ordering::Release);
}

/// Opens the gate in the child, where no other thread exists.
#[pyfunction]
pub fn _after_fork_in_child() {
    GATE.store(0, Ordering::Release);
}
