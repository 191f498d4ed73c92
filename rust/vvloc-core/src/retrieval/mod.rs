//! Exact descriptor retrieval: top-K and radius queries over L2 distances, with persistence.
//!
//! [`DescriptorIndex`] holds N descriptors of dimension d. Distances are L2 distances (not
//! squared), computed as `sqrt(max(0, ‖q‖² + ‖x‖² − 2 q·x))` in float32 with the stored squared
//! norms of the map rows (normalisation is not assumed). Top-K results are sorted by distance
//! ascending, ties broken by the lower map index; radius results hold every entry with
//! distance `< r`, each query's hits sorted the same way (DESIGN.md §3 "Retrieval").
//!
//! Speed comes from the layout (see [`kernels`]: blocks of 16 rows, dimension-major) and from
//! never storing or sorting rejected rows:
//! * a single query splits the map across threads, each with its own bounded top-K, merged;
//!   with float32 storage it reads the leading d/8 dimensions of a block of 16 rows first and
//!   skips the rest of the block when a Cauchy–Schwarz lower bound (stored per-row norms of the
//!   remaining dimensions) puts every row of the block beyond the current top-K or radius
//!   threshold, so most blocks cost ~1/8 of their bytes ([`DescriptorIndex::scan_abandon`]);
//! * a batch runs a GEMM-like tile kernel (8 queries × 32 rows per micro-kernel call, the map
//!   streamed once per 8 queries from cache-sized super-blocks) with per-query bounded selection;
//! * compressed storage (`float16` / `bfloat16` halve, `int8` with a per-dimension scale and
//!   AVX-512 VNNI `vpdpbusd` quarters the bytes a single query streams): the
//!   compressed scan yields a shortlist (every row whose approximate squared distance is within
//!   2ε of the approximate k-th, ε a proven bound on the approximation error, see
//!   [`DescriptorIndex::error_bound`]), which is re-scored exactly from the float32 originals the
//!   index keeps. Results are therefore identical to the float32 index. Batches of ≥ 8 queries
//!   are compute-bound and scan the float32 originals directly.
//!
//! Every distance is computed per (query, row) with the same sequential fma order in every
//! path, so results do not depend on the thread count, the tiling or the CPU features found.

pub mod format;
pub mod kernels;
mod select;

pub use select::Exclusion;

use crate::error::{check_alloc, checked_len};
use crate::{Error, Result};
use half::{bf16, f16};
use kernels::{Level, BLOCK};
use rayon::prelude::*;
use select::{BelowSink, Excluder, Hit, ShortlistSink, Sink, TopK, TopKSink};
use std::sync::Mutex;

/// Storage type of the scanned copy of the map.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Dtype {
    /// float32 only (exact scan).
    F32,
    /// float16 scan copy + float32 originals (exact after re-scoring).
    F16,
    /// bfloat16 scan copy + float32 originals (exact after re-scoring).
    BF16,
    /// int8 scan copy with a per-dimension scale + float32 originals (exact after re-scoring).
    I8,
}

impl Dtype {
    /// The numpy-style name: `"float32"`, `"float16"`, `"bfloat16"`, `"int8"`.
    pub fn name(self) -> &'static str {
        match self {
            Dtype::F32 => "float32",
            Dtype::F16 => "float16",
            Dtype::BF16 => "bfloat16",
            Dtype::I8 => "int8",
        }
    }

    /// Parses a numpy-style name.
    pub fn parse(s: &str) -> Result<Self> {
        match s {
            "float32" => Ok(Dtype::F32),
            "float16" => Ok(Dtype::F16),
            "bfloat16" => Ok(Dtype::BF16),
            "int8" => Ok(Dtype::I8),
            _ => Err(Error::value(
                "dtype",
                format!("expected 'float32', 'float16', 'bfloat16' or 'int8', got {s:?}"),
            )),
        }
    }

    pub(crate) fn code(self) -> u32 {
        match self {
            Dtype::F32 => 0,
            Dtype::F16 => 1,
            Dtype::BF16 => 2,
            Dtype::I8 => 3,
        }
    }

    pub(crate) fn from_code(c: u32) -> Option<Self> {
        match c {
            0 => Some(Dtype::F32),
            1 => Some(Dtype::F16),
            2 => Some(Dtype::BF16),
            3 => Some(Dtype::I8),
            _ => None,
        }
    }
}

/// Top-K results: row-major (nq, k); missing entries (k > eligible entries) are index -1,
/// distance +inf.
#[derive(Clone, Debug, PartialEq)]
pub struct TopKResult {
    pub k: usize,
    pub indices: Vec<i64>,
    pub distances: Vec<f32>,
}

/// Radius results in CSR form: query q's hits are `indices[offsets[q]..offsets[q+1]]`.
#[derive(Clone, Debug, PartialEq)]
pub struct RadiusResult {
    pub offsets: Vec<i64>,
    pub indices: Vec<i64>,
    pub distances: Vec<f32>,
}

/// Rows per parallel chunk at least (smaller maps run on one thread).
const MIN_CHUNK_BLOCKS: usize = 64;
/// The largest descriptor dimension an index takes (a guard against corrupt or absurd sizes,
/// e.g. a forged file header: global descriptors have tens to thousands of dimensions).
pub const MAX_DIM: usize = 1 << 20;
/// Blocks per super-block of the batch scan (re-used from cache by every query tile).
const SUPER_BLOCKS: usize = 4;
/// Query tile of the batch kernel.
const QT: usize = 8;
/// Segment boundaries tested by the early-abandoning float32 scan (at d/8, 2d/8, 3d/8).
const SEGMENTS: usize = 3;
/// The headroom an add gives the int8 ranges when a row outgrows one (see
/// `DescriptorIndex::grow_ranges`): up to 1.25x coarser codes in an index grown by adds, in
/// exchange for re-quantising it a logarithmic number of times.
const RANGE_GROWTH: f32 = 1.25;

/// A query prepared for the compressed scan of its index's dtype.
enum PackedQuery<'q> {
    F16(&'q [f32]),
    BF16(Vec<u32>),
    I8(kernels::QueryI8),
}

/// Locks `m`, also after a panic elsewhere (a `TopK` is always consistent).
fn lock(m: &Mutex<TopK>) -> std::sync::MutexGuard<'_, TopK> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// An exact L2 nearest-neighbour index over N descriptors of dimension d.
#[derive(Clone, Debug)]
pub struct DescriptorIndex {
    dim: usize,
    len: usize,
    dtype: Dtype,
    /// float32 rows in the blocked layout (padded rows are zero).
    data: Vec<f32>,
    /// Squared norms, padded to whole blocks with 0.
    norms: Vec<f32>,
    /// The compressed scan copy in its blocked layout (empty for float32).
    packed: Vec<u16>,
    /// int8 scan copy (see [`kernels::scan_i8`]; empty unless int8).
    packed8: Vec<u8>,
    /// int8: per-dimension scale s_j (x ≈ s_j·x̃), the range r_j = 127·s_j its codes span
    /// (see `grow_ranges`), the largest |x_j| over rows, and the largest |x_j − s_j·x̃_j| over
    /// rows (exact, rounded up).
    scales: Vec<f32>,
    ranges: Vec<f32>,
    absmax: Vec<f32>,
    resid_dim: Vec<f64>,
    /// Segment length of the early-abandoning float32 scans (0: off): a row is tested after
    /// each of the first [`SEGMENTS`] segments of `head` dimensions. Per block and segment
    /// boundary h (block-major, `(b * SEGMENTS + s) * 16 + l`): the squared norm of the row's
    /// first h dimensions (same fma order as the dot products) and the norm of the others (f64,
    /// rounded to f32).
    head: usize,
    head_norms: Vec<f32>,
    tail_norms: Vec<f32>,
    /// Largest row norm ‖x‖ (for the compressed error bound).
    max_norm: f32,
    /// Largest ‖x̃‖ and ‖x − x̃‖ over rows, x̃ the compressed row (exact, rounded up).
    max_packed_norm: f64,
    max_resid: f64,
    groups: Vec<i64>,
    seqs: Vec<i64>,
    level: Level,
    /// Scans with less work (blocks × query dimensions) run as one chunk (tests lower it).
    min_parallel_work: usize,
}

impl DescriptorIndex {
    /// An empty index of dimension `dim` (≥ 1).
    pub fn new(dim: usize, dtype: Dtype) -> Result<Self> {
        if dim == 0 {
            return Err(Error::value("descriptors", "dimension d must be >= 1"));
        }
        if dim > MAX_DIM {
            return Err(Error::value(
                "descriptors",
                format!("dimension d must be <= {MAX_DIM}, got {dim}"),
            ));
        }
        Ok(DescriptorIndex {
            dim,
            len: 0,
            dtype,
            data: Vec::new(),
            norms: Vec::new(),
            packed: Vec::new(),
            packed8: Vec::new(),
            scales: vec![0.0; dim],
            ranges: vec![0.0; dim],
            absmax: vec![0.0; dim],
            resid_dim: vec![0.0; dim],
            head: if dim >= 64 { dim.div_ceil(8) } else { 0 },
            head_norms: Vec::new(),
            tail_norms: Vec::new(),
            max_norm: 0.0,
            max_packed_norm: 0.0,
            max_resid: 0.0,
            groups: Vec::new(),
            seqs: Vec::new(),
            level: kernels::detect(),
            min_parallel_work: 1 << 21,
        })
    }

    /// An index over `descriptors` (row-major (n, dim)); see [`DescriptorIndex::add`].
    pub fn from_rows(
        descriptors: &[f32],
        dim: usize,
        dtype: Dtype,
        groups: Option<&[i64]>,
        seqs: Option<&[i64]>,
    ) -> Result<Self> {
        let mut idx = Self::new(dim, dtype)?;
        idx.add(descriptors, groups, seqs)?;
        Ok(idx)
    }

    /// Forces a kernel level (tests compare the paths); must be one of
    /// [`kernels::available_levels`].
    pub fn with_level(mut self, level: Level) -> Result<Self> {
        if !kernels::available_levels().contains(&level) {
            return Err(Error::value("level", "not supported by this CPU"));
        }
        self.level = level;
        self.repack();
        Ok(self)
    }

    /// Number of entries.
    pub fn len(&self) -> usize {
        self.len
    }

    /// True when the index holds no entry.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Descriptor dimension d.
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// Storage type of the scanned copy.
    pub fn dtype(&self) -> Dtype {
        self.dtype
    }

    /// Group id of every entry.
    pub fn groups(&self) -> &[i64] {
        &self.groups
    }

    /// Sequence number of every entry.
    pub fn seqs(&self) -> &[i64] {
        &self.seqs
    }

    fn nblocks(&self) -> usize {
        self.len.div_ceil(BLOCK)
    }

    fn pairs(&self) -> usize {
        self.dim.div_ceil(2)
    }

    /// Row `i` as float32 (copied out of the blocked layout).
    pub fn row(&self, i: usize) -> Vec<f32> {
        let base = (i / BLOCK) * self.dim * BLOCK + i % BLOCK;
        (0..self.dim).map(|j| self.data[base + j * BLOCK]).collect()
    }

    /// All rows, row-major (n, d).
    pub fn rows(&self) -> Vec<f32> {
        let mut out = Vec::with_capacity(self.len * self.dim);
        for i in 0..self.len {
            out.extend(self.row(i));
        }
        out
    }

    /// Appends `descriptors` (row-major (n, dim), finite; within ±65504 for float16 storage).
    /// `groups` defaults to 0 and `seqs` to the entry's index in the map.
    pub fn add(
        &mut self,
        descriptors: &[f32],
        groups: Option<&[i64]>,
        seqs: Option<&[i64]>,
    ) -> Result<()> {
        let d = self.dim;
        if !descriptors.len().is_multiple_of(d) {
            return Err(Error::shape(
                "descriptors",
                format!("(n, {d})"),
                descriptors.len(),
            ));
        }
        let n = descriptors.len() / d;
        for (arg, v) in [("groups", groups), ("seqs", seqs)] {
            if let Some(v) = v {
                if v.len() != n {
                    return Err(Error::shape(arg, format!("({n},)"), (v.len(),)));
                }
            }
        }
        crate::cost::check_rows(descriptors, d, "descriptors")?;
        if self.dtype == Dtype::F16 && descriptors.iter().any(|v| v.abs() > 65504.0) {
            return Err(Error::value(
                "descriptors",
                "values beyond ±65504 cannot be stored as float16 (use float32 or bfloat16)",
            ));
        }
        if self.dtype == Dtype::I8 && d > 65536 {
            return Err(Error::value(
                "descriptors",
                "int8 storage supports d <= 65536 (exact i32 accumulation)",
            ));
        }
        if self.len + n > u32::MAX as usize {
            return Err(Error::value("descriptors", "at most 2^32 - 1 entries"));
        }
        self.reserve_for(self.len + n)?;
        let old = self.len;
        self.len += n;
        let nb = self.nblocks();
        self.data.resize(nb * d * BLOCK, 0.0);
        self.norms.resize(nb * BLOCK, 0.0);
        for (r, row) in descriptors.chunks_exact(d).enumerate() {
            let i = old + r;
            let base = (i / BLOCK) * d * BLOCK + i % BLOCK;
            for (j, &v) in row.iter().enumerate() {
                self.data[base + j * BLOCK] = v;
            }
        }
        for b in old / BLOCK..nb {
            let norms = kernels::block_norms(self.level, &self.data[b * d * BLOCK..], d);
            self.norms[b * BLOCK..][..BLOCK].copy_from_slice(&norms);
        }
        for i in old..self.len {
            self.max_norm = self.max_norm.max(self.norms[i].sqrt());
        }
        self.head_norms.resize(nb * SEGMENTS * BLOCK, 0.0);
        self.tail_norms.resize(nb * SEGMENTS * BLOCK, 0.0);
        if self.head > 0 {
            for s in 0..SEGMENTS {
                let h = self.head * (s + 1);
                for b in old / BLOCK..nb {
                    let norms = kernels::block_norms(self.level, &self.data[b * d * BLOCK..], h);
                    self.head_norms[(b * SEGMENTS + s) * BLOCK..][..BLOCK].copy_from_slice(&norms);
                }
                for i in old..self.len {
                    let tail = self.row(i)[h..]
                        .iter()
                        .map(|&v| (v as f64).powi(2))
                        .sum::<f64>();
                    self.tail_norms[((i / BLOCK) * SEGMENTS + s) * BLOCK + i % BLOCK] =
                        tail.sqrt() as f32;
                }
            }
        }
        let rescale = self.dtype == Dtype::I8 && self.grow_ranges(descriptors, old == 0);
        match groups {
            Some(g) => self.groups.extend_from_slice(g),
            None => self.groups.extend(std::iter::repeat_n(0, n)),
        }
        self.seqs
            .extend(seqs.map_or_else(|| (old as i64..self.len as i64).collect(), |s| s.to_vec()));
        if rescale {
            // New per-dimension scales: the whole int8 copy is re-quantised.
            self.scales = self.ranges.iter().map(|&r| r / 127.0).collect();
            self.repack();
        } else {
            self.pack_blocks(old / BLOCK);
        }
        Ok(())
    }

    /// Widens the int8 ranges to hold `descriptors` (row-major (n, d)); true when one changed
    /// (the copy must be re-quantised, O(N·d)). The first rows (`first`) set each range to the
    /// largest |x_j|, as a one-shot build does. When a later row outgrows a range, every range
    /// widens to at least [`RANGE_GROWTH`] times its dimension's largest |x_j| so far: the
    /// next re-quantisation needs some |x_j| to grow by that factor, so N adds re-quantise at
    /// most Σ_j log_1.25(growth of |x_j|) times (about 100 for 2 000-8 000 of the benchmark's
    /// descriptors in any order), not on nearly every add (rows in order of rising |x_j|
    /// re-quantised on each: adding was quadratic). Results do not depend on the ranges (the
    /// scans' error bounds hold for any); a wider one (at most 1.25× the largest |x_j|) only
    /// re-scores more rows exactly. A saved index loads with the one-shot ranges.
    fn grow_ranges(&mut self, descriptors: &[f32], first: bool) -> bool {
        for row in descriptors.chunks_exact(self.dim) {
            for (m, &v) in self.absmax.iter_mut().zip(row) {
                *m = m.max(v.abs());
            }
        }
        if !self.absmax.iter().zip(&self.ranges).any(|(m, r)| m > r) {
            return false;
        }
        for (r, &m) in self.ranges.iter_mut().zip(&self.absmax) {
            *r = if first {
                m
            } else {
                r.max((m * RANGE_GROWTH).min(f32::MAX))
            };
        }
        true
    }

    /// Reserves every buffer [`Self::add`] grows for `len` entries, before anything changes:
    /// an allocation that fails is [`Error::Memory`] (the index as it was), not an abort.
    fn reserve_for(&mut self, len: usize) -> Result<()> {
        fn grow<T>(v: &mut Vec<T>, parts: &[usize]) -> Result<()> {
            let total = parts.iter().try_fold(1usize, |a, &b| a.checked_mul(b));
            let more = total.map(|t| t.saturating_sub(v.len()));
            match more.map(|m| v.try_reserve(m)) {
                // amortised: many small adds stay linear
                Some(Ok(())) => Ok(()),
                _ => Err(Error::Memory {
                    arg: "descriptors",
                    what: format!(
                        "{} elements of {} bytes",
                        total.map_or("more than usize::MAX".to_string(), |t| t.to_string()),
                        std::mem::size_of::<T>()
                    ),
                }),
            }
        }
        let (d, nb) = (self.dim, len.div_ceil(BLOCK));
        grow(&mut self.data, &[nb, d, BLOCK])?;
        grow(&mut self.norms, &[nb, BLOCK])?;
        grow(&mut self.head_norms, &[nb, SEGMENTS, BLOCK])?;
        grow(&mut self.tail_norms, &[nb, SEGMENTS, BLOCK])?;
        grow(&mut self.groups, &[len])?;
        grow(&mut self.seqs, &[len])?;
        match self.dtype {
            Dtype::F32 => Ok(()),
            Dtype::F16 => grow(&mut self.packed, &[nb, d, BLOCK]),
            Dtype::BF16 => grow(&mut self.packed, &[nb, d.div_ceil(2), BLOCK, 2]),
            Dtype::I8 => grow(&mut self.packed8, &[nb, d.div_ceil(4), BLOCK, 4]),
        }
    }

    fn repack(&mut self) {
        self.packed.clear();
        self.packed8.clear();
        self.max_packed_norm = 0.0;
        self.max_resid = 0.0;
        self.resid_dim.iter_mut().for_each(|r| *r = 0.0);
        self.pack_blocks(0);
    }

    /// The value row element `v` has in the compressed copy.
    fn compressed_value(&self, v: f32) -> f32 {
        match self.dtype {
            Dtype::F32 => v,
            Dtype::F16 => f16::from_f32(v).to_f32(),
            Dtype::BF16 => bf16::from_f32(v).to_f32(),
            Dtype::I8 => unreachable!("int8 values depend on the dimension"),
        }
    }

    /// The int8 value x̃ of `v` in dimension `j` (`v ≈ scales[j] · x̃`).
    fn quantise(&self, v: f32, j: usize) -> i32 {
        let s = self.scales[j];
        if s > 0.0 {
            (v as f64 / s as f64).round().clamp(-127.0, 127.0) as i32
        } else {
            0
        }
    }

    /// (Re)builds the compressed copy of blocks `from..`.
    fn pack_blocks(&mut self, from: usize) {
        let (d, nb, dp) = (self.dim, self.nblocks(), self.pairs());
        if self.dtype == Dtype::I8 {
            // Error-bound inputs: max ‖x̃‖ (integer domain), max ‖x − s·x̃‖ and per-dimension
            // max |x_j − s_j·x̃_j|, in f64 rounded up (s·x̃ is exact in f64).
            for i in (from * BLOCK)..self.len {
                let (mut pn, mut res) = (0f64, 0f64);
                for (j, v) in self.row(i).into_iter().enumerate() {
                    let c = self.quantise(v, j);
                    let e = (v as f64 - self.scales[j] as f64 * c as f64).abs() * (1.0 + 1e-15);
                    pn += (c * c) as f64;
                    res += e * e;
                    self.resid_dim[j] = self.resid_dim[j].max(e);
                }
                self.max_packed_norm = self.max_packed_norm.max(pn.sqrt() * (1.0 + 1e-9));
                self.max_resid = self.max_resid.max(res.sqrt() * (1.0 + 1e-9));
            }
            let d4 = d.div_ceil(4);
            self.packed8.truncate(from * d4 * BLOCK * 4);
            for b in from..nb {
                let blk = &self.data[b * d * BLOCK..][..d * BLOCK];
                for p in 0..d4 {
                    for l in 0..BLOCK {
                        for j in 4 * p..4 * p + 4 {
                            let c = if j < d {
                                self.quantise(blk[j * BLOCK + l], j)
                            } else {
                                0
                            };
                            self.packed8.push((c + 128) as u8);
                        }
                    }
                }
            }
            return;
        }
        if self.dtype != Dtype::F32 {
            // Error-bound inputs: ‖x̃‖ and ‖x − x̃‖ in f64, rounded up (relative 1e-9 covers
            // the f64 rounding of d ≤ 1e6 terms).
            for i in (from * BLOCK)..self.len {
                let (mut pn, mut res) = (0f64, 0f64);
                for v in self.row(i) {
                    let c = self.compressed_value(v) as f64;
                    pn += c * c;
                    res += (v as f64 - c).powi(2);
                }
                self.max_packed_norm = self.max_packed_norm.max(pn.sqrt() * (1.0 + 1e-9));
                self.max_resid = self.max_resid.max(res.sqrt() * (1.0 + 1e-9));
            }
        }
        match self.dtype {
            Dtype::F32 | Dtype::I8 => {}
            Dtype::F16 => {
                self.packed.truncate(from * d * BLOCK);
                self.packed.extend(
                    self.data[from * d * BLOCK..nb * d * BLOCK]
                        .iter()
                        .map(|&v| f16::from_f32(v).to_bits()),
                );
            }
            Dtype::BF16 => {
                self.packed.truncate(from * dp * BLOCK * 2);
                for b in from..nb {
                    let blk = &self.data[b * d * BLOCK..][..d * BLOCK];
                    for p in 0..dp {
                        for l in 0..BLOCK {
                            for j in [2 * p, 2 * p + 1] {
                                let v = if j < d { blk[j * BLOCK + l] } else { 0.0 };
                                self.packed.push(bf16::from_f32(v).to_bits());
                            }
                        }
                    }
                }
            }
        }
    }

    /// A bound ε on |approximate − exact| squared distance of the compressed scan for query `q`
    /// (exact = this index's float32 result), so that re-scoring every row within 2ε of the
    /// approximate k-th is provably exact.
    ///
    /// With x̃, q̃ the compressed row and query (the float16 scan keeps q̃ = q):
    /// |q·x − q̃·x̃| ≤ ‖q‖·‖x − x̃‖ + ‖q − q̃‖·‖x̃‖ (Cauchy–Schwarz), bounded with the largest
    /// residual and norm over the map (exact, computed at build time). Each float32
    /// accumulation of n terms adds at most γ_n·Σ|terms| ≤ γ_n·‖a‖‖b‖
    /// (γ_n = n·2⁻²⁴ / (1 − n·2⁻²⁴); n = 2d + 2 for `vdpbf16ps`, which may round twice per pair),
    /// the final `‖q‖² + ‖x‖² − 2 q·x` one rounding of at most 2⁻²⁴·(‖q‖ + ‖x‖)² on each side,
    /// and `d·2⁻¹²⁰` covers flushed subnormals. ε = 1.01 × (2·dot error + roundings).
    /// int8 storage bounds its per-dimension quantisation the same way (see `query_i8`).
    pub fn error_bound(&self, q: &[f32]) -> f32 {
        match self.dtype {
            Dtype::F32 => return 0.0,
            Dtype::I8 => return self.query_i8(q).1,
            _ => {}
        }
        let d = self.dim as f64;
        let u = 2f64.powi(-24);
        let gamma = |n: f64| n * u / (1.0 - n * u);
        let qn = q.iter().map(|&v| (v as f64).powi(2)).sum::<f64>().sqrt();
        let (qr, qpn) = q.iter().fold((0f64, 0f64), |(r, n), &v| {
            let c = match self.dtype {
                Dtype::BF16 => bf16::from_f32(v).to_f32() as f64,
                _ => v as f64,
            };
            (r + (v as f64 - c).powi(2), n + c * c)
        });
        let (qr, qpn) = (qr.sqrt(), qpn.sqrt());
        let (m, mp, res) = (
            self.max_norm as f64 * (1.0 + 1e-6),
            self.max_packed_norm,
            self.max_resid,
        );
        let terms = if self.dtype == Dtype::BF16 {
            2.0 * d + 2.0
        } else {
            d
        };
        let dot = qn * res + qr * mp + gamma(terms) * qpn * mp + gamma(d) * qn * m;
        let big = qn.max(qpn) + m.max(mp);
        let eps = 1.01 * (2.0 * dot + 2.0 * u * big * big + d * 2f64.powi(-120) * (big + 1.0));
        (eps * (1.0 + 1e-6)) as f32
    }

    /// The int8 query of `q` and its error bound ε (see [`DescriptorIndex::error_bound`]).
    ///
    /// With w_j = q_j·s_j = t·w̃_j + f_j and x_j = s_j·x̃_j + e_j, exactly
    /// q·x = t·Σ w̃_j x̃_j + Σ f_j x̃_j + Σ q_j e_j, so |q·x − t·I| ≤ T_q + T_x with
    /// T_q = min(127·Σ|f_j|, ‖f‖·max‖x̃‖) and T_x = min(Σ|q_j|·max|e_j|, ‖q‖·max‖e‖) (all
    /// residuals exact, from build time). The scan's f64 product and f32 rounding add at most
    /// 1.0001·2⁻²⁴·|t·I|, the float32 dot of the exact path γ_d·‖q‖·m; the final
    /// `‖q‖² + ‖x‖² − 2 q·x` rounds once on each side, as for the other dtypes.
    fn query_i8(&self, q: &[f32]) -> (kernels::QueryI8, f32) {
        let w: Vec<f64> = q
            .iter()
            .zip(&self.scales)
            .map(|(&v, &s)| v as f64 * s as f64)
            .collect();
        let (qi8, wq) = kernels::QueryI8::new(&w);
        let d = self.dim as f64;
        let u = 2f64.powi(-24);
        let gamma = d * u / (1.0 - d * u);
        let up = 1.0 + 1e-9;
        let f: Vec<f64> = w
            .iter()
            .zip(&wq)
            .map(|(&w, &c)| (w - qi8.t * c as f64).abs() * up)
            .collect();
        let qn = q.iter().map(|&v| (v as f64).powi(2)).sum::<f64>().sqrt() * up;
        let f1 = f.iter().sum::<f64>() * up;
        let f2 = f.iter().map(|v| v * v).sum::<f64>().sqrt() * up;
        let tq = (127.0 * f1).min(f2 * self.max_packed_norm);
        let qe = q
            .iter()
            .zip(&self.resid_dim)
            .map(|(&v, &e)| (v as f64).abs() * e)
            .sum::<f64>()
            * up;
        let tx = qe.min(qn * self.max_resid);
        let m = self.max_norm as f64 * (1.0 + 1e-6);
        let quant = tq + tx;
        let dot = quant + 1.0001 * u * (qn * m + quant) + gamma * qn * m;
        let big2 = (qn + m).powi(2) + 2.0 * dot;
        let eps = 1.01 * (2.0 * dot + 2.0 * u * big2 + d * 2f64.powi(-120) * (big2.sqrt() + 1.0));
        (qi8, (eps * (1.0 + 1e-6)) as f32)
    }

    fn check_queries(&self, queries: &[f32]) -> Result<usize> {
        let d = self.dim;
        if !queries.len().is_multiple_of(d) {
            return Err(Error::shape("queries", format!("(nq, {d})"), queries.len()));
        }
        crate::cost::check_rows(queries, d, "queries")?;
        Ok(queries.len() / d)
    }

    fn excluder<'a>(&'a self, nq: usize, rule: Option<Exclusion<'a>>) -> Result<Excluder<'a>> {
        if let Some(e) = &rule {
            for (arg, v) in [
                ("query_groups", e.query_groups),
                ("query_seqs", e.query_seqs),
            ] {
                if v.len() != nq {
                    return Err(Error::shape(arg, format!("({nq},)"), (v.len(),)));
                }
            }
            if e.window < 0 {
                return Err(Error::value(
                    "window",
                    format!("expected >= 0, got {}", e.window),
                ));
            }
        }
        Ok(Excluder {
            rule,
            groups: &self.groups,
            seqs: &self.seqs,
        })
    }

    /// Splits blocks into chunks for the parallel scans (one chunk for small work).
    fn chunks(&self, work_per_block: usize, per_thread: usize) -> Vec<(usize, usize)> {
        let nb = self.nblocks();
        let threads = rayon::current_num_threads().max(1);
        if threads == 1 || nb * work_per_block < self.min_parallel_work || nb < 2 * MIN_CHUNK_BLOCKS
        {
            return vec![(0, nb)];
        }
        let target = (threads * per_thread).min(nb / MIN_CHUNK_BLOCKS).max(1);
        let size = nb.div_ceil(target);
        (0..nb)
            .step_by(size)
            .map(|b| (b, (b + size).min(nb)))
            .collect()
    }

    /// Offers the rows of `g_blocks` blocks starting at `b` to query `q`'s sink, given their dot
    /// products `dots` (g_blocks × 16) with the query of squared norm `qn`.
    #[inline]
    fn emit<S: Sink>(&self, sink: &mut S, q: usize, qn: f32, b: usize, dots: &[f32]) {
        for (g, dg) in dots.chunks_exact(BLOCK).enumerate() {
            let blk = b + g;
            let xn = &self.norms[blk * BLOCK..][..BLOCK];
            let (sq, below) = kernels::block_sq(self.level, qn, xn, dg, sink.threshold(q));
            self.offer_below(sink, q, blk, &sq, below);
        }
    }

    /// Offers query `q`'s sink the rows of block `blk` in `below` (bit l: row l), at squared
    /// distances `sq`, in row order, each only if it is still below the sink's threshold: the
    /// threshold only falls as rows are offered, so `below`, taken against it at any earlier
    /// moment of the scan, holds every row that can still enter.
    #[inline]
    fn offer_below<S: Sink>(&self, sink: &mut S, q: usize, blk: usize, sq: &[f32], below: u16) {
        let mut below = below;
        while below != 0 {
            let l = below.trailing_zeros() as usize;
            below &= below - 1;
            let row = blk * BLOCK + l;
            if row < self.len && sq[l] < sink.threshold(q) {
                sink.offer(q, row, sq[l]);
            }
        }
    }

    /// [`kernels::tile_sq_f32`] of the `QT` queries `q` (squared norms `tn`, thresholds `thr`)
    /// and the `G` blocks from block `b`: squared distances into `out`, masks into `masks`.
    #[inline]
    fn tile_sq<const G: usize>(
        &self,
        q: &[f32],
        tn: &[f32],
        b: usize,
        thr: &[f32],
        out: &mut [f32],
        masks: &mut [u16],
    ) {
        let (d, xn) = (self.dim, &self.norms[b * BLOCK..(b + G) * BLOCK]);
        let blocks = &self.data[b * d * BLOCK..];
        kernels::tile_sq_f32::<QT, G>(self.level, q, d, blocks, tn, xn, thr, out, masks);
    }

    /// Exact float32 scan of blocks `b0..b1` for all queries (tiles of 8, then one by one).
    fn scan_f32<S: Sink>(&self, qs: &[f32], qn: &[f32], b0: usize, b1: usize, sink: &mut S) {
        let d = self.dim;
        let nq = qn.len();
        let full = nq / QT * QT;
        let mut out = [0f32; QT * 2 * BLOCK];
        let mut masks = [0u16; QT * 2];
        let blocks = |b: usize| &self.data[b * d * BLOCK..];
        for sb in (b0..b1).step_by(SUPER_BLOCKS) {
            let se = (sb + SUPER_BLOCKS).min(b1);
            for t0 in (0..full).step_by(QT) {
                let q = &qs[t0 * d..(t0 + QT) * d];
                let tn = &qn[t0..t0 + QT];
                let mut b = sb;
                while b < se {
                    let g = if b + 2 <= se { 2 } else { 1 };
                    // the thresholds before the tile: a mask may hold rows that the offers of
                    // an earlier block put above the threshold; `offer_below` skips them
                    let thr: [f32; QT] = std::array::from_fn(|t| sink.threshold(t0 + t));
                    if g == 2 {
                        self.tile_sq::<2>(q, tn, b, &thr, &mut out, &mut masks);
                    } else {
                        self.tile_sq::<1>(q, tn, b, &thr, &mut out, &mut masks);
                    }
                    for t in 0..QT {
                        for gi in 0..g {
                            let i = t * g + gi;
                            if masks[i] != 0 {
                                let sq = &out[i * BLOCK..(i + 1) * BLOCK];
                                self.offer_below(sink, t0 + t, b + gi, sq, masks[i]);
                            }
                        }
                    }
                    b += g;
                }
            }
        }
        for qi in full..nq {
            let q = &qs[qi * d..(qi + 1) * d];
            if self.head > 0 {
                self.scan_abandon(q, qi, qn[qi], b0, b1, sink);
                continue;
            }
            let mut b = b0;
            while b < b1 {
                if b + 8 <= b1 {
                    kernels::tile_f32::<1, 8>(self.level, q, d, blocks(b), &mut out);
                    self.emit(sink, qi, qn[qi], b, &out[..8 * BLOCK]);
                    b += 8;
                } else {
                    kernels::tile_f32::<1, 1>(self.level, q, d, blocks(b), &mut out);
                    self.emit(sink, qi, qn[qi], b, &out[..BLOCK]);
                    b += 1;
                }
            }
        }
    }

    /// Compressed (approximate) scan of blocks `b0..b1` for query `qi` alone.
    fn scan_packed<S: Sink>(
        &self,
        pq: &PackedQuery<'_>,
        qi: usize,
        qn: f32,
        b0: usize,
        b1: usize,
        sink: &mut S,
    ) {
        let (d, dp, d4) = (self.dim, self.pairs(), self.dim.div_ceil(4));
        let lv = self.level;
        let mut out = [0f32; 8 * BLOCK];
        let mut b = b0;
        while b < b1 {
            let g = if b + 8 <= b1 { 8 } else { 1 };
            let o = &mut out[..];
            match (pq, g) {
                (PackedQuery::F16(q), 8) => {
                    kernels::scan_f16::<8>(lv, q, d, &self.packed[b * d * BLOCK..], o)
                }
                (PackedQuery::F16(q), _) => {
                    kernels::scan_f16::<1>(lv, q, d, &self.packed[b * d * BLOCK..], o)
                }
                (PackedQuery::BF16(q), 8) => {
                    kernels::scan_bf16::<8>(lv, q, dp, &self.packed[b * dp * BLOCK * 2..], o)
                }
                (PackedQuery::BF16(q), _) => {
                    kernels::scan_bf16::<1>(lv, q, dp, &self.packed[b * dp * BLOCK * 2..], o)
                }
                (PackedQuery::I8(q), 8) => {
                    kernels::scan_i8::<8>(lv, q, d4, &self.packed8[b * d4 * BLOCK * 4..], o)
                }
                (PackedQuery::I8(q), _) => {
                    kernels::scan_i8::<1>(lv, q, d4, &self.packed8[b * d4 * BLOCK * 4..], o)
                }
            }
            self.emit(sink, qi, qn, b, &out[..g * BLOCK]);
            b += g;
        }
    }

    /// Query `q` prepared for the compressed scan, and its error bound ε.
    fn packed_query<'q>(&self, q: &'q [f32]) -> (PackedQuery<'q>, f32) {
        match self.dtype {
            Dtype::I8 => {
                let (pq, eps) = self.query_i8(q);
                (PackedQuery::I8(pq), eps)
            }
            Dtype::BF16 => (
                PackedQuery::BF16(kernels::pack_query_bf16(q)),
                self.error_bound(q),
            ),
            _ => (PackedQuery::F16(q), self.error_bound(q)),
        }
    }

    /// Exact float32 scan of blocks `b0..b1` for query `q` alone that abandons a block early:
    /// after each of the first [`SEGMENTS`] segments of `head` dimensions (h dimensions read so
    /// far) it bounds, for each row, ‖q − x‖² ≥ ‖q_h − x_h‖² + (‖q_t‖ − ‖x_t‖)² (Cauchy–Schwarz
    /// on the unread tail t); when no row of the block can pass `sink.threshold` (with a margin
    /// covering every float32 rounding of both sides) the rest of the block is never read.
    /// Kept blocks finish the same fma sequence, so distances are bitwise those of
    /// [`Self::scan_f32`].
    fn scan_abandon<S: Sink>(
        &self,
        q: &[f32],
        qi: usize,
        qn: f32,
        b0: usize,
        b1: usize,
        sink: &mut S,
    ) {
        let d = self.dim;
        let bounds: [usize; SEGMENTS] = std::array::from_fn(|s| self.head * (s + 1));
        let qh2 = bounds.map(|h| kernels::norm_sq(self.level, &q[..h]));
        let qt = bounds.map(|h| {
            q[h..]
                .iter()
                .map(|&v| (v as f64).powi(2))
                .sum::<f64>()
                .sqrt() as f32
        });
        let u = 2f64.powi(-24);
        let gamma = d as f64 * u / (1.0 - d as f64 * u);
        let big = (qn as f64).sqrt() * (1.0 + 1e-6) + self.max_norm as f64 * (1.0 + 1e-6);
        let margin = (4.0 * gamma + 16.0 * u) * big * big + d as f64 * 2f64.powi(-100);
        let mut acc = [0f32; BLOCK];
        'blocks: for b in b0..b1 {
            let blk = &self.data[b * d * BLOCK..][..d * BLOCK];
            acc.fill(0.0);
            let mut j = 0;
            for (s, &h) in bounds.iter().enumerate() {
                kernels::dot_range(self.level, q, blk, j, h, &mut acc);
                j = h;
                let thr = sink.threshold(qi);
                if !thr.is_finite() {
                    break;
                }
                let cut = ((thr as f64 + margin) as f32).next_up();
                let at = (b * SEGMENTS + s) * BLOCK;
                let (hn, tn) = (
                    &self.head_norms[at..][..BLOCK],
                    &self.tail_norms[at..][..BLOCK],
                );
                let mut keep = false;
                for l in 0..BLOCK {
                    let dt = qt[s] - tn[l];
                    let lb = ((qh2[s] + hn[l]) - 2.0 * acc[l]) + dt * dt;
                    keep |= lb <= cut;
                }
                if !keep {
                    continue 'blocks;
                }
            }
            kernels::dot_range(self.level, q, blk, j, d, &mut acc);
            self.emit(sink, qi, qn, b, &acc);
        }
    }

    fn query_norms(&self, queries: &[f32]) -> Vec<f32> {
        queries
            .chunks_exact(self.dim)
            .map(|q| kernels::norm_sq(self.level, q))
            .collect()
    }

    /// Compressed scans serve small batches (bandwidth-bound); larger ones scan float32.
    fn use_packed(&self, nq: usize) -> bool {
        self.dtype != Dtype::F32 && nq < QT
    }

    /// Exact squared distances of the candidates to query `q` (float32 re-scoring): each block
    /// holding a candidate is re-scanned with the float32 kernel (a contiguous, vectorised read,
    /// bitwise the result of the float32 scan).
    fn rescore(&self, q: &[f32], qn: f32, cands: &[Hit]) -> Vec<Hit> {
        let d = self.dim;
        let mut rows: Vec<u32> = cands.iter().map(|h| h.row).collect();
        rows.sort_unstable();
        let mut out = Vec::with_capacity(rows.len());
        let mut dots = [0f32; BLOCK];
        let mut last = usize::MAX;
        for &row in &rows {
            let (b, l) = (row as usize / BLOCK, row as usize % BLOCK);
            if b != last {
                kernels::tile_f32::<1, 1>(self.level, q, d, &self.data[b * d * BLOCK..], &mut dots);
                last = b;
            }
            let sq = ((qn + self.norms[row as usize]) - 2.0 * dots[l]).max(0.0);
            out.push(Hit { sq, row });
        }
        out
    }

    /// The `k` nearest entries of each query (row-major (nq, d)), sorted by distance then index;
    /// rows with fewer than k eligible entries are padded with index -1 and distance +inf.
    pub fn topk(
        &self,
        queries: &[f32],
        k: usize,
        exclude: Option<Exclusion<'_>>,
    ) -> Result<TopKResult> {
        let nq = self.check_queries(queries)?;
        if k == 0 {
            return Err(Error::value("k", "expected an int >= 1, got 0"));
        }
        // the (nq, k) result: an error, not an abort, when k asks for more than memory holds
        let cells = checked_len("k", &[nq, k])?;
        check_alloc::<(i64, f32)>("k", cells)?;
        let ex = self.excluder(nq, exclude)?;
        let qn = self.query_norms(queries);
        let per_query: Vec<Vec<Hit>> = if self.use_packed(nq) {
            (0..nq)
                .map(|qi| self.topk_packed(queries, &qn, qi, k, ex))
                .collect()
        } else {
            // Single queries abandon blocks early against their threshold: more, smaller chunks
            // share a tighter one. Each chunk starts from the k-th of the chunks finished so far
            // (`shared`, disjoint rows): a row farther than that k-th can never be in the result.
            let per_thread = if nq < QT && self.head > 0 { 16 } else { 4 };
            let chunks = self.chunks(nq * self.dim, per_thread);
            let shared: Vec<Mutex<TopK>> = (0..nq).map(|_| Mutex::new(TopK::new(k))).collect();
            // every chunk's hits go into `shared`, which so ends up with the k nearest of all
            chunks.par_iter().for_each(|&(b0, b1)| {
                let mut s = TopKSink {
                    heaps: vec![TopK::new(k); nq],
                    floor: shared
                        .iter()
                        .map(|m| lock(m).threshold().next_up())
                        .collect(),
                    ex,
                };
                self.scan_f32(queries, &qn, b0, b1, &mut s);
                for (m, h) in shared.iter().zip(&s.heaps) {
                    let mut g = lock(m);
                    h.iter().for_each(|&hit| g.push(hit));
                }
            });
            shared
                .into_iter()
                .map(|m| {
                    let mut v = m.into_inner().unwrap_or_else(|e| e.into_inner()).into_vec();
                    v.sort_unstable();
                    v
                })
                .collect()
        };
        let mut res = TopKResult {
            k,
            indices: vec![-1; nq * k],
            distances: vec![f32::INFINITY; nq * k],
        };
        for (qi, hits) in per_query.iter().enumerate() {
            for (c, h) in hits.iter().enumerate() {
                res.indices[qi * k + c] = h.row as i64;
                res.distances[qi * k + c] = h.sq.sqrt();
            }
        }
        Ok(res)
    }

    /// Compressed top-k of query `qi`: parallel shortlist, then exact re-scoring (module docs).
    fn topk_packed(
        &self,
        queries: &[f32],
        qn: &[f32],
        qi: usize,
        k: usize,
        ex: Excluder<'_>,
    ) -> Vec<Hit> {
        let d = self.dim;
        let q = &queries[qi * d..(qi + 1) * d];
        let (pq, eps) = self.packed_query(q);
        let slack = 2.0 * eps;
        let sinks: Vec<ShortlistSink> = self
            .chunks(self.dim, 4)
            .par_iter()
            .map(|&(b0, b1)| {
                let mut s = ShortlistSink::new(k, slack, ex);
                self.scan_packed(&pq, qi, qn[qi], b0, b1, &mut s);
                s.prune();
                s
            })
            .collect();
        // The global approximate k-th, then every candidate within 2ε of it.
        let mut approx: Vec<Hit> = Vec::new();
        let mut cands: Vec<Hit> = Vec::new();
        for s in sinks {
            approx.extend(s.heap.into_vec());
            cands.extend(s.cands);
        }
        approx.sort_unstable();
        let kth = if approx.len() >= k {
            approx[k - 1].sq
        } else {
            f32::INFINITY
        };
        let bound = kth + slack;
        cands.retain(|h| h.sq <= bound);
        let mut exact = self.rescore(q, qn[qi], &cands);
        exact.sort_unstable();
        exact.truncate(k);
        exact
    }

    /// Every entry at distance `< r` of each query, as CSR arrays, each query's hits sorted by
    /// distance then index. `r` must be finite and > 0.
    pub fn radius(
        &self,
        queries: &[f32],
        r: f32,
        exclude: Option<Exclusion<'_>>,
    ) -> Result<RadiusResult> {
        let nq = self.check_queries(queries)?;
        if !(r.is_finite() && r > 0.0) {
            return Err(Error::value(
                "r",
                format!("expected a finite value > 0, got {r}"),
            ));
        }
        let ex = self.excluder(nq, exclude)?;
        let qn = self.query_norms(queries);
        // Squared-distance prefilter that keeps every row with sqrt(sq) < r (checked after).
        // One ulp up: where r² is a float32 subnormal (r < 1.1e-19) the relative margin is
        // lost to rounding, and rounding down would drop rows (to 0 for r < 2.6e-23); since
        // rounding is monotone, sqrt(sq) < r implies sq < next_up(f32(r²)).
        let r2 = (((r as f64 * r as f64) * (1.0 + 1e-6)) as f32).next_up();
        // The early-abandoning float32 scan reads ~1/8 of the float32 bytes for most blocks,
        // less than any compressed copy: single radius queries use it for every dtype.
        let packed = self.use_packed(nq) && self.head == 0;
        let chunks = self.chunks(nq * self.dim, 4);
        let out_of_memory = || Error::Memory {
            arg: "r",
            what: "the hits within the radius".to_string(),
        };
        let scan =
            |packed: Option<(usize, &PackedQuery<'_>)>, bound: f32| -> Result<Vec<Vec<Hit>>> {
                let sinks: Vec<BelowSink> = chunks
                    .par_iter()
                    .map(|&(b0, b1)| {
                        let mut s = BelowSink::new(bound, nq, ex);
                        match packed {
                            None => self.scan_f32(queries, &qn, b0, b1, &mut s),
                            Some((qi, pq)) => self.scan_packed(pq, qi, qn[qi], b0, b1, &mut s),
                        }
                        s
                    })
                    .collect();
                if sinks.iter().any(|s| s.out_of_memory) {
                    return Err(out_of_memory());
                }
                let mut merged: Vec<Vec<Hit>> = vec![Vec::new(); nq];
                for s in sinks {
                    for (m, h) in merged.iter_mut().zip(s.hits) {
                        m.try_reserve(h.len()).map_err(|_| out_of_memory())?;
                        m.extend(h);
                    }
                }
                Ok(merged)
            };
        let mut per_query: Vec<Vec<Hit>> = if packed {
            (0..nq)
                .map(|qi| {
                    let q = &queries[qi * self.dim..(qi + 1) * self.dim];
                    let (pq, eps) = self.packed_query(q);
                    let cands = std::mem::take(&mut scan(Some((qi, &pq)), r2 + eps)?[qi]);
                    Ok(self.rescore(q, qn[qi], &cands))
                })
                .collect::<Result<_>>()?
        } else {
            scan(None, r2)?
        };
        let total: usize = per_query.iter().map(Vec::len).sum();
        let mut res = RadiusResult {
            offsets: Vec::with_capacity(nq + 1),
            indices: Vec::new(),
            distances: Vec::new(),
        };
        res.indices
            .try_reserve_exact(total)
            .map_err(|_| out_of_memory())?;
        res.distances
            .try_reserve_exact(total)
            .map_err(|_| out_of_memory())?;
        res.offsets.push(0);
        for hits in per_query.iter_mut() {
            hits.retain(|h| h.sq.sqrt() < r);
            hits.sort_unstable();
            res.indices.extend(hits.iter().map(|h| h.row as i64));
            res.distances.extend(hits.iter().map(|h| h.sq.sqrt()));
            res.offsets.push(res.indices.len() as i64);
        }
        Ok(res)
    }
}

#[cfg(test)]
mod tests;
