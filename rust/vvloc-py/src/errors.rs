//! Maps `vvloc_core::Error` to Python exceptions (`ValueError`, `OSError`, `MemoryError`).

use pyo3::exceptions::{PyMemoryError, PyOSError, PyValueError};
use pyo3::PyErr;

/// Local wrapper so that `?` converts core errors into Python exceptions.
pub struct PyVvlocErr(pub vvloc_core::Error);

impl From<vvloc_core::Error> for PyVvlocErr {
    fn from(e: vvloc_core::Error) -> Self {
        PyVvlocErr(e)
    }
}

impl From<PyVvlocErr> for PyErr {
    fn from(e: PyVvlocErr) -> PyErr {
        match e.0 {
            vvloc_core::Error::Io { .. } => PyOSError::new_err(e.0.to_string()),
            vvloc_core::Error::Memory { .. } => PyMemoryError::new_err(e.0.to_string()),
            other => PyValueError::new_err(other.to_string()),
        }
    }
}

/// Converts a core result into a `PyResult`.
pub fn to_py<T>(r: vvloc_core::Result<T>) -> pyo3::PyResult<T> {
    r.map_err(|e| PyVvlocErr(e).into())
}
