//! Bindings of the spatial kernels: `roll_interp`, `bev_pad`, `polar_sample`, `pad_polar`.
//!
//! Inputs are float32 (maps) and float64 (translations) numpy arrays; the gateway
//! `vvloc.kernels` validates and converts them. Each function releases the GIL and runs the
//! core kernel in vvloc's pool; results are returned without a copy.

use crate::arrays::view;
use crate::errors::to_py;
use crate::pool;
use numpy::{
    IntoPyArray, PyArray4, PyArrayDyn, PyReadonlyArray2, PyReadonlyArray3, PyReadonlyArrayDyn,
};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

fn non_negative(v: i64, name: &str) -> PyResult<usize> {
    usize::try_from(v)
        .map_err(|_| PyValueError::new_err(format!("{name}: expected an int >= 1, got {v}")))
}

/// Interpolated roll of `x` by `shift` elements along `axis` (0 <= axis < x.ndim).
#[pyfunction]
#[pyo3(signature = (x, shift, axis))]
fn roll_interp<'py>(
    py: Python<'py>,
    x: PyReadonlyArrayDyn<'py, f32>,
    shift: f64,
    axis: i64,
) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
    let view = view(&x, "x")?;
    let ndim = view.ndim();
    let axis = usize::try_from(axis).map_err(|_| {
        PyValueError::new_err(format!("axis: expected 0 <= axis < {ndim}, got {axis}"))
    })?;
    let sequential = vvloc_core::roll::runs_sequentially(view.len());
    let out = to_py(pool::run_where(py, sequential, || {
        vvloc_core::roll::roll_interp(view, shift, axis)
    })?)?;
    Ok(out.into_pyarray(py))
}

/// BEV padding: `bev` (H, W, C) float32, `translations` (N, 2) float64 metres → (N, H, W, C).
#[pyfunction]
#[pyo3(signature = (bev, translations, grid_size))]
fn bev_pad<'py>(
    py: Python<'py>,
    bev: PyReadonlyArray3<'py, f32>,
    translations: PyReadonlyArray2<'py, f64>,
    grid_size: f64,
) -> PyResult<Bound<'py, PyArray4<f32>>> {
    let (b, t) = (view(&bev, "bev")?, view(&translations, "translations")?);
    let out = to_py(pool::run(py, || vvloc_core::pad::bev_pad(b, t, grid_size))?)?;
    Ok(out.into_pyarray(py))
}

/// Polar sampling: `bev` (H, W, C) or (B, H, W, C) float32 → (T, R, C) or (B, T, R, C).
#[pyfunction]
#[pyo3(signature = (bev, num_angles, num_radii, grid_size))]
fn polar_sample<'py>(
    py: Python<'py>,
    bev: PyReadonlyArrayDyn<'py, f32>,
    num_angles: i64,
    num_radii: i64,
    grid_size: f64,
) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
    let t = non_negative(num_angles, "num_angles")?;
    let r = non_negative(num_radii, "num_radii")?;
    let b = view(&bev, "bev")?;
    let out = to_py(pool::run(py, || {
        vvloc_core::polar::polar_sample(b, t, r, grid_size)
    })?)?;
    Ok(out.into_pyarray(py))
}

/// Fused padding + polar sampling: `bev` (H, W, C), `translations` (N, 2) metres → (N, T, R, C).
#[pyfunction]
#[pyo3(signature = (bev, translations, num_angles, num_radii, grid_size))]
fn pad_polar<'py>(
    py: Python<'py>,
    bev: PyReadonlyArray3<'py, f32>,
    translations: PyReadonlyArray2<'py, f64>,
    num_angles: i64,
    num_radii: i64,
    grid_size: f64,
) -> PyResult<Bound<'py, PyArray4<f32>>> {
    let t = non_negative(num_angles, "num_angles")?;
    let r = non_negative(num_radii, "num_radii")?;
    let (b, tr) = (view(&bev, "bev")?, view(&translations, "translations")?);
    let out = to_py(pool::run(py, || {
        vvloc_core::pad::pad_polar(b, tr, t, r, grid_size)
    })?)?;
    Ok(out.into_pyarray(py))
}

/// Adds this area's functions and classes to the `_core` module.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(roll_interp, m)?)?;
    m.add_function(wrap_pyfunction!(bev_pad, m)?)?;
    m.add_function(wrap_pyfunction!(polar_sample, m)?)?;
    m.add_function(wrap_pyfunction!(pad_polar, m)?)?;
    Ok(())
}
