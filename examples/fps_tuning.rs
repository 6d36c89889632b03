//! Times the flat loop and the sampling tree at several leaf sizes (for tuning `fps.rs`).
//! `cargo run --release --example fps_tuning`
use std::time::Instant;

fn main() {
    let mut state = 12345u64;
    let mut next = || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (state >> 40) as f32 / (1u64 << 24) as f32
    };
    for (n, k) in [(2048usize, 512usize), (16384, 1024), (100_000, 4096)] {
        let points: Vec<[f32; 3]> = (0..n).map(|_| [next(), next(), next()]).collect();
        for leaf in [Some(128), Some(192), Some(256), Some(512)] {
            if leaf.is_none() && n > 20000 {
                continue;
            }
            let reps = if n > 20000 { 5 } else { 30 };
            let mut best = f64::MAX;
            for _ in 0..reps {
                let t = Instant::now();
                std::hint::black_box(_core::fps::sample_with(&points, k, leaf));
                best = best.min(t.elapsed().as_secs_f64());
            }
            println!("n={n} k={k} leaf={leaf:?}: {:.3} ms", best * 1e3);
        }
    }
}
