//! Polar sampling of a channels-last BEV (DESIGN.md §3 polar grid), bilinear, fill 1 outside.
//!
//! Bin `k`'s angle is `θ_k = (k + 0.5)·2π/T`, measured from +y towards +x; radius bin `m`'s
//! radius is `r_m = (m + 0.5)·r_max/R` with `r_max = min(H, W)·g/2`. The sample point
//! `(x, y) = (r sin θ, r cos θ)` is read by bilinear interpolation at the fractional cell index
//! `(x/g + (H−1)/2, y/g + (W−1)/2)`.
//!
//! **Outside the grid.** Each of the four bilinear taps that falls outside the grid reads the
//! fill value 1 and is blended with its ordinary bilinear weight. A tap whose weight is exactly
//! zero therefore contributes nothing (and is never read): a sample exactly on the last row or
//! column returns the border value, not a blend with 1. This is the same rule as BEV padding
//! (`pad.rs`), where only taps with non-zero weight outside the grid trigger the fill.
//!
//! This module also holds the small machinery shared with `pad.rs`: per-axis tap filters,
//! the weighted-rows kernel (`out = constant + Σ wₜ·rowₜ`, channels innermost, vectorised)
//! and the runtime choice between the portable and the AVX2+FMA build of that kernel.

use crate::error::{check_alloc, checked_len};
use crate::roll::PAR_THRESHOLD;
use crate::{Error, Result};
use ndarray::{ArrayD, ArrayViewD, IxDyn};
use rayon::prelude::*;
use std::f64::consts::PI;

/// Geometry of the polar sample points for one `(H, W, T, R, g)`, computed once and reused for
/// every map of a batch and every translation hypothesis.
#[derive(Debug, Clone)]
pub struct PolarGrid {
    /// Map rows H (↔ x).
    pub height: usize,
    /// Map columns W (↔ y).
    pub width: usize,
    /// Angle bins T.
    pub num_angles: usize,
    /// Radius bins R.
    pub num_radii: usize,
    /// Cell size g in metres.
    pub grid_size: f64,
    /// `(sin θ_k, cos θ_k)` of angle bin `k` (T entries).
    angles: Vec<[f64; 2]>,
    /// Radius `r_m` of radius bin `m`, metres (R entries).
    radii: Vec<f64>,
    /// Fractional (row, column) index of the BEV's centre.
    centre: [f64; 2],
    /// Every point's [`PolarGrid::point`] at `k·R + m`, when there are at most
    /// [`POINT_TABLE_MAX`] (a sampler reads each many times); computed on the fly beyond.
    table: Vec<[f64; 2]>,
}

/// The most points a [`PolarGrid`] keeps in a table (16 MiB): a table of every point was built
/// before the output's size was checked, also for an empty output, and grew without bound.
const POINT_TABLE_MAX: usize = 1 << 20;

impl PolarGrid {
    /// Builds the sample geometry. Errors if a size is 0 or `grid_size` is not finite and > 0.
    pub fn new(
        height: usize,
        width: usize,
        num_angles: usize,
        num_radii: usize,
        grid_size: f64,
    ) -> Result<Self> {
        check_grid_size(grid_size)?;
        if height == 0 || width == 0 {
            return Err(Error::shape(
                "bev",
                "(H, W, C) with H, W >= 1",
                (height, width),
            ));
        }
        if num_angles == 0 {
            return Err(Error::value("num_angles", "expected an int >= 1, got 0"));
        }
        if num_radii == 0 {
            return Err(Error::value("num_radii", "expected an int >= 1, got 0"));
        }
        let r_max = height.min(width) as f64 * grid_size / 2.0;
        if !r_max.is_finite() {
            return Err(Error::value(
                "grid_size",
                format!(
                    "expected the polar radius min(H, W)·g/2 to be finite, got g = {grid_size}"
                ),
            ));
        }
        let centre = [(height as f64 - 1.0) / 2.0, (width as f64 - 1.0) / 2.0];
        // T + R numbers, and a table of the T·R points only up to POINT_TABLE_MAX: the output
        // (T·R·C floats, checked by its caller) is the only allocation that grows with T·R
        let len = checked_len("num_angles", &[num_angles, num_radii])?;
        let (mut angles, mut radii) = (Vec::new(), Vec::new());
        let memory = |arg: &'static str, n: usize| Error::Memory {
            arg,
            what: format!("{n} polar bins"),
        };
        angles
            .try_reserve_exact(num_angles)
            .map_err(|_| memory("num_angles", num_angles))?;
        radii
            .try_reserve_exact(num_radii)
            .map_err(|_| memory("num_radii", num_radii))?;
        for k in 0..num_angles {
            let theta = (k as f64 + 0.5) * 2.0 * PI / num_angles as f64;
            let (s, c) = theta.sin_cos();
            angles.push([s, c]);
        }
        for m in 0..num_radii {
            radii.push((m as f64 + 0.5) * r_max / num_radii as f64);
        }
        let mut grid = PolarGrid {
            height,
            width,
            num_angles,
            num_radii,
            grid_size,
            angles,
            radii,
            centre,
            table: Vec::new(),
        };
        if len <= POINT_TABLE_MAX {
            let table = (0..len)
                .map(|n| grid.compute_point(n / num_radii, n % num_radii))
                .collect();
            grid.table = table;
        }
        Ok(grid)
    }

    /// Fractional (row, column) index of sample point (angle bin `k`, radius bin `m`):
    /// `(r_m·sin θ_k / g + (H − 1)/2, r_m·cos θ_k / g + (W − 1)/2)`.
    #[inline]
    pub fn point(&self, k: usize, m: usize) -> [f64; 2] {
        if self.table.is_empty() {
            self.compute_point(k, m)
        } else {
            self.table[k * self.num_radii + m]
        }
    }

    #[inline]
    fn compute_point(&self, k: usize, m: usize) -> [f64; 2] {
        let ([s, c], r) = (self.angles[k], self.radii[m]);
        let (x, y) = (r * s, r * c);
        [
            x / self.grid_size + self.centre[0],
            y / self.grid_size + self.centre[1],
        ]
    }
}

pub(crate) fn check_grid_size(grid_size: f64) -> Result<()> {
    if grid_size.is_finite() && grid_size > 0.0 {
        Ok(())
    } else {
        Err(Error::value(
            "grid_size",
            format!("expected a finite value > 0, got {grid_size}"),
        ))
    }
}

/// Interpolation weights along one axis: up to three consecutive map indices from `start`
/// with weights `w` (a zero weight means "not read"). `covered` is the total weight that reads
/// the map; the remaining `1 − covered` reads the fill value 1.
#[derive(Debug, Clone, Copy)]
pub(crate) struct AxisFilter {
    pub start: i64,
    pub w: [f64; 3],
    pub covered: f64,
}

impl AxisFilter {
    /// Plain linear interpolation at fractional index `p` on an axis of `n` cells, taps outside
    /// reading 1 (weighted).
    #[inline]
    pub fn linear(p: f64, n: usize) -> Self {
        let a0 = p.floor();
        let f = p - a0;
        // Sample points lie within a few cells of the grid; clamping keeps i64 arithmetic safe.
        let a0 = a0.clamp(-2.0, n as f64 + 1.0) as i64;
        let inside = |a: i64| a >= 0 && a < n as i64;
        let (in0, in1) = (inside(a0), inside(a0 + 1));
        let w0 = if in0 { 1.0 - f } else { 0.0 };
        let w1 = if in1 { f } else { 0.0 };
        AxisFilter {
            start: a0,
            w: [w0, w1, 0.0],
            covered: if in0 && in1 { 1.0 } else { w0 + w1 },
        }
    }
}

/// Up to 9 weighted rows of a map plus a constant: one output vector is
/// `constant + Σ wₜ·rowₜ` (accumulated in tap order, so every element is computed the same way
/// whatever the chunking or the thread count).
pub(crate) struct Taps<'a> {
    constant: f32,
    rows: [&'a [f32]; 9],
    weights: [f32; 9],
    len: usize,
}

impl<'a> Taps<'a> {
    /// The taps of the separable filter `rows ⊗ cols` on a (H, W, C) map.
    ///
    /// Every tap with a non-zero weight must lie inside the map (the filters guarantee it).
    #[inline]
    pub fn separable(
        map: &'a [f32],
        w: usize,
        c: usize,
        rows: &AxisFilter,
        cols: &AxisFilter,
    ) -> Self {
        let mut t = Taps {
            constant: (1.0 - rows.covered * cols.covered) as f32,
            rows: [&[]; 9],
            weights: [0.0; 9],
            len: 0,
        };
        for (dr, &wr) in rows.w.iter().enumerate() {
            if wr == 0.0 {
                continue;
            }
            let i = (rows.start + dr as i64) as usize;
            for (ds, &ws) in cols.w.iter().enumerate() {
                let wt = wr * ws;
                if wt == 0.0 {
                    continue;
                }
                let j = (cols.start + ds as i64) as usize;
                let at = (i * w + j) * c;
                t.rows[t.len] = &map[at..at + c];
                t.weights[t.len] = wt as f32;
                t.len += 1;
            }
        }
        t
    }
}

#[inline(always)]
fn madd<const FMA: bool>(a: f32, b: f32, c: f32) -> f32 {
    if FMA {
        a.mul_add(b, c)
    } else {
        a * b + c
    }
}

const LANES: usize = 32;

/// `out[c] = constant + Σ wₜ·rowₜ[c]`, in chunks of 32 channels accumulated in registers.
///
/// The result is clamped to float32's finite range: the blend is a convex combination of
/// finite values (the map's and the fill 1), so it is finite, but the weights rounded to f32
/// can sum to 1 + 1 ulp, and at ±`f32::MAX` the f32 sum then overflowed to ±inf (the true value
/// lies within an ulp or two of ±`f32::MAX`, which the clamp returns). Free: two vector
/// instructions on registers per chunk (benchmarked, BENCHMARKS.md "Spatial kernels at
/// float32's maximum").
#[inline(always)]
pub(crate) fn blend<const FMA: bool>(out: &mut [f32], taps: &Taps<'_>) {
    let rows = &taps.rows[..taps.len];
    let weights = &taps.weights[..taps.len];
    let mut chunks = out.chunks_exact_mut(LANES);
    let mut c0 = 0;
    for dst in &mut chunks {
        let mut acc = [taps.constant; LANES];
        for (row, &w) in rows.iter().zip(weights) {
            let src = &row[c0..c0 + LANES];
            for (a, &s) in acc.iter_mut().zip(src) {
                *a = madd::<FMA>(w, s, *a);
            }
        }
        for (d, &a) in dst.iter_mut().zip(&acc) {
            *d = finite(a);
        }
        c0 += LANES;
    }
    for (j, d) in chunks.into_remainder().iter_mut().enumerate() {
        let mut a = taps.constant;
        for (row, &w) in rows.iter().zip(weights) {
            a = madd::<FMA>(w, row[c0 + j], a);
        }
        *d = finite(a);
    }
}

/// `a` clamped to [−`f32::MAX`, `f32::MAX`] (written with comparisons that compile to one
/// vector min and max; `a` is never NaN here).
#[inline(always)]
fn finite(a: f32) -> f32 {
    let a = if a > f32::MAX { f32::MAX } else { a };
    if a < -f32::MAX {
        -f32::MAX
    } else {
        a
    }
}

/// Whether large outputs ask for transparent huge pages: yes unless the environment variable
/// `VVLOC_MADVISE_HUGEPAGE` is `0` when the first output is made (read once, as numpy reads
/// `NUMPY_MADVISE_HUGEPAGE`). Huge pages make the 600 MB `pad_polar` output about 3× faster
/// (50 against 140 ms), but where the system compacts memory on a huge-page fault (the usual
/// `defrag` setting, `madvise`) a call now and then waits for it (0.5-1.3 s, 2026-12-05):
/// turning them off trades that tail for the slower, steady median.
#[cfg(target_os = "linux")]
fn huge_pages_wanted() -> bool {
    static WANTED: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *WANTED
        .get_or_init(|| std::env::var("VVLOC_MADVISE_HUGEPAGE").map_or(true, |v| v.trim() != "0"))
}

/// A zeroed output buffer of `len` floats. Large buffers ask Linux for transparent huge pages
/// ([`huge_pages_wanted`]): the kernels write every element exactly once, so with 4 KiB pages
/// first-touch page faults would cost as much as the computation (a 600 MB output is 150 000
/// faults). `arg` names the argument that sets its size `dims`: an error instead of an abort
/// when the buffer cannot exist.
pub(crate) fn output_buffer(arg: &'static str, dims: &[usize]) -> Result<Vec<f32>> {
    let len = checked_len(arg, dims)?;
    check_alloc::<f32>(arg, len)?;
    let buf = vec![0.0f32; len];
    #[cfg(target_os = "linux")]
    {
        const HUGE: usize = 2 << 20;
        let start = buf.as_ptr() as usize;
        let end = start + len * std::mem::size_of::<f32>();
        let (lo, hi) = (start.next_multiple_of(HUGE), end / HUGE * HUGE);
        if hi > lo && huge_pages_wanted() {
            // SAFETY: [lo, hi) lies inside the allocation owned by `buf`; MADV_HUGEPAGE is only
            // a hint about how to back that range, it changes neither its contents nor its
            // validity. A failure (e.g. THP disabled) is harmless and ignored.
            unsafe {
                libc::madvise(lo as *mut libc::c_void, hi - lo, libc::MADV_HUGEPAGE);
            }
        }
    }
    Ok(buf)
}

/// Whether the AVX2+FMA build of the inner kernels can run on this CPU.
#[inline]
pub(crate) fn has_avx2_fma() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// Polar sampling of one angle bin `k` of one map: writes the (R, C) block `out`.
#[inline(always)]
fn polar_row<const FMA: bool>(map: &[f32], c: usize, grid: &PolarGrid, k: usize, out: &mut [f32]) {
    for (m, dst) in out.chunks_exact_mut(c).enumerate() {
        let [p, q] = grid.point(k, m);
        let rows = AxisFilter::linear(p, grid.height);
        let cols = AxisFilter::linear(q, grid.width);
        blend::<FMA>(dst, &Taps::separable(map, grid.width, c, &rows, &cols));
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn polar_row_avx2(map: &[f32], c: usize, grid: &PolarGrid, k: usize, out: &mut [f32]) {
    polar_row::<true>(map, c, grid, k, out)
}

fn polar_row_dispatch(
    fma: bool,
    map: &[f32],
    c: usize,
    grid: &PolarGrid,
    k: usize,
    out: &mut [f32],
) {
    #[cfg(target_arch = "x86_64")]
    if fma {
        // SAFETY: `fma` is true only when AVX2 and FMA were detected at runtime on this CPU.
        return unsafe { polar_row_avx2(map, c, grid, k, out) };
    }
    let _ = fma;
    polar_row::<false>(map, c, grid, k, out)
}

/// Polar sampling of a (H, W, C) or (B, H, W, C) BEV to (T, R, C) or (B, T, R, C).
///
/// `num_angles` = T ≥ 1, `num_radii` = R ≥ 1, `grid_size` = g > 0 metres. Parallel over
/// (map, angle bin) rows; results do not depend on the thread count.
pub fn polar_sample(
    bev: ArrayViewD<'_, f32>,
    num_angles: usize,
    num_radii: usize,
    grid_size: f64,
) -> Result<ArrayD<f32>> {
    let shape = bev.shape().to_vec();
    let (batch, dims) = match shape.as_slice() {
        [h, w, c] => (None, [*h, *w, *c]),
        [b, h, w, c] => (Some(*b), [*h, *w, *c]),
        _ => return Err(Error::shape("bev", "(H, W, C) or (B, H, W, C)", &shape)),
    };
    let [h, w, c] = dims;
    let grid = PolarGrid::new(h, w, num_angles, num_radii, grid_size)?;
    if !bev.is_standard_layout() {
        check_alloc::<f32>("bev", bev.len())?; // the copy below (a broadcast view may be vast)
    }
    let bev = bev.as_standard_layout();
    let src = bev
        .as_slice()
        .ok_or_else(|| Error::value("bev", "could not view the array as contiguous memory"))?;
    let b = batch.unwrap_or(1);
    let (t, r) = (num_angles, num_radii);
    let mut out = output_buffer("num_angles", &[b, t, r, c])?;
    if c > 0 && b > 0 {
        let fma = has_avx2_fma();
        let map_len = h * w * c;
        let row = |(idx, dst): (usize, &mut [f32])| {
            let (bi, k) = (idx / t, idx % t);
            polar_row_dispatch(
                fma,
                &src[bi * map_len..(bi + 1) * map_len],
                c,
                &grid,
                k,
                dst,
            );
        };
        if out.len() < PAR_THRESHOLD {
            out.chunks_mut(r * c).enumerate().for_each(row);
        } else {
            out.par_chunks_mut(r * c).enumerate().for_each(row);
        }
    }
    let out_shape = match batch {
        None => vec![t, r, c],
        Some(b) => vec![b, t, r, c],
    };
    ArrayD::from_shape_vec(IxDyn(&out_shape), out).map_err(|e| Error::value("bev", e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::{Array, Array3};

    fn field(h: usize, w: usize, c: usize) -> Array3<f32> {
        Array::from_shape_fn((h, w, c), |(i, j, k)| {
            ((i as f32 * 0.37 + j as f32 * 1.3 + k as f32 * 0.71).sin()) * 2.0
        })
    }

    #[test]
    fn vast_inputs_are_errors_not_aborts() {
        // a polar radius that overflows, and a broadcast view of 2^40 elements to copy
        let bev = field(8, 8, 1);
        let err = polar_sample(bev.view().into_dyn(), 4, 2, 1e308).unwrap_err();
        assert!(
            matches!(
                err,
                Error::Value {
                    arg: "grid_size",
                    ..
                }
            ),
            "{err:?}"
        );
        let one = Array::from_elem((1, 1, 1, 1), 1.0f32);
        let vast = one.broadcast((1 << 20, 1 << 10, 1 << 10, 1)).unwrap();
        let err = polar_sample(vast.into_dyn(), 4, 2, 0.3).unwrap_err();
        assert!(matches!(err, Error::Memory { arg: "bev", .. }), "{err:?}");
    }

    #[test]
    fn finite_maps_at_float32s_maximum_stay_finite() {
        // the f32 weights of a blend can sum to 1 + 1 ulp: at ±f32::MAX the sum overflowed
        let tr = ndarray::arr2(&[[0.1, 0.07], [0.33, -0.21], [0.0, 0.0]]);
        for v in [f32::MAX, -f32::MAX] {
            for (h, w, c) in [(2, 2, 1), (6, 5, 3), (7, 9, 40)] {
                let map = Array3::<f32>::from_elem((h, w, c), v);
                let outs = [
                    polar_sample(map.view().into_dyn(), 4, 1, 0.3).unwrap(),
                    polar_sample(map.view().into_dyn(), 7, 3, 0.3).unwrap(),
                    crate::pad::bev_pad(map.view(), tr.view(), 0.3)
                        .unwrap()
                        .into_dyn(),
                    crate::pad::pad_polar(map.view(), tr.view(), 7, 3, 0.3)
                        .unwrap()
                        .into_dyn(),
                ];
                for out in outs {
                    assert!(out.iter().all(|x| x.is_finite()), "{v} {h} {w} {c}");
                }
            }
        }
    }

    #[test]
    fn geometry_follows_the_convention() {
        // θ_0 = π/T measured from +y towards +x; with T = 4, θ_0 = 45°.
        let g = PolarGrid::new(10, 10, 4, 5, 0.5).unwrap();
        let r0 = 0.5 * (10.0 * 0.5 / 2.0) / 5.0;
        let [p, q] = g.point(0, 0);
        let d = r0 * (PI / 4.0).sin() / 0.5;
        assert!((p - (4.5 + d)).abs() < 1e-12 && (q - (4.5 + d)).abs() < 1e-12);
        // θ_1 = 135°: x > 0, y < 0.
        let [p, q] = g.point(1, 0);
        assert!(p > 4.5 && q < 4.5);
    }

    #[test]
    fn constant_map_stays_constant_inside_and_blends_with_one_outside() {
        let map = Array3::<f32>::from_elem((9, 12, 5), 3.0);
        let out = polar_sample(map.view().into_dyn(), 7, 6, 0.2).unwrap();
        assert_eq!(out.shape(), &[7, 6, 5]);
        for v in out.iter() {
            // Every point reads 3 or a blend of 3 with 1.
            assert!((1.0..=3.0 + 1e-6).contains(v));
        }
        // The innermost ring is well inside the grid.
        for k in 0..7 {
            assert!((out[[k, 0, 0]] - 3.0).abs() < 1e-6);
        }
    }

    #[test]
    fn matches_a_direct_bilinear_evaluation() {
        let map = field(8, 11, 3);
        let grid = PolarGrid::new(8, 11, 5, 4, 0.3).unwrap();
        let out = polar_sample(map.view().into_dyn(), 5, 4, 0.3).unwrap();
        let read = |i: i64, j: i64, ch: usize| -> f64 {
            if i < 0 || j < 0 || i >= 8 || j >= 11 {
                1.0
            } else {
                map[[i as usize, j as usize, ch]] as f64
            }
        };
        for k in 0..5 {
            for m in 0..4 {
                let [p, q] = grid.point(k, m);
                let (i0, j0) = (p.floor(), q.floor());
                let (fi, fj) = (p - i0, q - j0);
                let (i0, j0) = (i0 as i64, j0 as i64);
                for ch in 0..3 {
                    let want = (1.0 - fi) * (1.0 - fj) * read(i0, j0, ch)
                        + (1.0 - fi) * fj * read(i0, j0 + 1, ch)
                        + fi * (1.0 - fj) * read(i0 + 1, j0, ch)
                        + fi * fj * read(i0 + 1, j0 + 1, ch);
                    assert!((out[[k, m, ch]] as f64 - want).abs() < 1e-5);
                }
            }
        }
    }

    #[test]
    fn batch_equals_single_maps_and_thread_count_is_irrelevant() {
        let a = field(20, 17, 40);
        let b = a.mapv(|v| v * -0.5 + 0.25);
        let stacked = ndarray::stack(ndarray::Axis(0), &[a.view(), b.view()]).unwrap();
        let run = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| polar_sample(stacked.view().into_dyn(), 33, 9, 0.4).unwrap())
        };
        let one = run(1);
        assert_eq!(one, run(2));
        let sa = polar_sample(a.view().into_dyn(), 33, 9, 0.4).unwrap();
        assert_eq!(one.index_axis(ndarray::Axis(0), 0), sa);
    }

    #[test]
    fn rejects_bad_arguments() {
        let map = field(4, 4, 2);
        let v = map.view().into_dyn();
        assert!(matches!(
            polar_sample(v.clone(), 0, 3, 0.3),
            Err(Error::Value {
                arg: "num_angles",
                ..
            })
        ));
        assert!(matches!(
            polar_sample(v.clone(), 3, 0, 0.3),
            Err(Error::Value {
                arg: "num_radii",
                ..
            })
        ));
        assert!(matches!(
            polar_sample(v.clone(), 3, 3, -1.0),
            Err(Error::Value {
                arg: "grid_size",
                ..
            })
        ));
        let flat = Array::<f32, _>::zeros((4, 4));
        assert!(matches!(
            polar_sample(flat.view().into_dyn(), 3, 3, 0.3),
            Err(Error::Shape { arg: "bev", .. })
        ));
        let empty = Array::<f32, _>::zeros((0, 4, 2));
        assert!(polar_sample(empty.view().into_dyn(), 3, 3, 0.3).is_err());
    }
}
