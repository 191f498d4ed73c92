//! Coarse-to-fine translation hypothesis search (paper's hypothesis verification).
//!
//! Schedule: stage 0 proposes the full square grid `{i·step : |i·step| ≤ half_range}²` (row-major,
//! x outer, y inner); every later stage `s ≥ 1` proposes `fine_samples` points drawn uniformly
//! in the square of half-size `step·shrink^(s−1)` centred on the best hypothesis so far, clamped
//! to the search square `[−half_range, half_range]²`. The caller evaluates each stage's batch
//! and reports one cost and one yaw per proposal; the lowest cost wins (ties: the earlier one).
//!
//! Randomness: SplitMix64 (Steele, Lea & Flood 2014), written here so that the Python reference
//! reproduces it bit for bit. Stage `s` draws from the stream seeded with
//! `seed ^ (s · 0x9E3779B97F4A7C15)`; each sample takes two draws (x then y), each mapped to
//! [0, 1) as `(z >> 11)·2⁻⁵³`. The search itself is sequential, so it is deterministic for a seed
//! and any thread count.

use crate::error::{try_with_capacity, Error, Result};
use crate::pose::wrap_angle;
use std::f64::consts::PI;

/// SplitMix64 pseudo-random generator.
#[derive(Debug, Clone)]
pub struct SplitMix64 {
    state: u64,
}

impl SplitMix64 {
    /// A generator with the given state.
    pub fn new(seed: u64) -> Self {
        SplitMix64 { state: seed }
    }

    /// The next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// A uniform double in [0, 1).
    pub fn next_f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }
}

/// Configuration of the translation search (metres).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SearchConfig {
    /// Half-size of the search square around the origin, metres (≥ `step`).
    pub half_range: f64,
    /// Coarse grid step of stage 0, metres (> 0).
    pub step: f64,
    /// Number of random samples in each fine stage (≥ 1 when `stages` > 1).
    pub fine_samples: usize,
    /// Number of stages including the coarse grid (≥ 1).
    pub stages: usize,
    /// Factor in (0, 1] by which the fine square's half-size shrinks from one stage to the next.
    pub shrink: f64,
    /// Seed of the fine stages' sampling.
    pub seed: u64,
}

/// The most hypotheses one stage may propose (coarse grid or fine samples): 1e8 hypotheses of
/// 16 bytes are 1.6 GB of proposals alone, and each needs a decoder pass.
pub const MAX_STAGE_POINTS: usize = 100_000_000;

impl SearchConfig {
    /// Checks the configuration.
    pub fn validate(&self) -> Result<()> {
        if !(self.step.is_finite() && self.step > 0.0) {
            return Err(Error::value(
                "step",
                format!("expected a finite value > 0, got {}", self.step),
            ));
        }
        if !(self.half_range.is_finite() && self.half_range >= self.step) {
            return Err(Error::value(
                "half_range",
                format!(
                    "expected a finite value >= step ({}), got {}",
                    self.step, self.half_range
                ),
            ));
        }
        if self.stages == 0 {
            return Err(Error::value("stages", "expected an int >= 1, got 0"));
        }
        if self.stages > 1 && self.fine_samples == 0 {
            return Err(Error::value(
                "fine_samples",
                "expected an int >= 1 when stages > 1, got 0",
            ));
        }
        if !(self.shrink.is_finite() && self.shrink > 0.0 && self.shrink <= 1.0) {
            return Err(Error::value(
                "shrink",
                format!("expected a value in (0, 1], got {}", self.shrink),
            ));
        }
        if self.fine_samples > MAX_STAGE_POINTS {
            return Err(Error::value(
                "fine_samples",
                format!(
                    "expected at most {MAX_STAGE_POINTS} samples per stage, got {}",
                    self.fine_samples
                ),
            ));
        }
        let n = self.grid_side();
        if n.saturating_mul(n) > MAX_STAGE_POINTS {
            return Err(Error::value(
                "step",
                format!("the coarse grid would have {n}×{n} points; use a larger step"),
            ));
        }
        Ok(())
    }

    /// Number of grid points per axis in stage 0.
    fn grid_side(&self) -> usize {
        let m = (self.half_range / self.step + 1e-9).floor();
        2 * (m.min(1e9) as usize) + 1
    }
}

/// One evaluated hypothesis.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hypothesis {
    pub x: f64,
    pub y: f64,
    pub yaw: f64,
    pub cost: f64,
    pub stage: usize,
}

/// [`TranslationSearch::history`] as columns, the arrays the bindings hand out.
#[derive(Debug, Clone, PartialEq)]
pub struct HistoryColumns {
    /// (M, 2) row-major translations (x, y), metres.
    pub xy: Vec<f64>,
    /// (M,) yaws, radians in (−π, π].
    pub yaw: Vec<f64>,
    /// (M,) costs.
    pub cost: Vec<f64>,
    /// (M,) stage of each hypothesis.
    pub stage: Vec<i64>,
}

/// The coarse-to-fine search state machine: `proposals` → evaluate → `report`, until `done`.
///
/// Every buffer (proposals, history, their copies as columns) is allocated fallibly: one that
/// does not fit is [`Error::Memory`] naming `step` (the coarse grid) or `fine_samples`, and a
/// failed `report` leaves the search as it was.
#[derive(Debug, Clone)]
pub struct TranslationSearch {
    config: SearchConfig,
    stage: usize,
    pending: Vec<[f64; 2]>,
    history: Vec<Hypothesis>,
    best: Option<Hypothesis>,
}

impl TranslationSearch {
    /// Starts a search; invalid configurations are errors.
    pub fn new(config: SearchConfig) -> Result<Self> {
        config.validate()?;
        let mut s = TranslationSearch {
            config,
            stage: 0,
            pending: Vec::new(),
            history: Vec::new(),
            best: None,
        };
        s.pending = s.make_proposals(0, None)?;
        Ok(s)
    }

    /// The configuration.
    pub fn config(&self) -> &SearchConfig {
        &self.config
    }

    /// The current stage (equals `stages` when done).
    pub fn stage(&self) -> usize {
        self.stage
    }

    /// Whether every stage has been evaluated.
    pub fn done(&self) -> bool {
        self.stage >= self.config.stages
    }

    /// The translations (x, y) in metres to evaluate in the current stage (empty when done).
    pub fn proposals(&self) -> &[[f64; 2]] {
        &self.pending
    }

    /// Reports the costs and yaws of the current proposals (same order) and advances a stage.
    pub fn report(&mut self, costs: &[f64], yaws: &[f64]) -> Result<()> {
        if self.done() {
            return Err(Error::value("report", "the search is already done"));
        }
        let n = self.pending.len();
        if costs.len() != n {
            return Err(Error::shape("costs", format!("({n},)"), [costs.len()]));
        }
        if yaws.len() != n {
            return Err(Error::shape("yaws", format!("({n},)"), [yaws.len()]));
        }
        if costs.iter().any(|v| !v.is_finite()) {
            return Err(Error::value("costs", "contains non-finite values"));
        }
        if yaws.iter().any(|v| !v.is_finite()) {
            return Err(Error::value("yaws", "contains non-finite values"));
        }
        // Everything that can fail (the history's growth, the next stage's proposals) comes
        // before any change: a failed report leaves the search as it was.
        let arg = Self::stage_arg(self.stage);
        if self.history.try_reserve(n).is_err() {
            self.history
                .try_reserve_exact(n)
                .map_err(|_| Error::Memory {
                    arg,
                    what: format!("a history of {} hypotheses", self.history.len() + n),
                })?;
        }
        let hyps = self
            .pending
            .iter()
            .zip(costs.iter().zip(yaws))
            .map(|(p, (&cost, &yaw))| Hypothesis {
                x: p[0],
                y: p[1],
                // kept bit for bit inside (−π, π], as the reference keeps it; wrapped outside
                yaw: if yaw > -PI && yaw <= PI {
                    yaw
                } else {
                    wrap_angle(yaw)
                },
                cost,
                stage: self.stage,
            });
        let mut best = self.best;
        for h in hyps.clone() {
            if best.is_none_or(|b| h.cost < b.cost) {
                best = Some(h);
            }
        }
        let next = self.stage + 1;
        let pending = if next >= self.config.stages {
            Vec::new()
        } else {
            self.make_proposals(next, best)?
        };
        self.history.extend(hyps); // within the capacity reserved above
        self.best = best;
        self.stage = next;
        self.pending = pending;
        Ok(())
    }

    /// The argument that sets the number of hypotheses of stage `stage`.
    fn stage_arg(stage: usize) -> &'static str {
        if stage == 0 {
            "step"
        } else {
            "fine_samples"
        }
    }

    /// The current proposals as a row-major (N, 2) array of (x, y) metres, allocated fallibly.
    pub fn proposals_xy(&self) -> Result<Vec<f64>> {
        let mut out = try_with_capacity(Self::stage_arg(self.stage), 2 * self.pending.len())?;
        out.extend(self.pending.iter().flatten().copied());
        Ok(out)
    }

    /// [`TranslationSearch::history`] as columns, allocated fallibly ([`Error::Memory`] naming
    /// `step` or `fine_samples`, whichever sets more of the hypotheses).
    pub fn history_columns(&self) -> Result<HistoryColumns> {
        let h = &self.history;
        let grid = h.iter().take_while(|v| v.stage == 0).count();
        let arg = if h.len() - grid > grid {
            "fine_samples"
        } else {
            "step"
        };
        let mut xy = try_with_capacity(arg, 2 * h.len())?;
        xy.extend(h.iter().flat_map(|v| [v.x, v.y]));
        let column = |f: fn(&Hypothesis) -> f64| -> Result<Vec<f64>> {
            let mut out = try_with_capacity(arg, h.len())?;
            out.extend(h.iter().map(f));
            Ok(out)
        };
        let (yaw, cost) = (column(|v| v.yaw)?, column(|v| v.cost)?);
        let mut stage = try_with_capacity(arg, h.len())?;
        stage.extend(h.iter().map(|v| v.stage as i64));
        Ok(HistoryColumns {
            xy,
            yaw,
            cost,
            stage,
        })
    }

    /// The best hypothesis so far (None before the first report).
    pub fn best(&self) -> Option<Hypothesis> {
        self.best
    }

    /// Every evaluated hypothesis, in evaluation order.
    pub fn history(&self) -> &[Hypothesis] {
        &self.history
    }

    /// The proposals of stage `stage` around `best`, allocated fallibly.
    fn make_proposals(&self, stage: usize, best: Option<Hypothesis>) -> Result<Vec<[f64; 2]>> {
        let cfg = &self.config;
        if stage == 0 {
            let n = cfg.grid_side();
            let m = (n / 2) as f64;
            // i·step can round one ulp past half_range (3 × 0.1 > 0.3): clamped, the grid
            // keeps to its square as the fine stages do
            let tick =
                |i: usize| ((i as f64 - m) * cfg.step).clamp(-cfg.half_range, cfg.half_range);
            // n·n ≤ MAX_STAGE_POINTS (validated): no overflow
            let mut out = try_with_capacity(Self::stage_arg(0), n * n)?;
            for ix in 0..n {
                for iy in 0..n {
                    out.push([tick(ix), tick(iy)]);
                }
            }
            return Ok(out);
        }
        let centre = best.map_or([0.0, 0.0], |b| [b.x, b.y]);
        // Repeated multiplication (not powi) so that the Python reference matches bit for bit.
        let mut half = cfg.step;
        for _ in 1..stage {
            half *= cfg.shrink;
        }
        let mut rng =
            SplitMix64::new(cfg.seed ^ (stage as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15));
        let r = cfg.half_range;
        let mut out = try_with_capacity(Self::stage_arg(stage), cfg.fine_samples)?;
        out.extend((0..cfg.fine_samples).map(|_| {
            let x = centre[0] + (2.0 * rng.next_f64() - 1.0) * half;
            let y = centre[1] + (2.0 * rng.next_f64() - 1.0) * half;
            [x.clamp(-r, r), y.clamp(-r, r)]
        }));
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cfg() -> SearchConfig {
        SearchConfig {
            half_range: 3.0,
            step: 1.0,
            fine_samples: 16,
            stages: 4,
            shrink: 0.5,
            seed: 7,
        }
    }

    fn run(cfg: SearchConfig, f: impl Fn(f64, f64) -> f64) -> TranslationSearch {
        let mut s = TranslationSearch::new(cfg).unwrap();
        while !s.done() {
            let costs: Vec<f64> = s.proposals().iter().map(|p| f(p[0], p[1])).collect();
            let yaws = vec![0.25; costs.len()];
            s.report(&costs, &yaws).unwrap();
        }
        s
    }

    #[test]
    fn splitmix_known_values() {
        // Reference values of SplitMix64 seeded with 0 (as published with the algorithm).
        let mut r = SplitMix64::new(0);
        assert_eq!(r.next_u64(), 0xE220_A839_7B1D_CDAF);
        assert_eq!(r.next_u64(), 0x6E78_9E6A_A1B9_65F4);
    }

    #[test]
    fn the_coarse_grid_keeps_to_its_square_when_its_ticks_round_past_it() {
        // 3 × 0.1 = 0.30000000000000004 > 0.3
        let cfg = SearchConfig {
            half_range: 0.3,
            step: 0.1,
            ..cfg()
        };
        let s = TranslationSearch::new(cfg).unwrap();
        let p = s.proposals();
        assert_eq!(p.len(), 49);
        let top = p.iter().flatten().fold(0.0_f64, |a, &v| a.max(v.abs()));
        assert_eq!(top, 0.3);
    }

    #[test]
    fn reported_yaws_are_kept_inside_and_wrapped_outside_the_half_open_turn() {
        let mut s = TranslationSearch::new(SearchConfig { stages: 1, ..cfg() }).unwrap();
        let n = s.proposals().len();
        let mut yaws = vec![-0.1; n];
        yaws[1] = 100.0;
        let costs: Vec<f64> = (0..n).map(|i| if i == 1 { 0.0 } else { 1.0 }).collect();
        s.report(&costs, &yaws).unwrap();
        assert_eq!(s.best().unwrap().yaw, wrap_angle(100.0));
        assert!(s.history().iter().all(|h| h.yaw > -PI && h.yaw <= PI));
        assert_eq!(s.history()[0].yaw, -0.1); // bit for bit
    }

    #[test]
    fn grid_then_shrinking_samples_find_a_minimum() {
        let s = run(cfg(), |x, y| (x - 1.3).powi(2) + (y + 0.6).powi(2));
        let h = s.history();
        assert_eq!(h.iter().filter(|h| h.stage == 0).count(), 49);
        assert_eq!(h.len(), 49 + 3 * 16);
        let b = s.best().unwrap();
        assert!((b.x - 1.3).abs() < 0.2 && (b.y + 0.6).abs() < 0.2, "{b:?}");
        assert_eq!(b.yaw, 0.25);
        // Stage s samples lie within step·shrink^(s−1) of the best before that stage.
        for h in h.iter().filter(|h| h.stage == 3) {
            assert!((h.x - 1.3).abs() <= 1.0 && (h.y + 0.6).abs() <= 1.0);
        }
    }

    #[test]
    fn columns_are_the_proposals_and_the_history() {
        let mut s = TranslationSearch::new(cfg()).unwrap();
        let flat: Vec<f64> = s.proposals().iter().flatten().copied().collect();
        assert_eq!(s.proposals_xy().unwrap(), flat);
        let n = s.proposals().len();
        let costs: Vec<f64> = (0..n).map(|i| i as f64).collect();
        s.report(&costs, &vec![4.0; n]).unwrap();
        s.report(&[0.5; 16], &[0.1; 16]).unwrap();
        let h = s.history_columns().unwrap();
        assert_eq!(h.yaw.len(), n + 16);
        for (i, v) in s.history().iter().enumerate() {
            assert_eq!(
                (h.xy[2 * i], h.xy[2 * i + 1], h.yaw[i], h.cost[i]),
                (v.x, v.y, v.yaw, v.cost)
            );
            assert_eq!(h.stage[i], v.stage as i64);
        }
    }

    #[test]
    fn deterministic_for_a_seed() {
        let f = |x: f64, y: f64| (x * 0.7).sin() + (y * 1.3).cos();
        let (a, b) = (run(cfg(), f), run(cfg(), f));
        assert_eq!(a.history(), b.history());
        let c = run(SearchConfig { seed: 8, ..cfg() }, f);
        assert_ne!(a.history(), c.history());
    }

    #[test]
    fn invalid_configurations_are_errors() {
        for bad in [
            SearchConfig { step: 0.0, ..cfg() },
            SearchConfig {
                step: -1.0,
                ..cfg()
            },
            SearchConfig { stages: 0, ..cfg() },
            SearchConfig {
                fine_samples: MAX_STAGE_POINTS + 1,
                ..cfg()
            },
            SearchConfig {
                fine_samples: usize::MAX,
                ..cfg()
            },
            SearchConfig {
                half_range: 0.5,
                ..cfg()
            },
            SearchConfig {
                shrink: 0.0,
                ..cfg()
            },
            SearchConfig {
                shrink: 1.5,
                ..cfg()
            },
            SearchConfig {
                fine_samples: 0,
                ..cfg()
            },
            SearchConfig {
                half_range: f64::NAN,
                ..cfg()
            },
        ] {
            assert!(TranslationSearch::new(bad).is_err(), "{bad:?}");
        }
        let mut s = TranslationSearch::new(cfg()).unwrap();
        assert!(s.report(&[1.0], &[0.0]).is_err());
        let n = s.proposals().len();
        assert!(s.report(&vec![f64::NAN; n], &vec![0.0; n]).is_err());
    }
}
