//! Distance micro-kernels over the blocked map layout, with run-time CPU feature dispatch.
//!
//! The map is stored in blocks of [`BLOCK`] = 16 rows, dimension-major inside a block: element
//! (row `i`, dimension `j`) of block `b = i / 16` lies at `(b * d + j) * 16 + i % 16`. One
//! 512-bit register thus holds one dimension of 16 rows, and a dot product needs no horizontal
//! sum. Every kernel computes, for each (query, row) pair, `acc = fma(q[j], x[j], acc)` for
//! `j = 0, 1, …, d-1` starting from `acc = 0`, one accumulator per pair: the float32 result is
//! bitwise the same in the AVX-512, AVX2+FMA and portable paths, for any tiling, so the single
//! query, batch and re-scoring paths agree exactly and results never depend on the thread count.
//!
//! Compressed layouts: float16 uses the same layout with `u16` elements; bfloat16 packs pairs of
//! dimensions, element (i, j) at `((b * dp + j / 2) * 16 + i % 16) * 2 + j % 2` with
//! `dp = ceil(d / 2)`, so that `vdpbf16ps` consumes one pair of dimensions of 16 rows per
//! instruction.

// Index loops mirror the register layout (t = query, g = block, l = lane) and read best as is.
#![allow(clippy::needless_range_loop)]

use half::{bf16, f16};
use std::sync::OnceLock;

#[cfg(target_arch = "x86_64")]
use std::arch::x86_64::*;

/// Rows per block of the map layout.
pub const BLOCK: usize = 16;

/// The instruction set the kernels use, detected once at run time.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Level {
    /// AVX-512F (+ optional AVX-512 BF16 for the bfloat16 scan, AVX-512 VNNI + BW for int8).
    Avx512 { bf16: bool, vnni: bool },
    /// AVX2 + FMA: the generic kernels compiled with these features (auto-vectorised).
    Avx2,
    /// Portable Rust (any CPU).
    Portable,
}

/// The best level this CPU supports.
pub fn detect() -> Level {
    static LEVEL: OnceLock<Level> = OnceLock::new();
    *LEVEL.get_or_init(|| {
        #[cfg(target_arch = "x86_64")]
        {
            // Avx512 also runs AVX2+FMA code (norms, int8 without VNNI): require both, as a
            // VM may expose AVX-512F while hiding them
            if is_x86_feature_detected!("avx512f") && has_avx2_fma() {
                return Level::Avx512 {
                    bf16: is_x86_feature_detected!("avx512bf16"),
                    vnni: has_vnni(),
                };
            }
            if has_avx2_fma() {
                return Level::Avx2;
            }
        }
        Level::Portable
    })
}

#[cfg(target_arch = "x86_64")]
fn has_avx2_fma() -> bool {
    is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma")
}

#[cfg(target_arch = "x86_64")]
fn has_vnni() -> bool {
    is_x86_feature_detected!("avx512vnni") && is_x86_feature_detected!("avx512bw")
}

/// Every level this CPU can run (for tests that compare the paths).
pub fn available_levels() -> Vec<Level> {
    let mut v = vec![Level::Portable];
    #[cfg(target_arch = "x86_64")]
    {
        if has_avx2_fma() {
            v.push(Level::Avx2);
        }
        if is_x86_feature_detected!("avx512f") && has_avx2_fma() {
            v.push(Level::Avx512 {
                bf16: false,
                vnni: false,
            });
            let (bf16, vnni) = (is_x86_feature_detected!("avx512bf16"), has_vnni());
            if bf16 || vnni {
                v.push(Level::Avx512 { bf16, vnni });
            }
        }
    }
    v
}

// ---------------------------------------------------------------------------------------------
// The kernels below dispatch on a `Level` to `unsafe` `#[target_feature]` code. They are
// `pub(crate)`: inside this crate every `Level` is `detect()`'s or one of `available_levels()`
// (`DescriptorIndex::with_level` checks), so a level names only instructions this CPU has. Their
// length checks multiply with `fits`, whose products cannot wrap: a wrapped product would have
// passed a check and let the vector code read past a slice.

/// Whether `len >= factors[0] * factors[1] * …`, without overflow (a product past `usize::MAX`
/// exceeds every slice).
fn fits(len: usize, factors: &[usize]) -> bool {
    factors
        .iter()
        .try_fold(1usize, |p, &f| p.checked_mul(f))
        .is_some_and(|n| len >= n)
}

// float32 tiles: QT queries × G blocks.

/// Dot products of `QT` queries (rows of `q`, each of length `d`) with the `G` consecutive blocks
/// starting at `blocks[0]`; `out[t * G * 16 + g * 16 + l]` = query t · row l of block g.
///
/// Panics (a bug, never user input) if a slice is too short.
pub(crate) fn tile_f32<const QT: usize, const G: usize>(
    level: Level,
    q: &[f32],
    d: usize,
    blocks: &[f32],
    out: &mut [f32],
) {
    assert!(
        fits(q.len(), &[QT, d])
            && fits(blocks.len(), &[G, d, BLOCK])
            && fits(out.len(), &[QT, G, BLOCK])
    );
    match level {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: `level` is Avx512 only when `detect`/`available_levels` found avx512f on this
        // CPU (the function is crate-private, see above); the slice lengths were checked above.
        Level::Avx512 { .. } => unsafe { tile_f32_avx512::<QT, G>(q, d, blocks, out) },
        #[cfg(target_arch = "x86_64")]
        // SAFETY: Avx2 is only produced after detecting avx2 and fma.
        Level::Avx2 => unsafe { tile_f32_avx2::<QT, G>(q, d, blocks, out) },
        _ => tile_f32_generic::<QT, G>(q, d, blocks, out),
    }
}

#[inline(always)]
fn tile_f32_generic<const QT: usize, const G: usize>(
    q: &[f32],
    d: usize,
    blocks: &[f32],
    out: &mut [f32],
) {
    let mut acc = [[[0f32; BLOCK]; G]; QT];
    for j in 0..d {
        for g in 0..G {
            let x: &[f32; BLOCK] = blocks[(g * d + j) * BLOCK..][..BLOCK].try_into().unwrap();
            for (t, acc_t) in acc.iter_mut().enumerate() {
                let qv = q[t * d + j];
                for l in 0..BLOCK {
                    acc_t[g][l] = qv.mul_add(x[l], acc_t[g][l]);
                }
            }
        }
    }
    for t in 0..QT {
        for g in 0..G {
            out[(t * G + g) * BLOCK..][..BLOCK].copy_from_slice(&acc[t][g]);
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn tile_f32_avx2<const QT: usize, const G: usize>(
    q: &[f32],
    d: usize,
    blocks: &[f32],
    out: &mut [f32],
) {
    tile_f32_generic::<QT, G>(q, d, blocks, out)
}

/// The `QT` × `G` accumulators of [`tile_f32`]'s AVX-512 path: `acc[t][g]` lane l = query t ·
/// row l of block g, `fma` over j = 0..d in order.
///
/// # Safety
/// avx512f must be available; `q.len() >= QT * d` and `blocks.len() >= G * d * 16`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[inline]
unsafe fn tile_acc_avx512<const QT: usize, const G: usize>(
    q: &[f32],
    d: usize,
    blocks: &[f32],
) -> [[__m512; G]; QT] {
    let mut acc = [[_mm512_setzero_ps(); G]; QT];
    let mut x = [_mm512_setzero_ps(); G];
    let bp = blocks.as_ptr();
    let qp = q.as_ptr();
    for j in 0..d {
        for g in 0..G {
            // SAFETY: (g*d + j)*16 + 16 <= G*d*16 <= blocks.len() (checked by the caller).
            x[g] = unsafe { _mm512_loadu_ps(bp.add((g * d + j) * BLOCK)) };
        }
        for (t, acc_t) in acc.iter_mut().enumerate() {
            // SAFETY: t*d + j < QT*d <= q.len().
            let qv = _mm512_set1_ps(unsafe { *qp.add(t * d + j) });
            for g in 0..G {
                acc_t[g] = _mm512_fmadd_ps(qv, x[g], acc_t[g]);
            }
        }
    }
    acc
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn tile_f32_avx512<const QT: usize, const G: usize>(
    q: &[f32],
    d: usize,
    blocks: &[f32],
    out: &mut [f32],
) {
    // SAFETY: the caller checked the slice lengths.
    let acc = unsafe { tile_acc_avx512::<QT, G>(q, d, blocks) };
    for t in 0..QT {
        for g in 0..G {
            // SAFETY: (t*G + g)*16 + 16 <= QT*G*16 <= out.len().
            unsafe { _mm512_storeu_ps(out.as_mut_ptr().add((t * G + g) * BLOCK), acc[t][g]) };
        }
    }
}

/// Squared distances of `QT` queries to the rows of the `G` consecutive blocks starting at
/// `blocks[0]`, and per (query, block) the mask of rows below the query's threshold: for query t
/// (squared norm `qn[t]`, threshold `thr[t]`) and block g (rows' squared norms
/// `xn[g * 16..(g + 1) * 16]`), `sq[(t * G + g) * 16 + l]` and bit l of `masks[t * G + g]` are
/// what [`block_sq`] gives for the dot products [`tile_f32`] gives: the same bits, on every level.
/// The AVX-512 path forms them from the accumulators in registers, without storing the dot
/// products and calling [`block_sq`] per block.
///
/// Panics (a bug, never user input) if a slice is too short.
#[allow(clippy::too_many_arguments)]
pub(crate) fn tile_sq_f32<const QT: usize, const G: usize>(
    level: Level,
    q: &[f32],
    d: usize,
    blocks: &[f32],
    qn: &[f32],
    xn: &[f32],
    thr: &[f32],
    sq: &mut [f32],
    masks: &mut [u16],
) {
    assert!(
        fits(q.len(), &[QT, d])
            && fits(blocks.len(), &[G, d, BLOCK])
            && qn.len() >= QT
            && thr.len() >= QT
            && fits(xn.len(), &[G, BLOCK])
            && fits(sq.len(), &[QT, G, BLOCK])
            && masks.len() >= QT * G
    );
    match level {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: `level` is Avx512 only when avx512f was detected on this CPU (see
        // `tile_f32`); the slice lengths were checked above.
        Level::Avx512 { .. } => unsafe {
            tile_sq_f32_avx512::<QT, G>(q, d, blocks, qn, xn, thr, sq, masks)
        },
        _ => {
            tile_f32::<QT, G>(level, q, d, blocks, sq);
            for t in 0..QT {
                for g in 0..G {
                    let i = t * G + g;
                    let dots = &mut sq[i * BLOCK..(i + 1) * BLOCK];
                    let (s, below) =
                        block_sq(level, qn[t], &xn[g * BLOCK..(g + 1) * BLOCK], dots, thr[t]);
                    dots.copy_from_slice(&s);
                    masks[i] = below;
                }
            }
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[allow(clippy::too_many_arguments)]
unsafe fn tile_sq_f32_avx512<const QT: usize, const G: usize>(
    q: &[f32],
    d: usize,
    blocks: &[f32],
    qn: &[f32],
    xn: &[f32],
    thr: &[f32],
    sq: &mut [f32],
    masks: &mut [u16],
) {
    // SAFETY: the caller checked the slice lengths.
    let acc = unsafe { tile_acc_avx512::<QT, G>(q, d, blocks) };
    let mut x = [_mm512_setzero_ps(); G];
    for g in 0..G {
        // SAFETY: g*16 + 16 <= G*16 <= xn.len().
        x[g] = unsafe { _mm512_loadu_ps(xn.as_ptr().add(g * BLOCK)) };
    }
    for t in 0..QT {
        let (qv, tv) = (_mm512_set1_ps(qn[t]), _mm512_set1_ps(thr[t]));
        for g in 0..G {
            let (s, below) = sq_below_avx512(qv, x[g], acc[t][g], tv);
            // SAFETY: (t*G + g)*16 + 16 <= QT*G*16 <= sq.len().
            unsafe { _mm512_storeu_ps(sq.as_mut_ptr().add((t * G + g) * BLOCK), s) };
            masks[t * G + g] = below;
        }
    }
}

/// [`block_sq`]'s arithmetic on registers: `qn` and `thr` broadcast, `xn` the rows' squared norms,
/// `dots` their dot products with the query.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[inline]
fn sq_below_avx512(qn: __m512, xn: __m512, dots: __m512, thr: __m512) -> (__m512, u16) {
    let s = _mm512_sub_ps(_mm512_add_ps(qn, xn), _mm512_add_ps(dots, dots));
    // vmaxps returns its second operand when the first is NaN or both are zeros: +0 then, as
    // f32::max gives for NaN (and -0 cannot occur: (qn + xn) >= +0 and a - a = +0)
    let s = _mm512_max_ps(s, _mm512_setzero_ps());
    (s, _mm512_cmp_ps_mask::<_CMP_LT_OQ>(s, thr))
}

/// Squared distances of one block's 16 rows to a query of squared norm `qn`, from the rows'
/// squared norms `xn` and their dot products `dots` with it: `sq[l] = max((qn + xn[l]) −
/// 2·dots[l], 0)`, each operation rounded once in float32 (2·dots is exact), so every level gives
/// the same bits; and the mask of those below `thr` (bit l: row l). A NaN becomes 0 on every
/// level (none occurs: the index holds finite values).
///
/// Panics (a bug, never user input) if a slice is shorter than a block.
pub(crate) fn block_sq(
    level: Level,
    qn: f32,
    xn: &[f32],
    dots: &[f32],
    thr: f32,
) -> ([f32; BLOCK], u16) {
    assert!(xn.len() >= BLOCK && dots.len() >= BLOCK);
    match level {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: Avx512 only after detecting avx512f (see above); the lengths were checked.
        Level::Avx512 { .. } => unsafe { block_sq_avx512(qn, xn, dots, thr) },
        _ => block_sq_generic(qn, xn, dots, thr),
    }
}

#[inline(always)]
fn block_sq_generic(qn: f32, xn: &[f32], dots: &[f32], thr: f32) -> ([f32; BLOCK], u16) {
    let mut sq = [0f32; BLOCK];
    let mut below = 0u16;
    for l in 0..BLOCK {
        sq[l] = ((qn + xn[l]) - 2.0 * dots[l]).max(0.0);
        below |= u16::from(sq[l] < thr) << l;
    }
    (sq, below)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn block_sq_avx512(qn: f32, xn: &[f32], dots: &[f32], thr: f32) -> ([f32; BLOCK], u16) {
    // SAFETY: both slices hold at least 16 f32 (checked by the caller).
    let (x, d) = unsafe { (_mm512_loadu_ps(xn.as_ptr()), _mm512_loadu_ps(dots.as_ptr())) };
    let (s, below) = sq_below_avx512(_mm512_set1_ps(qn), x, d, _mm512_set1_ps(thr));
    let mut sq = [0f32; BLOCK];
    // SAFETY: `sq` holds 16 f32, the width of one unaligned 512-bit store.
    unsafe { _mm512_storeu_ps(sq.as_mut_ptr(), s) };
    (sq, below)
}

/// Squared norms of the 16 rows of one block (same accumulation order as the dot products).
pub(crate) fn block_norms(level: Level, block: &[f32], d: usize) -> [f32; BLOCK] {
    assert!(fits(block.len(), &[d, BLOCK]));
    #[inline(always)]
    fn generic(block: &[f32], d: usize) -> [f32; BLOCK] {
        let mut acc = [0f32; BLOCK];
        for j in 0..d {
            let x = &block[j * BLOCK..][..BLOCK];
            for l in 0..BLOCK {
                acc[l] = x[l].mul_add(x[l], acc[l]);
            }
        }
        acc
    }
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn fast(block: &[f32], d: usize) -> [f32; BLOCK] {
        generic(block, d)
    }
    match level {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: avx2 and fma were detected: `detect` and `available_levels` produce Avx2 and
        // Avx512 only after detecting both (Avx512 also after avx512f).
        Level::Avx2 | Level::Avx512 { .. } => unsafe { fast(block, d) },
        _ => generic(block, d),
    }
}

/// `Σ_j v[j]²` accumulated sequentially with fma (the query-norm convention).
pub(crate) fn norm_sq(level: Level, v: &[f32]) -> f32 {
    #[inline(always)]
    fn generic(v: &[f32]) -> f32 {
        v.iter().fold(0.0f32, |acc, &x| x.mul_add(x, acc))
    }
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn fast(v: &[f32]) -> f32 {
        generic(v)
    }
    match level {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: fma detected (see `block_norms`).
        Level::Avx2 | Level::Avx512 { .. } => unsafe { fast(v) },
        _ => generic(v),
    }
}

/// Continues the dot products of one query with the 16 rows of one block over dimensions
/// `j0..j1`: `acc[l] = fma(q[j], x[j][l], acc[l])` for j = j0, …, j1-1. Starting from zeros at
/// j0 = 0 and continuing to d gives bitwise the [`tile_f32`] result (same fma sequence), so a
/// scan may test a leading block of dimensions first and finish only the rows it keeps.
pub(crate) fn dot_range(
    level: Level,
    q: &[f32],
    block: &[f32],
    j0: usize,
    j1: usize,
    acc: &mut [f32; BLOCK],
) {
    assert!(j0 <= j1 && q.len() >= j1 && fits(block.len(), &[j1, BLOCK]));
    #[inline(always)]
    fn generic(q: &[f32], block: &[f32], j0: usize, j1: usize, acc: &mut [f32; BLOCK]) {
        for j in j0..j1 {
            let x = &block[j * BLOCK..][..BLOCK];
            for l in 0..BLOCK {
                acc[l] = q[j].mul_add(x[l], acc[l]);
            }
        }
    }
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn avx2(q: &[f32], block: &[f32], j0: usize, j1: usize, acc: &mut [f32; BLOCK]) {
        generic(q, block, j0, j1, acc)
    }
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f")]
    unsafe fn avx512(q: &[f32], block: &[f32], j0: usize, j1: usize, acc: &mut [f32; BLOCK]) {
        // SAFETY (all loads/stores): acc holds 16 f32; j < j1 <= q.len() and
        // j*16 + 16 <= j1*16 <= block.len() (checked by the caller).
        let mut a = unsafe { _mm512_loadu_ps(acc.as_ptr()) };
        let bp = block.as_ptr();
        for j in j0..j1 {
            let x = unsafe { _mm512_loadu_ps(bp.add(j * BLOCK)) };
            a = _mm512_fmadd_ps(_mm512_set1_ps(unsafe { *q.get_unchecked(j) }), x, a);
        }
        unsafe { _mm512_storeu_ps(acc.as_mut_ptr(), a) };
    }
    match level {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: avx512f detected; lengths checked above.
        Level::Avx512 { .. } => unsafe { avx512(q, block, j0, j1, acc) },
        #[cfg(target_arch = "x86_64")]
        // SAFETY: avx2 and fma detected.
        Level::Avx2 => unsafe { avx2(q, block, j0, j1, acc) },
        _ => generic(q, block, j0, j1, acc),
    }
}

// ---------------------------------------------------------------------------------------------
// Compressed scans (one query × G blocks). Approximate: callers bound the error and re-score.

/// float16 map × float32 query: `out[g * 16 + l]` ≈ q · row l of block g.
pub(crate) fn scan_f16<const G: usize>(
    level: Level,
    q: &[f32],
    d: usize,
    blocks: &[u16],
    out: &mut [f32],
) {
    assert!(q.len() >= d && fits(blocks.len(), &[G, d, BLOCK]) && fits(out.len(), &[G, BLOCK]));
    match level {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: avx512f detected; lengths checked above.
        Level::Avx512 { .. } => unsafe { scan_f16_avx512::<G>(q, d, blocks, out) },
        _ => {
            let mut acc = [[0f32; BLOCK]; G];
            for j in 0..d {
                for (g, acc_g) in acc.iter_mut().enumerate() {
                    let x = &blocks[(g * d + j) * BLOCK..][..BLOCK];
                    for l in 0..BLOCK {
                        acc_g[l] = q[j].mul_add(f16::from_bits(x[l]).to_f32(), acc_g[l]);
                    }
                }
            }
            for g in 0..G {
                out[g * BLOCK..][..BLOCK].copy_from_slice(&acc[g]);
            }
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn scan_f16_avx512<const G: usize>(q: &[f32], d: usize, blocks: &[u16], out: &mut [f32]) {
    let mut acc = [_mm512_setzero_ps(); G];
    let bp = blocks.as_ptr();
    for j in 0..d {
        let qv = _mm512_set1_ps(q[j]);
        for g in 0..G {
            // SAFETY: 16 u16 at (g*d + j)*16 lie inside blocks (G*d*16 elements, checked).
            let h = unsafe { _mm256_loadu_si256(bp.add((g * d + j) * BLOCK) as *const __m256i) };
            acc[g] = _mm512_fmadd_ps(qv, _mm512_cvtph_ps(h), acc[g]);
        }
    }
    for g in 0..G {
        // SAFETY: g*16 + 16 <= G*16 <= out.len().
        unsafe { _mm512_storeu_ps(out.as_mut_ptr().add(g * BLOCK), acc[g]) };
    }
}

/// The query packed for [`scan_bf16`]: pairs (q[2p], q[2p+1]) rounded to bfloat16, low half first.
pub fn pack_query_bf16(q: &[f32]) -> Vec<u32> {
    q.chunks(2)
        .map(|c| {
            let lo = bf16::from_f32(c[0]).to_bits() as u32;
            let hi = c.get(1).map_or(0, |&v| bf16::from_f32(v).to_bits() as u32);
            lo | (hi << 16)
        })
        .collect()
}

/// bfloat16 map × bfloat16 query (pairs from [`pack_query_bf16`]), `dp = ceil(d/2)`.
pub(crate) fn scan_bf16<const G: usize>(
    level: Level,
    qp: &[u32],
    dp: usize,
    blocks: &[u16],
    out: &mut [f32],
) {
    assert!(
        qp.len() >= dp && fits(blocks.len(), &[G, dp, BLOCK, 2]) && fits(out.len(), &[G, BLOCK])
    );
    match level {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: avx512f and avx512bf16 detected; lengths checked above.
        Level::Avx512 { bf16: true, .. } => unsafe { scan_bf16_avx512::<G>(qp, dp, blocks, out) },
        _ => {
            let mut acc = [[0f32; BLOCK]; G];
            for p in 0..dp {
                let q0 = bf16::from_bits(qp[p] as u16).to_f32();
                let q1 = bf16::from_bits((qp[p] >> 16) as u16).to_f32();
                for (g, acc_g) in acc.iter_mut().enumerate() {
                    let x = &blocks[(g * dp + p) * BLOCK * 2..][..BLOCK * 2];
                    for l in 0..BLOCK {
                        let a = q0.mul_add(bf16::from_bits(x[2 * l]).to_f32(), acc_g[l]);
                        acc_g[l] = q1.mul_add(bf16::from_bits(x[2 * l + 1]).to_f32(), a);
                    }
                }
            }
            for g in 0..G {
                out[g * BLOCK..][..BLOCK].copy_from_slice(&acc[g]);
            }
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bf16")]
unsafe fn scan_bf16_avx512<const G: usize>(qp: &[u32], dp: usize, blocks: &[u16], out: &mut [f32]) {
    let mut acc = [_mm512_setzero_ps(); G];
    let bp = blocks.as_ptr();
    for p in 0..dp {
        // SAFETY: __m512i and __m512bh are both 64-byte plain vectors; every bit pattern is valid.
        let qv: __m512bh = unsafe { std::mem::transmute(_mm512_set1_epi32(qp[p] as i32)) };
        for g in 0..G {
            // SAFETY: 32 u16 at (g*dp + p)*32 lie inside blocks (G*dp*32 elements, checked).
            let x: __m512bh = unsafe {
                std::mem::transmute(_mm512_loadu_si512(
                    bp.add((g * dp + p) * BLOCK * 2) as *const __m512i
                ))
            };
            acc[g] = _mm512_dpbf16_ps(acc[g], qv, x);
        }
    }
    for g in 0..G {
        // SAFETY: g*16 + 16 <= G*16 <= out.len().
        unsafe { _mm512_storeu_ps(out.as_mut_ptr().add(g * BLOCK), acc[g]) };
    }
}

// ---------------------------------------------------------------------------------------------
// int8 scan. Layout: element (i, j) stored as the byte `x̃ + 128` (x̃ ∈ [-127, 127] the quantised
// value) at `((b * d4 + j / 4) * 16 + i % 16) * 4 + j % 4`, `d4 = ceil(d / 4)`, padding 128, so
// that `vpdpbusd` consumes four dimensions of 16 rows per instruction.

/// A query quantised for [`scan_i8`]: `w̃ = 128·h + l` per dimension (h ∈ [-125, 125],
/// l ∈ [-64, 63]), the approximate dot product with row x being `t · Σ_j w̃_j x̃_j`.
#[derive(Clone, Debug)]
pub struct QueryI8 {
    /// High parts h, four dimensions per word (low byte first), `d4` words.
    pub hi: Vec<u32>,
    /// Low parts l, same packing.
    pub lo: Vec<u32>,
    /// `128 · Σ h` and `128 · Σ l` (remove the +128 offset of the map bytes).
    pub corr: [i32; 2],
    /// Scale t of w̃.
    pub t: f64,
}

/// Largest |w̃| of a quantised query.
pub const QMAX: f64 = 16000.0;

impl QueryI8 {
    /// Quantises `w` (the query times the per-dimension map scales) with `t = max|w| / 16000`.
    /// Returns the query and w̃ (for the error bound).
    pub fn new(w: &[f64]) -> (Self, Vec<i32>) {
        let amax = w.iter().fold(0f64, |m, v| m.max(v.abs()));
        let t = if amax > 0.0 { amax / QMAX } else { 1.0 };
        let wq: Vec<i32> = w
            .iter()
            .map(|&v| (v / t).round().clamp(-QMAX, QMAX) as i32)
            .collect();
        let d4 = w.len().div_ceil(4);
        let (mut hi, mut lo) = (vec![0u32; d4], vec![0u32; d4]);
        let (mut sh, mut sl) = (0i32, 0i32);
        for (j, &v) in wq.iter().enumerate() {
            let h = (v + 64).div_euclid(128);
            let l = v - 128 * h;
            sh += h;
            sl += l;
            hi[j / 4] |= ((h as i8) as u8 as u32) << (8 * (j % 4));
            lo[j / 4] |= ((l as i8) as u8 as u32) << (8 * (j % 4));
        }
        (
            QueryI8 {
                hi,
                lo,
                corr: [128 * sh, 128 * sl],
                t,
            },
            wq,
        )
    }
}

/// int8 map × quantised query: `out[g * 16 + l] = f32(t · (128·I_h + I_l))` computed in f64,
/// `I_h = Σ_j x̃_j h_j`, `I_l = Σ_j x̃_j l_j` exact integers (d ≤ 65536), so every level returns
/// bitwise the same values.
pub(crate) fn scan_i8<const G: usize>(
    level: Level,
    q: &QueryI8,
    d4: usize,
    blocks: &[u8],
    out: &mut [f32],
) {
    assert!(
        q.hi.len() >= d4
            && q.lo.len() >= d4
            && fits(blocks.len(), &[G, d4, BLOCK, 4])
            && fits(out.len(), &[G, BLOCK])
    );
    match level {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: avx512f, avx512bw and avx512vnni detected; lengths checked above.
        Level::Avx512 { vnni: true, .. } => unsafe { scan_i8_vnni::<G>(q, d4, blocks, out) },
        #[cfg(target_arch = "x86_64")]
        // SAFETY: avx2 detected (every AVX-512F CPU has it too).
        Level::Avx2 | Level::Avx512 { .. } => unsafe { scan_i8_avx2::<G>(q, d4, blocks, out) },
        _ => scan_i8_generic::<G>(q, d4, blocks, out),
    }
}

#[inline(always)]
fn scan_i8_generic<const G: usize>(q: &QueryI8, d4: usize, blocks: &[u8], out: &mut [f32]) {
    for g in 0..G {
        let mut ih = [0i32; BLOCK];
        let mut il = [0i32; BLOCK];
        for p in 0..d4 {
            let x = &blocks[(g * d4 + p) * BLOCK * 4..][..BLOCK * 4];
            let (hw, lw) = (q.hi[p].to_le_bytes(), q.lo[p].to_le_bytes());
            for l in 0..BLOCK {
                for k in 0..4 {
                    let xv = x[4 * l + k] as i32 - 128;
                    ih[l] += xv * (hw[k] as i8 as i32);
                    il[l] += xv * (lw[k] as i8 as i32);
                }
            }
        }
        for l in 0..BLOCK {
            out[g * BLOCK + l] = ((128.0 * ih[l] as f64 + il[l] as f64) * q.t) as f32;
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn scan_i8_avx2<const G: usize>(q: &QueryI8, d4: usize, blocks: &[u8], out: &mut [f32]) {
    scan_i8_generic::<G>(q, d4, blocks, out)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
unsafe fn scan_i8_vnni<const G: usize>(q: &QueryI8, d4: usize, blocks: &[u8], out: &mut [f32]) {
    let mut ah = [_mm512_setzero_si512(); G];
    let mut al = [_mm512_setzero_si512(); G];
    let bp = blocks.as_ptr();
    for p in 0..d4 {
        let hv = _mm512_set1_epi32(q.hi[p] as i32);
        let lv = _mm512_set1_epi32(q.lo[p] as i32);
        for g in 0..G {
            // SAFETY: 64 bytes at (g*d4 + p)*64 lie inside blocks (G*d4*64 bytes, checked).
            let x =
                unsafe { _mm512_loadu_si512(bp.add((g * d4 + p) * BLOCK * 4) as *const __m512i) };
            // u8 map bytes × i8 query bytes, 4 products summed into each i32 lane (no saturation).
            ah[g] = _mm512_dpbusd_epi32(ah[g], x, hv);
            al[g] = _mm512_dpbusd_epi32(al[g], x, lv);
        }
    }
    let (ch, cl) = (_mm512_set1_epi32(q.corr[0]), _mm512_set1_epi32(q.corr[1]));
    let (c128, t) = (_mm512_set1_pd(128.0), _mm512_set1_pd(q.t));
    for g in 0..G {
        let ih = _mm512_sub_epi32(ah[g], ch);
        let il = _mm512_sub_epi32(al[g], cl);
        for half in 0..2 {
            let (h, l) = if half == 0 {
                (_mm512_castsi512_si256(ih), _mm512_castsi512_si256(il))
            } else {
                (
                    _mm512_extracti64x4_epi64::<1>(ih),
                    _mm512_extracti64x4_epi64::<1>(il),
                )
            };
            // 128·I_h + I_l is exact in f64 (|.| < 2^53); then one f64 product, one f32 rounding.
            let i = _mm512_fmadd_pd(c128, _mm512_cvtepi32_pd(h), _mm512_cvtepi32_pd(l));
            let v = _mm512_cvtpd_ps(_mm512_mul_pd(i, t));
            // SAFETY: g*16 + half*8 + 8 <= G*16 <= out.len().
            unsafe { _mm256_storeu_ps(out.as_mut_ptr().add(g * BLOCK + half * 8), v) };
        }
    }
}
