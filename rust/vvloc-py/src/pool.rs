//! vvloc's own rayon thread pool.
//!
//! Sized from `VVLOC_NUM_THREADS` (default: the number of available cores) or
//! `vvloc.set_num_threads(n)`. The pool remembers the process id that built it: a forked child
//! (e.g. a PyTorch DataLoader worker) inherits no worker threads, so it rebuilds its own pool on
//! first use. `_reset_pool_after_fork` is also registered with `os.register_at_fork`.

use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use rayon::{ThreadPool, ThreadPoolBuilder};
use std::any::Any;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::{Arc, Mutex};

struct PoolState {
    pool: Option<Arc<ThreadPool>>,
    pid: u32,
    threads: usize,
}

static STATE: Mutex<PoolState> = Mutex::new(PoolState {
    pool: None,
    pid: 0,
    threads: 0,
});

/// The thread count `VVLOC_NUM_THREADS` asks for: ASCII digits alone, ASCII blanks around
/// them allowed (space, tab, line feed, form feed, carriage return), at least 1; a larger
/// number than [`MAX_THREADS`], however many digits, asks for [`MAX_THREADS`]. None for
/// anything else (a sign, `_`, other digits than ASCII's). The Python package warns of the
/// same values (`vvloc._check_threads_variable`).
fn threads_asked(text: &str) -> Option<usize> {
    let digits = text.trim_matches(|c: char| c.is_ascii_whitespace());
    if digits.is_empty() || !digits.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    let n = digits.parse::<usize>().unwrap_or(usize::MAX); // only too many digits fail here
    (n > 0).then(|| n.min(MAX_THREADS as usize))
}

fn default_threads() -> usize {
    std::env::var("VVLOC_NUM_THREADS")
        .ok()
        .and_then(|v| threads_asked(&v))
        .unwrap_or_else(|| {
            std::thread::available_parallelism()
                .map(|n| n.get())
                .unwrap_or(1)
        })
}

fn build(threads: usize) -> PyResult<Arc<ThreadPool>> {
    ThreadPoolBuilder::new()
        .num_threads(threads)
        .thread_name(|i| format!("vvloc-{i}"))
        .build()
        .map(Arc::new)
        .map_err(|e| PyValueError::new_err(format!("could not start the vvloc thread pool: {e}")))
}

fn lock() -> std::sync::MutexGuard<'static, PoolState> {
    // A poisoned lock only means another thread panicked while holding it; the state is still valid.
    STATE.lock().unwrap_or_else(|p| p.into_inner())
}

/// The current pool, (re)built if absent or inherited across a fork.
pub fn get() -> PyResult<Arc<ThreadPool>> {
    let mut st = lock();
    let pid = std::process::id();
    if st.pool.is_none() || st.pid != pid {
        if st.pid != pid {
            // A pool inherited across fork has no worker threads here: leak it, never drop it.
            if let Some(p) = st.pool.take() {
                std::mem::forget(p);
            }
        }
        if st.threads == 0 {
            st.threads = default_threads();
        }
        st.pool = Some(build(st.threads)?);
        st.pid = pid;
    }
    Ok(st.pool.as_ref().expect("pool was just built").clone())
}

/// Runs `f`, catching a panic in it: the kernels return errors for the input they refuse, so
/// a panic is a bug (or input changed under a running kernel by another thread). Its message
/// comes back as the error, for [`internal_error`]: no `PanicException`, a `BaseException`
/// that `except Exception` lets through, reaches Python. Unwind safety (`AssertUnwindSafe`):
/// what `f` was building is dropped with the panic; shared state that it changed (an index that
/// a panicking `add` left half-updated) stays as the panic left it, as it did when the panic
/// reached Python (the index's lock ignores poisoning).
pub fn guarded<T>(f: impl FnOnce() -> T) -> Result<T, String> {
    catch_unwind(AssertUnwindSafe(f)).map_err(|p| panic_message(p.as_ref()))
}

/// Runs `f` on the calling thread, holding the GIL, with a panic in it turned into the
/// `RuntimeError` of [`internal_error`]: for the bindings' light methods (the translation
/// search's steps, the index's accessors) that do not go through [`run`].
pub fn guard<T>(f: impl FnOnce() -> PyResult<T>) -> PyResult<T> {
    guarded(f).map_err(internal_error)?
}

fn panic_message(payload: &(dyn Any + Send)) -> String {
    if let Some(s) = payload.downcast_ref::<&str>() {
        (*s).to_string()
    } else if let Some(s) = payload.downcast_ref::<String>() {
        s.clone()
    } else {
        "a panic without a message".to_string()
    }
}

/// The Python exception of a panic caught by [`guarded`]: a `RuntimeError` that names it.
pub fn internal_error(message: String) -> PyErr {
    PyRuntimeError::new_err(format!(
        "vvloc internal error in a Rust kernel ({message}): a bug, or an input array that \
         another thread changed during the call; please report it with the call's shapes \
         and dtypes"
    ))
}

/// Runs `f` with the GIL released, inside vvloc's pool; a panic becomes a `RuntimeError`
/// ([`guarded`]).
pub fn run<T, F>(py: Python<'_>, f: F) -> PyResult<T>
where
    T: Send,
    F: FnOnce() -> T + Send,
{
    let pool = get()?;
    py.detach(move || guarded(|| pool.install(f)))
        .map_err(internal_error)
}

/// Runs `f` with the GIL released: on the calling thread when `sequential` (the kernel is known
/// not to use rayon for this input, so the pool's thread count is not at stake), which saves
/// the ~20 µs hand-over to a pool thread and back; inside vvloc's pool otherwise ([`run`]).
pub fn run_where<T, F>(py: Python<'_>, sequential: bool, f: F) -> PyResult<T>
where
    T: Send,
    F: FnOnce() -> T + Send,
{
    if sequential {
        py.detach(|| guarded(f)).map_err(internal_error)
    } else {
        run(py, f)
    }
}

/// Panics inside [`run_where`], for the tests of the path that turns a kernel's panic into a
/// `RuntimeError`: no kernel has a panic left that a test could trigger. `in_pool`: in a pool
/// thread, one item of a parallel loop (rayon carries the panic back to the calling thread);
/// otherwise on the calling thread. Not part of vvloc's API.
#[pyfunction]
pub fn _panic_for_tests(py: Python<'_>, in_pool: bool) -> PyResult<()> {
    run_where(py, !in_pool, move || {
        if in_pool {
            use rayon::prelude::*;
            (0..64usize).into_par_iter().for_each(|i| {
                if i == 37 {
                    panic!("a test panic in item {i}");
                }
            });
        } else {
            panic!("a test panic");
        }
    })
}

/// The most threads vvloc's kernel pool may have (building thousands of threads takes
/// seconds and helps nothing).
const MAX_THREADS: i64 = 1024;

/// Sets the number of threads of vvloc's kernel pool (1 ≤ n ≤ 1024).
#[pyfunction]
pub fn set_num_threads(n: i64) -> PyResult<()> {
    if !(1..=MAX_THREADS).contains(&n) {
        return Err(PyValueError::new_err(format!(
            "n: expected an integer in [1, {MAX_THREADS}], got {n}"
        )));
    }
    let n = n as usize;
    let pool = build(n)?;
    let mut st = lock();
    st.threads = n;
    st.pool = Some(pool);
    st.pid = std::process::id();
    Ok(())
}

/// The number of threads of vvloc's kernel pool.
#[pyfunction]
pub fn get_num_threads() -> usize {
    let st = lock();
    if st.threads == 0 {
        default_threads()
    } else {
        st.threads
    }
}

/// Forgets the pool inherited from the parent process (called in a fork child).
#[pyfunction]
pub fn _reset_pool_after_fork() {
    let mut st = lock();
    // Dropping an inherited pool would try to join threads that do not exist in the child:
    // leak it instead (a few bytes, once per fork).
    if let Some(p) = st.pool.take() {
        std::mem::forget(p);
    }
    st.pid = 0;
}
