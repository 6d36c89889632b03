//! Times the nearest-neighbour index on uniform clouds: build and query separately, at 100k and
//! 2048 points (for tuning `kdtree.rs`). `cargo run --release --example nn_timing [rounds]`;
//! `RAYON_NUM_THREADS=1` for one thread.
use _core::chamfer::chamfer;
use _core::nn::NearestNeighborIndex;

fn cloud(n: usize, seed: u64) -> Vec<[f32; 3]> {
    let mut state = seed;
    let mut next = || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (state >> 40) as f32 / (1u64 << 23) as f32 - 1.0
    };
    (0..n).map(|_| [next(), next(), next()]).collect()
}

#[repr(C)]
struct Timespec {
    sec: i64,
    nsec: i64,
}

extern "C" {
    fn clock_gettime(clock: i32, t: *mut Timespec) -> i32;
}

/// CPU time of this process in ms, all threads (wall time is useless on a shared machine).
fn cpu_ms() -> f64 {
    let mut t = Timespec { sec: 0, nsec: 0 };
    unsafe { clock_gettime(2, &mut t) }; // CLOCK_PROCESS_CPUTIME_ID
    t.sec as f64 * 1e3 + t.nsec as f64 * 1e-6
}

fn best_of(rounds: usize, mut f: impl FnMut()) -> f64 {
    (0..rounds)
        .map(|_| {
            let t = cpu_ms();
            f();
            cpu_ms() - t
        })
        .fold(f64::MAX, f64::min)
}

fn morton(p: &[f32; 3]) -> u64 {
    let mut key = 0u64;
    let c = p.map(|v| (((v + 1.0) * 1023.0) as u64).min(2047));
    for bit in (0..11).rev() {
        for v in &c {
            key = key << 1 | (v >> bit & 1);
        }
    }
    key
}

fn main() {
    let rounds = std::env::args()
        .nth(1)
        .and_then(|r| r.parse().ok())
        .unwrap_or(20);
    for n in [100_000, 2048] {
        let (a, b) = (cloud(n, 1), cloud(n, 2));
        let (mut d, mut i) = (vec![0.0; n], vec![0; n]);
        let build = best_of(rounds, || {
            std::hint::black_box(NearestNeighborIndex::new(&a));
        });
        let index = NearestNeighborIndex::new(&a);
        let query = best_of(rounds, || index.query_into(&b, &mut d, &mut i, false));
        let mut sorted = b.clone();
        sorted.sort_by_key(morton);
        let query_sorted = best_of(rounds, || index.query_into(&sorted, &mut d, &mut i, false));
        let both = best_of(rounds, || {
            std::hint::black_box(chamfer(&a, &b).unwrap());
        });
        println!(
            "n={n}: build {build:.3} ms, query {query:.3} ms, sorted {query_sorted:.3} ms, chamfer {both:.3} ms (CPU time)"
        );
    }
}
