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
    /// AVX-512F (+ optional AVX-512 BF16 for the bfloat16 scan).
    Avx512 { bf16: bool },
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
            if is_x86_feature_detected!("avx512f") {
                return Level::Avx512 {
                    bf16: is_x86_feature_detected!("avx512bf16"),
                };
            }
            if is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma") {
                return Level::Avx2;
            }
        }
        Level::Portable
    })
}

/// Every level this CPU can run (for tests that compare the paths).
pub fn available_levels() -> Vec<Level> {
    let mut v = vec![Level::Portable];
    #[cfg(target_arch = "x86_64")]
    {
        if is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma") {
            v.push(Level::Avx2);
        }
        if is_x86_feature_detected!("avx512f") {
            v.push(Level::Avx512 { bf16: false });
            if is_x86_feature_detected!("avx512bf16") {
                v.push(Level::Avx512 { bf16: true });
            }
        }
    }
    v
}

// ---------------------------------------------------------------------------------------------
// float32 tiles: QT queries × G blocks.

/// Dot products of `QT` queries (rows of `q`, each of length `d`) with the `G` consecutive blocks
/// starting at `blocks[0]`; `out[t * G * 16 + g * 16 + l]` = query t · row l of block g.
///
/// Panics (a bug, never user input) if a slice is too short.
pub fn tile_f32<const QT: usize, const G: usize>(
    level: Level,
    q: &[f32],
    d: usize,
    blocks: &[f32],
    out: &mut [f32],
) {
    assert!(q.len() >= QT * d && blocks.len() >= G * d * BLOCK && out.len() >= QT * G * BLOCK);
    match level {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: `level` is Avx512 only when `detect`/`available_levels` found avx512f on this
        // CPU; the slice lengths were checked above.
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

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn tile_f32_avx512<const QT: usize, const G: usize>(
    q: &[f32],
    d: usize,
    blocks: &[f32],
    out: &mut [f32],
) {
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
    for t in 0..QT {
        for g in 0..G {
            // SAFETY: (t*G + g)*16 + 16 <= QT*G*16 <= out.len().
            unsafe { _mm512_storeu_ps(out.as_mut_ptr().add((t * G + g) * BLOCK), acc[t][g]) };
        }
    }
}

/// Squared norms of the 16 rows of one block (same accumulation order as the dot products).
pub fn block_norms(level: Level, block: &[f32], d: usize) -> [f32; BLOCK] {
    assert!(block.len() >= d * BLOCK);
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
        // SAFETY: avx2 and fma were detected (both Avx2 and Avx512 machines have them: every
        // AVX-512F CPU implements AVX2 and FMA).
        Level::Avx2 | Level::Avx512 { .. } => unsafe { fast(block, d) },
        _ => generic(block, d),
    }
}

/// `Σ_j v[j]²` accumulated sequentially with fma (the query-norm convention).
pub fn norm_sq(level: Level, v: &[f32]) -> f32 {
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

// ---------------------------------------------------------------------------------------------
// Compressed scans (one query × G blocks). Approximate: callers bound the error and re-score.

/// float16 map × float32 query: `out[g * 16 + l]` ≈ q · row l of block g.
pub fn scan_f16<const G: usize>(
    level: Level,
    q: &[f32],
    d: usize,
    blocks: &[u16],
    out: &mut [f32],
) {
    assert!(q.len() >= d && blocks.len() >= G * d * BLOCK && out.len() >= G * BLOCK);
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
pub fn scan_bf16<const G: usize>(
    level: Level,
    qp: &[u32],
    dp: usize,
    blocks: &[u16],
    out: &mut [f32],
) {
    assert!(qp.len() >= dp && blocks.len() >= G * dp * BLOCK * 2 && out.len() >= G * BLOCK);
    match level {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: avx512f and avx512bf16 detected; lengths checked above.
        Level::Avx512 { bf16: true } => unsafe { scan_bf16_avx512::<G>(qp, dp, blocks, out) },
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
