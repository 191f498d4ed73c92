//! Per-query result collectors ("sinks") fed by the distance scans.
//!
//! A scan computes squared distances block by block and offers a row to the sink only when its
//! squared distance is below `sink.threshold(query)`: rejected rows are never stored or sorted.

use std::cmp::Ordering;
use std::collections::BinaryHeap;

/// Which map entries a query may not return (loop closure: temporal neighbours).
///
/// Entry `i` is excluded for query `q` when `groups[i] == query_groups[q]` and either
/// `whole_group` is set or `|seqs[i] - query_seqs[q]| <= window`.
#[derive(Clone, Copy, Debug)]
pub struct Exclusion<'a> {
    /// Group id (e.g. session) of each query, length nq.
    pub query_groups: &'a [i64],
    /// Sequence number of each query, length nq.
    pub query_seqs: &'a [i64],
    /// Half-width of the excluded sequence window (≥ 0).
    pub window: i64,
    /// Exclude every entry of the query's group.
    pub whole_group: bool,
}

/// The exclusion rule bound to the map's per-entry groups and sequence numbers.
#[derive(Clone, Copy)]
pub(crate) struct Excluder<'a> {
    pub rule: Option<Exclusion<'a>>,
    pub groups: &'a [i64],
    pub seqs: &'a [i64],
}

impl Excluder<'_> {
    #[inline]
    pub fn excluded(&self, q: usize, row: usize) -> bool {
        match &self.rule {
            None => false,
            Some(e) => {
                self.groups[row] == e.query_groups[q]
                    && (e.whole_group
                        || (self.seqs[row] as i128 - e.query_seqs[q] as i128).abs()
                            <= e.window as i128)
            }
        }
    }
}

/// A (squared distance, row) pair ordered by distance then row (the result order).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Hit {
    pub sq: f32,
    pub row: u32,
}

impl Eq for Hit {}
impl Ord for Hit {
    fn cmp(&self, other: &Self) -> Ordering {
        self.sq.total_cmp(&other.sq).then(self.row.cmp(&other.row))
    }
}
impl PartialOrd for Hit {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}

/// The k smallest hits seen so far (a max-heap bounded to k).
#[derive(Clone, Debug)]
pub(crate) struct TopK {
    k: usize,
    heap: BinaryHeap<Hit>,
}

impl TopK {
    pub fn new(k: usize) -> Self {
        TopK {
            k,
            // k may exceed the rows there are (even usize::MAX): the heap grows as it fills
            heap: BinaryHeap::with_capacity(k.min(1 << 12) + 1),
        }
    }

    /// Squared distances at or above this can never enter (rows arrive in increasing order, so
    /// a tie with the current k-th loses on the index).
    #[inline]
    pub fn threshold(&self) -> f32 {
        if self.heap.len() < self.k {
            f32::INFINITY
        } else {
            self.heap.peek().map_or(f32::INFINITY, |h| h.sq)
        }
    }

    #[inline]
    pub fn push(&mut self, h: Hit) {
        if self.heap.len() < self.k {
            self.heap.push(h);
        } else if let Some(mut top) = self.heap.peek_mut() {
            if h < *top {
                *top = h;
            }
        }
    }

    /// The hits held (any order).
    pub fn iter(&self) -> impl Iterator<Item = &Hit> {
        self.heap.iter()
    }

    pub fn into_vec(self) -> Vec<Hit> {
        self.heap.into_vec()
    }
}

/// Receives the squared distances of one scan (rows of a chunk, in increasing order per query).
pub(crate) trait Sink {
    /// Rows with a squared distance `< threshold(q)` are offered; others are skipped unseen. It
    /// never rises as rows are offered (the scans test a block's rows once against it, or
    /// against its value before a tile of blocks, then offer those still below it).
    fn threshold(&self, q: usize) -> f32;
    /// Offers row `row` at squared distance `sq` to query `q`.
    fn offer(&mut self, q: usize, row: usize, sq: f32);
}

/// Exact top-k per query.
pub(crate) struct TopKSink<'a> {
    pub heaps: Vec<TopK>,
    /// Per query, rows at squared distances `>= floor` are known to be beaten by k others
    /// (found by other chunks); `+inf` when nothing is known.
    pub floor: Vec<f32>,
    pub ex: Excluder<'a>,
}

impl Sink for TopKSink<'_> {
    #[inline]
    fn threshold(&self, q: usize) -> f32 {
        self.heaps[q].threshold().min(self.floor[q])
    }
    #[inline]
    fn offer(&mut self, q: usize, row: usize, sq: f32) {
        if !self.ex.excluded(q, row) {
            self.heaps[q].push(Hit {
                sq,
                row: row as u32,
            });
        }
    }
}

/// Every row under a fixed squared-distance bound, per query (radius search, or the shortlist
/// of a compressed radius scan).
pub(crate) struct BelowSink<'a> {
    pub bound: f32,
    pub hits: Vec<Vec<Hit>>,
    pub ex: Excluder<'a>,
    /// A hit list could not grow (out of memory): the scan's result is incomplete, and the
    /// caller reports [`crate::Error::Memory`] instead of aborting the process.
    pub out_of_memory: bool,
}

impl<'a> BelowSink<'a> {
    pub fn new(bound: f32, nq: usize, ex: Excluder<'a>) -> Self {
        BelowSink {
            bound,
            hits: vec![Vec::new(); nq],
            ex,
            out_of_memory: false,
        }
    }
}

impl Sink for BelowSink<'_> {
    #[inline]
    fn threshold(&self, _q: usize) -> f32 {
        if self.out_of_memory {
            f32::NEG_INFINITY // the result is lost: offer nothing more
        } else {
            self.bound
        }
    }
    #[inline]
    fn offer(&mut self, q: usize, row: usize, sq: f32) {
        if !self.out_of_memory && !self.ex.excluded(q, row) {
            let hits = &mut self.hits[q];
            if hits.len() == hits.capacity() && hits.try_reserve(hits.len().max(64)).is_err() {
                self.out_of_memory = true;
                return;
            }
            hits.push(Hit {
                sq,
                row: row as u32,
            });
        }
    }
}

/// Shortlist of a compressed top-k scan (one query): the approximate top-k, and every row whose
/// approximate squared distance is within `slack` (= 2ε) of the running approximate k-th.
pub(crate) struct ShortlistSink<'a> {
    pub heap: TopK,
    pub slack: f32,
    pub cands: Vec<Hit>,
    pub ex: Excluder<'a>,
    /// Shortlist length at which the next prune runs.
    next_prune: usize,
}

impl<'a> ShortlistSink<'a> {
    pub fn new(k: usize, slack: f32, ex: Excluder<'a>) -> Self {
        ShortlistSink {
            heap: TopK::new(k),
            slack,
            cands: Vec::new(),
            ex,
            next_prune: Self::min_prune(k),
        }
    }

    fn min_prune(k: usize) -> usize {
        4 * k + 256
    }

    /// Keeps only the candidates that can still be within `slack` of the k-th. The next prune
    /// waits until the shortlist has doubled: when many rows lie within `slack` of the k-th
    /// (one place seen many times) a prune removes few, and pruning again at every row would
    /// make the scan quadratic in the rows.
    pub fn prune(&mut self) {
        let bound = self.bound();
        self.cands.retain(|h| h.sq <= bound);
        self.next_prune = Self::min_prune(self.heap.k).max(2 * self.cands.len());
    }

    #[inline]
    fn bound(&self) -> f32 {
        self.heap.threshold() + self.slack
    }
}

impl Sink for ShortlistSink<'_> {
    #[inline]
    fn threshold(&self, _q: usize) -> f32 {
        self.bound().next_up()
    }
    #[inline]
    fn offer(&mut self, q: usize, row: usize, sq: f32) {
        if self.ex.excluded(q, row) {
            return;
        }
        let h = Hit {
            sq,
            row: row as u32,
        };
        self.heap.push(h);
        self.cands.push(h);
        if self.cands.len() >= self.next_prune {
            self.prune();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn topk_keeps_smallest_with_lower_index_on_ties() {
        let mut t = TopK::new(2);
        for (row, sq) in [(0u32, 3.0f32), (1, 1.0), (2, 1.0), (3, 0.5), (4, 1.0)] {
            if sq < t.threshold() {
                t.push(Hit { sq, row });
            }
        }
        let mut v = t.into_vec();
        v.sort();
        assert_eq!(v.iter().map(|h| h.row).collect::<Vec<_>>(), vec![3, 1]);
    }

    #[test]
    fn exclusion_window_and_whole_group() {
        let groups = [0i64, 0, 0, 1];
        let seqs = [10i64, 12, 20, 11];
        let rule = Exclusion {
            query_groups: &[0],
            query_seqs: &[11],
            window: 1,
            whole_group: false,
        };
        let ex = Excluder {
            rule: Some(rule),
            groups: &groups,
            seqs: &seqs,
        };
        let got: Vec<bool> = (0..4).map(|i| ex.excluded(0, i)).collect();
        assert_eq!(got, vec![true, true, false, false]);
        let ex = Excluder {
            rule: Some(Exclusion {
                whole_group: true,
                ..rule
            }),
            ..ex
        };
        let got: Vec<bool> = (0..4).map(|i| ex.excluded(0, i)).collect();
        assert_eq!(got, vec![true, true, true, false]);
    }
}
