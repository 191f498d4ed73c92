//! Interpolated circular roll (DESIGN.md §3): `roll(D, s)[i] = D[(i - s) mod n]`, linear
//! interpolation between the two neighbouring integer rolls for real `s`.
//!
//! For real `s` with `k = ⌊s⌋`, `w = s − k`:
//! `ρ(D, s) = (1 − w)·roll(D, k) + w·roll(D, k + 1)`, which is continuous in `s` and equals
//! `torch.roll` exactly at integers.

use crate::{Error, Result};
use ndarray::{ArrayD, ArrayViewD};
use rayon::prelude::*;

/// Output elements below which the spatial kernels run sequentially (no rayon overhead).
pub(crate) const PAR_THRESHOLD: usize = 1 << 15;

/// Whether [`roll_interp`] of an array of `len` elements runs without rayon, on the calling
/// thread (callers may then skip the hand-over to a thread pool).
pub fn runs_sequentially(len: usize) -> bool {
    len < PAR_THRESHOLD
}

/// Splits a real shift into `(⌊s⌋ mod n, s − ⌊s⌋)`, exactly for any finite `s`.
///
/// `n` must be ≥ 1. The modulus is taken in f64, which is exact for integral values.
pub fn split_shift(shift: f64, n: usize) -> (usize, f64) {
    let k = shift.floor();
    let w = shift - k;
    let k_mod = k.rem_euclid(n as f64) as usize;
    (k_mod % n, w)
}

/// Interpolated roll of `x` by `shift` (elements, real) along `axis`.
///
/// Returns an array of the same shape. `shift` must be finite and `axis < x.ndim()`.
/// Non-contiguous inputs are accepted (copied to standard layout first).
pub fn roll_interp(x: ArrayViewD<'_, f32>, shift: f64, axis: usize) -> Result<ArrayD<f32>> {
    if !shift.is_finite() {
        return Err(Error::value(
            "shift",
            format!("expected a finite value, got {shift}"),
        ));
    }
    let ndim = x.ndim();
    if axis >= ndim {
        return Err(Error::value(
            "axis",
            format!("expected 0 <= axis < {ndim}, got {axis}"),
        ));
    }
    let shape = x.shape().to_vec();
    let n = shape[axis];
    let inner: usize = shape[axis + 1..].iter().product();
    if !x.is_standard_layout() {
        crate::error::check_alloc::<f32>("x", x.len())?; // a broadcast view may be vast
    }
    let x = x.as_standard_layout();
    let src = x
        .as_slice()
        .ok_or_else(|| Error::value("x", "could not view the array as contiguous memory"))?;
    let mut out = crate::error::try_filled("x", src.len(), 0.0f32)?;
    if n > 0 && inner > 0 {
        let (k, w) = split_shift(shift, n);
        let (w0, w1) = ((1.0 - w) as f32, w as f32);
        // Output row r = (outer o, position i) reads rows (i − k) mod n and (i − k − 1) mod n.
        let row = |(r, dst): (usize, &mut [f32])| {
            let (o, i) = (r / n, r % n);
            let i0 = (i + n - k) % n;
            let i1 = (i0 + n - 1) % n;
            let a = &src[(o * n + i0) * inner..(o * n + i0 + 1) * inner];
            let b = &src[(o * n + i1) * inner..(o * n + i1 + 1) * inner];
            for ((d, &a), &b) in dst.iter_mut().zip(a).zip(b) {
                *d = w0 * a + w1 * b;
            }
        };
        if runs_sequentially(out.len()) {
            out.chunks_mut(inner).enumerate().for_each(row);
        } else {
            out.par_chunks_mut(inner)
                .with_min_len((4096 / inner).max(1))
                .enumerate()
                .for_each(row);
        }
    }
    ArrayD::from_shape_vec(shape, out).map_err(|e| Error::value("x", e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::{Array, IxDyn};

    fn ramp(shape: &[usize]) -> ArrayD<f32> {
        let n: usize = shape.iter().product();
        Array::from_shape_vec(IxDyn(shape), (0..n).map(|v| v as f32).collect()).unwrap()
    }

    #[test]
    fn a_vast_broadcast_view_is_an_error_not_an_abort() {
        let one = ndarray::Array1::from_elem(1, 1.0f32);
        let vast = one.broadcast(1usize << 40).unwrap();
        let err = roll_interp(vast.into_dyn(), 1.0, 0).unwrap_err();
        assert!(matches!(err, Error::Memory { arg: "x", .. }), "{err:?}");
    }

    #[test]
    fn integer_shift_is_torch_roll() {
        let x = ramp(&[5]);
        let y = roll_interp(x.view(), 2.0, 0).unwrap();
        assert_eq!(y.as_slice().unwrap(), &[3.0, 4.0, 0.0, 1.0, 2.0]);
        let y = roll_interp(x.view(), -1.0, 0).unwrap();
        assert_eq!(y.as_slice().unwrap(), &[1.0, 2.0, 3.0, 4.0, 0.0]);
        let y = roll_interp(x.view(), 7.0, 0).unwrap();
        assert_eq!(y.as_slice().unwrap(), &[3.0, 4.0, 0.0, 1.0, 2.0]);
    }

    #[test]
    fn fractional_shift_interpolates_and_is_continuous() {
        let x = ramp(&[4]);
        let y = roll_interp(x.view(), 0.25, 0).unwrap();
        // 0.75·x[i] + 0.25·x[i−1]
        let want = [0.75 * 0.0 + 0.25 * 3.0, 0.75, 1.75, 2.75];
        for (a, b) in y.iter().zip(want) {
            assert!((a - b).abs() < 1e-6);
        }
        let below = roll_interp(x.view(), 1.0 - 1e-9, 0).unwrap();
        let at = roll_interp(x.view(), 1.0, 0).unwrap();
        for (a, b) in below.iter().zip(at.iter()) {
            assert!((a - b).abs() < 1e-6);
        }
    }

    #[test]
    fn rolls_along_any_axis() {
        let x = ramp(&[2, 3, 4]);
        let y = roll_interp(x.view(), 1.0, 1).unwrap();
        for o in 0..2 {
            for i in 0..3 {
                for c in 0..4 {
                    assert_eq!(y[[o, i, c]], x[[o, (i + 2) % 3, c]]);
                }
            }
        }
        let y = roll_interp(x.view(), -1.0, 2).unwrap();
        assert_eq!(y[[1, 2, 3]], x[[1, 2, 0]]);
        // non-contiguous input
        let t = x.view().reversed_axes();
        let y = roll_interp(t.view(), 1.0, 0).unwrap();
        assert_eq!(y[[0, 0, 0]], t[[3, 0, 0]]);
    }

    #[test]
    fn huge_shift_and_parallel_path() {
        let x = ramp(&[7, 8000]);
        let a = roll_interp(x.view(), 3.5 + 7.0 * 1e12, 0).unwrap();
        let b = roll_interp(x.view(), 3.5, 0).unwrap();
        assert_eq!(a, b);
    }

    #[test]
    fn rejects_bad_arguments() {
        let x = ramp(&[3, 2]);
        assert!(matches!(
            roll_interp(x.view(), 1.0, 2),
            Err(Error::Value { arg: "axis", .. })
        ));
        assert!(matches!(
            roll_interp(x.view(), f64::NAN, 0),
            Err(Error::Value { arg: "shift", .. })
        ));
        let e = ramp(&[0, 2]);
        assert_eq!(roll_interp(e.view(), 1.5, 0).unwrap().len(), 0);
    }
}
