//! `vvloc._core`: thin PyO3 bindings of `vvloc-core`.
//!
//! Each `#[pyfunction]` validates its arguments, takes numpy views, releases the GIL, runs the
//! core kernel inside vvloc's own rayon pool ([`pool::run`]; on the calling thread when the
//! kernel is known to run sequentially for that input, [`pool::run_where`]) and wraps the
//! result. No algorithm lives here. Each area registers its functions from its own file.

mod arrays;
mod errors;
mod fork;
mod pool;

mod matching;
mod retrieval;
mod spatial;

use pyo3::prelude::*;

#[pymodule]
mod _core {
    use super::*;

    #[pymodule_export]
    use super::fork::{_after_fork_in_child, _after_fork_in_parent, _before_fork};
    #[pymodule_export]
    use super::pool::{_panic_for_tests, _reset_pool_after_fork, get_num_threads, set_num_threads};

    #[pymodule_init]
    fn init(m: &Bound<'_, PyModule>) -> PyResult<()> {
        m.add("__version__", env!("CARGO_PKG_VERSION"))?;
        m.add("build_profile", env!("VVLOC_BUILD_PROFILE"))?;
        crate::spatial::register(m)?;
        crate::matching::register(m)?;
        crate::retrieval::register(m)?;
        Ok(())
    }
}
