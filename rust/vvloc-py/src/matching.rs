//! Bindings of the matching kernels: matching cost, yaw cost curves, exact yaw estimation,
//! re-ranking and the translation search.

use crate::arrays::{check_aligned, view};
use crate::errors::to_py;
use crate::pool;
use numpy::{IntoPyArray, PyArray1, PyArray2, PyReadonlyArray1, PyReadonlyArray3};
use pyo3::prelude::*;
use std::borrow::Cow;
use vvloc_core::cost;
use vvloc_core::error::try_collect;
use vvloc_core::search::{SearchConfig, TranslationSearch as CoreSearch};

type F64Vec<'py> = Bound<'py, PyArray1<f64>>;

/// The estimates' (shift, yaw, cost) columns as arrays, each allocated fallibly (a
/// `MemoryError` naming `src`, the argument that sets their length, instead of an abort).
fn estimates_to_py<'py>(
    py: Python<'py>,
    est: &[cost::YawEstimate],
) -> PyResult<(F64Vec<'py>, F64Vec<'py>, F64Vec<'py>)> {
    let column = |f: fn(&cost::YawEstimate) -> f64| to_py(try_collect("src", est.iter().map(f)));
    let (shift, yaw, c) = (
        column(|e| e.shift)?,
        column(|e| e.yaw)?,
        column(|e| e.cost)?,
    );
    Ok((
        shift.into_pyarray(py),
        yaw.into_pyarray(py),
        c.into_pyarray(py),
    ))
}

/// The elements of a float64 vector: borrowed when contiguous (the gateway's arrays), else
/// copied into a fallibly allocated vector (`MemoryError` naming `arg`).
fn f64_slice<'a>(x: &'a PyReadonlyArray1<'_, f64>, arg: &'static str) -> PyResult<Cow<'a, [f64]>> {
    check_aligned(x, arg)?;
    match x.as_slice() {
        Ok(s) => Ok(Cow::Borrowed(s)),
        Err(_) => Ok(Cow::Owned(to_py(try_collect(
            arg,
            x.as_array().iter().copied(),
        ))?)),
    }
}

/// Matching cost of P pairs (P, T, C) float32 → (P,) float64.
#[pyfunction]
fn matching_cost<'py>(
    py: Python<'py>,
    a: PyReadonlyArray3<'py, f32>,
    b: PyReadonlyArray3<'py, f32>,
) -> PyResult<F64Vec<'py>> {
    let (a, b) = (view(&a, "a")?, view(&b, "b")?);
    let out = to_py(pool::run_where(
        py,
        cost::runs_sequentially(a.shape()[0]),
        || cost::matching_cost(a, b),
    )?)?;
    Ok(out.into_pyarray(py))
}

/// Integer-shift yaw cost curves: src (P, T, C), tgt (P, T, C) or (1, T, C) → (P, T) float64.
#[pyfunction]
fn yaw_costs<'py>(
    py: Python<'py>,
    src: PyReadonlyArray3<'py, f32>,
    tgt: PyReadonlyArray3<'py, f32>,
) -> PyResult<Bound<'py, PyArray2<f64>>> {
    let (s, t) = (view(&src, "src")?, view(&tgt, "tgt")?);
    let out = to_py(pool::run_where(
        py,
        cost::runs_sequentially(s.shape()[0]),
        || cost::yaw_costs(s, t),
    )?)?;
    Ok(out.into_pyarray(py))
}

/// Exact yaw estimate per pair → (shift, yaw, cost), each (P,) float64.
#[pyfunction]
fn estimate_yaw<'py>(
    py: Python<'py>,
    src: PyReadonlyArray3<'py, f32>,
    tgt: PyReadonlyArray3<'py, f32>,
) -> PyResult<(F64Vec<'py>, F64Vec<'py>, F64Vec<'py>)> {
    let (s, t) = (view(&src, "src")?, view(&tgt, "tgt")?);
    let est = to_py(pool::run_where(
        py,
        cost::runs_sequentially(s.shape()[0]),
        || cost::estimate_yaw(s, t),
    )?)?;
    estimates_to_py(py, &est)
}

/// Re-ranking of K candidates → (order int64, cost, yaw, shift), costs etc. in input order.
#[pyfunction]
#[allow(clippy::type_complexity)]
fn rerank<'py>(
    py: Python<'py>,
    src: PyReadonlyArray3<'py, f32>,
    tgt: PyReadonlyArray3<'py, f32>,
) -> PyResult<(
    Bound<'py, PyArray1<i64>>,
    F64Vec<'py>,
    F64Vec<'py>,
    F64Vec<'py>,
)> {
    let (s, t) = (view(&src, "src")?, view(&tgt, "tgt")?);
    let r = to_py(pool::run_where(
        py,
        cost::runs_sequentially(s.shape()[0]),
        || cost::rerank(s, t),
    )?)?;
    let order = to_py(try_collect("src", r.order.iter().map(|&k| k as i64)))?;
    let (shift, yaw, c) = estimates_to_py(py, &r.estimates)?;
    Ok((order.into_pyarray(py), c, yaw, shift))
}

/// The coarse-to-fine translation search (see `vvloc_core::search`).
#[pyclass(name = "TranslationSearch", module = "vvloc._core")]
struct TranslationSearch {
    inner: CoreSearch,
}

#[pymethods]
impl TranslationSearch {
    #[new]
    #[pyo3(signature = (half_range, step, fine_samples, stages, shrink, seed))]
    fn new(
        half_range: f64,
        step: f64,
        fine_samples: usize,
        stages: usize,
        shrink: f64,
        seed: u64,
    ) -> PyResult<Self> {
        pool::guard(|| {
            let inner = to_py(CoreSearch::new(SearchConfig {
                half_range,
                step,
                fine_samples,
                stages,
                shrink,
                seed,
            }))?;
            Ok(TranslationSearch { inner })
        })
    }

    /// The current stage's translations (N, 2) float64 in metres ((0, 2) when done).
    fn proposals<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        pool::guard(|| {
            let n = self.inner.proposals().len();
            let xy = to_py(self.inner.proposals_xy())?;
            let arr = ndarray::Array2::from_shape_vec((n, 2), xy)
                .map_err(|e| pyo3::exceptions::PyValueError::new_err(e.to_string()))?;
            Ok(arr.into_pyarray(py))
        })
    }

    /// Reports (N,) costs and (N,) yaws of the current proposals and advances a stage.
    fn report(
        &mut self,
        costs: PyReadonlyArray1<'_, f64>,
        yaws: PyReadonlyArray1<'_, f64>,
    ) -> PyResult<()> {
        let c = f64_slice(&costs, "costs")?;
        let y = f64_slice(&yaws, "yaws")?;
        pool::guard(|| to_py(self.inner.report(&c, &y)))
    }

    /// Whether every stage has been evaluated.
    #[getter]
    fn done(&self) -> PyResult<bool> {
        pool::guard(|| Ok(self.inner.done()))
    }

    /// The current stage index.
    #[getter]
    fn stage(&self) -> PyResult<usize> {
        pool::guard(|| Ok(self.inner.stage()))
    }

    /// The best hypothesis (x, y, yaw, cost), or None before the first report.
    fn best(&self) -> PyResult<Option<(f64, f64, f64, f64)>> {
        pool::guard(|| Ok(self.inner.best().map(|b| (b.x, b.y, b.yaw, b.cost))))
    }

    /// Every evaluated hypothesis: (xy (M, 2), yaw (M,), cost (M,), stage (M,) int64).
    #[allow(clippy::type_complexity)]
    fn history<'py>(
        &self,
        py: Python<'py>,
    ) -> PyResult<(
        Bound<'py, PyArray2<f64>>,
        F64Vec<'py>,
        F64Vec<'py>,
        Bound<'py, PyArray1<i64>>,
    )> {
        pool::guard(|| {
            let h = to_py(self.inner.history_columns())?;
            let m = h.yaw.len();
            let xy = ndarray::Array2::from_shape_vec((m, 2), h.xy)
                .map_err(|e| pyo3::exceptions::PyValueError::new_err(e.to_string()))?;
            Ok((
                xy.into_pyarray(py),
                h.yaw.into_pyarray(py),
                h.cost.into_pyarray(py),
                h.stage.into_pyarray(py),
            ))
        })
    }
}

/// Adds this area's functions and classes to the `_core` module.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(matching_cost, m)?)?;
    m.add_function(wrap_pyfunction!(yaw_costs, m)?)?;
    m.add_function(wrap_pyfunction!(estimate_yaw, m)?)?;
    m.add_function(wrap_pyfunction!(rerank, m)?)?;
    m.add_class::<TranslationSearch>()?;
    Ok(())
}
