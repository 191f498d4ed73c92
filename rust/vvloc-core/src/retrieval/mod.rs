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
//! * a batch runs a GEMM-like tile kernel (8 queries × 32 rows per micro-kernel call, the map
//!   streamed once per 8 queries from cache-sized super-blocks) with per-query bounded selection;
//! * compressed storage (`float16` / `bfloat16`) halves the bytes a single query streams: the
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

use crate::{Error, Result};
use half::{bf16, f16};
use kernels::{Level, BLOCK};
use rayon::prelude::*;
use select::{BelowSink, Excluder, Hit, ShortlistSink, Sink, TopK, TopKSink};

/// Storage type of the scanned copy of the map.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Dtype {
    /// float32 only (exact scan).
    F32,
    /// float16 scan copy + float32 originals (exact after re-scoring).
    F16,
    /// bfloat16 scan copy + float32 originals (exact after re-scoring).
    BF16,
}

impl Dtype {
    /// The numpy-style name: `"float32"`, `"float16"`, `"bfloat16"`.
    pub fn name(self) -> &'static str {
        match self {
            Dtype::F32 => "float32",
            Dtype::F16 => "float16",
            Dtype::BF16 => "bfloat16",
        }
    }

    /// Parses a numpy-style name.
    pub fn parse(s: &str) -> Result<Self> {
        match s {
            "float32" => Ok(Dtype::F32),
            "float16" => Ok(Dtype::F16),
            "bfloat16" => Ok(Dtype::BF16),
            _ => Err(Error::value(
                "dtype",
                format!("expected 'float32', 'float16' or 'bfloat16', got {s:?}"),
            )),
        }
    }

    pub(crate) fn code(self) -> u32 {
        match self {
            Dtype::F32 => 0,
            Dtype::F16 => 1,
            Dtype::BF16 => 2,
        }
    }

    pub(crate) fn from_code(c: u32) -> Option<Self> {
        match c {
            0 => Some(Dtype::F32),
            1 => Some(Dtype::F16),
            2 => Some(Dtype::BF16),
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
/// Blocks per super-block of the batch scan (re-used from cache by every query tile).
const SUPER_BLOCKS: usize = 4;
/// Query tile of the batch kernel.
const QT: usize = 8;

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
    /// Largest row norm ‖x‖ (for the compressed error bound).
    max_norm: f32,
    /// Largest ‖x̃‖ and ‖x − x̃‖ over rows, x̃ the compressed row (exact, rounded up).
    max_packed_norm: f64,
    max_resid: f64,
    groups: Vec<i64>,
    seqs: Vec<i64>,
    level: Level,
}

impl DescriptorIndex {
    /// An empty index of dimension `dim` (≥ 1).
    pub fn new(dim: usize, dtype: Dtype) -> Result<Self> {
        if dim == 0 {
            return Err(Error::value("descriptors", "dimension d must be >= 1"));
        }
        Ok(DescriptorIndex {
            dim,
            len: 0,
            dtype,
            data: Vec::new(),
            norms: Vec::new(),
            packed: Vec::new(),
            max_norm: 0.0,
            max_packed_norm: 0.0,
            max_resid: 0.0,
            groups: Vec::new(),
            seqs: Vec::new(),
            level: kernels::detect(),
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
        if descriptors.iter().any(|v| !v.is_finite()) {
            return Err(Error::value(
                "descriptors",
                "contains non-finite values (NaN or inf)",
            ));
        }
        if self.dtype == Dtype::F16 && descriptors.iter().any(|v| v.abs() > 65504.0) {
            return Err(Error::value(
                "descriptors",
                "values beyond ±65504 cannot be stored as float16 (use float32 or bfloat16)",
            ));
        }
        if self.len + n > u32::MAX as usize {
            return Err(Error::value("descriptors", "at most 2^32 - 1 entries"));
        }
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
        self.groups
            .extend(groups.map_or(vec![0; n], |g| g.to_vec()));
        self.seqs
            .extend(seqs.map_or_else(|| (old as i64..self.len as i64).collect(), |s| s.to_vec()));
        self.pack_blocks(old / BLOCK);
        Ok(())
    }

    fn repack(&mut self) {
        self.packed.clear();
        self.max_packed_norm = 0.0;
        self.max_resid = 0.0;
        self.pack_blocks(0);
    }

    /// The value row element `v` has in the compressed copy.
    fn compressed_value(&self, v: f32) -> f32 {
        match self.dtype {
            Dtype::F32 => v,
            Dtype::F16 => f16::from_f32(v).to_f32(),
            Dtype::BF16 => bf16::from_f32(v).to_f32(),
        }
    }

    /// (Re)builds the compressed copy of blocks `from..`.
    fn pack_blocks(&mut self, from: usize) {
        let (d, nb, dp) = (self.dim, self.nblocks(), self.pairs());
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
            Dtype::F32 => {}
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
    pub fn error_bound(&self, q: &[f32]) -> f32 {
        if self.dtype == Dtype::F32 {
            return 0.0;
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

    fn check_queries(&self, queries: &[f32]) -> Result<usize> {
        let d = self.dim;
        if !queries.len().is_multiple_of(d) {
            return Err(Error::shape("queries", format!("(nq, {d})"), queries.len()));
        }
        if queries.iter().any(|v| !v.is_finite()) {
            return Err(Error::value(
                "queries",
                "contains non-finite values (NaN or inf)",
            ));
        }
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
    fn chunks(&self, work_per_block: usize) -> Vec<(usize, usize)> {
        let nb = self.nblocks();
        let threads = rayon::current_num_threads().max(1);
        if threads == 1 || nb * work_per_block < (1 << 21) || nb < 2 * MIN_CHUNK_BLOCKS {
            return vec![(0, nb)];
        }
        let target = (threads * 4).min(nb / MIN_CHUNK_BLOCKS).max(1);
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
            let thr = sink.threshold(q);
            let mut sq = [0f32; BLOCK];
            let mut any = false;
            for l in 0..BLOCK {
                sq[l] = ((qn + xn[l]) - 2.0 * dg[l]).max(0.0);
                any |= sq[l] < thr;
            }
            if any {
                for (l, &s) in sq.iter().enumerate() {
                    let row = blk * BLOCK + l;
                    if row < self.len && s < sink.threshold(q) {
                        sink.offer(q, row, s);
                    }
                }
            }
        }
    }

    /// Exact float32 scan of blocks `b0..b1` for all queries (tiles of 8, then one by one).
    fn scan_f32<S: Sink>(&self, qs: &[f32], qn: &[f32], b0: usize, b1: usize, sink: &mut S) {
        let d = self.dim;
        let nq = qn.len();
        let full = nq / QT * QT;
        let mut out = [0f32; QT * 2 * BLOCK];
        let blocks = |b: usize| &self.data[b * d * BLOCK..];
        for sb in (b0..b1).step_by(SUPER_BLOCKS) {
            let se = (sb + SUPER_BLOCKS).min(b1);
            for t0 in (0..full).step_by(QT) {
                let q = &qs[t0 * d..(t0 + QT) * d];
                let mut b = sb;
                while b < se {
                    let g = if b + 2 <= se { 2 } else { 1 };
                    if g == 2 {
                        kernels::tile_f32::<QT, 2>(self.level, q, d, blocks(b), &mut out);
                    } else {
                        kernels::tile_f32::<QT, 1>(self.level, q, d, blocks(b), &mut out);
                    }
                    for t in 0..QT {
                        let dots = &out[t * g * BLOCK..(t + 1) * g * BLOCK];
                        self.emit(sink, t0 + t, qn[t0 + t], b, dots);
                    }
                    b += g;
                }
            }
        }
        for qi in full..nq {
            let q = &qs[qi * d..(qi + 1) * d];
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

    #[allow(clippy::too_many_arguments)]
    /// Compressed (approximate) scan of blocks `b0..b1` for query `qi` alone.
    fn scan_packed<S: Sink>(
        &self,
        q: &[f32],
        qpair: &[u32],
        qi: usize,
        qn: f32,
        b0: usize,
        b1: usize,
        sink: &mut S,
    ) {
        let (d, dp) = (self.dim, self.pairs());
        let mut out = [0f32; 8 * BLOCK];
        let mut b = b0;
        while b < b1 {
            let g = if b + 8 <= b1 { 8 } else { 1 };
            match (self.dtype, g) {
                (Dtype::F16, 8) => kernels::scan_f16::<8>(
                    self.level,
                    q,
                    d,
                    &self.packed[b * d * BLOCK..],
                    &mut out,
                ),
                (Dtype::F16, _) => kernels::scan_f16::<1>(
                    self.level,
                    q,
                    d,
                    &self.packed[b * d * BLOCK..],
                    &mut out,
                ),
                (_, 8) => kernels::scan_bf16::<8>(
                    self.level,
                    qpair,
                    dp,
                    &self.packed[b * dp * BLOCK * 2..],
                    &mut out,
                ),
                _ => kernels::scan_bf16::<1>(
                    self.level,
                    qpair,
                    dp,
                    &self.packed[b * dp * BLOCK * 2..],
                    &mut out,
                ),
            }
            self.emit(sink, qi, qn, b, &out[..g * BLOCK]);
            b += g;
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
        let ex = self.excluder(nq, exclude)?;
        let qn = self.query_norms(queries);
        let per_query: Vec<Vec<Hit>> = if self.use_packed(nq) {
            (0..nq)
                .map(|qi| self.topk_packed(queries, &qn, qi, k, ex))
                .collect()
        } else {
            let chunks = self.chunks(nq * self.dim);
            let sinks: Vec<TopKSink> = chunks
                .par_iter()
                .map(|&(b0, b1)| {
                    let mut s = TopKSink {
                        heaps: vec![TopK::new(k); nq],
                        ex,
                    };
                    self.scan_f32(queries, &qn, b0, b1, &mut s);
                    s
                })
                .collect();
            let mut merged: Vec<Vec<Hit>> = vec![Vec::new(); nq];
            for s in sinks {
                for (m, h) in merged.iter_mut().zip(s.heaps) {
                    m.extend(h.into_vec());
                }
            }
            merged
                .into_iter()
                .map(|mut v| {
                    v.sort_unstable();
                    v.truncate(k);
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
        let qpair = if self.dtype == Dtype::BF16 {
            kernels::pack_query_bf16(q)
        } else {
            Vec::new()
        };
        let slack = 2.0 * self.error_bound(q);
        let sinks: Vec<ShortlistSink> = self
            .chunks(self.dim)
            .par_iter()
            .map(|&(b0, b1)| {
                let mut s = ShortlistSink {
                    heap: TopK::new(k),
                    slack,
                    cands: Vec::new(),
                    ex,
                };
                self.scan_packed(q, &qpair, qi, qn[qi], b0, b1, &mut s);
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
        let r2 = ((r as f64 * r as f64) * (1.0 + 1e-6)) as f32;
        let packed = self.use_packed(nq);
        let chunks = self.chunks(nq * self.dim);
        let scan = |qi: Option<usize>, bound: f32| -> Vec<Vec<Hit>> {
            let sinks: Vec<BelowSink> = chunks
                .par_iter()
                .map(|&(b0, b1)| {
                    let mut s = BelowSink {
                        bound,
                        hits: vec![Vec::new(); nq],
                        ex,
                    };
                    match qi {
                        None => self.scan_f32(queries, &qn, b0, b1, &mut s),
                        Some(qi) => {
                            let q = &queries[qi * self.dim..(qi + 1) * self.dim];
                            let qpair = if self.dtype == Dtype::BF16 {
                                kernels::pack_query_bf16(q)
                            } else {
                                Vec::new()
                            };
                            self.scan_packed(q, &qpair, qi, qn[qi], b0, b1, &mut s)
                        }
                    }
                    s
                })
                .collect();
            let mut merged: Vec<Vec<Hit>> = vec![Vec::new(); nq];
            for s in sinks {
                for (m, h) in merged.iter_mut().zip(s.hits) {
                    m.extend(h);
                }
            }
            merged
        };
        let mut per_query: Vec<Vec<Hit>> = if packed {
            (0..nq)
                .map(|qi| {
                    let q = &queries[qi * self.dim..(qi + 1) * self.dim];
                    let eps = self.error_bound(q);
                    let cands = std::mem::take(&mut scan(Some(qi), r2 + eps)[qi]);
                    self.rescore(q, qn[qi], &cands)
                })
                .collect()
        } else {
            scan(None, r2)
        };
        let mut res = RadiusResult {
            offsets: Vec::with_capacity(nq + 1),
            indices: Vec::new(),
            distances: Vec::new(),
        };
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
