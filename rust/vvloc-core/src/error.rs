//! The one error type of the core crate. The Python bindings map it to `ValueError`/`TypeError`.

/// Errors raised by vvloc-core on invalid input. Kernels never panic on user input.
#[derive(Debug, thiserror::Error, Clone, PartialEq)]
pub enum Error {
    /// An argument has the wrong shape; `arg` names it, `expected` says what was required.
    #[error("{arg}: expected shape {expected}, got {got}")]
    Shape {
        arg: &'static str,
        expected: String,
        got: String,
    },
    /// An argument has an invalid value (non-finite, out of range, inconsistent).
    #[error("{arg}: {msg}")]
    Value { arg: &'static str, msg: String },
    /// A stored file (index, map) is malformed, truncated or from another version.
    #[error("{0}")]
    Format(String),
    /// An I/O failure, with the path it concerns.
    #[error("{path}: {msg}")]
    Io { path: String, msg: String },
    /// A buffer the input asks for is larger than memory (or than `usize`); `arg` names the
    /// argument that sets its size. The bindings raise `MemoryError`.
    #[error("{arg}: the result needs {what}, more than this machine can allocate")]
    Memory { arg: &'static str, what: String },
}

/// Result alias of the core crate.
pub type Result<T> = std::result::Result<T, Error>;

impl Error {
    /// Convenience constructor for [`Error::Value`].
    pub fn value(arg: &'static str, msg: impl Into<String>) -> Self {
        Error::Value {
            arg,
            msg: msg.into(),
        }
    }

    /// Convenience constructor for [`Error::Shape`].
    pub fn shape(
        arg: &'static str,
        expected: impl Into<String>,
        got: impl std::fmt::Debug,
    ) -> Self {
        Error::Shape {
            arg,
            expected: expected.into(),
            got: format!("{got:?}"),
        }
    }
}

/// The largest element of an array the kernels hand out (`f64`, `i64`): shapes are bounded
/// for it.
const MAX_ITEM_BYTES: usize = 8;

/// The element count of an array of shape `dims`, or [`Error::Memory`] naming `arg` when the
/// array could not exist (sizes are never computed with wrapping arithmetic). As ndarray and
/// numpy require, the product of the non-zero axis lengths, in bytes, must fit `isize`, even
/// when another axis is 0: a (0, 2^60) result is refused here, not left to crash numpy.
pub fn checked_len(arg: &'static str, dims: &[usize]) -> Result<usize> {
    let too_big = || Error::Memory {
        arg,
        what: format!("an array of shape {dims:?}"),
    };
    let nonzero = dims
        .iter()
        .filter(|&&d| d != 0)
        .try_fold(1usize, |acc, &d| acc.checked_mul(d))
        .ok_or_else(too_big)?;
    if nonzero > isize::MAX as usize / MAX_ITEM_BYTES {
        return Err(too_big());
    }
    Ok(if dims.contains(&0) { 0 } else { nonzero })
}

/// Checks that a buffer of `len` elements of `T` can be allocated, so that the allocation that
/// follows does not abort the process: [`Error::Memory`] naming `arg` otherwise. The probe
/// reserves the memory and frees it at once (address space only: no page is touched), which
/// keeps the zeroed allocation that follows lazy.
pub fn check_alloc<T>(arg: &'static str, len: usize) -> Result<()> {
    try_with_capacity::<T>(arg, len).map(drop)
}

/// An empty vector with room for exactly `len` elements of `T`, or [`Error::Memory`] naming
/// `arg` when they cannot be allocated (`Vec::with_capacity` would abort the process).
pub fn try_with_capacity<T>(arg: &'static str, len: usize) -> Result<Vec<T>> {
    let mut v: Vec<T> = Vec::new();
    v.try_reserve_exact(len).map_err(|_| Error::Memory {
        arg,
        what: format!(
            "{len} elements of {} bytes",
            std::mem::size_of::<T>().max(1)
        ),
    })?;
    Ok(v)
}

/// The items of `iter` in a vector allocated fallibly for its exact length ([`Error::Memory`]
/// naming `arg` instead of the abort of `collect`).
pub fn try_collect<T>(arg: &'static str, iter: impl ExactSizeIterator<Item = T>) -> Result<Vec<T>> {
    let mut v = try_with_capacity(arg, iter.len())?;
    v.extend(iter);
    Ok(v)
}

/// A `vec![value; len]` that returns [`Error::Memory`] naming `arg` instead of aborting.
pub fn try_filled<T: Clone>(arg: &'static str, len: usize, value: T) -> Result<Vec<T>> {
    check_alloc::<T>(arg, len)?;
    Ok(vec![value; len])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_that_overflow_or_exceed_memory_are_errors_not_aborts() {
        assert_eq!(checked_len("x", &[3, 4, 5]), Ok(60));
        assert_eq!(checked_len("x", &[]), Ok(1));
        assert_eq!(checked_len("x", &[3, 0, 5]), Ok(0));
        // empty, yet no array can have these axes (numpy bounds the non-zero ones)
        for dims in [[0, 1 << 60], [0, usize::MAX], [1 << 61, 0]] {
            assert!(matches!(
                checked_len("x", &dims),
                Err(Error::Memory { arg: "x", .. })
            ));
        }
        assert_eq!(checked_len("x", &[0, 1 << 40]), Ok(0));
        assert!(matches!(
            checked_len("x", &[1 << 32, 1 << 32]),
            Err(Error::Memory { arg: "x", .. })
        ));
        assert!(check_alloc::<f32>("x", 1 << 10).is_ok());
        assert!(matches!(
            check_alloc::<f32>("x", usize::MAX / 2),
            Err(Error::Memory { arg: "x", .. })
        ));
        assert!(try_filled("x", usize::MAX / 8, 0.0f64).is_err());
        assert_eq!(try_filled("x", 3, 1u8).unwrap(), vec![1, 1, 1]);
        assert!(matches!(
            try_with_capacity::<u64>("y", usize::MAX / 4),
            Err(Error::Memory { arg: "y", .. })
        ));
        assert!(try_with_capacity::<u64>("y", 5).unwrap().capacity() >= 5);
        assert_eq!(
            try_collect("x", (0..4).map(|v| v * 2)).unwrap(),
            vec![0, 2, 4, 6]
        );
        assert!(matches!(
            try_collect("z", (0..usize::MAX / 4).map(|_| 0u64)),
            Err(Error::Memory { arg: "z", .. })
        ));
    }
}
