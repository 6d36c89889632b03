//! Iterative farthest point sampling (IFPS), exact.
//!
//! The result equals the naive O(N·K) float32 algorithm from the same start: every point keeps
//! its squared distance to the chosen set, computed as `dx*dx + dy*dy + dz*dz` in float32 (no
//! fused multiply-add), and the next sample is the point with the largest such distance, ties
//! going to the lowest index.
//!
//! For speed, points live in the leaves of a KD-tree whose nodes cache the largest distance below
//! them (the idea of QuickFPS, Han et al. 2023). After a new sample `s` is chosen, a node is
//! skipped when the squared distance from `s` to its bounding box is at least the node's cached
//! maximum: then no point below it can move closer. The box distance is computed with the same
//! float32 operations in the same order as the point distances, and rounding is monotone, so the
//! bound never exceeds any point's computed distance and the pruning is exact, not approximate.

use crate::error::{check_finite, check_point_count, GeometryError, Result};

/// Leaf size of the sampling tree: large leaves vectorise well and keep the traversal short;
/// measured with `examples/fps_tuning.rs` (256 is within a few % of the best at 2k–100k points).
const LEAF_SIZE: usize = 256;

/// Below this many points the tree would be a single leaf: use the plain loop.
const TREE_MIN_POINTS: usize = 2 * LEAF_SIZE;

/// Exact IFPS of one cloud; returns `n_samples` indices into `points`, the first `start_index`.
///
/// `points` may hold at most [`crate::error::MAX_POINTS`] points (the tree stores `u32` indices).
pub fn farthest_point_sample(
    points: &[[f32; 3]],
    n_samples: usize,
    start_index: usize,
) -> Result<Vec<usize>> {
    check_sizes(points.len(), n_samples, start_index)?;
    check_finite("points", 0, points)?;
    Ok(sample_unchecked(points, n_samples, start_index))
}

/// The size checks of IFPS on a cloud of `n` points. They need only `n`, so the bindings check a
/// batch once and a test can pass a number no cloud in memory has.
pub(crate) fn check_sizes(n: usize, n_samples: usize, start_index: usize) -> Result<()> {
    check_point_count("points", n)?;
    if n_samples == 0 || n_samples > n {
        return Err(GeometryError::out_of_range(
            "n_samples",
            format!("must be in 1..={n} (the number of points), got {n_samples}"),
        ));
    }
    if start_index >= n {
        return Err(GeometryError::out_of_range(
            "start_index",
            format!("must be in 0..{n} (the number of points), got {start_index}"),
        ));
    }
    Ok(())
}

/// IFPS without input checks (the caller has validated sizes and finiteness).
pub(crate) fn sample_unchecked(
    points: &[[f32; 3]],
    n_samples: usize,
    start_index: usize,
) -> Vec<usize> {
    if points.len() < TREE_MIN_POINTS {
        sample_flat(points, n_samples, start_index)
    } else {
        SamplingTree::new(points, LEAF_SIZE).sample(n_samples, start_index)
    }
}

/// Squared distance exactly as the reference computes it (no FMA, this order).
#[inline(always)]
fn sq_dist(x: f32, y: f32, z: f32, s: [f32; 3]) -> f32 {
    let dx = x - s[0];
    let dy = y - s[1];
    let dz = z - s[2];
    dx * dx + dy * dy + dz * dz
}

/// Lower `min_dist` with the distances to `s`; return (largest value, first index holding it).
#[inline(always)]
fn relax(xs: &[f32], ys: &[f32], zs: &[f32], min_dist: &mut [f32], s: [f32; 3]) -> (f32, usize) {
    let n = min_dist.len();
    let (xs, ys, zs) = (&xs[..n], &ys[..n], &zs[..n]);
    #[cfg(target_arch = "x86_64")]
    let (best, body) = if std::arch::is_x86_feature_detected!("avx") {
        // SAFETY: AVX is available (checked) and all slices hold at least n values.
        unsafe { relax_avx(xs, ys, zs, min_dist, s) }
    } else {
        (f32::NEG_INFINITY, 0)
    };
    #[cfg(not(target_arch = "x86_64"))]
    let (best, body) = (f32::NEG_INFINITY, 0);
    let best = relax_scalar(xs, ys, zs, min_dist, s, body, best);
    let first = min_dist.iter().position(|&v| v == best).unwrap_or(0);
    (best, first)
}

/// The scalar update of `min_dist[from..]`; returns the maximum of it and `best`.
#[inline(always)]
fn relax_scalar(
    xs: &[f32],
    ys: &[f32],
    zs: &[f32],
    min_dist: &mut [f32],
    s: [f32; 3],
    from: usize,
    mut best: f32,
) -> f32 {
    for i in from..min_dist.len() {
        let d = sq_dist(xs[i], ys[i], zs[i], s);
        let v = if d < min_dist[i] { d } else { min_dist[i] };
        min_dist[i] = v;
        best = if v > best { v } else { best };
    }
    best
}

/// 8 points at a time with AVX: the same float32 operations as [`sq_dist`] (sub, mul, add in
/// the same order; no FMA), so the values are bit-identical. Returns the maximum of the
/// processed prefix and its length (a multiple of 8).
///
/// # Safety
///
/// The CPU must support AVX (callers check `is_x86_feature_detected!("avx")`), and `xs`,
/// `ys`, `zs` must each hold at least `min_dist.len()` values: the loads read
/// `[i, i + 8)` for every `i + 8 <= min_dist.len()`. The test
/// `avx_and_scalar_updates_are_bit_identical` runs both paths on the same data.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
unsafe fn relax_avx(
    xs: &[f32],
    ys: &[f32],
    zs: &[f32],
    min_dist: &mut [f32],
    s: [f32; 3],
) -> (f32, usize) {
    use std::arch::x86_64::*;
    let n = min_dist.len();
    let body = n - n % 8;
    let (sx, sy, sz) = (
        _mm256_set1_ps(s[0]),
        _mm256_set1_ps(s[1]),
        _mm256_set1_ps(s[2]),
    );
    let mut best = _mm256_set1_ps(f32::NEG_INFINITY);
    let mut i = 0;
    while i < body {
        let dx = _mm256_sub_ps(_mm256_loadu_ps(xs.as_ptr().add(i)), sx);
        let dy = _mm256_sub_ps(_mm256_loadu_ps(ys.as_ptr().add(i)), sy);
        let dz = _mm256_sub_ps(_mm256_loadu_ps(zs.as_ptr().add(i)), sz);
        let d = _mm256_add_ps(
            _mm256_add_ps(_mm256_mul_ps(dx, dx), _mm256_mul_ps(dy, dy)),
            _mm256_mul_ps(dz, dz),
        );
        let m = _mm256_loadu_ps(min_dist.as_ptr().add(i));
        // minps(d, m) is `d < m ? d : m`, maxps(v, b) is `v > b ? v : b`: exact on finite values.
        let v = _mm256_min_ps(d, m);
        _mm256_storeu_ps(min_dist.as_mut_ptr().add(i), v);
        best = _mm256_max_ps(v, best);
        i += 8;
    }
    let mut lanes = [0.0f32; 8];
    _mm256_storeu_ps(lanes.as_mut_ptr(), best);
    let best = lanes
        .iter()
        .fold(f32::NEG_INFINITY, |a, &b| if b > a { b } else { a });
    (best, body)
}

/// The plain O(N·K) loop over structure-of-arrays coordinates; fastest for small clouds.
pub(crate) fn sample_flat(points: &[[f32; 3]], n_samples: usize, start_index: usize) -> Vec<usize> {
    let xs: Vec<f32> = points.iter().map(|p| p[0]).collect();
    let ys: Vec<f32> = points.iter().map(|p| p[1]).collect();
    let zs: Vec<f32> = points.iter().map(|p| p[2]).collect();
    let mut min_dist = vec![f32::INFINITY; points.len()];
    let mut selected = Vec::with_capacity(n_samples);
    let mut current = start_index;
    selected.push(current);
    for _ in 1..n_samples {
        let (_, next) = relax(&xs, &ys, &zs, &mut min_dist, points[current]);
        current = next;
        selected.push(current);
    }
    selected
}

/// A KD-tree over the cloud whose nodes cache the largest min-distance below them. Indices and
/// node ranges are `u32`: the cloud holds at most [`crate::error::MAX_POINTS`] points (checked by
/// [`check_sizes`]).
pub(crate) struct SamplingTree {
    // Coordinates in tree order (each leaf a contiguous run, sorted by original index).
    xs: Vec<f32>,
    ys: Vec<f32>,
    zs: Vec<f32>,
    original: Vec<u32>,
    min_dist: Vec<f32>,
    nodes: Vec<Node>,
    // Per node: the largest min-distance below it and the lowest original index holding it.
    best: Vec<f32>,
    best_index: Vec<u32>,
}

#[derive(Clone, Copy)]
struct Node {
    lo: [f32; 3],
    hi: [f32; 3],
    start: u32,
    end: u32,
    /// Index of the left child (the right one is `left + 1`); 0 for a leaf.
    left: u32,
}

impl SamplingTree {
    pub(crate) fn new(points: &[[f32; 3]], leaf_size: usize) -> Self {
        let n = points.len();
        let mut order: Vec<u32> = (0..n as u32).collect();
        let mut nodes = Vec::with_capacity(2 * n / leaf_size + 2);
        nodes.push(bounding_node(points, &order, 0, n));
        // Breadth-first splitting keeps both children of a node next to each other.
        let mut next = 0;
        while next < nodes.len() {
            let node = nodes[next];
            let (start, end) = (node.start as usize, node.end as usize);
            if end - start <= leaf_size {
                order[start..end].sort_unstable();
            } else {
                let axis = widest_axis(&node);
                let mid = start + (end - start) / 2;
                order[start..end].select_nth_unstable_by(mid - start, |&a, &b| {
                    let (pa, pb) = (points[a as usize][axis], points[b as usize][axis]);
                    pa.total_cmp(&pb).then(a.cmp(&b))
                });
                nodes[next].left = nodes.len() as u32;
                nodes.push(bounding_node(points, &order, start, mid));
                nodes.push(bounding_node(points, &order, mid, end));
            }
            next += 1;
        }
        let n_nodes = nodes.len();
        SamplingTree {
            xs: order.iter().map(|&i| points[i as usize][0]).collect(),
            ys: order.iter().map(|&i| points[i as usize][1]).collect(),
            zs: order.iter().map(|&i| points[i as usize][2]).collect(),
            original: order,
            min_dist: vec![f32::INFINITY; n],
            nodes,
            best: vec![f32::INFINITY; n_nodes],
            best_index: vec![0; n_nodes],
        }
    }

    pub(crate) fn sample(mut self, n_samples: usize, start_index: usize) -> Vec<usize> {
        let mut selected = Vec::with_capacity(n_samples);
        let mut stack = Vec::with_capacity(64);
        let mut current = start_index;
        // Positions in tree order, to read the coordinates of an original index.
        let mut position = vec![0u32; self.original.len()];
        for (pos, &orig) in self.original.iter().enumerate() {
            position[orig as usize] = pos as u32;
        }
        selected.push(current);
        for _ in 1..n_samples {
            let p = position[current] as usize;
            self.relax_from([self.xs[p], self.ys[p], self.zs[p]], &mut stack);
            current = self.best_index[0] as usize;
            selected.push(current);
        }
        selected
    }

    /// Update every min-distance that the new sample `s` lowers, and the cached maxima above it.
    fn relax_from(&mut self, s: [f32; 3], stack: &mut Vec<(u32, bool)>) {
        // Depth-first with an explicit stack: (node, children done?).
        stack.clear();
        stack.push((0, false));
        while let Some((id, children_done)) = stack.pop() {
            let id = id as usize;
            let node = self.nodes[id];
            if children_done {
                let (l, r) = (node.left as usize, node.left as usize + 1);
                let take_left = self.best[l] > self.best[r]
                    || (self.best[l] == self.best[r] && self.best_index[l] < self.best_index[r]);
                let winner = if take_left { l } else { r };
                self.best[id] = self.best[winner];
                self.best_index[id] = self.best_index[winner];
                continue;
            }
            if box_sq_dist(&node, s) >= self.best[id] {
                continue; // no point below can get closer to s than it already is
            }
            if node.left == 0 {
                let range = node.start as usize..node.end as usize;
                let (value, first) = relax(
                    &self.xs[range.clone()],
                    &self.ys[range.clone()],
                    &self.zs[range.clone()],
                    &mut self.min_dist[range.clone()],
                    s,
                );
                self.best[id] = value;
                self.best_index[id] = self.original[range.start + first];
            } else {
                stack.push((id as u32, true));
                stack.push((node.left + 1, false));
                stack.push((node.left, false));
            }
        }
    }
}

fn bounding_node(points: &[[f32; 3]], order: &[u32], start: usize, end: usize) -> Node {
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    for &i in &order[start..end] {
        let p = points[i as usize];
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    Node {
        lo,
        hi,
        start: start as u32,
        end: end as u32,
        left: 0,
    }
}

fn widest_axis(node: &Node) -> usize {
    let extent = [0, 1, 2].map(|a| node.hi[a] - node.lo[a]);
    if extent[0] >= extent[1] && extent[0] >= extent[2] {
        0
    } else if extent[1] >= extent[2] {
        1
    } else {
        2
    }
}

/// Squared distance from `s` to the node's box, with the float32 operations of [`sq_dist`] in the
/// same order, so it is never larger than the computed distance of any point in the box.
#[inline(always)]
fn box_sq_dist(node: &Node, s: [f32; 3]) -> f32 {
    let gap = |a: usize| {
        if s[a] < node.lo[a] {
            node.lo[a] - s[a]
        } else if s[a] > node.hi[a] {
            s[a] - node.hi[a]
        } else {
            0.0
        }
    };
    let (gx, gy, gz) = (gap(0), gap(1), gap(2));
    gx * gx + gy * gy + gz * gz
}

/// The naive reference: O(N·K), array-of-structs, written for clarity. Used by tests.
pub fn farthest_point_sample_naive(
    points: &[[f32; 3]],
    n_samples: usize,
    start_index: usize,
) -> Vec<usize> {
    let mut min_dist = vec![f32::INFINITY; points.len()];
    let mut selected = vec![start_index];
    while selected.len() < n_samples {
        let s = points[*selected.last().unwrap_or(&start_index)];
        let mut best = (f32::NEG_INFINITY, 0);
        for (i, p) in points.iter().enumerate() {
            min_dist[i] = min_dist[i].min(sq_dist(p[0], p[1], p[2], s));
            if min_dist[i] > best.0 {
                best = (min_dist[i], i);
            }
        }
        selected.push(best.1);
    }
    selected
}

/// Timing hooks for tuning the leaf size and the flat/tree switch (`examples/fps_tuning.rs`).
#[doc(hidden)]
pub fn sample_with(points: &[[f32; 3]], n_samples: usize, leaf_size: Option<usize>) -> Vec<usize> {
    match leaf_size {
        None => sample_flat(points, n_samples, 0),
        Some(leaf) => SamplingTree::new(points, leaf).sample(n_samples, 0),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{rngs::StdRng, Rng, SeedableRng};

    #[test]
    #[cfg(target_arch = "x86_64")]
    fn avx_and_scalar_updates_are_bit_identical() {
        if !std::arch::is_x86_feature_detected!("avx") {
            return; // nothing to compare on this CPU; the scalar path is the reference
        }
        let mut rng = StdRng::seed_from_u64(11);
        for n in [0usize, 1, 7, 8, 9, 16, 61, 1000] {
            let coords = |rng: &mut StdRng| -> Vec<f32> {
                // a coarse grid makes equal distances (ties) common
                (0..n)
                    .map(|_| rng.gen_range(-4i32..4) as f32 * 0.25)
                    .collect()
            };
            let (xs, ys, zs) = (coords(&mut rng), coords(&mut rng), coords(&mut rng));
            let start: Vec<f32> = (0..n).map(|_| rng.gen_range(0.0f32..9.0)).collect();
            let s = [0.25f32, -0.5, 0.75];
            let mut scalar = start.clone();
            let best_scalar = relax_scalar(&xs, &ys, &zs, &mut scalar, s, 0, f32::NEG_INFINITY);
            let mut vector = start.clone();
            // SAFETY: AVX was detected above; all slices hold n values.
            let (best_head, body) = unsafe { relax_avx(&xs, &ys, &zs, &mut vector, s) };
            let best_vector = relax_scalar(&xs, &ys, &zs, &mut vector, s, body, best_head);
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&scalar), bits(&vector), "n={n}");
            assert_eq!(best_scalar.to_bits(), best_vector.to_bits(), "n={n}");
        }
    }

    fn random_cloud(n: usize, seed: u64) -> Vec<[f32; 3]> {
        let mut rng = StdRng::seed_from_u64(seed);
        (0..n)
            .map(|_| {
                [
                    rng.gen_range(-1.0..1.0),
                    rng.gen_range(-1.0..1.0),
                    rng.gen_range(-1.0..1.0),
                ]
            })
            .collect()
    }

    #[test]
    fn tiny_hand_computed_case() {
        let points = [
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [5.0, 0.0, 0.0],
            [2.0, 0.0, 0.0],
        ];
        assert_eq!(farthest_point_sample(&points, 3, 0).unwrap(), vec![0, 2, 3]);
        assert_eq!(farthest_point_sample(&points, 2, 2).unwrap(), vec![2, 0]);
    }

    #[test]
    fn matches_naive_on_random_clouds_flat_and_tree() {
        for (n, k, seed) in [(50, 20, 1), (700, 300, 2), (3000, 500, 3), (20000, 700, 4)] {
            let points = random_cloud(n, seed);
            for start in [0, n / 3, n - 1] {
                assert_eq!(
                    farthest_point_sample(&points, k, start).unwrap(),
                    farthest_point_sample_naive(&points, k, start),
                    "n={n} k={k} start={start}"
                );
            }
        }
    }

    #[test]
    fn small_leaves_prune_exactly() {
        // Many levels of boxes exercise the pruning bound, not just the leaf loop.
        for (n, k, leaf) in [(3000, 900, 4), (5000, 400, 9), (1000, 1000, 1)] {
            let points = random_cloud(n, n as u64);
            let got = SamplingTree::new(&points, leaf).sample(k, 17);
            assert_eq!(
                got,
                farthest_point_sample_naive(&points, k, 17),
                "n={n} leaf={leaf}"
            );
        }
    }

    #[test]
    fn ties_go_to_the_lowest_index_on_a_grid_with_duplicates() {
        let mut points = Vec::new();
        for x in 0..12 {
            for y in 0..12 {
                for z in 0..12 {
                    points.push([x as f32, y as f32, z as f32]);
                }
            }
        }
        points.extend(points.clone());
        assert_eq!(
            farthest_point_sample(&points, points.len(), 5).unwrap(),
            farthest_point_sample_naive(&points, points.len(), 5)
        );
    }

    #[test]
    fn all_points_equal_picks_the_start_then_index_zero() {
        let points = vec![[0.5f32, -0.25, 2.0]; 2000];
        let got = farthest_point_sample(&points, 4, 7).unwrap();
        assert_eq!(got, vec![7, 0, 0, 0]);
        assert_eq!(got, farthest_point_sample_naive(&points, 4, 7));
    }

    #[test]
    fn rejects_bad_arguments_without_panicking() {
        let points = random_cloud(10, 0);
        assert!(matches!(
            farthest_point_sample(&[], 1, 0),
            Err(GeometryError::Empty { arg: "points" })
        ));
        let err = farthest_point_sample(&points, 11, 0).unwrap_err();
        assert!(
            err.to_string().contains("n_samples must be in 1..=10"),
            "{err}"
        );
        let err = farthest_point_sample(&points, 0, 0).unwrap_err();
        assert!(err.to_string().contains("n_samples"), "{err}");
        let err = farthest_point_sample(&points, 3, 10).unwrap_err();
        assert!(
            err.to_string().contains("start_index must be in 0..10"),
            "{err}"
        );
        let mut bad = points.clone();
        bad[4][1] = f32::NAN;
        let err = farthest_point_sample(&bad, 3, 0).unwrap_err();
        assert!(err.to_string().contains("point 4"), "{err}");
    }

    #[test]
    #[cfg(target_pointer_width = "64")]
    fn clouds_beyond_u32_indices_are_refused_before_sampling() {
        let max = crate::error::MAX_POINTS;
        assert_eq!(check_sizes(max, max, max - 1), Ok(()));
        assert_eq!(
            check_sizes(max + 1, 1, 0),
            Err(GeometryError::TooManyPoints {
                arg: "points",
                points: max + 1
            })
        );
    }
}
