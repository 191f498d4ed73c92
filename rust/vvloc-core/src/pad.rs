//! BEV padding (paper Alg. 1 with corrected fill) and the fused padding + polar sampling kernel.
//!
//! **Padding** (DESIGN.md §3). For a translation `t = (x, y)` metres and cell size `g`, the
//! shift in cells is `u = x/g` (rows) and `v = y/g` (columns), computed in f64. The padded map is
//! `Qᵗ[i, j]` = bilinear sample of `Q` at `(i + u, j + v)`, except 1 wherever a tap with a
//! non-zero weight falls outside the grid; this equals Alg. 1
//! (`ρ(ρ(Q, −u, 0), −v, 1)` then the wrapped-in rows/columns set to 1).
//! Along one axis with `k = ⌊u⌋`, `f = u − k`, row `a` is *valid* iff `a + k` lies in the grid
//! and, when `f > 0`, so does `a + k + 1`.
//!
//! **Snapping.** A shift within [`SHIFT_SNAP`] cells of an integer is rounded to it, so that e.g.
//! a float32 translation of 0.3 m on a 0.3 m grid (`u = 1.0000000397`) is the one-cell shift it
//! means instead of filling a second row because of a tap weighted 4e-8. The reference applies
//! the same rule.
//!
//! **Fused** `pad_polar` evaluates `polar_sample(bev_pad(Q, t))` without materialising `Qᵗ`:
//! along each axis a polar tap `a` (weight `wₐ`) that is valid in `Qᵗ` reads map rows `a + k`
//! (weight `wₐ(1 − f)`) and `a + k + 1` (weight `wₐ f`), so the two polar taps become a 3-tap
//! filter over consecutive map rows; an invalid or outside polar tap reads 1. Since the fill of
//! `Qᵗ[a, b]` is "row `a` invalid or column `b` invalid", the 2-D value is
//! `Σ αᵣ β_s Q[r, s] + 1 − (Σα)(Σβ)`.

use crate::error::{check_alloc, checked_len};
use crate::polar::{
    blend, check_grid_size, has_avx2_fma, output_buffer, AxisFilter, PolarGrid, Taps,
};
use crate::roll::PAR_THRESHOLD;
use crate::{Error, Result};
use ndarray::{Array4, ArrayView2, ArrayView3};
use rayon::prelude::*;

/// Shifts (in cells) closer than this to an integer are rounded to it.
pub const SHIFT_SNAP: f64 = 1e-6;

/// The padding shift along one axis of `n` cells: `u = ⌊u⌋ + f`.
#[derive(Debug, Clone, Copy)]
pub(crate) struct AxisShift {
    k: i64,
    f: f64,
    n: i64,
}

impl AxisShift {
    /// The shift for a translation of `metres` on an axis of `n` cells of `grid_size` metres.
    pub fn new(metres: f64, grid_size: f64, n: usize) -> Self {
        let mut u = metres / grid_size;
        let nearest = u.round();
        if (u - nearest).abs() <= SHIFT_SNAP {
            u = nearest;
        }
        // Beyond ±(n + 2) cells every row is filled anyway; clamping keeps i64 math safe.
        let lim = n as f64 + 2.0;
        let u = u.clamp(-lim, lim);
        let k = u.floor();
        AxisShift {
            k: k as i64,
            f: u - k,
            n: n as i64,
        }
    }

    /// Whether row `a` of the padded map is inside the grid and not filled.
    #[inline]
    fn valid(&self, a: i64) -> bool {
        let inside = |i: i64| i >= 0 && i < self.n;
        inside(a) && inside(a + self.k) && (self.f == 0.0 || inside(a + self.k + 1))
    }

    /// Weights over map rows of the padded map read by linear interpolation at fractional
    /// index `p` (a polar tap outside or on a filled row reads 1).
    #[inline]
    pub fn filter(&self, p: f64) -> AxisFilter {
        let a0 = p.floor();
        let fp = p - a0;
        let a0 = a0.clamp(-2.0, self.n as f64 + 1.0) as i64;
        let (g0, g1) = (self.valid(a0), self.valid(a0 + 1));
        let u0 = if g0 { 1.0 - fp } else { 0.0 };
        let u1 = if g1 { fp } else { 0.0 };
        let f = self.f;
        AxisFilter {
            start: a0 + self.k,
            w: [u0 * (1.0 - f), u0 * f + u1 * (1.0 - f), u1 * f],
            covered: if g0 && g1 { 1.0 } else { u0 + u1 },
        }
    }
}

fn check_bev(bev: &ArrayView3<'_, f32>) -> Result<()> {
    let (h, w, _) = bev.dim();
    if h == 0 || w == 0 {
        return Err(Error::shape("bev", "(H, W, C) with H, W >= 1", bev.shape()));
    }
    Ok(())
}

/// Validates translations (N, 2) metres and returns the per-hypothesis (row, column) shifts.
fn shifts(
    translations: &ArrayView2<'_, f64>,
    grid_size: f64,
    h: usize,
    w: usize,
) -> Result<Vec<(AxisShift, AxisShift)>> {
    check_grid_size(grid_size)?;
    if translations.ncols() != 2 {
        return Err(Error::shape("translations", "(N, 2)", translations.shape()));
    }
    // the size first: a vast broadcast view is refused before it is scanned
    check_alloc::<(AxisShift, AxisShift)>("translations", translations.nrows())?;
    // each value read once, checked where it is used (read twice, a value that another thread
    // changed in between could pass the check as finite and be used as NaN)
    translations
        .rows()
        .into_iter()
        .map(|t| {
            let (x, y) = (t[0], t[1]);
            if !(x.is_finite() && y.is_finite()) {
                return Err(Error::value(
                    "translations",
                    "contains non-finite values (NaN or inf)",
                ));
            }
            Ok((
                AxisShift::new(x, grid_size, h),
                AxisShift::new(y, grid_size, w),
            ))
        })
        .collect()
}

/// One row `i` of the padded map for shift `s`: writes the (W, C) block `out`.
#[inline(always)]
fn pad_row<const FMA: bool>(
    map: &[f32],
    (w, c): (usize, usize),
    s: &(AxisShift, AxisShift),
    i: usize,
    out: &mut [f32],
) {
    let rows = s.0.filter(i as f64);
    for (j, dst) in out.chunks_exact_mut(c).enumerate() {
        let cols = s.1.filter(j as f64);
        blend::<FMA>(dst, &Taps::separable(map, w, c, &rows, &cols));
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn pad_row_avx2(
    map: &[f32],
    wc: (usize, usize),
    s: &(AxisShift, AxisShift),
    i: usize,
    out: &mut [f32],
) {
    pad_row::<true>(map, wc, s, i, out)
}

/// BEV padding of `bev` (H, W, C) for each translation (N, 2) metres → (N, H, W, C).
///
/// Zero shift returns the map unchanged; shifts of a whole map size or more give all ones.
/// Parallel over (hypothesis, row); results do not depend on the thread count.
pub fn bev_pad(
    bev: ArrayView3<'_, f32>,
    translations: ArrayView2<'_, f64>,
    grid_size: f64,
) -> Result<Array4<f32>> {
    check_bev(&bev)?;
    let (h, w, c) = bev.dim();
    let shifts = shifts(&translations, grid_size, h, w)?;
    let n = shifts.len();
    if !bev.is_standard_layout() {
        check_alloc::<f32>("bev", bev.len())?; // the copy below (a broadcast view may be vast)
    }
    let bev = bev.as_standard_layout();
    let map = bev
        .as_slice()
        .ok_or_else(|| Error::value("bev", "could not view the array as contiguous memory"))?;
    let mut out = output_buffer("translations", &[n, h, w, c])?;
    if c > 0 && n > 0 {
        let fma = has_avx2_fma();
        let row = |(idx, dst): (usize, &mut [f32])| {
            let (hyp, i) = (idx / h, idx % h);
            #[cfg(target_arch = "x86_64")]
            if fma {
                // SAFETY: `fma` is true only when AVX2 and FMA were detected at runtime.
                return unsafe { pad_row_avx2(map, (w, c), &shifts[hyp], i, dst) };
            }
            let _ = fma;
            pad_row::<false>(map, (w, c), &shifts[hyp], i, dst)
        };
        if out.len() < PAR_THRESHOLD {
            out.chunks_mut(w * c).enumerate().for_each(row);
        } else {
            out.par_chunks_mut(w * c).enumerate().for_each(row);
        }
    }
    Array4::from_shape_vec((n, h, w, c), out).map_err(|e| Error::value("bev", e.to_string()))
}

/// Fused padding + polar sampling for a group of hypotheses: `out` is their (G, T, R, C) block.
///
/// Loops angle bin outermost and hypothesis inside, so that the map rows under one ray (and its
/// translated copies) are reused from cache by every hypothesis of the group.
#[inline(always)]
fn pad_polar_group<const FMA: bool>(
    map: &[f32],
    c: usize,
    grid: &PolarGrid,
    shifts: &[(AxisShift, AxisShift)],
    out: &mut [f32],
) {
    let (t, r) = (grid.num_angles, grid.num_radii);
    let per_hyp = t * r * c;
    for k in 0..t {
        for (g, s) in shifts.iter().enumerate() {
            let block = &mut out[g * per_hyp + k * r * c..g * per_hyp + (k + 1) * r * c];
            for (m, dst) in block.chunks_exact_mut(c).enumerate() {
                let [p, q] = grid.point(k, m);
                let rows = s.0.filter(p);
                let cols = s.1.filter(q);
                blend::<FMA>(dst, &Taps::separable(map, grid.width, c, &rows, &cols));
            }
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn pad_polar_group_avx2(
    map: &[f32],
    c: usize,
    grid: &PolarGrid,
    shifts: &[(AxisShift, AxisShift)],
    out: &mut [f32],
) {
    pad_polar_group::<true>(map, c, grid, shifts, out)
}

/// Fused BEV padding + polar sampling: `bev` (H, W, C), `translations` (N, 2) metres →
/// (N, T, R, C), equal to `polar_sample(bev_pad(bev, translations, g), T, R, g)` up to float
/// rounding, without materialising the padded maps. Parallel over groups of hypotheses.
pub fn pad_polar(
    bev: ArrayView3<'_, f32>,
    translations: ArrayView2<'_, f64>,
    num_angles: usize,
    num_radii: usize,
    grid_size: f64,
) -> Result<Array4<f32>> {
    check_bev(&bev)?;
    let (h, w, c) = bev.dim();
    let grid = PolarGrid::new(h, w, num_angles, num_radii, grid_size)?;
    let shifts = shifts(&translations, grid_size, h, w)?;
    let n = shifts.len();
    if !bev.is_standard_layout() {
        check_alloc::<f32>("bev", bev.len())?; // the copy below (a broadcast view may be vast)
    }
    let bev = bev.as_standard_layout();
    let map = bev
        .as_slice()
        .ok_or_else(|| Error::value("bev", "could not view the array as contiguous memory"))?;
    let per_hyp = checked_len("num_angles", &[num_angles, num_radii, c])?;
    let mut out = output_buffer("num_angles", &[n, num_angles, num_radii, c])?;
    if per_hyp > 0 && n > 0 {
        let fma = has_avx2_fma();
        let run = |(gi, dst): (usize, &mut [f32]), group: usize| {
            let s = &shifts[gi * group..(gi * group + dst.len() / per_hyp)];
            #[cfg(target_arch = "x86_64")]
            if fma {
                // SAFETY: `fma` is true only when AVX2 and FMA were detected at runtime.
                return unsafe { pad_polar_group_avx2(map, c, &grid, s, dst) };
            }
            let _ = fma;
            pad_polar_group::<false>(map, c, &grid, s, dst)
        };
        if out.len() < PAR_THRESHOLD {
            out.chunks_mut(n * per_hyp)
                .enumerate()
                .for_each(|x| run(x, n));
        } else {
            // Groups small enough to balance the load, large enough to share the map in cache.
            let group = n.div_ceil(4 * rayon::current_num_threads()).clamp(1, 16);
            out.par_chunks_mut(group * per_hyp)
                .enumerate()
                .for_each(|x| run(x, group));
        }
    }
    Array4::from_shape_vec((n, num_angles, num_radii, c), out)
        .map_err(|e| Error::value("bev", e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::polar::polar_sample;
    use crate::roll::roll_interp;
    use ndarray::{array, s, Array, Array2, Array3, Axis};

    fn field(h: usize, w: usize, c: usize) -> Array3<f32> {
        Array::from_shape_fn((h, w, c), |(i, j, k)| {
            ((i as f32 * 0.37 + j as f32 * 1.3 + k as f32 * 0.71).sin()) * 2.0
        })
    }

    /// Literal Alg. 1: two interpolated rolls, then the wrapped-in rows/columns set to 1.
    fn alg1(q: &Array3<f32>, x: f64, y: f64, g: f64) -> Array3<f32> {
        let snap = |u: f64| {
            if (u - u.round()).abs() <= SHIFT_SNAP {
                u.round()
            } else {
                u
            }
        };
        let (u, v) = (snap(x / g), snap(y / g));
        let a = roll_interp(q.view().into_dyn(), -u, 0).unwrap();
        let mut b = roll_interp(a.view(), -v, 1)
            .unwrap()
            .into_dimensionality::<ndarray::Ix3>()
            .unwrap();
        let (h, w, _) = q.dim();
        let fill = |mut b: ndarray::ArrayViewMut3<f32>, s: f64, n: usize, axis: usize| {
            let (lo, hi) = if s >= 0.0 {
                ((n as f64 - s.ceil()).max(0.0) as usize, n)
            } else {
                (0, ((-s).ceil() as usize).min(n))
            };
            for i in lo..hi {
                b.index_axis_mut(Axis(axis), i).fill(1.0);
            }
        };
        fill(b.view_mut(), u, h, 0);
        fill(b.view_mut(), v, w, 1);
        b
    }

    fn close(a: &[f32], b: &[f32], tol: f32) {
        assert_eq!(a.len(), b.len());
        for (x, y) in a.iter().zip(b) {
            assert!((x - y).abs() <= tol, "{x} vs {y}");
        }
    }

    #[test]
    fn closed_form_equals_algorithm_one() {
        let q = field(9, 7, 5);
        let g = 0.3;
        for &(x, y) in &[
            (0.0, 0.0),
            (0.3, 0.0),
            (0.45, -0.2),
            (-0.9, 1.11),
            (-0.05, -0.61),
            (2.0, -1.9),
            (0.3f32 as f64 * 3.0, -0.6f32 as f64),
        ] {
            let t = array![[x, y]];
            let got = bev_pad(q.view(), t.view(), g).unwrap();
            let want = alg1(&q, x, y, g);
            close(
                got.index_axis(Axis(0), 0).as_slice().unwrap(),
                want.as_slice().unwrap(),
                1e-5,
            );
        }
    }

    #[test]
    fn zero_shift_is_identity_and_huge_shift_is_all_ones() {
        let q = field(6, 8, 3);
        let t = array![[0.0, 0.0], [100.0, 0.0], [0.0, -1e30], [3.0 * 0.5, 0.0]];
        let out = bev_pad(q.view(), t.view(), 0.5).unwrap();
        assert_eq!(out.index_axis(Axis(0), 0), q);
        assert!(out.index_axis(Axis(0), 1).iter().all(|&v| v == 1.0));
        assert!(out.index_axis(Axis(0), 2).iter().all(|&v| v == 1.0));
        // Integer shift of 3 rows: rows 0..3 read rows 3..6, rows 3..6 are filled.
        let p = out.index_axis(Axis(0), 3);
        assert_eq!(p.slice(s![..3, .., ..]), q.slice(s![3.., .., ..]));
        assert!(p.slice(s![3.., .., ..]).iter().all(|&v| v == 1.0));
    }

    #[test]
    fn fused_equals_composition() {
        let q = field(13, 10, 37);
        let g = 0.25;
        let t: Array2<f64> = array![
            [0.0, 0.0],
            [0.25, -0.5],
            [0.13, 0.61],
            [-0.77, -0.02],
            [5.0, 0.0],
            [-0.1, 40.0]
        ];
        let fused = pad_polar(q.view(), t.view(), 11, 6, g).unwrap();
        let padded = bev_pad(q.view(), t.view(), g).unwrap();
        let composed = polar_sample(padded.view().into_dyn(), 11, 6, g).unwrap();
        close(
            fused.as_slice().unwrap(),
            composed.as_slice().unwrap(),
            1e-5,
        );
    }

    #[test]
    fn results_do_not_depend_on_the_thread_count() {
        let q = field(30, 30, 64);
        let t = Array::from_shape_fn((21, 2), |(n, d)| (n as f64 - 10.0) * 0.13 + d as f64 * 0.07);
        let run = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| {
                    (
                        pad_polar(q.view(), t.view(), 24, 10, 0.3).unwrap(),
                        bev_pad(q.view(), t.view(), 0.3).unwrap(),
                    )
                })
        };
        assert_eq!(run(1), run(2));
        assert_eq!(run(1), run(3));
    }

    #[test]
    fn rejects_bad_arguments() {
        let q = field(4, 4, 2);
        let ok = array![[0.0, 0.0]];
        let bad_shape = Array2::<f64>::zeros((2, 3));
        let bad_value = array![[0.0, f64::NAN]];
        assert!(matches!(
            bev_pad(q.view(), bad_shape.view(), 0.3),
            Err(Error::Shape {
                arg: "translations",
                ..
            })
        ));
        assert!(matches!(
            pad_polar(q.view(), bad_value.view(), 3, 3, 0.3),
            Err(Error::Value {
                arg: "translations",
                ..
            })
        ));
        assert!(matches!(
            bev_pad(q.view(), ok.view(), 0.0),
            Err(Error::Value {
                arg: "grid_size",
                ..
            })
        ));
        assert!(matches!(
            pad_polar(q.view(), ok.view(), 3, 0, 0.3),
            Err(Error::Value {
                arg: "num_radii",
                ..
            })
        ));
        let empty = Array3::<f32>::zeros((4, 0, 2));
        assert!(bev_pad(empty.view(), ok.view(), 0.3).is_err());
        let none = Array2::<f64>::zeros((0, 2));
        assert_eq!(
            pad_polar(q.view(), none.view(), 3, 3, 0.3).unwrap().len(),
            0
        );
    }
}
