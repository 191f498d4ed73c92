#![allow(clippy::needless_range_loop)]

use super::*;
use select::Hit;

/// Deterministic pseudo-random floats in [-1, 1) (xorshift).
fn rand_vec(n: usize, seed: u64) -> Vec<f32> {
    let mut s = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    (0..n)
        .map(|_| {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            ((s >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
        })
        .collect()
}

/// Clustered, L2-normalised descriptors (realistic: many close neighbours).
fn clustered(n: usize, d: usize, seed: u64) -> Vec<f32> {
    let centres = rand_vec(8 * d, seed);
    let noise = rand_vec(n * d, seed + 1);
    let mut out = vec![0f32; n * d];
    for i in 0..n {
        let c = i % 8;
        let row = &mut out[i * d..(i + 1) * d];
        for j in 0..d {
            row[j] = centres[c * d + j] + 0.15 * noise[i * d + j];
        }
        let norm = row.iter().map(|v| v * v).sum::<f32>().sqrt();
        row.iter_mut().for_each(|v| *v /= norm);
    }
    out
}

/// Brute force in f64 (the oracle): sorted (distance, index) of all rows.
fn brute(data: &[f32], d: usize, q: &[f32]) -> Vec<(f64, usize)> {
    let mut v: Vec<(f64, usize)> = data
        .chunks_exact(d)
        .enumerate()
        .map(|(i, x)| {
            let s: f64 = x
                .iter()
                .zip(q)
                .map(|(&a, &b)| (a as f64 - b as f64).powi(2))
                .sum();
            (s.sqrt(), i)
        })
        .collect();
    v.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    v
}

#[test]
fn topk_matches_brute_force_for_all_levels_and_dtypes() {
    let (n, d, k) = (1000, 37, 10);
    let data = clustered(n, d, 1);
    let queries = clustered(11, d, 2);
    let base = DescriptorIndex::from_rows(&data, d, Dtype::F32, None, None).unwrap();
    let want = base.topk(&queries, k, None).unwrap();
    for qi in 0..11 {
        let oracle = brute(&data, d, &queries[qi * d..(qi + 1) * d]);
        for c in 0..k {
            assert!((want.distances[qi * k + c] as f64 - oracle[c].0).abs() < 1e-3);
        }
    }
    for level in kernels::available_levels() {
        for dtype in [Dtype::F32, Dtype::F16, Dtype::BF16, Dtype::I8] {
            let idx = DescriptorIndex::from_rows(&data, d, dtype, None, None)
                .unwrap()
                .with_level(level)
                .unwrap();
            // One query at a time (compressed path) and as a batch (tile path).
            for qi in 0..11 {
                let got = idx.topk(&queries[qi * d..(qi + 1) * d], k, None).unwrap();
                assert_eq!(
                    got.indices,
                    want.indices[qi * k..(qi + 1) * k],
                    "{level:?} {dtype:?}"
                );
                assert_eq!(got.distances, want.distances[qi * k..(qi + 1) * k]);
            }
            assert_eq!(idx.topk(&queries, k, None).unwrap(), want);
        }
    }
}

#[test]
fn ties_break_by_lower_index_and_k_beyond_n_pads() {
    let d = 4;
    let mut data = rand_vec(5 * d, 3);
    let dup = data[..d].to_vec();
    data.extend(&dup); // row 5 duplicates row 0
    let idx = DescriptorIndex::from_rows(&data, d, Dtype::F32, None, None).unwrap();
    let res = idx.topk(&dup, 8, None).unwrap();
    assert_eq!(&res.indices[..2], &[0, 5]);
    assert_eq!(res.distances[0], res.distances[1]);
    assert_eq!(&res.indices[6..], &[-1, -1]);
    assert!(res.distances[6].is_infinite());
}

#[test]
fn empty_index_returns_padding() {
    let idx = DescriptorIndex::new(3, Dtype::F16).unwrap();
    let res = idx.topk(&[1.0, 0.0, 0.0], 2, None).unwrap();
    assert_eq!(res.indices, vec![-1, -1]);
    let rad = idx.radius(&[1.0, 0.0, 0.0], 1.0, None).unwrap();
    assert_eq!(rad.offsets, vec![0, 0]);
}

#[test]
fn radius_matches_brute_force_and_exclusion_applies() {
    let (n, d) = (700, 16);
    let data = clustered(n, d, 5);
    let queries = clustered(9, d, 6);
    let r = 0.5f32;
    for dtype in [Dtype::F32, Dtype::BF16, Dtype::F16, Dtype::I8] {
        let idx = DescriptorIndex::from_rows(&data, d, dtype, None, None).unwrap();
        for batch in [true, false] {
            for qi in 0..9 {
                let q = &queries[qi * d..(qi + 1) * d];
                let res = if batch {
                    let all = idx.radius(&queries, r, None).unwrap();
                    let (a, b) = (all.offsets[qi] as usize, all.offsets[qi + 1] as usize);
                    all.indices[a..b].to_vec()
                } else {
                    idx.radius(q, r, None).unwrap().indices
                };
                let want: Vec<i64> = brute(&data, d, q)
                    .into_iter()
                    .filter(|&(s, _)| s < r as f64)
                    .map(|(_, i)| i as i64)
                    .collect();
                assert_eq!(res, want, "{dtype:?} batch={batch}");
            }
        }
    }
    // Exclusion: query = row 100 (group 0, seq 100), window 3 removes rows 97..=103.
    let idx = DescriptorIndex::from_rows(&data, d, Dtype::F32, None, None).unwrap();
    let q = &data[100 * d..101 * d];
    let ex = Exclusion {
        query_groups: &[0],
        query_seqs: &[100],
        window: 3,
        whole_group: false,
    };
    let res = idx.radius(q, 2.5, Some(ex)).unwrap();
    assert_eq!(res.indices.len(), n - 7);
    assert!(res.indices.iter().all(|&i| !(97..=103).contains(&i)));
    let top = idx.topk(q, 1, Some(ex)).unwrap();
    assert!(!(97..=103).contains(&top.indices[0]));
}

#[test]
fn add_appends_and_equals_one_shot_construction() {
    let d = 20;
    let data = rand_vec(100 * d, 9);
    let mut inc = DescriptorIndex::new(d, Dtype::BF16).unwrap();
    inc.add(&data[..37 * d], None, None).unwrap();
    inc.add(&data[37 * d..], None, None).unwrap();
    let one = DescriptorIndex::from_rows(&data, d, Dtype::BF16, None, None).unwrap();
    assert_eq!(inc.rows(), one.rows());
    assert_eq!(inc.seqs(), one.seqs());
    assert_eq!(inc.packed, one.packed);
    assert_eq!(inc.norms, one.norms);
}

#[test]
fn bad_input_is_an_error_not_a_panic() {
    let mut idx = DescriptorIndex::new(4, Dtype::F16).unwrap();
    assert!(matches!(
        idx.add(&[1.0; 6], None, None),
        Err(Error::Shape { .. })
    ));
    assert!(idx.add(&[f32::NAN, 0.0, 0.0, 0.0], None, None).is_err());
    assert!(idx.add(&[1e6, 0.0, 0.0, 0.0], None, None).is_err());
    assert!(idx.add(&[1.0; 4], Some(&[1, 2]), None).is_err());
    idx.add(&[1.0; 4], None, None).unwrap();
    assert!(idx.topk(&[1.0; 4], 0, None).is_err());
    assert!(idx.topk(&[1.0; 3], 1, None).is_err());
    assert!(idx.radius(&[1.0; 4], 0.0, None).is_err());
    assert!(idx.radius(&[1.0; 4], f32::NAN, None).is_err());
    assert!(DescriptorIndex::new(0, Dtype::F32).is_err());
    assert!(DescriptorIndex::new(MAX_DIM + 1, Dtype::F32).is_err());
    assert!(Dtype::parse("int4").is_err());
    // values whose squared distances overflow float32 are refused, not answered with inf or 0
    for arg in ["descriptors", "queries"] {
        let mut idx = DescriptorIndex::new(4, Dtype::F32).unwrap();
        idx.add(&[1.0; 4], None, None).unwrap();
        let big = [4e18f32; 4];
        let e = if arg == "descriptors" {
            idx.add(&big, None, None).unwrap_err()
        } else {
            idx.topk(&big, 1, None).unwrap_err()
        };
        assert!(
            e.to_string()
                .starts_with(&format!("{arg}: values too large")),
            "{e}"
        );
    }
    // k may exceed the rows, but a result larger than memory is an error, not an abort
    assert_eq!(idx.topk(&[1.0; 4], 1000, None).unwrap().indices[1], -1);
    for k in [1usize << 40, usize::MAX] {
        assert!(matches!(
            idx.topk(&[1.0; 4], k, None),
            Err(Error::Memory { arg: "k", .. })
        ));
        assert!(matches!(
            idx.topk(&[], k, None),
            Ok(TopKResult { .. }) | Err(Error::Memory { .. })
        ));
    }
}

#[test]
fn a_forged_header_with_a_huge_dimension_is_refused() {
    // an empty index (N = 0) claiming d = 2^40, with a valid checksum: 40 bytes in all
    let mut bytes = format::to_bytes(&DescriptorIndex::new(4, Dtype::F32).unwrap()).unwrap();
    assert_eq!(bytes.len(), 40);
    bytes[24..32].copy_from_slice(&(1u64 << 40).to_le_bytes());
    let sum = format::checksum(&[&bytes[8..32], &bytes[40..]]);
    bytes[32..40].copy_from_slice(&sum.to_le_bytes());
    let e = format::from_bytes(&bytes).unwrap_err();
    assert!(e.to_string().contains("dimension d must be <="), "{e}");
}

#[test]
fn results_do_not_depend_on_thread_count() {
    let (n, d) = (20_000, 64);
    let data = clustered(n, d, 11);
    let queries = clustered(10, d, 12);
    for dtype in [Dtype::F32, Dtype::BF16, Dtype::I8] {
        let mut idx = DescriptorIndex::from_rows(&data, d, dtype, None, None).unwrap();
        idx.min_parallel_work = 1; // many chunks (shared top-k floor, merges) even here
        let run = |t: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(t)
                .build()
                .unwrap();
            pool.install(|| {
                (
                    idx.topk(&queries, 20, None).unwrap(),
                    (0..10)
                        .map(|qi| idx.topk(&queries[qi * d..(qi + 1) * d], 20, None).unwrap())
                        .collect::<Vec<_>>(),
                    idx.radius(&queries, 0.4, None).unwrap(),
                )
            })
        };
        let (batch, single, radius) = run(1);
        assert_eq!(run(3), (batch.clone(), single.clone(), radius));
        for (qi, s) in single.iter().enumerate() {
            assert_eq!(
                s.indices,
                batch.indices[qi * 20..(qi + 1) * 20],
                "{dtype:?}"
            );
            assert_eq!(s.distances, batch.distances[qi * 20..(qi + 1) * 20]);
        }
    }
}

#[test]
fn save_load_round_trip_and_corruption_detected() {
    let d = 7;
    let data = rand_vec(50 * d, 13);
    let groups: Vec<i64> = (0..50).map(|i| i / 10).collect();
    let idx = DescriptorIndex::from_rows(&data, d, Dtype::F16, Some(&groups), None).unwrap();
    let dir = std::env::temp_dir().join(format!("vvloc-idx-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("map.vvidx");
    idx.save(&path).unwrap();
    let back = DescriptorIndex::load(&path).unwrap();
    assert_eq!(back.rows(), idx.rows());
    assert_eq!(back.groups(), idx.groups());
    assert_eq!(back.seqs(), idx.seqs());
    assert_eq!(back.dtype(), Dtype::F16);
    let bytes = std::fs::read(&path).unwrap();
    for cut in [0, 10, 39, 40, bytes.len() - 1] {
        assert!(matches!(
            format::from_bytes(&bytes[..cut]),
            Err(Error::Format(_))
        ));
    }
    for pos in [0, 9, 13, 20, 33, 45, bytes.len() - 3] {
        let mut bad = bytes.clone();
        bad[pos] ^= 0x10;
        assert!(
            matches!(format::from_bytes(&bad), Err(Error::Format(_))),
            "byte {pos}"
        );
    }
    assert!(matches!(
        DescriptorIndex::load(&dir.join("missing")),
        Err(Error::Io { .. })
    ));
    // the header is checked against the file's length before the body is read: a foreign
    // file of 1 GiB (sparse: nothing on disk) is refused by its magic bytes, and a header
    // whose sizes differ from the file's by its length
    let foreign = dir.join("foreign.vvidx");
    let f = std::fs::File::create(&foreign).unwrap();
    f.set_len(1 << 30).unwrap();
    drop(f);
    let e = DescriptorIndex::load(&foreign).unwrap_err().to_string();
    assert!(
        e.contains("foreign.vvidx") && e.contains("wrong magic bytes"),
        "{e}"
    );
    let mut longer = bytes.clone();
    longer.extend_from_slice(&[0; 8]);
    std::fs::write(&foreign, &longer).unwrap();
    let e = DescriptorIndex::load(&foreign).unwrap_err().to_string();
    assert!(
        e.contains(&format!("but the file has {} bytes", longer.len())),
        "{e}"
    );
    let e = DescriptorIndex::load(&dir).unwrap_err().to_string();
    assert!(e.contains("not a regular file"), "{e}");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn compressed_error_bound_holds() {
    let d = 96;
    let mut data = rand_vec(64 * d, 21);
    data.iter_mut()
        .enumerate()
        .for_each(|(i, v)| *v *= 1.0 + (i % 7) as f32); // uneven scales
    let queries = rand_vec(5 * d, 22);
    // int8 also grown row by row (ranges with headroom) and with ranges far too wide: the
    // bound holds for any scales
    let builds = [
        (Dtype::F16, 0),
        (Dtype::BF16, 0),
        (Dtype::I8, 0),
        (Dtype::I8, 1),
        (Dtype::I8, 2),
    ];
    for level in kernels::available_levels() {
        for (dtype, build) in builds {
            let mut idx = DescriptorIndex::from_rows(&data[..d], d, dtype, None, None)
                .unwrap()
                .with_level(level)
                .unwrap();
            if build == 0 {
                idx = DescriptorIndex::from_rows(&data, d, dtype, None, None)
                    .unwrap()
                    .with_level(level)
                    .unwrap();
            } else {
                for row in data[d..].chunks_exact(d) {
                    idx.add(row, None, None).unwrap();
                }
            }
            if build == 2 {
                idx.ranges.iter_mut().for_each(|r| *r *= 100.0);
                idx.scales = idx.ranges.iter().map(|&r| r / 127.0).collect();
                idx.repack();
            }
            for q in queries.chunks_exact(d) {
                let qn = kernels::norm_sq(level, q);
                let eps = idx.error_bound(q);
                let (pq, eps2) = idx.packed_query(q);
                assert_eq!(eps, eps2);
                let (mut approx, mut exact): (Vec<Hit>, Vec<Hit>) = (Vec::new(), Vec::new());
                let mut a = BelowSink::new(f32::INFINITY, 1, idx.excluder(1, None).unwrap());
                idx.scan_packed(&pq, 0, qn, 0, idx.nblocks(), &mut a);
                let mut e = BelowSink::new(f32::INFINITY, 1, idx.excluder(1, None).unwrap());
                idx.scan_f32(q, &[qn], 0, idx.nblocks(), &mut e);
                approx.extend(&a.hits[0]);
                exact.extend(&e.hits[0]);
                assert_eq!(approx.len(), 64);
                let worst = approx
                    .iter()
                    .zip(&exact)
                    .map(|(x, y)| (x.sq - y.sq).abs())
                    .fold(0f32, f32::max);
                assert!(worst <= eps, "{level:?} {dtype:?} {build}: {worst} > {eps}");
                assert!(
                    worst > 0.0 && eps < 1e3 * worst.max(1e-6),
                    "bound far too loose: {eps} vs {worst}"
                );
            }
        }
    }
}

#[test]
fn int8_is_exact_on_clustered_data_with_ties_and_appends() {
    let (n, d, k) = (3000, 64, 20);
    let mut data = clustered(n, d, 31);
    // Exact duplicates (ties broken by the lower index) and a far outlier dimension.
    let dup = data[5 * d..6 * d].to_vec();
    for r in [700, 1500, 2999] {
        data[r * d..(r + 1) * d].copy_from_slice(&dup);
    }
    data[17 * d + 3] = 4.0;
    let queries = {
        let mut q = clustered(9, d, 32);
        q.extend(&dup);
        q
    };
    let exact = DescriptorIndex::from_rows(&data, d, Dtype::F32, None, None).unwrap();
    let want = exact.topk(&queries, k, None).unwrap();
    let want_r = exact.radius(&queries, 0.45, None).unwrap();
    assert_eq!(&want.indices[9 * k..9 * k + 4], &[5, 700, 1500, 2999]);
    for level in kernels::available_levels() {
        let idx = DescriptorIndex::from_rows(&data, d, Dtype::I8, None, None)
            .unwrap()
            .with_level(level)
            .unwrap();
        // Built in three appends (the ranges grow with the outlier, with headroom): another
        // copy than one shot's, the same results.
        let mut inc = DescriptorIndex::new(d, Dtype::I8)
            .unwrap()
            .with_level(level)
            .unwrap();
        for (a, b) in [(0, 10), (10, 1000), (1000, n)] {
            inc.add(&data[a * d..b * d], None, None).unwrap();
        }
        assert_ne!(inc.packed8, idx.packed8);
        for index in [&idx, &inc] {
            for qi in 0..10 {
                let q = &queries[qi * d..(qi + 1) * d];
                let got = index.topk(q, k, None).unwrap();
                assert_eq!(got.indices, want.indices[qi * k..(qi + 1) * k], "{level:?}");
                assert_eq!(got.distances, want.distances[qi * k..(qi + 1) * k]);
                let r = index.radius(q, 0.45, None).unwrap();
                let (a, b) = (want_r.offsets[qi] as usize, want_r.offsets[qi + 1] as usize);
                assert_eq!(r.indices, want_r.indices[a..b]);
                assert_eq!(r.distances, want_r.distances[a..b]);
            }
        }
    }
}

#[test]
fn int8_adds_requantise_logarithmically_often() {
    // Rows one at a time in order of rising |x_0| (from 1e-3 to 1): every add outgrew the
    // range and re-quantised the whole copy (quadratic); with headroom the ranges widen
    // geometrically. Results stay those of the float32 index.
    let (n, d) = (2000, 8);
    let mut data = rand_vec(n * d, 51);
    for i in 0..n {
        data[i * d] = 1e-3 * 1000f32.powf(i as f32 / (n - 1) as f32);
    }
    let mut inc = DescriptorIndex::new(d, Dtype::I8).unwrap();
    let mut requantised = 0;
    for i in 0..n {
        let before = inc.scales.clone();
        inc.add(&data[i * d..(i + 1) * d], None, None).unwrap();
        requantised += usize::from(i > 0 && inc.scales != before);
    }
    // each re-quantisation follows a growth of some |x_j| by 1.25x at least: at most
    // sum_j log_1.25(largest |x_j| / the first row's) of them (1 999 without headroom)
    let bound: f64 = (0..d)
        .map(|j| {
            let first = data[j].abs() as f64;
            let last = (0..n).map(|i| data[i * d + j].abs()).fold(0f32, f32::max) as f64;
            (last / first).ln() / 1.25f64.ln() + 1.0
        })
        .sum();
    assert!((requantised as f64) <= bound, "{requantised} > {bound}");
    assert!(requantised < 100, "{requantised}");
    assert!(
        inc.ranges[0] >= 1.0 && inc.ranges[0] <= 1.25,
        "{}",
        inc.ranges[0]
    );
    // a one-shot build (as a saved index loads) takes the exact maxima
    let one = DescriptorIndex::from_rows(&data, d, Dtype::I8, None, None).unwrap();
    assert_eq!(one.ranges[0], 1.0);
    let exact = DescriptorIndex::from_rows(&data, d, Dtype::F32, None, None).unwrap();
    let q = rand_vec(5 * d, 52);
    let want = exact.topk(&q, 10, None).unwrap();
    for index in [&inc, &one] {
        let got = index.topk(&q, 10, None).unwrap();
        assert_eq!(got.indices, want.indices);
        assert_eq!(got.distances, want.distances);
    }
}

#[test]
fn int8_scan_is_identical_on_every_level() {
    let d = 45; // not a multiple of 4: padded dimensions
    let data = rand_vec(40 * d, 41);
    let q = rand_vec(d, 42);
    let outs: Vec<Vec<f32>> = kernels::available_levels()
        .into_iter()
        .map(|level| {
            let idx = DescriptorIndex::from_rows(&data, d, Dtype::I8, None, None)
                .unwrap()
                .with_level(level)
                .unwrap();
            let (pq, _) = idx.query_i8(&q);
            let mut out = vec![0f32; 3 * BLOCK];
            for b in 0..3 {
                let blocks = &idx.packed8[b * d.div_ceil(4) * BLOCK * 4..];
                kernels::scan_i8::<1>(level, &pq, d.div_ceil(4), blocks, &mut out[b * BLOCK..]);
            }
            out
        })
        .collect();
    assert!(outs.windows(2).all(|w| w[0] == w[1]));
}

#[test]
fn early_abandon_radius_and_topk_equal_full_scan() {
    // d >= 64 enables the early-abandoning single-query scan; compare against the batch
    // (tile) path, which never abandons, and against brute force.
    let (n, d) = (4000, 128);
    let data = clustered(n, d, 51);
    let idx = DescriptorIndex::from_rows(&data, d, Dtype::F32, None, None).unwrap();
    assert!(idx.head > 0);
    let mut queries = clustered(8, d, 52); // exactly one tile of 8: no abandoning
    queries[..d].copy_from_slice(&data[77 * d..78 * d]); // distance 0 to row 77
    let all = idx.radius(&queries, 0.6, None).unwrap();
    let top = idx.topk(&queries, 20, None).unwrap();
    for qi in 0..8 {
        let q = &queries[qi * d..(qi + 1) * d];
        for r in [0.3f32, 0.6] {
            let one = idx.radius(q, r, None).unwrap();
            // Same set as brute force (the order may differ from f64 at float32 near-ties).
            let mut want: Vec<i64> = brute(&data, d, q)
                .into_iter()
                .filter(|&(s, _)| s < r as f64)
                .map(|(_, i)| i as i64)
                .collect();
            let mut got = one.indices.clone();
            want.sort_unstable();
            got.sort_unstable();
            assert_eq!(got, want);
            if r == 0.6 {
                let (a, b) = (all.offsets[qi] as usize, all.offsets[qi + 1] as usize);
                assert_eq!(one.indices, all.indices[a..b]);
                assert_eq!(one.distances, all.distances[a..b]);
            }
        }
        let one = idx.topk(q, 20, None).unwrap();
        assert_eq!(one.indices, top.indices[qi * 20..(qi + 1) * 20]);
        assert_eq!(one.distances, top.distances[qi * 20..(qi + 1) * 20]);
    }
}

#[test]
fn int8_save_load_round_trip() {
    let d = 70;
    let data = clustered(300, d, 61);
    let idx = DescriptorIndex::from_rows(&data, d, Dtype::I8, None, None).unwrap();
    let back = format::from_bytes(&format::to_bytes(&idx).unwrap()).unwrap();
    assert_eq!(back.dtype(), Dtype::I8);
    assert_eq!(back.packed8, idx.packed8);
    assert_eq!(back.scales, idx.scales);
    let q = &data[..d];
    assert_eq!(
        back.topk(q, 5, None).unwrap(),
        idx.topk(q, 5, None).unwrap()
    );
    // an index grown by adds (ranges with headroom) loads with the one-shot ranges
    let mut grown = DescriptorIndex::new(d, Dtype::I8).unwrap();
    for row in data.chunks_exact(d) {
        grown.add(row, None, None).unwrap();
    }
    assert_ne!(grown.scales, idx.scales);
    let back = format::from_bytes(&format::to_bytes(&grown).unwrap()).unwrap();
    assert_eq!((&back.scales, &back.packed8), (&idx.scales, &idx.packed8));
    assert_eq!(
        back.topk(q, 5, None).unwrap(),
        grown.topk(q, 5, None).unwrap()
    );
}

#[test]
fn a_radius_whose_square_is_subnormal_keeps_the_rows_inside_it() {
    // r² underflows float32 (to 0 for r < 2.6e-23): the rows at distance 0 must stay.
    let d = 4;
    let mut data = vec![0f32; 4 * d];
    for i in 0..4 {
        data[i * d + i] = 1.0;
    }
    for dtype in [Dtype::F32, Dtype::F16] {
        let idx = DescriptorIndex::from_rows(&data, d, dtype, None, None).unwrap();
        for r in [1e-23f32, 1e-30, 1e-38, f32::from_bits(1)] {
            let res = idx.radius(&data[..d], r, None).unwrap();
            assert_eq!(res.indices, vec![0], "{dtype:?} r={r:e}");
        }
    }
}

#[test]
fn compressed_topk_stays_exact_when_many_rows_tie_near_the_kth() {
    // One place seen many times: thousands of rows within 2ε of the k-th, which used to
    // re-prune the shortlist at every row (quadratic); the amortised prune keeps it exact.
    let (n, d, k) = (6000, 64, 20);
    let noise = rand_vec(n * d, 9);
    let mut data = vec![0f32; n * d];
    for i in 0..n {
        let row = &mut data[i * d..(i + 1) * d];
        row[0] = 1.0;
        for j in 0..d {
            row[j] += 1e-3 * noise[i * d + j];
        }
        let norm = row.iter().map(|v| v * v).sum::<f32>().sqrt();
        row.iter_mut().for_each(|v| *v /= norm);
    }
    let mut q = vec![0f32; d];
    q[1] = 1.0;
    let base = DescriptorIndex::from_rows(&data, d, Dtype::F32, None, None).unwrap();
    let want = base.topk(&q, k, None).unwrap();
    for dtype in [Dtype::F16, Dtype::BF16, Dtype::I8] {
        let idx = DescriptorIndex::from_rows(&data, d, dtype, None, None).unwrap();
        let got = idx.topk(&q, k, None).unwrap();
        assert_eq!(got.indices, want.indices, "{dtype:?}");
        assert_eq!(got.distances, want.distances, "{dtype:?}");
    }
}

#[test]
fn an_add_that_cannot_be_allocated_is_an_error_and_changes_nothing() {
    let mut idx =
        DescriptorIndex::from_rows(&[1.0, 2.0, 3.0, 4.0], 4, Dtype::BF16, None, None).unwrap();
    for len in [1usize << 60, usize::MAX] {
        assert!(matches!(
            idx.reserve_for(len),
            Err(Error::Memory {
                arg: "descriptors",
                ..
            })
        ));
    }
    assert_eq!(idx.len(), 1);
    assert_eq!(idx.row(0), vec![1.0, 2.0, 3.0, 4.0]);
    idx.add(&[0.0, 0.0, 0.0, 1.0], None, None).unwrap();
    assert_eq!(
        idx.topk(&[0.0, 0.0, 0.0, 1.0], 1, None).unwrap().indices,
        vec![1]
    );
}

#[test]
fn a_header_with_d_zero_says_so() {
    let mut bytes = format::to_bytes(&DescriptorIndex::new(4, Dtype::F32).unwrap()).unwrap();
    bytes[24..32].copy_from_slice(&0u64.to_le_bytes());
    let sum = format::checksum(&[&bytes[8..32], &bytes[40..]]);
    bytes[32..40].copy_from_slice(&sum.to_le_bytes());
    let e = format::from_bytes(&bytes).unwrap_err();
    assert!(e.to_string().contains("header says d=0"), "{e}");
}

#[test]
fn kernel_length_checks_do_not_wrap() {
    // d * 16 * 8 wraps to 0 in usize: the check must refuse it, not pass it on to the vector
    // loads (which read past the empty slices)
    let d = 1usize << 61;
    for level in kernels::available_levels() {
        let wrapped = std::panic::catch_unwind(|| {
            let mut out = [0f32; 8 * BLOCK];
            kernels::tile_f32::<8, 1>(level, &[], d, &[], &mut out);
        });
        assert!(
            wrapped.is_err(),
            "{level:?}: a wrapped length passed the check"
        );
        let fused = std::panic::catch_unwind(|| {
            let (mut sq, mut masks) = ([0f32; 8 * 2 * BLOCK], [0u16; 16]);
            let (qn, thr, xn) = ([0f32; 8], [0f32; 8], [0f32; 2 * BLOCK]);
            kernels::tile_sq_f32::<8, 2>(level, &[], d, &[], &qn, &xn, &thr, &mut sq, &mut masks);
        });
        assert!(
            fused.is_err(),
            "{level:?}: a wrapped length passed the fused check"
        );
        let norms = std::panic::catch_unwind(|| kernels::block_norms(level, &[], d));
        assert!(norms.is_err(), "{level:?}");
    }
}

#[test]
fn block_distances_are_the_same_bits_on_every_level() {
    let xn = rand_vec(BLOCK * 64, 7);
    let dots = rand_vec(BLOCK * 64, 8);
    for (b, (x, g)) in xn
        .chunks_exact(BLOCK)
        .zip(dots.chunks_exact(BLOCK))
        .enumerate()
    {
        let x: Vec<f32> = x.iter().map(|v| v.abs()).collect(); // squared norms are >= 0
        let mut g = g.to_vec();
        g[0] = 0.5 * (0.25 + x[0]); // a distance of exactly 0
        g[1] = f32::NAN; // none occurs in an index; 0 on every level all the same
        let (qn, thr) = (0.25, 0.1 * (b % 8) as f32);
        let want = kernels::block_sq(kernels::Level::Portable, qn, &x, &g, thr);
        assert_eq!(want.0[0].to_bits(), 0.0f32.to_bits());
        assert_eq!(want.0[1].to_bits(), 0.0f32.to_bits());
        let lanes = (0..BLOCK)
            .filter(|&l| want.0[l] < thr)
            .fold(0u16, |m, l| m | 1 << l);
        assert_eq!(want.1, lanes);
        for level in kernels::available_levels() {
            let got = kernels::block_sq(level, qn, &x, &g, thr);
            let bits = |v: &[f32; BLOCK]| v.map(f32::to_bits);
            assert_eq!(
                (bits(&got.0), got.1),
                (bits(&want.0), want.1),
                "{level:?}, block {b}"
            );
        }
    }
}

#[test]
fn fused_tile_distances_are_those_of_the_tile_and_block_kernels() {
    // tile_sq_f32 = tile_f32 then block_sq per (query, block), bit for bit, on every level, for
    // both tile widths the scans use
    fn check<const G: usize>(level: kernels::Level) {
        let d = 37;
        let q = rand_vec(8 * d, 11);
        let blocks = rand_vec(G * d * BLOCK, 12);
        let xn: Vec<f32> = rand_vec(G * BLOCK, 13)
            .iter()
            .map(|v| v.abs() * 9.0)
            .collect();
        let qn: Vec<f32> = rand_vec(8, 14).iter().map(|v| v.abs() * 9.0).collect();
        // thresholds from none below to all below
        let thr = [0.0, 1.0, 4.0, 9.0, 16.0, 25.0, 100.0, f32::INFINITY];
        let mut dots = vec![0f32; 8 * G * BLOCK];
        kernels::tile_f32::<8, G>(level, &q, d, &blocks, &mut dots);
        let (mut want_sq, mut want_masks) = (Vec::new(), Vec::new());
        for t in 0..8 {
            for g in 0..G {
                let i = t * G + g;
                let dg = &dots[i * BLOCK..(i + 1) * BLOCK];
                let xg = &xn[g * BLOCK..(g + 1) * BLOCK];
                let (s, m) = kernels::block_sq(level, qn[t], xg, dg, thr[t]);
                want_sq.extend(s.map(f32::to_bits));
                want_masks.push(m);
            }
        }
        // masks with no row, every row and some rows below their threshold
        assert!(want_masks.contains(&0) && want_masks.contains(&u16::MAX));
        assert!(want_masks.iter().any(|&m| m != 0 && m != u16::MAX));
        let (mut sq, mut masks) = (vec![0f32; 8 * G * BLOCK], vec![0u16; 8 * G]);
        kernels::tile_sq_f32::<8, G>(level, &q, d, &blocks, &qn, &xn, &thr, &mut sq, &mut masks);
        let got_sq: Vec<u32> = sq.iter().map(|v| v.to_bits()).collect();
        assert_eq!(got_sq, want_sq, "{level:?}, G = {G}");
        assert_eq!(masks, want_masks, "{level:?}, G = {G}");
        // and the same bits as the portable code (block_sq's AVX-512 arithmetic is shared)
        if level != kernels::Level::Portable {
            let mut portable = (vec![0f32; 8 * G * BLOCK], vec![0u16; 8 * G]);
            kernels::tile_sq_f32::<8, G>(
                kernels::Level::Portable,
                &q,
                d,
                &blocks,
                &qn,
                &xn,
                &thr,
                &mut portable.0,
                &mut portable.1,
            );
            assert_eq!(portable.0, sq, "{level:?}, G = {G}");
            assert_eq!(portable.1, masks, "{level:?}, G = {G}");
        }
    }
    for level in kernels::available_levels() {
        check::<1>(level);
        check::<2>(level);
    }
}

#[test]
fn batched_radius_is_the_same_on_every_level_and_thread_count() {
    // the batch scan's fused tiles (AVX-512) and tile + block kernels (other levels) give the
    // same hits: 19 queries (two tiles of 8 and three alone) against 2200 rows (two chunks
    // with several threads; a last block with padding rows)
    let (n, d, r) = (2200, 37, 0.6f32);
    let data = clustered(n, d, 21);
    let queries = &data[..19 * d]; // rows of the map: hits in their clusters
    let base = DescriptorIndex::from_rows(&data, d, Dtype::F32, None, None).unwrap();
    let want = base.radius(queries, r, None).unwrap();
    assert!(
        want.indices.len() > 19,
        "too few hits to compare: {}",
        want.indices.len()
    );
    for level in kernels::available_levels() {
        let mut idx = DescriptorIndex::from_rows(&data, d, Dtype::F32, None, None)
            .unwrap()
            .with_level(level)
            .unwrap();
        idx.min_parallel_work = 0; // chunks for this small map
        for threads in [1, 3] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            let got = pool.install(|| idx.radius(queries, r, None).unwrap());
            assert_eq!(got.offsets, want.offsets, "{level:?}, {threads} threads");
            assert_eq!(got.indices, want.indices, "{level:?}, {threads} threads");
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&got.distances), bits(&want.distances), "{level:?}");
        }
    }
}
