//! Times the yaw kernels on one thread, without the Python gateway, for profiling:
//!
//! ```text
//! cargo run --release -p vvloc-core --example profile_yaw [T C ROUNDS]
//! perf record target/release/examples/profile_yaw && perf report
//! ```
//!
//! One pair of random (T, C) descriptors (default 120 × 256, the paper's size); prints the mean
//! time per call of `yaw_costs` and `estimate_yaw`, twice. The benchmarks with ratios against
//! torch and the reference are `benches/bench_matching.py`.

use ndarray::Array3;
use std::time::Instant;

fn main() {
    let arg = |n: usize, default: usize| {
        std::env::args()
            .nth(n)
            .and_then(|v| v.parse().ok())
            .unwrap_or(default)
    };
    let (t, c, rounds) = (arg(1, 120), arg(2, 256), arg(3, 3000) as u32);
    let mut state: u64 = 0x9E37_79B9_7F4A_7C15;
    let mut uniform = || {
        // xorshift64: reproducible values in [-1, 1)
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state % 20_000) as f32 / 10_000.0 - 1.0
    };
    let a = Array3::from_shape_fn((1, t, c), |_| uniform());
    let b = Array3::from_shape_fn((1, t, c), |_| uniform());
    for _ in 0..2 {
        let t0 = Instant::now();
        for _ in 0..rounds {
            std::hint::black_box(vvloc_core::cost::yaw_costs(a.view(), b.view()).ok());
        }
        println!("yaw_costs    {:?} per call", t0.elapsed() / rounds.max(1));
        let t0 = Instant::now();
        for _ in 0..rounds {
            std::hint::black_box(vvloc_core::cost::estimate_yaw(a.view(), b.view()).ok());
        }
        println!("estimate_yaw {:?} per call", t0.elapsed() / rounds.max(1));
    }
}
