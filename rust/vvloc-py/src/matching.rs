//! Bindings of the matching kernels.

use pyo3::prelude::*;

/// Adds this area's functions and classes to the `_core` module.
pub fn register(_m: &Bound<'_, PyModule>) -> PyResult<()> {
    Ok(())
}
