//! vvloc-core: the pure-Rust kernels of vvloc.
//!
//! Conventions (frames, BEV indexing, polar angles, roll, padding, pose signs) are those of
//! `DESIGN.md` §3 and are binding. Every kernel here is a plain function over ndarray views or
//! slices; parallel kernels use rayon over independent outer items (pairs, hypotheses,
//! queries) and keep inner sums sequential, so results do not depend on the thread count.
//! Callers choose the thread pool (the Python bindings run kernels inside vvloc's own pool).
//! Nothing here knows about Python.

pub mod error;

pub mod pad;
pub mod polar;
pub mod roll;

pub mod cost;
pub mod search;

pub mod retrieval;

pub mod pose;

pub use error::{Error, Result};
