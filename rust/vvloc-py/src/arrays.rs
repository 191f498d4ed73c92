//! Views of numpy arrays for the kernels, each checked first: an array whose view would be
//! unsound or panic is refused with a `ValueError` naming the argument.

use numpy::ndarray::{ArrayView, Dimension};
use numpy::{Element, PyArrayMethods, PyReadonlyArray, PyUntypedArrayMethods};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

/// The most dimensions rust-numpy takes into a view (more would panic in `as_array`).
const MAX_DIMS: usize = 32;

/// `ValueError` naming `name` unless every element of `x` is aligned for its type: numpy's
/// `ALIGNED` flag, which covers the data pointer and the strides, and the data pointer itself
/// (numpy calls every empty array aligned, while ndarray asserts its pointer). ndarray's views
/// and Rust slices read elements through references, which must be aligned: a buffer viewed at
/// an odd byte offset (`np.frombuffer(buf, np.float32, offset=1)`) is refused here rather than
/// read (a panic in a debug build, undefined behaviour in release). `vvloc.kernels` and
/// `vvloc.retrieval` copy such arrays before they get here.
pub fn check_aligned<T: Element, D: Dimension>(
    x: &PyReadonlyArray<'_, T, D>,
    name: &str,
) -> PyResult<()> {
    if x.is_aligned() && (x.data() as usize).is_multiple_of(std::mem::align_of::<T>()) {
        Ok(())
    } else {
        Err(PyValueError::new_err(format!(
            "{name}: expected an aligned array (its elements lie at addresses that are not a \
             multiple of their size); copy it first, e.g. np.require(x, requirements='CA')"
        )))
    }
}

/// A view of `x`, or a `ValueError` naming `name` for a misaligned array
/// ([`check_aligned`]) or one of more than [`MAX_DIMS`] dimensions.
pub fn view<'a, T: Element, D: Dimension>(
    x: &'a PyReadonlyArray<'_, T, D>,
    name: &str,
) -> PyResult<ArrayView<'a, T, D>> {
    check_aligned(x, name)?;
    let ndim = x.ndim();
    if ndim > MAX_DIMS {
        return Err(PyValueError::new_err(format!(
            "{name}: expected at most {MAX_DIMS} dimensions, got {ndim}"
        )));
    }
    Ok(x.as_array())
}
