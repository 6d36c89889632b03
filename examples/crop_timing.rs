//! Times one viewpoint crop of a 16k cloud, phase by phase (for tuning `crop.rs`).
//! `cargo run --release --example crop_timing`
use std::time::Instant;

use _core::crop::{crop_count_into, crop_mask, write_split, CropSize};

fn main() {
    let mut state = 7u64;
    let mut next = || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (state >> 40) as f32 / (1u64 << 24) as f32
    };
    let points: Vec<[f32; 3]> = (0..16384).map(|_| [next(), next(), next()]).collect();
    let (mut t_mask, mut t_split) = (f64::MAX, f64::MAX);
    for _ in 0..200 {
        let t = Instant::now();
        let mask = crop_mask(&points, [1.0, 0.0, 0.0], CropSize::Count(4096)).unwrap();
        t_mask = t_mask.min(t.elapsed().as_secs_f64());
        let t = Instant::now();
        let mut kept = vec![0.0f32; 12288 * 3 + 3];
        let mut removed = vec![0.0f32; 4096 * 3 + 3];
        write_split(&points, &mask, &mut kept, &mut removed);
        std::hint::black_box((&kept, &removed));
        t_split = t_split.min(t.elapsed().as_secs_f64());
    }
    let mut t_fused = f64::MAX;
    for _ in 0..200 {
        let t = Instant::now();
        let mut kept = vec![0.0f32; 12288 * 3 + 3];
        let mut removed = vec![0.0f32; 4096 * 3 + 3];
        crop_count_into(&points, [1.0, 0.0, 0.0], 4096, &mut kept, &mut removed).unwrap();
        std::hint::black_box((&kept, &removed));
        t_fused = t_fused.min(t.elapsed().as_secs_f64());
    }
    println!("fused crop {:.1} us", t_fused * 1e6);
    println!("mask {:.1} us, split {:.1} us", t_mask * 1e6, t_split * 1e6);
}
