//! Matching cost, integer-shift yaw cost curves and the exact continuous yaw minimum.
//!
//! Conventions (DESIGN.md §3): for local-view descriptors `Ds`, `Dt` of shape (T, C) the yaw cost
//! curve is `c(s) = δ(ρ(Ds, s), Dt)` with `δ(A, B) = (1/T)·Σᵢ ‖Aᵢ − Bᵢ‖₂` and the interpolated
//! roll `ρ(D, k + w)ᵢ = (1 − w)·D[i − k] + w·D[i − k − 1]` (indices mod T). The estimated shift is
//! the global continuous minimiser `s* ∈ [0, T)`, the yaw `φ̂ = 2π·s*/T` wrapped to (−π, π].
//!
//! # Method (exact, near the matrix-multiply floor)
//! Per pair (a pair whose values all lie within ±2⁻³² is first multiplied by a power of two, which
//! is exact, and its costs scaled back: below ~1e-19 the f32 products and tables below would
//! leave float32's normal range):
//! 1. one Gram product `G = Ds·Dtᵀ` (f32, AVX-512 or AVX2/FMA when the CPU has them, a portable
//!    fallback otherwise); squared row distances `d²[j][i] = ‖Ds_j‖² + ‖Dt_i‖² − 2·G[j][i]`
//!    (f64, row by row) stored in *diagonal layout* `dg[k][i] = d²[(i − k) mod T][i]`, so that
//!    shift `k` reads one contiguous row (rows padded with zeros to whole vectors). Entries with
//!    `d² ≤ 1e-2·(‖Ds_j‖² + ‖Dt_i‖²)` (where fp32 cancellation would hurt) are recomputed
//!    directly in f64;
//! 2. integer-shift costs `c(k) = (1/T)·Σᵢ sqrt(dg[k][i])`;
//! 3. on `[k, k+1]`, with `a = dg[k][i]`, `b = dg[k+1][i]` and `e = ‖Ds_j − Ds_{j−1}‖²`
//!    (`j = i − k`), the squared row distance is `(1 − w)·a + w·b − w(1 − w)·e`: any fractional
//!    shift costs O(T). Each `c` restricted to an interval is convex (a sum of norms of affine
//!    functions). Intervals are pruned with a Lipschitz bound and then with the tangents at both
//!    ends (end slopes from the same entries); the survivors are minimised by safeguarded
//!    Newton/bisection, which stops once a Newton step no longer moves the shift (1e-14 bins);
//! 4. the winner and every near-tie (within a small margin of the approximate best) are re-scored
//!    from rows recomputed directly in f64 and re-minimised, so the reported shift and cost do
//!    not suffer from fp32 cancellation;
//! 5. a pair the f32 stage cannot resolve takes the exact path instead (every integer-shift row
//!    in f64, every interval the Lipschitz bound leaves minimised on them): rows whose squared
//!    norms span more than 1024 (`WIDE_ROWS`, checked first: the f32 slopes and bounds sum
//!    terms of very different sizes) or an approximate best within 1 % (`NEAR_PERFECT`) of the
//!    rms row norm (checked after step 3: the f32 values cancel near a perfect match, and a
//!    second basin within their error could win).

// Index loops over fixed lane counts are deliberate: they are what the compiler vectorises.
#![allow(clippy::needless_range_loop)]

use crate::error::{check_alloc, checked_len, try_filled, try_with_capacity, Error, Result};
use ndarray::{Array2, ArrayView3};
use rayon::prelude::*;
use std::borrow::Cow;
use std::f64::consts::PI;

/// Checked pair batch: (P, T, C, src data, tgt data, whether tgt is shared by all pairs).
type Pairs<'a> = (usize, usize, usize, Cow<'a, [f32]>, Cow<'a, [f32]>, bool);

/// Entries whose Gram-derived squared distance is below this fraction of `‖u‖² + ‖z‖²` are
/// recomputed directly in f64 (fp32 cancellation would make their square roots inaccurate).
const NEAR_ZERO_REL: f64 = 1e-2;
/// Margin, relative to the pair's rms row norm plus the best cost, within which the approximate
/// stage keeps intervals and polishes candidates exactly. The f32 tables' errors grow with the
/// rows' sizes, not with the cost: a margin of the cost alone (it was `1 + cost`) let a pair
/// whose rows share a large common part (a constant channel of 3e7: best/rms ≈ 0.02) prune its
/// best interval, and made the answer change when a pair was scaled by a power of two.
const POLISH_MARGIN: f64 = 1e-5;
/// A pair whose largest nonzero row (of either descriptor) exceeds its smallest by more than
/// this in squared norm (32× in norm) takes the exact path ([`estimate_exact`]): the first
/// pass's f32 slopes and bounds sum terms of very different sizes there, and erred past the
/// pruning margin for rows spanning 10³ and more (a review's fuzz, 2026-12-07). Learned
/// descriptors have unit rows (the interactor's L2 normalisation) and never take it.
const WIDE_ROWS: f64 = 1024.0;
/// A pair whose approximate best cost is at most this fraction of its rms row norm takes the
/// exact path too: near a perfect match the interpolated rows cancel, and the f32 tables' values
/// there err by ~5e-4 of the row norm, enough to prefer another basin within that error.
const NEAR_PERFECT: f64 = 1e-2;

/// The yaw estimate of one (source, target) pair.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct YawEstimate {
    /// Continuous minimiser s* ∈ [0, T) of the cost curve, in bins.
    pub shift: f64,
    /// φ̂ = 2π·s*/T wrapped to (−π, π], radians.
    pub yaw: f64,
    /// The matching cost c(s*).
    pub cost: f64,
}

/// Candidates ordered by matching cost, with their per-candidate estimates.
#[derive(Debug, Clone, PartialEq)]
pub struct Reranked {
    /// Candidate indices sorted by cost ascending, ties broken by lower index.
    pub order: Vec<usize>,
    /// Estimates in input order (`estimates[k]` belongs to candidate `k`).
    pub estimates: Vec<YawEstimate>,
}

// --------------------------------------------------------------------------------------------
// Input checks
// --------------------------------------------------------------------------------------------

fn check_finite(x: &[f32], arg: &'static str) -> Result<()> {
    if x.iter().all(|v| v.is_finite()) {
        Ok(())
    } else {
        Err(Error::value(arg, "contains non-finite values (NaN or inf)"))
    }
}

/// The largest squared norm of a descriptor row that the f32 Gram products of the yaw and
/// retrieval kernels handle: with ‖a‖², ‖b‖² ≤ 1e37, every partial dot product and every squared
/// distance stays below 4e37 < f32::MAX (3.4e38), so nothing overflows to inf (or inf − inf to
/// NaN).
pub const MAX_ROW_SQNORM: f64 = 1e37;

/// Finite values whose rows of `c` have squared norms ≤ [`MAX_ROW_SQNORM`]. The usual case costs
/// one comparison per value (every |v| ≤ √(MAX_ROW_SQNORM / c) bounds every row); only when
/// that fails are the rows' norms summed (in f64).
pub(crate) fn check_rows(x: &[f32], c: usize, arg: &'static str) -> Result<()> {
    let bound = (MAX_ROW_SQNORM / c.max(1) as f64).sqrt() as f32;
    if Isa::detect().all_within(x, bound) {
        return Ok(()); // false for NaN and inf: they are caught below
    }
    let ok = x.chunks(c.max(1)).all(|row| {
        let n: f64 = row.iter().map(|&v| v as f64 * v as f64).sum();
        n <= MAX_ROW_SQNORM // false for NaN and inf
    });
    if ok {
        return Ok(());
    }
    check_finite(x, arg)?;
    Err(Error::value(
        arg,
        format!(
            "values too large: a descriptor row's squared norm exceeds {MAX_ROW_SQNORM:e}, \
             beyond what float32 arithmetic holds (scale the descriptors down)"
        ),
    ))
}

/// Checks a batch of pairs; `tgt` may hold one matrix shared by all pairs. Returns (P, T, C)
/// and C-contiguous data of both (P = 0, an empty batch, passes: its results are empty).
/// `tables`: how many (T, S) f32 tables (or their equivalent in bytes) one pair's computation
/// holds at once, to probe their allocation; `min_bins`: the fewest angle bins T taken (2 for
/// cost curves; 3 for a yaw estimate, [`MIN_YAW_BINS`]).
fn check_pairs<'a>(
    src: &'a ArrayView3<'a, f32>,
    tgt: &'a ArrayView3<'a, f32>,
    tables: usize,
    min_bins: usize,
) -> Result<Pairs<'a>> {
    let (p, t, c) = src.dim();
    let (pt, tt, ct) = tgt.dim();
    if t < min_bins.max(2) {
        let why = if min_bins > 2 {
            " (with 2 bins, rolling by s and by -s give one curve: a yaw's sign is undetermined)"
        } else {
            ""
        };
        return Err(Error::shape(
            "src",
            format!("(P, T, C) with T >= {}{why}", min_bins.max(2)),
            src.shape(),
        ));
    }
    if c == 0 {
        return Err(Error::shape("src", "(P, T, C) with C >= 1", src.shape()));
    }
    if (pt != p && pt != 1) || tt != t || ct != c {
        return Err(Error::shape(
            "tgt",
            if p == 1 {
                format!("(1, {t}, {c}) to match src")
            } else {
                format!("({p}, {t}, {c}) or (1, {t}, {c}) to match src")
            },
            tgt.shape(),
        ));
    }
    let s = contiguous(src, "src")?;
    let g = contiguous(tgt, "tgt")?;
    check_rows(&s, c, "src")?;
    check_rows(&g, c, "tgt")?;
    // each pair holds up to `tables` (T, S) tables at once, and a tiny pair its rescaled copy
    // (2·T·C), and one pair per thread runs at a time
    // (no rayon call when the pairs run sequentially: outside a pool, asking rayon for its
    // thread count would start its global pool)
    let concurrent = if p == 0 {
        0 // an empty batch computes nothing: no table to probe, whatever T
    } else if runs_sequentially(p) {
        1
    } else {
        p.min(rayon::current_num_threads()).max(1)
    };
    let work = checked_len("src", &[tables, concurrent, t, stride(t)])?
        .checked_add(checked_len("src", &[2, concurrent, t, c])?)
        .ok_or_else(|| Error::Memory {
            arg: "src",
            what: "work tables larger than the address space".into(),
        })?;
    check_alloc::<f32>("src", work)?;
    Ok((p, t, c, s, g, pt == 1 && p > 1))
}

/// The array's elements in standard order: borrowed when already contiguous, else copied (a
/// broadcast view of a few bytes can stand for terabytes: the copy is checked first).
fn contiguous<'a>(x: &'a ArrayView3<'a, f32>, arg: &'static str) -> Result<Cow<'a, [f32]>> {
    match x.as_slice() {
        Some(s) => Ok(Cow::Borrowed(s)),
        None => {
            check_alloc::<f32>(arg, x.len())?;
            Ok(Cow::Owned(x.iter().copied().collect()))
        }
    }
}

/// Whether the pair kernels (`matching_cost`, `yaw_costs`, `estimate_yaw`, `rerank`) run
/// without rayon for a batch of `pairs` pairs, on the calling thread (callers may then skip the
/// hand-over to a thread pool).
pub fn runs_sequentially(pairs: usize) -> bool {
    pairs <= 1
}

/// Runs `f` for every pair index, in parallel when there is more than one pair. Each pair is
/// computed sequentially, so results do not depend on the thread count. The results' vector is
/// allocated first, fallibly ([`Error::Memory`] naming `arg`; `collect` would abort), and
/// filled in place.
fn per_pair<T: Send, F: Fn(usize) -> T + Sync + Send>(
    arg: &'static str,
    p: usize,
    f: F,
) -> Result<Vec<T>> {
    let mut out = try_with_capacity(arg, p)?;
    if runs_sequentially(p) {
        out.extend((0..p).map(f));
    } else {
        // an indexed parallel iterator writes into the reserved capacity (no reallocation)
        out.par_extend((0..p).into_par_iter().with_min_len(1).map(f));
    }
    Ok(out)
}

// --------------------------------------------------------------------------------------------
// Public kernels
// --------------------------------------------------------------------------------------------

/// Matching cost `δ(A, B) = (1/T)·Σᵢ ‖Aᵢ − Bᵢ‖₂` of P pairs `a`, `b` (P, T, C), without shifting.
/// Computed directly (differences in f64). Requires T ≥ 1, C ≥ 1, equal shapes, finite values;
/// P = 0 gives an empty result.
pub fn matching_cost(a: ArrayView3<f32>, b: ArrayView3<f32>) -> Result<Vec<f64>> {
    let (p, t, c) = a.dim();
    if b.dim() != (p, t, c) {
        return Err(Error::shape(
            "b",
            format!("({p}, {t}, {c}) like a"),
            b.shape(),
        ));
    }
    if t == 0 || c == 0 {
        return Err(Error::shape(
            "a",
            "(P, T, C) with T >= 1, C >= 1",
            a.shape(),
        ));
    }
    let (sa, sb) = (contiguous(&a, "a")?, contiguous(&b, "b")?);
    check_rows(&sa, c, "a")?;
    check_rows(&sb, c, "b")?;
    let isa = Isa::detect();
    per_pair("a", p, |q| {
        let (x, y) = (
            &sa[q * t * c..(q + 1) * t * c],
            &sb[q * t * c..(q + 1) * t * c],
        );
        let sum: f64 = (0..t)
            .map(|i| {
                isa.sqdist(&x[i * c..(i + 1) * c], &y[i * c..(i + 1) * c])
                    .sqrt()
            })
            .sum();
        sum / t as f64
    })
}

/// Integer-shift yaw cost curves: `out[p][k] = c_p(k)` for k = 0..T−1, from `src`, `tgt`
/// (P, T, C) (or `tgt` (1, T, C) shared by all pairs; P = 0 gives a (0, T) result). Gram-based;
/// relative accuracy ~1e-6 at any scale (tiny pairs are rescaled first, see the module docs).
pub fn yaw_costs(src: ArrayView3<f32>, tgt: ArrayView3<f32>) -> Result<Array2<f64>> {
    // the Gram products, the diagonal distances and their roots
    let (p, t, c, s, g, shared) = check_pairs(&src, &tgt, 3, 2)?;
    let isa = Isa::detect();
    // the (P, T) result, allocated fallibly and written in place, a row per pair
    let mut out = try_filled("src", checked_len("src", &[p, t])?, 0.0f64)?;
    let row = |(q, dst): (usize, &mut [f64])| {
        let (ds, dt) = pair_slices(&s, &g, q, t, c, shared);
        dst.copy_from_slice(&isa.curve_costs(ds, dt, t, c));
    };
    if runs_sequentially(p) {
        out.chunks_mut(t).enumerate().for_each(row);
    } else {
        out.par_chunks_mut(t)
            .with_min_len(1)
            .enumerate()
            .for_each(row);
    }
    Array2::from_shape_vec((p, t), out).map_err(|e| Error::value("src", e.to_string()))
}

/// The fewest angle bins a yaw estimate takes: with T = 2 the interpolated roll by s and by
/// 2 − s (= −s) are the same matrix, so every curve is symmetric, c(s) = c(2 − s), and a
/// minimum off s = 1 has an equally good twin of the opposite yaw.
pub const MIN_YAW_BINS: usize = 3;

/// Exact global continuous yaw minimum of each pair (see the module docs for the method); an
/// empty batch (P = 0) gives no estimates; T >= [`MIN_YAW_BINS`].
pub fn estimate_yaw(src: ArrayView3<f32>, tgt: ArrayView3<f32>) -> Result<Vec<YawEstimate>> {
    // the curve's three tables, then its distances and inverse roots beside the polish's exact
    // rows (up to T rows of T f64, two tables' worth, when every shift is a near tie); the
    // exact path holds T rows of T f64 alone (the tables are freed before it)
    let (p, t, c, s, g, shared) = check_pairs(&src, &tgt, 4, MIN_YAW_BINS)?;
    let isa = Isa::detect();
    per_pair("src", p, |q| {
        let (ds, dt) = pair_slices(&s, &g, q, t, c, shared);
        isa.estimate_rescaled(ds, dt, t, c)
    })
}

/// Re-ranks K candidates `src` (K, T, C) against `tgt` (K, T, C) or one shared target (1, T, C):
/// exact yaw estimate per candidate (parallel over candidates), then the order by cost
/// ascending, ties broken by lower index. No candidates (K = 0) give an empty order.
pub fn rerank(src: ArrayView3<f32>, tgt: ArrayView3<f32>) -> Result<Reranked> {
    let estimates = estimate_yaw(src, tgt)?;
    let mut order = crate::error::try_collect("src", 0..estimates.len())?;
    order.sort_by(|&x, &y| {
        estimates[x]
            .cost
            .total_cmp(&estimates[y].cost)
            .then(x.cmp(&y))
    });
    Ok(Reranked { order, estimates })
}

fn pair_slices<'a>(
    s: &'a [f32],
    g: &'a [f32],
    q: usize,
    t: usize,
    c: usize,
    shared: bool,
) -> (&'a [f32], &'a [f32]) {
    let n = t * c;
    let qt = if shared { 0 } else { q };
    (&s[q * n..(q + 1) * n], &g[qt * n..(qt + 1) * n])
}

// --------------------------------------------------------------------------------------------
// Instruction-set dispatch
// --------------------------------------------------------------------------------------------

/// The instruction set the kernels run with, detected at run time (the build stays portable).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Isa {
    #[cfg(target_arch = "x86_64")]
    Avx512,
    #[cfg(target_arch = "x86_64")]
    Avx2,
    Generic,
}

impl Isa {
    /// The widest instruction set the CPU has, at most AVX2 when `VVLOC_NO_AVX512` is on and
    /// the portable code when `VVLOC_NO_SIMD` is on (to test and benchmark the other paths;
    /// see [`switch_on`]).
    fn detect() -> Isa {
        #[cfg(target_arch = "x86_64")]
        {
            if !switch_on(std::env::var("VVLOC_NO_SIMD").ok().as_deref()) {
                let no_avx512 = switch_on(std::env::var("VVLOC_NO_AVX512").ok().as_deref());
                // the AVX-512 functions are compiled with what avx512f implies (AVX2, FMA): a
                // virtual CPU may offer avx512f and hide those
                if is_x86_feature_detected!("avx512f")
                    && is_x86_feature_detected!("avx2")
                    && is_x86_feature_detected!("fma")
                    && !no_avx512
                {
                    return Isa::Avx512;
                }
                if is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma") {
                    return Isa::Avx2;
                }
            }
        }
        Isa::Generic
    }

    /// Whether every |v| ≤ bound (false for NaN).
    fn all_within(self, x: &[f32], bound: f32) -> bool {
        match self {
            // SAFETY (all arms): the target features were detected at run time by `detect`.
            #[cfg(target_arch = "x86_64")]
            Isa::Avx512 => unsafe { x86::all_within_avx512(x, bound) },
            #[cfg(target_arch = "x86_64")]
            Isa::Avx2 => unsafe { x86::all_within_avx2(x, bound) },
            Isa::Generic => all_within(x, bound),
        }
    }

    fn sqdist(self, x: &[f32], y: &[f32]) -> f64 {
        match self {
            // SAFETY (all arms): the target features were detected at run time by `detect`.
            #[cfg(target_arch = "x86_64")]
            Isa::Avx512 => unsafe { x86::sqdist_avx512(x, y) },
            #[cfg(target_arch = "x86_64")]
            Isa::Avx2 => unsafe { x86::sqdist_avx2(x, y) },
            Isa::Generic => sqdist_f64(x, y),
        }
    }

    fn curve(self, ds: &[f32], dt: &[f32], t: usize, c: usize, slopes: bool) -> Curve {
        match self {
            // SAFETY (all arms): the target features were detected at run time by `detect`.
            #[cfg(target_arch = "x86_64")]
            Isa::Avx512 => unsafe { x86::curve_avx512(ds, dt, t, c, slopes) },
            #[cfg(target_arch = "x86_64")]
            Isa::Avx2 => unsafe { x86::curve_avx2(ds, dt, t, c, slopes) },
            Isa::Generic => curve_impl(ds, dt, t, c, slopes, &GenericGram),
        }
    }

    fn estimate(self, ds: &[f32], dt: &[f32], t: usize, c: usize) -> YawEstimate {
        match self {
            // SAFETY (all arms): the target features were detected at run time by `detect`.
            #[cfg(target_arch = "x86_64")]
            Isa::Avx512 => unsafe { x86::estimate_avx512(ds, dt, t, c) },
            #[cfg(target_arch = "x86_64")]
            Isa::Avx2 => unsafe { x86::estimate_avx2(ds, dt, t, c) },
            Isa::Generic => estimate_impl(ds, dt, t, c, &GenericGram)
                .unwrap_or_else(|| estimate_exact(ds, dt, t, c)),
        }
    }

    /// The integer-shift costs of one pair ([`Isa::curve`]'s `cint`), a tiny pair rescaled
    /// first ([`tiny_pair_scale`]).
    fn curve_costs(self, ds: &[f32], dt: &[f32], t: usize, c: usize) -> Vec<f64> {
        match tiny_pair_scale(self, ds, dt) {
            None => self.curve(ds, dt, t, c, false).cint,
            Some(e) => {
                let (us, ut) = (scaled(ds, e), scaled(dt, e));
                let back = pow2(-e);
                let mut cint = self.curve(&us, &ut, t, c, false).cint;
                for v in cint.iter_mut() {
                    *v *= back;
                }
                cint
            }
        }
    }

    /// [`Isa::estimate`] of one pair, a tiny pair rescaled first ([`tiny_pair_scale`]): the
    /// shift is that of the rescaled pair, the cost scaled back.
    fn estimate_rescaled(self, ds: &[f32], dt: &[f32], t: usize, c: usize) -> YawEstimate {
        match tiny_pair_scale(self, ds, dt) {
            None => self.estimate(ds, dt, t, c),
            Some(e) => {
                let est = self.estimate(&scaled(ds, e), &scaled(dt, e), t, c);
                YawEstimate {
                    cost: est.cost * pow2(-e),
                    ..est
                }
            }
        }
    }
}

/// A pair whose values all lie within ±`TINY` is rescaled before its f32 Gram products and
/// tables: below ~1e-19 the products of its values fall below float32's normal range
/// (1.2e-38) and lose their digits, and at 1e-25 every entry of the curve was 0.
const TINY: f32 = 1.0 / (1u64 << 32) as f32;

/// For a pair whose values all lie within ±[`TINY`] and are not all zero: the exponent `e` such
/// that `2^e` times its largest magnitude lies in [0.5, 1). The costs are homogeneous of degree
/// one, and scaling by a power of two is exact (every scaled value is a normal float32), so the
/// rescaled pair's costs times `2^−e` are the pair's to the kernels' accuracy. `None` for any
/// other pair: the test reads the first value above [`TINY`], at most a chunk of 4096 values,
/// for ordinary descriptors.
fn tiny_pair_scale(isa: Isa, ds: &[f32], dt: &[f32]) -> Option<i32> {
    if !(isa.all_within(ds, TINY) && isa.all_within(dt, TINY)) {
        return None;
    }
    let m = ds.iter().chain(dt).fold(0.0f32, |m, v| m.max(v.abs()));
    if m == 0.0 {
        return None; // all zeros: nothing to lose
    }
    // m = f·2^x with f in [0.5, 1): x from the exponent field of m as an f64 (normal there)
    let x = ((f64::from(m).to_bits() >> 52) & 0x7ff) as i32 - 1022;
    Some(-x)
}

/// `2^e` as an f64, for |e| ≤ 1022.
fn pow2(e: i32) -> f64 {
    f64::from_bits(((1023 + e) as u64) << 52)
}

/// `x·2^e`, exact for the pairs [`tiny_pair_scale`] scales (the products are normal floats).
fn scaled(x: &[f32], e: i32) -> Vec<f32> {
    let f = pow2(e);
    x.iter().map(|&v| (f64::from(v) * f) as f32).collect()
}

/// Whether an on/off environment switch with value `v` is on: set, and neither empty nor "0"
/// (so that `VVLOC_NO_AVX512=0` leaves AVX-512 on, as `VVLOC_MADVISE_HUGEPAGE=0` turns huge
/// pages off).
fn switch_on(v: Option<&str>) -> bool {
    v.is_some_and(|v| !matches!(v.trim(), "" | "0"))
}

/// A 4×4 block of dot products: `out[r][s] = a_r · b_s` (f32).
trait Gram {
    fn dot4x4(&self, a: [&[f32]; 4], b: [&[f32]; 4]) -> [[f32; 4]; 4];
    fn dot(&self, a: &[f32], b: &[f32]) -> f32;
}

/// Portable Gram blocks: 8 independent lanes the compiler can vectorise.
struct GenericGram;

impl Gram for GenericGram {
    #[inline(always)]
    fn dot4x4(&self, a: [&[f32]; 4], b: [&[f32]; 4]) -> [[f32; 4]; 4] {
        let mut out = [[0.0f32; 4]; 4];
        for r in 0..4 {
            for s in 0..4 {
                out[r][s] = self.dot(a[r], b[s]);
            }
        }
        out
    }

    #[inline(always)]
    fn dot(&self, a: &[f32], b: &[f32]) -> f32 {
        const L: usize = 8;
        let mut acc = [0.0f32; L];
        let (ca, cb) = (a.chunks_exact(L), b.chunks_exact(L));
        let (ra, rb) = (ca.remainder(), cb.remainder());
        for (x, y) in ca.zip(cb) {
            for l in 0..L {
                acc[l] += x[l] * y[l];
            }
        }
        let tail: f32 = ra.iter().zip(rb).map(|(x, y)| x * y).sum();
        acc.iter().sum::<f32>() + tail
    }
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    //! AVX-512 and AVX2/FMA instantiations. Every function here requires its target features;
    //! callers (`Isa`) only call them after run-time detection.
    use super::*;
    use std::arch::x86_64::*;

    /// AVX-512 Gram blocks: 16 zmm accumulators, 16-lane fused multiply-adds, masked tail.
    pub struct Avx512Gram;

    impl Gram for Avx512Gram {
        #[inline(always)]
        fn dot4x4(&self, a: [&[f32]; 4], b: [&[f32]; 4]) -> [[f32; 4]; 4] {
            // SAFETY: `Avx512Gram` is only used inside `#[target_feature(enable = "avx512f")]`
            // functions, which run only after run-time detection of AVX-512F.
            unsafe { dot4x4_avx512(a, b) }
        }
        #[inline(always)]
        fn dot(&self, a: &[f32], b: &[f32]) -> f32 {
            GenericGram.dot(a, b)
        }
    }

    /// AVX2/FMA Gram blocks: the 4×4 block as two 2×4 halves of 8 ymm accumulators each (the 16
    /// accumulators of a whole block and its loads would not fit AVX2's 16 registers), 8-lane
    /// fused multiply-adds, scalar tail.
    pub struct Avx2Gram;

    impl Gram for Avx2Gram {
        #[inline(always)]
        fn dot4x4(&self, a: [&[f32]; 4], b: [&[f32]; 4]) -> [[f32; 4]; 4] {
            // SAFETY: `Avx2Gram` is only used inside `#[target_feature(enable = "avx2,fma")]`
            // functions, which run only after run-time detection of AVX2 and FMA.
            unsafe { dot4x4_avx2(a, b) }
        }
        #[inline(always)]
        fn dot(&self, a: &[f32], b: &[f32]) -> f32 {
            GenericGram.dot(a, b)
        }
    }

    #[target_feature(enable = "avx2,fma")]
    fn dot4x4_avx2(a: [&[f32]; 4], b: [&[f32]; 4]) -> [[f32; 4]; 4] {
        let c = a[0].len();
        // the loads below read elements 0..c / 8 · 8 of every row: all rows must have length c
        assert!(a.iter().chain(b.iter()).all(|r| r.len() == c));
        let full = c / 8 * 8;
        let mut out = [[0.0f32; 4]; 4];
        for h in 0..2 {
            let mut acc = [_mm256_setzero_ps(); 8]; // accumulator n: rows (2h + n / 4, n % 4)
            let mut off = 0;
            while off < full {
                // SAFETY: off + 8 ≤ full ≤ c, the length of every row (asserted above).
                let av = [0, 1].map(|r| unsafe { _mm256_loadu_ps(a[2 * h + r].as_ptr().add(off)) });
                let bv = [0, 1, 2, 3].map(|s| unsafe { _mm256_loadu_ps(b[s].as_ptr().add(off)) });
                for n in 0..8 {
                    acc[n] = _mm256_fmadd_ps(av[n / 4], bv[n % 4], acc[n]);
                }
                off += 8;
            }
            // transposing reduction: the pairwise sums of hadd twice, then the 128-bit halves
            let g = [0, 4].map(|n| {
                _mm256_hadd_ps(
                    _mm256_hadd_ps(acc[n], acc[n + 1]),
                    _mm256_hadd_ps(acc[n + 2], acc[n + 3]),
                )
            });
            let sums = _mm256_add_ps(
                _mm256_permute2f128_ps::<0x20>(g[0], g[1]),
                _mm256_permute2f128_ps::<0x31>(g[0], g[1]),
            );
            let mut lanes = [0.0f32; 8];
            // SAFETY: `lanes` holds 8 f32, the width of one unaligned 256-bit store.
            unsafe { _mm256_storeu_ps(lanes.as_mut_ptr(), sums) };
            for (n, &v) in lanes.iter().enumerate() {
                let (r, s) = (2 * h + n / 4, n % 4);
                let mut tail = 0.0f32;
                for i in full..c {
                    tail += a[r][i] * b[s][i];
                }
                out[r][s] = v + tail;
            }
        }
        out
    }

    #[target_feature(enable = "avx512f")]
    fn dot4x4_avx512(a: [&[f32]; 4], b: [&[f32]; 4]) -> [[f32; 4]; 4] {
        let c = a[0].len();
        // the masked loads below read lanes off..c of every row: all rows must have length c
        // (a once-per-tile comparison; the callers slice every row to C)
        assert!(a.iter().chain(b.iter()).all(|r| r.len() == c));
        let mut acc = [[_mm512_setzero_ps(); 4]; 4];
        let mut off = 0;
        while off < c {
            let rem = c - off;
            let mask: __mmask16 = if rem >= 16 {
                0xFFFF
            } else {
                ((1u32 << rem) - 1) as u16
            };
            let mut av = [_mm512_setzero_ps(); 4];
            let mut bv = [_mm512_setzero_ps(); 4];
            for r in 0..4 {
                // SAFETY: all rows have length c (asserted above); the mask
                // enables only lanes off..off + min(16, c − off), which lie inside each row.
                av[r] = unsafe { _mm512_maskz_loadu_ps(mask, a[r].as_ptr().add(off)) };
                bv[r] = unsafe { _mm512_maskz_loadu_ps(mask, b[r].as_ptr().add(off)) };
            }
            for r in 0..4 {
                for s in 0..4 {
                    acc[r][s] = _mm512_fmadd_ps(av[r], bv[s], acc[r][s]);
                }
            }
            off += 16;
        }
        // The 16 accumulators reduced together (a transposing tree of 15 additions) instead of
        // one by one (16 reductions of 4 steps each): lane n of the result holds the sum of
        // accumulator (r, s) = (n mod 4, n div 4).
        let v = [0, 2, 4, 6, 8, 10, 12, 14].map(|n| {
            let (x, y) = (acc[n / 4][n % 4], acc[(n + 1) / 4][(n + 1) % 4]);
            // 128-bit blocks (x0 x1 y0 y1) + (x2 x3 y2 y3)
            _mm512_add_ps(
                _mm512_shuffle_f32x4::<0b01_00_01_00>(x, y),
                _mm512_shuffle_f32x4::<0b11_10_11_10>(x, y),
            )
        });
        let v = [0, 2, 4, 6].map(|n| {
            let (x, y) = (v[n], v[n + 1]);
            // (x0 x2 y0 y2) + (x1 x3 y1 y3): each 128-bit block now sums one accumulator
            _mm512_add_ps(
                _mm512_shuffle_f32x4::<0b10_00_10_00>(x, y),
                _mm512_shuffle_f32x4::<0b11_01_11_01>(x, y),
            )
        });
        let v = [0, 2].map(|n| {
            let (x, y) = (v[n], v[n + 1]);
            _mm512_add_ps(_mm512_unpacklo_ps(x, y), _mm512_unpackhi_ps(x, y))
        });
        let (x, y) = (_mm512_castps_pd(v[0]), _mm512_castps_pd(v[1]));
        let sums = _mm512_add_ps(
            _mm512_castpd_ps(_mm512_unpacklo_pd(x, y)),
            _mm512_castpd_ps(_mm512_unpackhi_pd(x, y)),
        );
        let mut lanes = [0.0f32; 16];
        // SAFETY: `lanes` holds 16 f32, the width of one unaligned 512-bit store.
        unsafe { _mm512_storeu_ps(lanes.as_mut_ptr(), sums) };
        let mut out = [[0.0f32; 4]; 4];
        for (n, &v) in lanes.iter().enumerate() {
            out[n % 4][n / 4] = v;
        }
        out
    }

    #[target_feature(enable = "avx512f")]
    pub fn all_within_avx512(x: &[f32], bound: f32) -> bool {
        all_within(x, bound)
    }
    #[target_feature(enable = "avx2,fma")]
    pub fn all_within_avx2(x: &[f32], bound: f32) -> bool {
        all_within(x, bound)
    }
    #[target_feature(enable = "avx512f")]
    pub fn sqdist_avx512(x: &[f32], y: &[f32]) -> f64 {
        sqdist_f64(x, y)
    }
    #[target_feature(enable = "avx2,fma")]
    pub fn sqdist_avx2(x: &[f32], y: &[f32]) -> f64 {
        sqdist_f64(x, y)
    }
    #[target_feature(enable = "avx512f")]
    pub fn curve_avx512(ds: &[f32], dt: &[f32], t: usize, c: usize, slopes: bool) -> Curve {
        curve_impl(ds, dt, t, c, slopes, &Avx512Gram)
    }
    #[target_feature(enable = "avx2,fma")]
    pub fn curve_avx2(ds: &[f32], dt: &[f32], t: usize, c: usize, slopes: bool) -> Curve {
        curve_impl(ds, dt, t, c, slopes, &Avx2Gram)
    }
    #[target_feature(enable = "avx512f")]
    pub fn estimate_avx512(ds: &[f32], dt: &[f32], t: usize, c: usize) -> YawEstimate {
        match estimate_impl(ds, dt, t, c, &Avx512Gram) {
            Some(est) => est,
            None => exact_avx512(ds, dt, t, c),
        }
    }
    #[inline(never)]
    #[target_feature(enable = "avx512f")]
    fn exact_avx512(ds: &[f32], dt: &[f32], t: usize, c: usize) -> YawEstimate {
        estimate_exact(ds, dt, t, c)
    }
    #[target_feature(enable = "avx2,fma")]
    pub fn estimate_avx2(ds: &[f32], dt: &[f32], t: usize, c: usize) -> YawEstimate {
        match estimate_impl(ds, dt, t, c, &Avx2Gram) {
            Some(est) => est,
            None => exact_avx2(ds, dt, t, c),
        }
    }
    #[inline(never)]
    #[target_feature(enable = "avx2,fma")]
    fn exact_avx2(ds: &[f32], dt: &[f32], t: usize, c: usize) -> YawEstimate {
        estimate_exact(ds, dt, t, c)
    }
}

// --------------------------------------------------------------------------------------------
// Vectorisable helpers (inlined into the target-feature instantiations above)
// --------------------------------------------------------------------------------------------

/// Whether every |v| ≤ bound (false for NaN), a chunk at a time without stopping inside a
/// chunk, so that the test vectorises (`all` over the values stops early: one at a time).
#[inline(always)]
fn all_within(x: &[f32], bound: f32) -> bool {
    x.chunks(4096).all(|ch| {
        let mut ok = true;
        for v in ch {
            ok &= v.abs() <= bound;
        }
        ok
    })
}

/// `‖x − y‖²` with the differences and the sum in f64 (no cancellation).
#[inline(always)]
fn sqdist_f64(x: &[f32], y: &[f32]) -> f64 {
    const L: usize = 8;
    let mut acc = [0.0f64; L];
    let (cx, cy) = (x.chunks_exact(L), y.chunks_exact(L));
    let (rx, ry) = (cx.remainder(), cy.remainder());
    for (a, b) in cx.zip(cy) {
        for l in 0..L {
            let d = a[l] as f64 - b[l] as f64;
            acc[l] += d * d;
        }
    }
    let tail: f64 = rx
        .iter()
        .zip(ry)
        .map(|(a, b)| {
            let d = *a as f64 - *b as f64;
            d * d
        })
        .sum();
    acc.iter().sum::<f64>() + tail
}

/// `‖x‖²` in f64.
#[inline(always)]
fn sqnorm_f64(x: &[f32]) -> f64 {
    const L: usize = 8;
    let mut acc = [0.0f64; L];
    let cx = x.chunks_exact(L);
    let rx = cx.remainder();
    for a in cx {
        for l in 0..L {
            acc[l] += a[l] as f64 * a[l] as f64;
        }
    }
    acc.iter().sum::<f64>() + rx.iter().map(|a| *a as f64 * *a as f64).sum::<f64>()
}

/// Sums of `f` over the rows of N equally long slices, M sums at once: `out[o] = Σᵢ
/// f([x₀[i], …, x_{N−1}[i]])[o]`, accumulated in 16 f32 lanes and combined in f64. The last
/// partial chunk is padded with zeros, so `f` must give 0 for a row of zeros. Slices are read
/// in whole chunks (one bounds check per chunk), which is what lets the compiler vectorise `f`.
#[inline(always)]
fn lane_sums<const N: usize, const M: usize>(
    xs: [&[f32]; N],
    f: impl Fn([f32; N]) -> [f32; M],
) -> [f64; M] {
    const L: usize = 16;
    let n = xs.first().map_or(0, |x| x.len());
    assert!(
        xs.iter().all(|x| x.len() == n),
        "lane_sums: slices of unequal length"
    );
    let mut acc = [[0.0f32; L]; M];
    let full = n / L * L;
    for base in (0..full).step_by(L) {
        lane_add(
            &mut acc,
            std::array::from_fn(|m| &xs[m][base..base + L]),
            &f,
        );
    }
    if full < n {
        let mut pad = [[0.0f32; L]; N];
        for m in 0..N {
            pad[m][..n - full].copy_from_slice(&xs[m][full..]);
        }
        lane_add(&mut acc, std::array::from_fn(|m| &pad[m][..]), &f);
    }
    let mut out = [0.0f64; M];
    for o in 0..M {
        for &v in &acc[o] {
            out[o] += v as f64;
        }
    }
    out
}

/// One chunk of [`lane_sums`]: `acc[o][l] += f(rows[·][l])[o]` (a function, not a closure, so
/// that it is inlined into the kernels and compiled with their target features).
#[inline(always)]
fn lane_add<const N: usize, const M: usize, const L: usize>(
    acc: &mut [[f32; L]; M],
    rows: [&[f32]; N],
    f: &impl Fn([f32; N]) -> [f32; M],
) {
    for l in 0..L {
        let v = f(std::array::from_fn(|m| rows[m][l]));
        for o in 0..M {
            acc[o][l] += v[o];
        }
    }
}

// --------------------------------------------------------------------------------------------
// Per-pair analysis
// --------------------------------------------------------------------------------------------

/// Squared norms of the T rows of a (T, C) matrix, f64. Closures would not do here: a closure is
/// a function of its own, compiled without the kernels' target features (AVX-512, AVX2) and
/// not always inlined, so the heavy loops are written out in `#[inline(always)]` functions.
#[inline(always)]
fn row_sqnorms(m: &[f32], t: usize, c: usize) -> Vec<f64> {
    let mut out = vec![0.0; t];
    for (j, o) in out.iter_mut().enumerate() {
        *o = sqnorm_f64(row_of(c, m, j));
    }
    out
}

/// `out[i] = ‖Ds[(i − k) mod T] − Dt[i]‖²` in f64: row k of the curve, recomputed directly.
#[inline(always)]
fn exact_curve_row(ds: &[f32], dt: &[f32], t: usize, c: usize, k: usize) -> Vec<f64> {
    let mut out = vec![0.0; t];
    for (i, o) in out.iter_mut().enumerate() {
        *o = sqdist_f64(row_of(c, ds, (i + t - k) % t), row_of(c, dt, i));
    }
    out
}

/// `e[j] = ‖Ds_j − Ds_{j−1}‖²` (T,) of a (T, C) matrix, f64, exact.
#[inline(always)]
fn diff_sqnorms(ds: &[f32], t: usize, c: usize) -> Vec<f64> {
    let mut e = vec![0.0; t];
    for (j, ej) in e.iter_mut().enumerate() {
        *ej = sqdist_f64(row_of(c, ds, j), row_of(c, ds, (j + t - 1) % t));
    }
    e
}

/// `Σᵢ sqrt(x[i])` in f64.
#[inline(always)]
fn sum_sqrt(x: &[f64]) -> f64 {
    let mut acc = 0.0;
    for &v in x {
        acc += v.sqrt();
    }
    acc
}

/// Row `j` of a (rows, c) row-major matrix.
#[inline(always)]
fn row_of(c: usize, m: &[f32], j: usize) -> &[f32] {
    &m[j * c..(j + 1) * c]
}

/// Lanes of the f32 sums of the tables below; their rows are padded with zeros to a multiple.
const LANES: usize = 16;

/// Gram-derived quantities of one pair (see the module docs). The tables are (T, S) with rows
/// of `S = stride(T)` ≥ T entries, zero beyond T, so that every row is read in whole chunks.
struct Curve {
    /// Row length S of the tables.
    stride: usize,
    /// (T, S) diagonal layout: `dg[k·S + i] = ‖Ds[(i − k) mod T] − Dt[i]‖²` for i < T.
    dg: Vec<f32>,
    /// (T, S) `1/sqrt(dg)` (0 where dg = 0); empty unless slopes were requested.
    rinv: Vec<f32>,
    /// (T,) integer-shift costs.
    cint: Vec<f64>,
    /// Smallest nonzero and largest squared row norm of either matrix (∞, 0 for all zeros).
    norm_range: (f64, f64),
    /// RMS row norm of the two matrices.
    rms: f64,
}

#[inline(always)]
fn curve_impl<G: Gram>(ds: &[f32], dt: &[f32], t: usize, c: usize, slopes: bool, g: &G) -> Curve {
    let (ns, nt) = (row_sqnorms(ds, t, c), row_sqnorms(dt, t, c));
    // 1. the Gram products G[j][i] = Ds_j · Dt_i, in (T, T) row-major order
    let mut gm = vec![0.0f32; t * t];
    let (t4j, t4i) = (t / 4 * 4, t / 4 * 4);
    for jb in (0..t4j).step_by(4) {
        let a = [
            row_of(c, ds, jb),
            row_of(c, ds, jb + 1),
            row_of(c, ds, jb + 2),
            row_of(c, ds, jb + 3),
        ];
        for ib in (0..t4i).step_by(4) {
            let b = [
                row_of(c, dt, ib),
                row_of(c, dt, ib + 1),
                row_of(c, dt, ib + 2),
                row_of(c, dt, ib + 3),
            ];
            let blk = g.dot4x4(a, b);
            for (r, br) in blk.iter().enumerate() {
                gm[(jb + r) * t + ib..(jb + r) * t + ib + 4].copy_from_slice(br);
            }
        }
    }
    for j in 0..t {
        let i0 = if j < t4j { t4i } else { 0 };
        for i in i0..t {
            gm[j * t + i] = g.dot(row_of(c, ds, j), row_of(c, dt, i));
        }
    }
    // 2. squared distances d²[j][i] = ‖Ds_j‖² + ‖Dt_i‖² − 2·G[j][i] in f64, in place, row by
    //    row (vectorised); entries where fp32 cancellation would hurt are recomputed directly
    //    (in place, row by row: no list of them, which could hold every entry)
    let mut flag = vec![false; t];
    for (j, row) in gm.chunks_exact_mut(t).enumerate() {
        let mut any = false;
        for ((v, &n), f) in row.iter_mut().zip(&nt).zip(flag.iter_mut()) {
            let scale = ns[j] + n;
            let d2 = scale - 2.0 * *v as f64;
            *f = d2 <= NEAR_ZERO_REL * scale;
            any |= *f;
            *v = d2.max(0.0) as f32;
        }
        if any {
            for (i, (v, &f)) in row.iter_mut().zip(&flag).enumerate() {
                if f {
                    *v = sqdist_f64(row_of(c, ds, j), row_of(c, dt, i)).max(0.0) as f32;
                }
            }
        }
    }
    // 3. the diagonal layout dg[k][i] = d²[(i − k) mod T][i], a block of LANES columns at a
    //    time: the block's rows of both tables stay in the first-level cache
    let st = stride(t);
    let mut dg = vec![0.0f32; t * st];
    for i0 in (0..t).step_by(LANES) {
        let i1 = (i0 + LANES).min(t);
        for j in 0..t {
            // entry (j, i) goes to k = (i − j) mod T, index k·S + i: a step of S + 1 per i
            let row = &gm[j * t..(j + 1) * t];
            let mid = j.clamp(i0, i1); // columns i < j wrap: k = i + T − j
            if i0 < mid {
                scatter_diag(&mut dg, (i0 + t - j) * st + i0, st + 1, &row[i0..mid]);
            }
            if mid < i1 {
                scatter_diag(&mut dg, (mid - j) * st + mid, st + 1, &row[mid..i1]);
            }
        }
    }
    drop(gm); // at most two (T, S) tables and the small vectors are alive from here
    let inv_t = 1.0 / t as f64;
    let mut sq = dg.clone();
    for v in sq.iter_mut() {
        *v = v.sqrt();
    }
    let mut cint = vec![0.0; t];
    for (k, ck) in cint.iter_mut().enumerate() {
        *ck = lane_sums([&sq[k * st..(k + 1) * st]], |[v]| [v])[0] * inv_t;
    }
    let rinv = if slopes {
        for v in sq.iter_mut() {
            *v = if *v > 0.0 { 1.0 / *v } else { 0.0 };
        }
        sq
    } else {
        Vec::new()
    };
    let norm_range = ns
        .iter()
        .chain(&nt)
        .fold((f64::INFINITY, 0.0f64), |(lo, hi), &v| {
            (if v > 0.0 { lo.min(v) } else { lo }, hi.max(v))
        });
    let rms = ((ns.iter().sum::<f64>() + nt.iter().sum::<f64>()) / (2 * t) as f64).sqrt();
    Curve {
        stride: st,
        dg,
        rinv,
        cint,
        norm_range,
        rms,
    }
}

/// `dst[start + n·step] = src[n]` for every n; every index must lie in `dst`.
#[inline(always)]
fn scatter_diag(dst: &mut [f32], start: usize, step: usize, src: &[f32]) {
    for (x, &v) in dst[start..].iter_mut().step_by(step).zip(src) {
        *x = v;
    }
}

/// Row length of the curve tables for T shifts: T rounded up to whole chunks of [`LANES`].
fn stride(t: usize) -> usize {
    t.div_ceil(LANES) * LANES
}

/// Value, first and second derivative of `g(w) = (1/T)·Σᵢ sqrt((1−w)aᵢ + w·bᵢ − w(1−w)eᵢ)`.
/// Rows whose squared distance is 0 at `w` contribute nothing. Summed in 8 f64 lanes (written
/// without closures, which would be compiled without the kernels' target features).
#[inline(always)]
fn eval_interval(a: &[f64], b: &[f64], e: &[f64], w: f64) -> (f64, f64, f64) {
    const L: usize = 8;
    let n = a.len();
    let (b, e) = (&b[..n], &e[..n]);
    let mut acc = [[0.0f64; L]; 3];
    let full = n / L * L;
    for base in (0..full).step_by(L) {
        for l in 0..L {
            let i = base + l;
            interval_row(&mut acc, l, a[i], b[i], e[i], w);
        }
    }
    for i in full..n {
        interval_row(&mut acc, i - full, a[i], b[i], e[i], w);
    }
    let m = n as f64;
    let [g0, g1, g2] = acc.map(|v| v.iter().sum::<f64>() / m);
    (g0, g1, g2)
}

/// One row's terms of [`eval_interval`], added to lane `l`.
#[inline(always)]
fn interval_row<const L: usize>(acc: &mut [[f64; L]; 3], l: usize, a: f64, b: f64, e: f64, w: f64) {
    let f = ((1.0 - w) * a + w * b - w * (1.0 - w) * e).max(0.0);
    let r = f.sqrt();
    let q = 1.0 / r; // formed for every row, then selected: a branch kept the loop scalar
    let inv = if f > 0.0 { q } else { 0.0 };
    let d = 0.5 * (b - a - e + 2.0 * w * e) * inv;
    acc[0][l] += r;
    acc[1][l] += d;
    acc[2][l] += (e - d * d).max(0.0) * inv;
}

/// Exact one-sided end slopes `g'(0+)`, `g'(1−)` of the interval function (rows with a zero
/// end distance contribute `±sqrt(e)`). Summed in 8 f64 lanes.
#[inline(always)]
fn end_slopes(a: &[f64], b: &[f64], e: &[f64]) -> (f64, f64) {
    const L: usize = 8;
    let n = a.len();
    let (b, e) = (&b[..n], &e[..n]);
    let mut acc = [[0.0f64; L]; 2];
    let full = n / L * L;
    for base in (0..full).step_by(L) {
        for l in 0..L {
            let i = base + l;
            slope_row(&mut acc, l, a[i], b[i], e[i]);
        }
    }
    for i in full..n {
        slope_row(&mut acc, i - full, a[i], b[i], e[i]);
    }
    let m = n as f64;
    let [d0, d1] = acc.map(|v| v.iter().sum::<f64>() / m);
    (d0, d1)
}

/// One row's terms of [`end_slopes`], added to lane `l`.
#[inline(always)]
fn slope_row<const L: usize>(acc: &mut [[f64; L]; 2], l: usize, a: f64, b: f64, e: f64) {
    // both arms formed for every row, then selected: a branch kept the loop scalar
    let (s0, s1, se) = (
        (b - a - e) / (2.0 * a.sqrt()),
        (b - a + e) / (2.0 * b.sqrt()),
        e.sqrt(),
    );
    acc[0][l] += if a > 0.0 { s0 } else { se };
    acc[1][l] += if b > 0.0 { s1 } else { -se };
}

/// Minimises the convex interval function on [0, 1]: returns (w*, g(w*)). Safeguarded Newton
/// on g' = 0 inside the bracket, falling back to bisection (Numerical Recipes' `rtsafe` idea).
#[inline(always)]
fn minimise_interval(a: &[f64], b: &[f64], e: &[f64], c0: f64, c1: f64) -> (f64, f64) {
    let (d0, d1) = end_slopes(a, b, e);
    if d0 >= 0.0 || d1 <= 0.0 {
        return if c0 <= c1 { (0.0, c0) } else { (1.0, c1) };
    }
    let (mut lo, mut hi) = (0.0f64, 1.0f64);
    // Start where the two end tangents meet.
    let mut w = ((c1 - d1 - c0) / (d0 - d1)).clamp(0.0, 1.0);
    let mut step_old = 1.0f64;
    let mut best = (0.0, c0);
    if c1 < c0 {
        best = (1.0, c1);
    }
    for _ in 0..100 {
        let (g0, g1, g2) = eval_interval(a, b, e, w);
        if g0 < best.1 {
            best = (w, g0);
        }
        if g1 > 0.0 {
            hi = w;
        } else {
            lo = w;
        }
        if hi - lo <= 1e-13 || g1 == 0.0 {
            break;
        }
        let newton = if g2 > 0.0 { w - g1 / g2 } else { f64::NAN };
        if (newton - w).abs() <= 1e-14 {
            // converged: the Newton step no longer moves w (near the minimiser it rounds to w
            // itself, which the bracket test below would refuse and bisect ~20 more times)
            break;
        }
        let next = if newton > lo && newton < hi && (g1 / g2).abs() * 2.0 <= step_old.abs() {
            newton
        } else {
            0.5 * (lo + hi)
        };
        step_old = next - w;
        if step_old.abs() <= 1e-15 {
            break;
        }
        w = next;
    }
    best
}

/// The yaw estimate of one pair by the approximate stage and the polish (module docs, steps
/// 1-4), or `None` for a pair it cannot resolve, which the caller gives to [`estimate_exact`]
/// (step 5; its own instantiation per instruction set, `x86::exact_*`, called only then).
#[inline(always)]
fn estimate_impl<G: Gram>(
    ds: &[f32],
    dt: &[f32],
    t: usize,
    c: usize,
    g: &G,
) -> Option<YawEstimate> {
    let cv = curve_impl(ds, dt, t, c, true, g);
    let (lo, hi) = cv.norm_range;
    if hi > WIDE_ROWS * lo {
        return None; // a rare pair: its curve's tables were built for nothing
    }
    let e = diff_sqnorms(ds, t, c);
    // two periods and the padding, so that every shift reads a row-long slice (the padding's
    // values are finite and ≥ 0, and meet zeros in dg and rinv: they add nothing)
    let st = cv.stride;
    let mut e2 = vec![0.0f32; t + st];
    for (n, v) in e2.iter_mut().enumerate() {
        *v = e[n % t] as f32;
    }
    let lipschitz = sum_sqrt(&e) / t as f64;
    let inv_2t = 0.5 / t as f64;

    // Approximate stage on the Gram-derived entries. Inside an interval its values come from
    // the f32 entries through (1−w)a + wb − w(1−w)e, which cancels where the interpolated rows
    // match closely; the margin is relative, so at a near-perfect match (cost ≲ 1e-3) with two
    // basins closer than the f32 error (a scene periodic under a half turn) the other basin
    // could win: such a pair (best ≤ NEAR_PERFECT·rms) takes the exact path after pass 2. A
    // bound that covered it here (an absolute allowance of √(τ·(2(‖Ds‖² + ‖Dt‖²) + e))) kept
    // nearly every interval of flat curves and made every pair 20× slower (BENCHMARKS.md,
    // "estimate_yaw near a perfect match").
    let mut best = cv.cint.iter().copied().fold(f64::INFINITY, f64::min);
    let rms = cv.rms;
    let margin = |b: f64| POLISH_MARGIN * (rms + b.abs());
    let mut cands: Vec<(usize, f64)> = Vec::new(); // (interval k, approximate minimum)
    let (mut a64, mut b64, mut e64) = (vec![0.0; t], vec![0.0; t], vec![0.0; t]);
    // Pass 1 (vectorised f32): end slopes, plus value and slope where the end tangents meet;
    // the three tangents give a lower bound of the interval's minimum, the value an upper bound.
    let mut open: Vec<(f64, usize)> = Vec::new(); // (lower bound, interval k)
    let mut unsure: Vec<usize> = Vec::new(); // intervals whose end slopes' signs are not known
    let slope_error = slope_error_bound(t, c);
    for k in 0..t {
        let k1 = (k + 1) % t;
        let (c0, c1) = (cv.cint[k], cv.cint[k1]);
        // Lipschitz bound: |g'| ≤ (1/T)·Σ sqrt(e).
        if 0.5 * (c0 + c1 - lipschitz) > best + margin(best) {
            continue;
        }
        let (ra, rb) = (
            &cv.rinv[k * st..(k + 1) * st],
            &cv.rinv[k1 * st..(k1 + 1) * st],
        );
        let (da, db) = (&cv.dg[k * st..(k + 1) * st], &cv.dg[k1 * st..(k1 + 1) * st]);
        let er = &e2[t - k..t - k + st]; // er[i] = e[(i − k) mod T]
        let [d0, d1, s0, s1] = lane_sums([da, db, er, ra, rb], |[a, b, e, ra, rb]| {
            let size = a + b + e;
            [(b - a - e) * ra, (b - a + e) * rb, size * ra, size * rb]
        })
        .map(|v| v * inv_2t);
        // the f32 slopes' error is at most slope_error·s (rows of very different sizes cancel
        // in b − a ± e): a sign within it is not known, and the interval is minimised on
        // exact rows below rather than taken as minimal at an end
        if d0 - slope_error * s0 >= 0.0 || d1 + slope_error * s1 <= 0.0 {
            continue; // the minimum is at an end: an integer shift, already in cint
        }
        if d0 >= 0.0 || d1 <= 0.0 {
            unsure.push(k);
            continue;
        }
        let wx = ((c1 - d1 - c0) / (d0 - d1)).clamp(0.0, 1.0);
        if wx.is_nan() {
            continue; // unreachable for inputs check_rows admits; never a panic below
        }
        // The bounds below take the f32 slopes as they are: with rows of similar size (a pair
        // of rows spanning more than WIDE_ROWS took the exact path above) their error was below
        // the margin in every pair the fuzz tried, not by proof. Moving the bounds by
        // slope_error_bound, a worst-case bound, kept most intervals of flat curves and doubled
        // the kernel's time.
        if c0 + d0 * wx > best + margin(best) {
            continue; // the end tangents' lower bound cannot beat the best
        }
        // value and slope at wx, in one pass (zero rows give 0: r = 0 selects 0)
        // 1 − wx is rounded to f32 itself, not formed from wx as f32: near wx = 1 the latter
        // keeps a few bits of it, and a minimum just below a whole bin (a close match) then
        // read ~1e-4 too high, its interval was pruned and the neighbouring one won.
        let (w, u, v, q) = (
            wx as f32,
            (1.0 - wx) as f32,
            2.0 * wx as f32,
            (wx * (1.0 - wx)) as f32,
        );
        // The quotient is formed for every row and then selected, not branched on: with the
        // division inside the branch, LLVM vectorised this loop in some builds and left half of
        // its lanes scalar in others (BENCHMARKS.md, "A branch in the first stage's loop").
        let [gx, sx] = lane_sums([da, db, er], |[a, b, e]| {
            let r = (u * a + w * b - q * e).max(0.0).sqrt();
            let slope = (b - a - e + v * e) / r;
            [r, if r > 0.0 { slope } else { 0.0 }]
        });
        let (gx, sx) = (gx / t as f64, sx * inv_2t);
        // Lower envelope of the tangents at 0, wx, 1 (each a lower bound of a convex function).
        let lb = if sx > 0.0 {
            let wi = ((gx - sx * wx) - c0) / (d0 - sx); // tangent at 0 meets tangent at wx
            c0 + d0 * wi.clamp(0.0, wx)
        } else {
            let wi = ((c1 - d1) - (gx - sx * wx)) / (sx - d1); // tangent at wx meets tangent at 1
            c1 + d1 * (wi.clamp(wx, 1.0) - 1.0)
        };
        open.push((lb.min(gx), k));
    }
    // Pass 2: minimise the surviving intervals, most promising first.
    open.sort_by(|x, y| x.0.total_cmp(&y.0).then(x.1.cmp(&y.1)));
    for &(lb, k) in &open {
        if lb > best + margin(best) {
            break; // sorted: no later interval can beat the best either
        }
        let k1 = (k + 1) % t;
        let (da, db) = (&cv.dg[k * st..k * st + t], &cv.dg[k1 * st..k1 * st + t]);
        for i in 0..t {
            a64[i] = da[i] as f64;
            b64[i] = db[i] as f64;
            e64[i] = e[(i + t - k) % t];
        }
        let (_, v) = minimise_interval(&a64, &b64, &e64, cv.cint[k], cv.cint[k1]);
        best = best.min(v);
        cands.push((k, v));
    }

    // Exact polish: the intervals around every near-best integer shift and every near-best
    // interior candidate, from rows recomputed directly in f64.
    let best = cands
        .iter()
        .map(|c| c.1)
        .chain(cv.cint.iter().copied())
        .fold(f64::INFINITY, f64::min);
    if best <= NEAR_PERFECT * rms {
        return None;
    }
    let mut polish: Vec<usize> = Vec::new();
    for (k, &v) in cv.cint.iter().enumerate() {
        if v <= best + margin(best) {
            polish.push((k + t - 1) % t);
            polish.push(k);
        }
    }
    for &(k, v) in &cands {
        if v <= best + margin(best) {
            polish.push(k);
        }
    }
    polish.extend_from_slice(&unsure);
    polish.sort_unstable();
    polish.dedup();
    // rows of the curve at integer shifts, recomputed directly in f64, each at most once
    let mut exact_rows: Vec<Vec<f64>> = vec![Vec::new(); t];
    for &k in &polish {
        for kk in [k, (k + 1) % t] {
            if exact_rows[kk].is_empty() {
                exact_rows[kk] = exact_curve_row(ds, dt, t, c, kk);
            }
        }
    }
    let mut result = (0usize, 0.0f64, f64::INFINITY); // (interval k, w, value)
    for &k in &polish {
        let k1 = (k + 1) % t;
        let (ea, eb) = (&exact_rows[k], &exact_rows[k1]);
        for (i, ei) in e64.iter_mut().enumerate() {
            *ei = e[(i + t - k) % t];
        }
        let (c0, c1) = (sum_sqrt(ea) / t as f64, sum_sqrt(eb) / t as f64);
        let (w, v) = minimise_interval(ea, eb, &e64, c0, c1);
        if v < result.2 {
            result = (k, w, v);
        }
    }
    let (k, w, _) = result;
    Some(finish_estimate(
        ds,
        dt,
        t,
        c,
        &e,
        &exact_rows[k],
        &exact_rows[(k + 1) % t],
        k,
        w,
    ))
}

/// The exact path: every row of the curve at an integer shift recomputed directly in f64, and
/// every interval that the (exact) Lipschitz bound leaves minimised on them, the most promising
/// first. O(T²·C) in f64 and O(T) minimisations: several times the approximate stage, for the
/// pairs it cannot resolve (rows of very different sizes, a near-perfect match). Among equal
/// minima the lowest interval wins, as in the polish. Its margin need not follow the rows'
/// sizes (its values are exact): a larger one only minimises more intervals.
#[inline(always)]
fn estimate_exact(ds: &[f32], dt: &[f32], t: usize, c: usize) -> YawEstimate {
    let e = diff_sqnorms(ds, t, c);
    let e = &e[..];
    // plain loops, not `map(…).collect()`: the collect's closure is compiled outside this
    // function, without the instruction set it was instantiated for (BENCHMARKS.md, "A branch
    // in the first stage's loop")
    let inv_t = 1.0 / t as f64;
    let mut rows: Vec<Vec<f64>> = Vec::with_capacity(t);
    let mut cint: Vec<f64> = Vec::with_capacity(t);
    for k in 0..t {
        let row = exact_curve_row(ds, dt, t, c, k);
        cint.push(sum_sqrt(&row) * inv_t);
        rows.push(row);
    }
    let lipschitz = sum_sqrt(e) * inv_t;
    let margin = |b: f64| POLISH_MARGIN * (1.0 + b.abs());
    let mut order: Vec<(f64, usize)> = (0..t)
        .map(|k| (0.5 * (cint[k] + cint[(k + 1) % t] - lipschitz), k))
        .collect();
    order.sort_by(|x, y| x.0.total_cmp(&y.0).then(x.1.cmp(&y.1)));
    // (interval k, w, value), from the best integer shift (its first, at w = 0)
    let mut result = (0usize, 0.0f64, cint[0]);
    for (k, &v) in cint.iter().enumerate() {
        if v < result.2 {
            result = (k, 0.0, v);
        }
    }
    let mut best = result.2;
    let mut e64 = vec![0.0; t];
    for &(lb, k) in &order {
        if lb > best + margin(best) {
            break; // sorted: no later interval can come near the best either
        }
        let k1 = (k + 1) % t;
        for (i, ei) in e64.iter_mut().enumerate() {
            *ei = e[(i + t - k) % t];
        }
        let (w, v) = minimise_interval(&rows[k], &rows[k1], &e64, cint[k], cint[k1]);
        if v < result.2 || (v == result.2 && k < result.0) {
            result = (k, w, v);
        }
        best = best.min(v);
    }
    let (k, w, _) = result;
    finish_estimate(ds, dt, t, c, e, &rows[k], &rows[(k + 1) % t], k, w)
}

/// The estimate at shift `k + w`, from the exact rows `ea`, `eb` of the curve at shifts k and
/// k + 1 (mod T).
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn finish_estimate(
    ds: &[f32],
    dt: &[f32],
    t: usize,
    c: usize,
    e: &[f64],
    ea: &[f64],
    eb: &[f64],
    k: usize,
    w: f64,
) -> YawEstimate {
    // The minimiser's value is the expanded quadratic (1−w)a + wb − w(1−w)e in f64, which
    // cancels where a row matches closely: those rows are summed literally, so that the cost
    // is c(s*) to f64 rounding.
    let mut cost = 0.0;
    for i in 0..t {
        let ei = e[(i + t - k) % t];
        let mut f = ((1.0 - w) * ea[i] + w * eb[i] - w * (1.0 - w) * ei).max(0.0);
        if f < NEAR_ZERO_REL * (ea[i] + eb[i] + ei) {
            f = interpolated_sqdist(ds, dt, t, c, k, w, i);
        }
        cost += f.sqrt();
    }
    let mut shift = k as f64 + w;
    if shift >= t as f64 {
        shift -= t as f64;
    }
    YawEstimate {
        shift,
        yaw: shift_to_yaw(shift, t),
        cost: cost / t as f64,
    }
}

/// A bound, relative to `s = (1/2T)·Σᵢ (aᵢ + bᵢ + eᵢ)/sqrt(aᵢ)`, on the error of the f32 end
/// slope `(1/2T)·Σᵢ (bᵢ − aᵢ − eᵢ)/sqrt(aᵢ)` of [`estimate_impl`]'s first pass (and likewise at
/// the other end), for rows of C channels and T shifts. With u = 2⁻²⁴: an entry a of the
/// diagonal table that was not recomputed directly has d² > [`NEAR_ZERO_REL`]·(‖s‖² + ‖t‖²),
/// and its f32 Gram product errs by at most C·u·(‖s‖² + ‖t‖²)/2, so a, b and their f32 storage
/// err by ρ = (C/NEAR_ZERO_REL + 1)·u relatively (recomputed entries by u); 1/sqrt(a) by
/// ρ/2 + 2u; b − a ± e formed in f32 adds u·(a + b + e); the lanes' f32 sums add (T/16 + 1)·u
/// of the sum of magnitudes. A first-order estimate of the worst case (it leaves out products of
/// these errors and a few roundings of u each, far below the Gram term), not the typical error:
/// it costs only the exact minimisation of intervals whose end slope lies within it.
fn slope_error_bound(t: usize, c: usize) -> f64 {
    let u = f32::EPSILON as f64 / 2.0;
    let rho = (c as f64 / NEAR_ZERO_REL + 1.0) * u;
    rho + (rho / 2.0 + 2.0 * u) + u + ((t / LANES) as f64 + 1.0) * u
}

/// φ = 2π·s/T wrapped to (−π, π] for a shift s ∈ [0, T), in bins first so that s = T/2 gives
/// exactly π (2π·s/T rounds above π for some T, and the wrap then gave −π + 4e-16).
fn shift_to_yaw(shift: f64, t: usize) -> f64 {
    let t = t as f64;
    let s = if shift <= 0.5 * t { shift } else { shift - t };
    PI * (2.0 * s / t)
}

/// ‖(1−w)·Ds_{i−k} + w·Ds_{i−k−1} − Dt_i‖² in f64: row i of the curve at s = k + w.
#[inline(always)]
fn interpolated_sqdist(
    ds: &[f32],
    dt: &[f32],
    t: usize,
    c: usize,
    k: usize,
    w: f64,
    i: usize,
) -> f64 {
    let u = row_of(c, ds, (i + t - k) % t);
    let v = row_of(c, ds, (i + 2 * t - k - 1) % t);
    let z = row_of(c, dt, i);
    let mut d2 = 0.0;
    for ch in 0..c {
        let x = (1.0 - w) * u[ch] as f64 + w * v[ch] as f64 - z[ch] as f64;
        d2 += x * x;
    }
    d2
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::{Array3, Axis};

    /// Small deterministic generator for test data.
    fn data(p: usize, t: usize, c: usize, seed: u64) -> Array3<f32> {
        let mut s = seed;
        Array3::from_shape_fn((p, t, c), |_| {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 40) as f32 / (1u64 << 24) as f32) - 0.5
        })
    }

    /// Literal cost at a real shift: roll-interpolate the source rows, mean row distance (f64).
    fn literal_cost(ds: &ndarray::ArrayView2<f32>, dt: &ndarray::ArrayView2<f32>, s: f64) -> f64 {
        let (t, c) = ds.dim();
        let k = s.floor();
        let w = s - k;
        let k = k as i64;
        let mut sum = 0.0;
        for i in 0..t {
            let u = ((i as i64 - k).rem_euclid(t as i64)) as usize;
            let v = ((i as i64 - k - 1).rem_euclid(t as i64)) as usize;
            let mut d2 = 0.0;
            for ch in 0..c {
                let x = (1.0 - w) * ds[[u, ch]] as f64 + w * ds[[v, ch]] as f64;
                let d = x - dt[[i, ch]] as f64;
                d2 += d * d;
            }
            sum += d2.sqrt();
        }
        sum / t as f64
    }

    #[test]
    fn yaw_costs_match_literal_integer_shifts() {
        // T on both sides of the tables' row padding (rows of 16), C on both sides of a vector
        for (t, c) in [
            (2, 1),
            (5, 3),
            (12, 37),
            (16, 16),
            (17, 16),
            (32, 17),
            (33, 48),
        ] {
            let (s, g) = (data(3, t, c, 1), data(3, t, c, 2));
            assert_literal_curves(&s, &g, |want| 1e-5 * (1.0 + want));
        }
    }

    /// `yaw_costs` of the pairs `s`, `g` against [`literal_cost`] at every integer shift,
    /// within `tol(literal)`.
    fn assert_literal_curves(s: &Array3<f32>, g: &Array3<f32>, tol: impl Fn(f64) -> f64) {
        let out = yaw_costs(s.view(), g.view()).unwrap();
        let (p, t, _) = s.dim();
        for q in 0..p {
            for k in 0..t {
                let want = literal_cost(
                    &s.index_axis(Axis(0), q),
                    &g.index_axis(Axis(0), q),
                    k as f64,
                );
                assert!(
                    (out[[q, k]] - want).abs() <= tol(want),
                    "pair {q}, shift {k}"
                );
            }
        }
    }

    #[test]
    fn rows_beyond_float32_are_refused_and_the_bound_itself_works() {
        let (s, g) = (data(2, 6, 4, 5), data(2, 6, 4, 6));
        // 1e19 per element: squared row norms ~1e37-1e38, whose Gram products overflow f32
        for (arg, big_s, big_g) in [("src", 4e19f32, 1.0f32), ("tgt", 1.0, 4e19)] {
            let (bs, bg) = (s.mapv(|v| v * big_s), g.mapv(|v| v * big_g));
            for r in [
                yaw_costs(bs.view(), bg.view()).map(|_| ()),
                estimate_yaw(bs.view(), bg.view()).map(|_| ()),
                rerank(bs.view(), bg.view()).map(|_| ()),
                matching_cost(bs.view(), bg.view()).map(|_| ()),
            ] {
                let e = r.unwrap_err().to_string();
                assert!(e.contains("values too large"), "{e}");
                assert!(e.starts_with(arg) || e.starts_with(if arg == "src" { "a" } else { "b" }));
            }
        }
        // just inside the bound (4 elements of 1.6e18: norm² 0.98e37) every result is finite
        let scale = (MAX_ROW_SQNORM / 4.0).sqrt() as f32 * 0.99;
        let (bs, bg) = (
            s.mapv(|v| v.signum() * scale),
            g.mapv(|v| v.signum() * scale),
        );
        let curve = yaw_costs(bs.view(), bg.view()).unwrap();
        assert!(curve.iter().all(|v| v.is_finite()));
        assert!(estimate_yaw(bs.view(), bg.view())
            .unwrap()
            .iter()
            .all(|e| e.cost.is_finite() && e.shift.is_finite()));
    }

    #[test]
    fn tiny_pairs_are_rescaled_not_lost_below_float32s_normal_range() {
        // at 1e-25 the squared distances underflowed the f32 tables: every cost came out 0
        let (t, c) = (12, 7);
        let (s0, g0) = (data(2, t, c, 21), data(2, t, c, 22));
        let want = yaw_costs(s0.view(), g0.view()).unwrap();
        let est0 = estimate_yaw(s0.view(), g0.view()).unwrap();
        for scale in [1e-12f32, 1e-19, 1e-23, 1e-25, 1e-30, 1e-36] {
            // a power of two near `scale`, so that the scaled data is exact (no subnormals)
            let p2 = 2f32.powi(scale.log2().round() as i32);
            let (s, g) = (s0.mapv(|v| v * p2), g0.mapv(|v| v * p2));
            let got = yaw_costs(s.view(), g.view()).unwrap();
            for (a, b) in got.iter().zip(want.iter()) {
                let a = a / p2 as f64;
                assert!((a - b).abs() <= 1e-6 * b, "{scale}: {a} vs {b}");
            }
            let est = estimate_yaw(s.view(), g.view()).unwrap();
            for (e, e0) in est.iter().zip(&est0) {
                assert!(
                    (e.cost / p2 as f64 - e0.cost).abs() <= 1e-9 * e0.cost,
                    "{scale}"
                );
                assert!((e.shift - e0.shift).abs() <= 1e-6, "{scale}");
            }
        }
        // subnormal values too: each matches the literal curve
        let s = s0.mapv(|v| v * 1e-40);
        let g = g0.mapv(|v| v * 1e-40);
        assert_literal_curves(&s, &g, |lit| 1e-6 * lit);
        // all zeros stay zeros
        let z = Array3::<f32>::zeros((1, t, c));
        assert!(yaw_costs(z.view(), z.view())
            .unwrap()
            .iter()
            .all(|&v| v == 0.0));
    }

    #[test]
    fn the_yaw_kernels_of_an_empty_batch_are_empty() {
        for (pt, t) in [(0usize, 8usize), (1, 8)] {
            let src = Array3::<f32>::zeros((0, t, 4));
            let tgt = Array3::<f32>::ones((pt, t, 4));
            assert_eq!(yaw_costs(src.view(), tgt.view()).unwrap().dim(), (0, t));
            assert!(estimate_yaw(src.view(), tgt.view()).unwrap().is_empty());
            let r = rerank(src.view(), tgt.view()).unwrap();
            assert!(r.order.is_empty() && r.estimates.is_empty());
        }
        // nothing is allocated for an empty batch, however long its rows
        let huge = Array3::<f32>::zeros((0, 1 << 24, 4));
        assert!(estimate_yaw(huge.view(), huge.view()).unwrap().is_empty());
        // the other checks still apply to an empty batch
        let src = Array3::<f32>::zeros((0, 1, 4));
        assert!(estimate_yaw(src.view(), src.view()).is_err());
        let tgt = Array3::<f32>::zeros((2, 8, 4));
        assert!(estimate_yaw(Array3::<f32>::zeros((0, 8, 4)).view(), tgt.view()).is_err());
    }

    #[test]
    fn matching_cost_of_an_empty_batch_is_empty() {
        let e = Array3::<f32>::zeros((0, 4, 3));
        assert_eq!(
            matching_cost(e.view(), e.view()).unwrap(),
            Vec::<f64>::new()
        );
    }

    #[test]
    fn a_curve_table_larger_than_memory_is_an_error() {
        let x = Array3::<f32>::zeros((1, 1 << 24, 1));
        let r = yaw_costs(x.view(), x.view());
        assert!(matches!(r, Err(Error::Memory { arg: "src", .. })), "{r:?}");
    }

    #[test]
    fn estimate_yaw_is_the_dense_minimum() {
        for (t, c) in [
            (3, 3),
            (7, 5),
            (16, 20),
            (17, 16),
            (24, 33),
            (32, 8),
            (40, 64),
        ] {
            let (s, g) = (data(4, t, c, 3), data(4, t, c, 4));
            let est = estimate_yaw(s.view(), g.view()).unwrap();
            for q in 0..4 {
                let (ds, dt) = (s.index_axis(Axis(0), q), g.index_axis(Axis(0), q));
                let dense = (0..t * 200)
                    .map(|m| literal_cost(&ds, &dt, m as f64 / 200.0))
                    .fold(f64::INFINITY, f64::min);
                let e = est[q];
                assert!(e.cost <= dense + 1e-9, "{t} {c}: {} > {dense}", e.cost);
                assert!((literal_cost(&ds, &dt, e.shift) - e.cost).abs() < 1e-9);
                assert!((0.0..t as f64).contains(&e.shift));
                assert!(e.yaw > -PI && e.yaw <= PI);
            }
        }
    }

    #[test]
    fn recovers_an_exact_fractional_roll() {
        let (t, c) = (36, 20);
        let s = data(1, t, c, 5);
        for s_true in [0.0, 3.25, 17.5, 35.9] {
            let k = f64::floor(s_true);
            let w = s_true - k;
            let ds = s.index_axis(Axis(0), 0);
            let dt = Array3::from_shape_fn((1, t, c), |(_, i, ch)| {
                let u = ((i as i64 - k as i64).rem_euclid(t as i64)) as usize;
                let v = ((i as i64 - k as i64 - 1).rem_euclid(t as i64)) as usize;
                ((1.0 - w) * ds[[u, ch]] as f64 + w * ds[[v, ch]] as f64) as f32
            });
            let e = estimate_yaw(s.view(), dt.view()).unwrap()[0];
            assert!((e.shift - s_true).abs() < 1e-4, "{s_true}: {e:?}");
            assert!(e.cost < 1e-5, "{e:?}");
        }
    }

    #[test]
    fn finds_a_close_match_just_below_a_whole_bin() {
        // the minimum at k + 1 − ε, ε ~ 1e-4: its interval's value at the end tangents' meeting
        // point was read in f32 from 1 − (wx as f32), ~1e-4 too high, and the interval [k+1, k+2]
        // (a local minimum ~1e-4 above) won
        let (t, c) = (40, 16);
        for seed in 0..8 {
            let s = data(1, t, c, 100 + seed);
            let ds = s.index_axis(Axis(0), 0);
            for eps in [2e-5, 8e-5, 1.5e-4, 4e-4] {
                let s_true = 7.0 - eps;
                let (k, w) = (6i64, 1.0 - eps);
                let dt = Array3::from_shape_fn((1, t, c), |(_, i, ch)| {
                    let u = ((i as i64 - k).rem_euclid(t as i64)) as usize;
                    let v = ((i as i64 - k - 1).rem_euclid(t as i64)) as usize;
                    ((1.0 - w) * ds[[u, ch]] as f64 + w * ds[[v, ch]] as f64) as f32
                });
                for isa in [Isa::detect(), Isa::Generic] {
                    let (src, tgt) = (s.as_slice().unwrap(), dt.as_slice().unwrap());
                    let e = isa.estimate(src, tgt, t, c);
                    assert!(
                        (e.shift - s_true).abs() < 1e-6,
                        "{seed} {eps} {isa:?}: {e:?}"
                    );
                }
            }
        }
    }

    #[test]
    fn the_exact_path_is_the_approximate_stage_where_both_are_exact() {
        // ordinary pairs (unit rows, no near-perfect match) take the approximate stage; the
        // exact path must give them the same minimum
        for (t, c) in [(3, 3), (7, 5), (17, 16), (40, 64)] {
            let (s, g) = (data(4, t, c, 5), data(4, t, c, 6));
            for q in 0..4 {
                let (ds, dt) = (
                    s.index_axis(Axis(0), q).to_owned(),
                    g.index_axis(Axis(0), q).to_owned(),
                );
                let (ds, dt) = (ds.as_slice().unwrap(), dt.as_slice().unwrap());
                let fast = estimate_impl(ds, dt, t, c, &GenericGram).expect("approximate stage");
                let exact = estimate_exact(ds, dt, t, c);
                assert!(
                    (fast.cost - exact.cost).abs() < 1e-12,
                    "{t} {c}: {fast:?} {exact:?}"
                );
                let d = (fast.shift - exact.shift).abs();
                assert!(d.min(t as f64 - d) < 1e-6, "{t} {c}: {fast:?} {exact:?}");
            }
        }
    }

    #[test]
    fn a_near_perfect_match_keeps_its_basin_against_a_half_turn_twin() {
        // Ds's two halves differ by 1e-5, Dt is Ds rolled by s0: the basin half a turn away
        // costs ~1e-5 more, within the f32 tables' error near a perfect match, and the
        // approximate stage alone chose it for 17 of 40 such pairs (T = 24, C = 16)
        let (t, c) = (24, 16);
        let h = data(1, t / 2, c, 9);
        let p = data(1, t / 2, c, 10);
        let mut ds = vec![0.0f32; t * c];
        for j in 0..t {
            for ch in 0..c {
                let base = h[[0, j % (t / 2), ch]];
                ds[j * c + ch] = if j < t / 2 {
                    base
                } else {
                    base + 1e-5 * p[[0, j - t / 2, ch]]
                };
            }
        }
        let s0: f64 = 5.3;
        let dsv = ndarray::ArrayView2::from_shape((t, c), &ds).unwrap();
        let mut dt = vec![0.0f32; t * c];
        for i in 0..t {
            // the interpolated roll ρ(Ds, s0) in f64, as the module docs define it
            let (k, w) = (s0.floor() as usize, s0 - s0.floor());
            for ch in 0..c {
                let u = dsv[[(i + t - k) % t, ch]] as f64;
                let v = dsv[[(i + 2 * t - k - 1) % t, ch]] as f64;
                dt[i * c + ch] = ((1.0 - w) * u + w * v) as f32;
            }
        }
        let dtv = ndarray::ArrayView2::from_shape((t, c), &dt).unwrap();
        let at_s0 = literal_cost(&dsv, &dtv, s0);
        let twin = literal_cost(&dsv, &dtv, s0 + (t / 2) as f64);
        // the twin basin is worse, and the approximate stage hands the pair on (a near-perfect
        // match)
        assert!(twin > at_s0 + 1e-6, "{twin} {at_s0}");
        assert!(estimate_impl(&ds, &dt, t, c, &GenericGram).is_none());
        for isa in [Isa::detect(), Isa::Generic] {
            let e = isa.estimate(&ds, &dt, t, c);
            assert!((e.shift - s0).abs() < 1e-3, "{isa:?}: {e:?}");
            // at a cost of ~2e-8 the f64 expanded quadratic's own rounding is ~1e-8
            assert!(e.cost <= at_s0 + 1e-9, "{isa:?}: {} > {at_s0}", e.cost);
        }
    }

    #[test]
    fn rows_of_very_different_sizes_keep_the_interior_minimum() {
        // rows of sizes 1 to 1e6 in one descriptor: the f32 end slope of the best interval
        // came out −391 where it is +64.5 (b − a + e cancels), the interval was taken as
        // minimal at an end and the estimate was half a turn off, 0.02 % too costly
        let s = Array3::from_shape_vec((1, 4, 1), vec![-1.0f32, 1.1e6, 1.0, -130.0]).unwrap();
        let g = Array3::from_shape_vec((1, 4, 1), vec![35000.0f32, -180.0, 4000.0, -17.0]).unwrap();
        let (ds, dt) = (s.index_axis(Axis(0), 0), g.index_axis(Axis(0), 0));
        let dense = (0..4 * 2000)
            .map(|m| literal_cost(&ds, &dt, m as f64 / 2000.0))
            .fold(f64::INFINITY, f64::min);
        for isa in [Isa::detect(), Isa::Generic] {
            let e = isa.estimate(s.as_slice().unwrap(), g.as_slice().unwrap(), 4, 1);
            assert!((e.shift - 2.0318).abs() < 1e-3, "{isa:?}: {e:?}");
            assert!(
                e.cost <= dense * (1.0 + 1e-12),
                "{isa:?}: {} > {dense}",
                e.cost
            );
        }
    }

    #[test]
    fn shared_target_and_rerank_order() {
        let (t, c) = (10, 8);
        let s = data(5, t, c, 7);
        let g = data(1, t, c, 8);
        let full = g.broadcast((5, t, c)).unwrap().to_owned();
        let a = estimate_yaw(s.view(), g.view()).unwrap();
        let b = estimate_yaw(s.view(), full.view()).unwrap();
        assert_eq!(a, b);
        let r = rerank(s.view(), g.view()).unwrap();
        for w in r.order.windows(2) {
            assert!(r.estimates[w[0]].cost <= r.estimates[w[1]].cost);
        }
        let mut sorted = r.order.clone();
        sorted.sort_unstable();
        assert_eq!(sorted, (0..5).collect::<Vec<_>>());
    }

    #[test]
    fn environment_switches_are_on_unless_unset_empty_or_zero() {
        for (v, on) in [
            (None, false),
            (Some(""), false),
            (Some("0"), false),
            (Some(" 0 "), false),
        ] {
            assert_eq!(switch_on(v), on, "{v:?}");
        }
        for v in ["1", "yes", "true", "2"] {
            assert!(switch_on(Some(v)), "{v}");
        }
    }

    #[test]
    fn generic_path_agrees_with_simd_path() {
        // every instruction set this CPU has (AVX-512 and AVX2 both run where AVX-512 does)
        let mut isas = vec![Isa::Generic];
        #[cfg(target_arch = "x86_64")]
        {
            if is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma") {
                isas.push(Isa::Avx2);
            }
            if is_x86_feature_detected!("avx512f")
                && is_x86_feature_detected!("avx2")
                && is_x86_feature_detected!("fma")
            {
                isas.push(Isa::Avx512);
            }
        }
        for (t, c) in [(20, 45), (32, 64), (13, 7), (8, 256)] {
            let (s, g) = (data(3, t, c, 9), data(3, t, c, 10));
            for q in 0..3 {
                let (ds, dt) = (s.index_axis(Axis(0), q), g.index_axis(Axis(0), q));
                let (ds, dt) = (ds.as_slice().unwrap(), dt.as_slice().unwrap());
                let a = Isa::Generic.estimate(ds, dt, t, c);
                let x = curve_impl(ds, dt, t, c, true, &GenericGram);
                for &isa in &isas {
                    let b = isa.estimate(ds, dt, t, c);
                    assert!(
                        (a.cost - b.cost).abs() < 1e-9 && (a.shift - b.shift).abs() < 1e-6,
                        "{isa:?} {t} {c}"
                    );
                    // the Gram-derived tables: each tile's sums agree with the portable ones
                    let y = isa.curve(ds, dt, t, c, true);
                    assert_eq!(x.stride, y.stride);
                    for (u, v) in x.dg.iter().zip(&y.dg) {
                        assert!((u - v).abs() <= 1e-5 * (1.0 + u.abs()), "{isa:?} {t} {c}");
                    }
                }
            }
        }
    }

    #[test]
    fn matching_cost_is_mean_row_distance() {
        let (a, b) = (data(2, 6, 9, 11), data(2, 6, 9, 12));
        let got = matching_cost(a.view(), b.view()).unwrap();
        for q in 0..2 {
            let want = literal_cost(&a.index_axis(Axis(0), q), &b.index_axis(Axis(0), q), 0.0);
            assert!((got[q] - want).abs() < 1e-12);
        }
    }

    #[test]
    fn bad_inputs_are_errors() {
        let ok = data(2, 4, 3, 1);
        assert!(estimate_yaw(ok.view(), data(2, 5, 3, 1).view()).is_err());
        assert!(estimate_yaw(ok.view(), data(2, 4, 2, 1).view()).is_err());
        assert!(estimate_yaw(ok.view(), data(3, 4, 3, 1).view()).is_err());
        assert!(estimate_yaw(data(2, 1, 3, 1).view(), data(2, 1, 3, 1).view()).is_err());
        // an empty batch is no error: nothing to estimate
        assert!(
            estimate_yaw(data(0, 4, 3, 1).view(), data(0, 4, 3, 1).view())
                .unwrap()
                .is_empty()
        );
        let mut nan = ok.clone();
        nan[[1, 2, 0]] = f32::NAN;
        assert!(matches!(
            yaw_costs(ok.view(), nan.view()),
            Err(Error::Value { arg: "tgt", .. })
        ));
        assert!(matching_cost(ok.view(), data(2, 4, 4, 1).view()).is_err());
    }

    #[test]
    fn two_bins_give_cost_curves_but_no_yaw() {
        // with T = 2 every curve is symmetric, c(s) = c(2 - s): the yaw's sign is undetermined
        let (src, tgt) = (data(3, 2, 4, 5), data(3, 2, 4, 6));
        let curves = yaw_costs(src.view(), tgt.view()).unwrap();
        for q in 0..3 {
            let (ds, dt) = (src.index_axis(Axis(0), q), tgt.index_axis(Axis(0), q));
            let (a, b) = (literal_cost(&ds, &dt, 0.3), literal_cost(&ds, &dt, 1.7));
            assert!((a - b).abs() <= 1e-12 * a.abs().max(1.0), "{a} vs {b}");
            assert!(curves[[q, 0]].is_finite() && curves[[q, 1]].is_finite());
        }
        for result in [
            estimate_yaw(src.view(), tgt.view()).map(|_| ()),
            rerank(src.view(), tgt.view()).map(|_| ()),
        ] {
            let message = result.unwrap_err().to_string();
            assert!(
                message.starts_with("src: expected shape (P, T, C) with T >= 3"),
                "{message}"
            );
        }
        assert!(estimate_yaw(data(3, 3, 4, 5).view(), data(3, 3, 4, 6).view()).is_ok());
    }
}
