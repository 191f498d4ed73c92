//! Bindings of the retrieval kernels: `_core.DescriptorIndex`.
//!
//! Arrays must already be C-contiguous float32 / int64 (the Python wrapper
//! `vvloc.retrieval.DescriptorIndex` converts and validates); the core re-checks shapes and
//! values. The index sits behind a `RwLock`: queries from several Python threads run
//! concurrently (GIL released), `add` waits for them.
//!
//! Locking rules, which keep every wait free of cycles:
//! - A lock is taken only with the GIL released, and let go before the GIL is taken back: a
//!   thread holding the GIL never waits for the lock, so a writer waiting for a reader never
//!   waits, through the GIL, for itself.
//! - A lock is taken on the calling thread, never inside vvloc's pool: a pool worker waiting
//!   in one query's join may run another query's job, and had that job waited there for a
//!   read lock queued behind a writer (std's lock lets no new reader pass a waiting writer),
//!   the writer would have waited for the first query's read lock, held lower on the same
//!   worker's stack, for ever.
//! - `dim` and `dtype` never change, so they are kept beside the lock.
//! - Every lock is taken inside the fork gate ([`fork::enter`]): `os.fork()` waits until no
//!   index is locked, so a child never inherits one locked for ever or half changed.

use crate::errors::to_py;
use crate::fork;
use crate::pool;
use ndarray::{Array1, Array2};
use numpy::{
    IntoPyArray, PyArray1, PyArray2, PyReadonlyArray1, PyReadonlyArray2, PyUntypedArrayMethods,
};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyBytes;
use std::sync::{RwLock, RwLockReadGuard};
use vvloc_core::retrieval::{DescriptorIndex as CoreIndex, Dtype, Exclusion};

/// Adds this area's functions and classes to the `_core` module.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<DescriptorIndex>()?;
    Ok(())
}

fn slice<'a, T: numpy::Element, D: ndarray::Dimension>(
    a: &'a numpy::PyReadonlyArray<'_, T, D>,
    name: &str,
) -> PyResult<&'a [T]> {
    crate::arrays::check_aligned(a, name)?;
    let err = || PyValueError::new_err(format!("{name}: expected a C-contiguous array"));
    // as_slice() also takes a Fortran-ordered array, whose memory is not row-major
    if !a.is_c_contiguous() {
        return Err(err());
    }
    a.as_slice().map_err(|_| err())
}

fn matrix<'a>(a: &'a PyReadonlyArray2<'_, f32>, name: &str, dim: usize) -> PyResult<&'a [f32]> {
    let shape = a.shape();
    if shape[1] != dim {
        return Err(PyValueError::new_err(format!(
            "{name}: expected shape (n, {dim}), got ({}, {})",
            shape[0], shape[1]
        )));
    }
    slice(a, name)
}

type TopK<'py> = (Bound<'py, PyArray2<i64>>, Bound<'py, PyArray2<f32>>);
type Csr<'py> = (
    Bound<'py, PyArray1<i64>>,
    Bound<'py, PyArray1<i64>>,
    Bound<'py, PyArray1<f32>>,
);
type Exclude<'py> = (
    PyReadonlyArray1<'py, i64>,
    PyReadonlyArray1<'py, i64>,
    i64,
    bool,
);

/// Exact L2 nearest-neighbour index (see `vvloc.DescriptorIndex`).
#[pyclass(module = "vvloc._core", frozen)]
pub struct DescriptorIndex {
    inner: RwLock<CoreIndex>,
    dim: usize,
    dtype: Dtype,
}

impl DescriptorIndex {
    fn wrap(index: CoreIndex) -> Self {
        DescriptorIndex {
            dim: index.dim(),
            dtype: index.dtype(),
            inner: RwLock::new(index),
        }
    }

    fn read(&self) -> RwLockReadGuard<'_, CoreIndex> {
        // A poisoned lock means a panic in a kernel (a bug); the index itself is still valid.
        self.inner.read().unwrap_or_else(|p| p.into_inner())
    }

    /// Runs `f` on the index with the GIL released: the read lock is taken on this thread,
    /// then `f` runs inside vvloc's pool (the module's locking rules).
    fn query<T, F>(&self, py: Python<'_>, f: F) -> PyResult<T>
    where
        T: Send,
        F: FnOnce(&CoreIndex) -> T + Send,
    {
        let pool = pool::get()?;
        py.detach(|| {
            let _inside = fork::enter();
            let guard = self.read();
            let index: &CoreIndex = &guard;
            pool::guarded(|| pool.install(|| f(index)))
        })
        .map_err(pool::internal_error)
    }

    /// Runs `f` on the index with the GIL released, on this thread (a panic in it a
    /// `RuntimeError`, as in [`Self::query`]).
    fn inspect<T, F>(&self, py: Python<'_>, f: F) -> PyResult<T>
    where
        T: Send,
        F: FnOnce(&CoreIndex) -> T + Send,
    {
        py.detach(|| {
            let _inside = fork::enter();
            // a local, dropped before `_inside` (a temporary of the tail expression would be
            // dropped after it, leaving the gate with the lock still held)
            let guard = self.read();
            pool::guarded(|| f(&guard))
        })
        .map_err(pool::internal_error)
    }
}

#[pymethods]
impl DescriptorIndex {
    #[new]
    #[pyo3(signature = (descriptors, dtype = "float32", groups = None, seqs = None))]
    fn new(
        py: Python<'_>,
        descriptors: PyReadonlyArray2<'_, f32>,
        dtype: &str,
        groups: Option<PyReadonlyArray1<'_, i64>>,
        seqs: Option<PyReadonlyArray1<'_, i64>>,
    ) -> PyResult<Self> {
        let dtype = to_py(Dtype::parse(dtype))?;
        let dim = descriptors.shape()[1];
        let rows = slice(&descriptors, "descriptors")?;
        let groups = groups.as_ref().map(|g| slice(g, "groups")).transpose()?;
        let seqs = seqs.as_ref().map(|s| slice(s, "seqs")).transpose()?;
        let index = pool::run(py, || CoreIndex::from_rows(rows, dim, dtype, groups, seqs))?;
        Ok(Self::wrap(to_py(index)?))
    }

    #[pyo3(signature = (descriptors, groups = None, seqs = None))]
    fn add(
        &self,
        py: Python<'_>,
        descriptors: PyReadonlyArray2<'_, f32>,
        groups: Option<PyReadonlyArray1<'_, i64>>,
        seqs: Option<PyReadonlyArray1<'_, i64>>,
    ) -> PyResult<()> {
        let rows = matrix(&descriptors, "descriptors", self.dim)?;
        let groups = groups.as_ref().map(|g| slice(g, "groups")).transpose()?;
        let seqs = seqs.as_ref().map(|s| slice(s, "seqs")).transpose()?;
        let added = py.detach(|| {
            let _inside = fork::enter();
            let mut w = self.inner.write().unwrap_or_else(|p| p.into_inner());
            pool::guarded(|| w.add(rows, groups, seqs))
        });
        to_py(added.map_err(pool::internal_error)?)
    }

    #[pyo3(signature = (queries, k, exclude = None))]
    fn topk<'py>(
        &self,
        py: Python<'py>,
        queries: PyReadonlyArray2<'py, f32>,
        k: usize,
        exclude: Option<Exclude<'py>>,
    ) -> PyResult<TopK<'py>> {
        let q = matrix(&queries, "queries", self.dim)?;
        let nq = queries.shape()[0];
        let ex = exclusion(&exclude)?;
        let res = to_py(self.query(py, |index| index.topk(q, k, ex))?)?;
        let shape = (nq, res.k);
        // the core has checked that an (nq, k) array can exist (vvloc_core::error::checked_len)
        let bad = |e: ndarray::ShapeError| PyValueError::new_err(format!("k: {e}"));
        let idx = Array2::from_shape_vec(shape, res.indices).map_err(bad)?;
        let dist = Array2::from_shape_vec(shape, res.distances).map_err(bad)?;
        Ok((idx.into_pyarray(py), dist.into_pyarray(py)))
    }

    #[pyo3(signature = (queries, r, exclude = None))]
    fn radius<'py>(
        &self,
        py: Python<'py>,
        queries: PyReadonlyArray2<'py, f32>,
        r: f32,
        exclude: Option<Exclude<'py>>,
    ) -> PyResult<Csr<'py>> {
        let q = matrix(&queries, "queries", self.dim)?;
        let ex = exclusion(&exclude)?;
        let res = to_py(self.query(py, |index| index.radius(q, r, ex))?)?;
        Ok((
            Array1::from(res.offsets).into_pyarray(py),
            Array1::from(res.indices).into_pyarray(py),
            Array1::from(res.distances).into_pyarray(py),
        ))
    }

    /// The index in the file format of `vvloc_core::retrieval::format` (the Python wrapper
    /// writes it with vvloc's atomic writer, which keeps a file's mode and follows links).
    fn to_bytes<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyBytes>> {
        let bytes = to_py(self.inspect(py, vvloc_core::retrieval::format::to_bytes)?)?;
        Ok(PyBytes::new(py, &bytes))
    }

    #[staticmethod]
    fn load(py: Python<'_>, path: std::path::PathBuf) -> PyResult<Self> {
        let index = to_py(pool::run(py, || CoreIndex::load(&path))?)?;
        Ok(Self::wrap(index))
    }

    /// All descriptors, float32 (N, d).
    fn descriptors<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f32>>> {
        let (n, rows) = self.inspect(py, |index| (index.len(), index.rows()))?;
        let a = Array2::from_shape_vec((n, self.dim), rows)
            .map_err(|e| pool::internal_error(format!("descriptors: {e}")))?;
        Ok(a.into_pyarray(py))
    }

    /// Group id of every entry, int64 (N,).
    fn groups<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray1<i64>>> {
        Ok(Array1::from(self.inspect(py, |index| index.groups().to_vec())?).into_pyarray(py))
    }

    /// Sequence number of every entry, int64 (N,).
    fn seqs<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray1<i64>>> {
        Ok(Array1::from(self.inspect(py, |index| index.seqs().to_vec())?).into_pyarray(py))
    }

    fn __len__(&self, py: Python<'_>) -> PyResult<usize> {
        self.inspect(py, CoreIndex::len)
    }

    #[getter]
    fn dim(&self) -> usize {
        self.dim
    }

    #[getter]
    fn dtype(&self) -> &'static str {
        self.dtype.name()
    }
}

fn exclusion<'a>(e: &'a Option<Exclude<'_>>) -> PyResult<Option<Exclusion<'a>>> {
    e.as_ref()
        .map(|(g, s, window, whole_group)| {
            Ok(Exclusion {
                query_groups: slice(g, "exclude.groups")?,
                query_seqs: slice(s, "exclude.seqs")?,
                window: *window,
                whole_group: *whole_group,
            })
        })
        .transpose()
}
