//! Metrics against a reference set: the minimal matching distance (MMD) of KITTI's benchmark.
//!
//! MMD (GRNet, PoinTr `KITTI_metric.py`): for each completion, the smallest Chamfer distance
//! CD-L2 = mean_c d(c, R)² + mean_r d(r, C)² to any cloud R of a reference set (ShapeNet's
//! cars), averaged over the completions. PoinTr computes all pairs (2,401 completions × 5,927
//! cars of 16,384 points: 3.5 days on a GPU). Here the search is an exact branch and bound.
//! Every reference gets its KD-tree once; each completion C gets its tree, a distance grid
//! and a few coarse levels, and then:
//!
//! 1. **Reference → completion bound, every reference.** A grid of about 2^20 cells over all
//!    the clouds holds, per cell, a lower bound of the distance from the cell's centre q to C,
//!    exact within 3 cells of C (every point of C writes its distance into the 7³ cells
//!    around it; a cell left alone is farther than that from all of C). For a point r,
//!    d(r, C) ≥ d(q, C) − |r − q| (triangle inequality), so mean_r max(0, d(q, C) − |r − q|)²
//!    bounds mean_r d(r, C)² from below at a few float operations a point, with no query.
//! 2. **Completion → reference bound, on demand.** The first 16, 64, 256, 1,024 points of C's
//!    farthest point sample are centres; a point c of centre s has d(c, R) ≥ d(s, R) − δ_c.
//!    Per centre a histogram of δ (upper bin edges) turns one query per centre into a bound
//!    of mean_c d(c, R)².
//! 3. **Search.** The references are visited nearest first by an estimate (the grid's bounds
//!    of 64 spread points), so a near-best distance is known early. A reference is dropped
//!    as soon as the grid's bounds of its points summed so far (in the spread order, checked
//!    every 16 points) exceed the best distance: most go after a few dozen look-ups. A
//!    survivor's bound is tightened level by level, then it is computed exactly.
//! 4. **Exact distance, dropped early.** Reference → completion first: the running sum plus
//!    the grid's bound of the points still to come plus the other term's bound is checked
//!    against the best distance every 16 points; then completion → reference, its running
//!    sum plus the exact first term.
//!
//! The exact distance of a pair is summed as before these bounds existed (each point's
//! float32 squared distance to its nearest neighbour, added in float64 in the cloud's spread
//! order), and a reference is dropped only when a lower bound is *strictly* above the best
//! exact distance, so the answer (distance and index, the lowest index among equal distances) is
//! bit-for-bit that of computing every pair with [`chamfer_exact`]. The bounds are made safe
//! against rounding by [`BOUND_SHRINK`] and [`BOUND_SLACK`], far above float32 and float64
//! rounding errors.

use rayon::prelude::*;

use crate::error::{GeometryError, Result};
use crate::nn::{validate_pair, NearestNeighborIndex};

/// Queries between two comparisons of a partial sum with the best distance.
const CHECK_EVERY: usize = 16;
/// Centres of the coarsest level; each next level has [`LEVEL_GROWTH`] times more.
const FIRST_LEVEL: usize = 16;
const LEVEL_GROWTH: usize = 4;
/// A level is made only if it has at most this fraction (1/n) of the cloud's points as centres.
const MIN_POINTS_PER_CENTRE: usize = 8;
/// Histogram bins of the distances to a centre (besides one bin for distance 0: the centre).
const BINS: usize = 8;
/// Cells of the completion's distance grid (about; 8 bytes each).
const GRID_CELLS: usize = 1 << 20;
/// How many cells around each completion point its distance field is exact.
const SPLAT_CELLS: usize = 3;
/// Lower bounds are multiplied by this before any comparison. The distances the exact sum adds
/// are float64 `dx*dx + dy*dy + dz*dz` rounded to float32 (relative error below 7e-8 against the
/// true squared distance) summed in float64 (relative error below n·1.2e-16, n < 2^32: under
/// 6e-7); the bounds are float64 from float32 coordinates with a 1e-6 relative margin on every
/// distance. 1e-5 leaves a wide gap above all of it.
const BOUND_SHRINK: f64 = 1.0 - 1e-5;
/// Subtracted from every lower bound: squared distances rounded to float32 below its smallest
/// normal (1.2e-38) lose their relative precision (absolute error under 1e-45 a point).
const BOUND_SLACK: f64 = 1e-36;

/// A fixed pseudo-random order of `0..n` (xorshift-driven Fisher–Yates), so that any prefix
/// of the points is spread over the whole cloud, whatever order the file had.
fn spread_order(n: usize) -> Vec<u32> {
    let mut order: Vec<u32> = (0..n as u32).collect();
    let mut state: u64 = 0x9e37_79b9_7f4a_7c15;
    for i in (1..n).rev() {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        let j = (state % (i as u64 + 1)) as usize;
        order.swap(i, j);
    }
    order
}

/// One coarse level of a cloud: centres, and for each centre its points' distances to it as a
/// histogram (`counts[g * (BINS + 1)]` the points at the centre itself, then `BINS` bins of
/// width `radius[g] / BINS`, a point in bin `b` being at most `radius[g] * b / BINS` away).
struct Level {
    centres: Vec<[f32; 3]>,
    radius: Vec<f64>,
    counts: Vec<u32>,
}

impl Level {
    /// The level of `points` with these centres (points of the cloud).
    fn new(points: &[[f32; 3]], centres: Vec<[f32; 3]>) -> Self {
        let index = NearestNeighborIndex::new(&centres);
        let k = centres.len();
        let mut owner = vec![0u32; points.len()];
        let mut delta = vec![0f64; points.len()];
        let mut radius = vec![0f64; k];
        for (i, p) in points.iter().enumerate() {
            let g = index.nearest(p).1 as usize;
            let s = centres[g];
            let d = (0..3)
                .map(|a| {
                    let x = p[a] as f64 - s[a] as f64;
                    x * x
                })
                .sum::<f64>()
                .sqrt();
            owner[i] = g as u32;
            delta[i] = d;
            radius[g] = radius[g].max(d);
        }
        // Bin edges slightly above the largest distance, so rounding cannot put a point in a
        // bin whose edge lies below its distance.
        for r in &mut radius {
            *r *= 1.0 + 1e-9;
        }
        let mut counts = vec![0u32; k * (BINS + 1)];
        for (&g, &d) in owner.iter().zip(&delta) {
            let g = g as usize;
            let slot = if d == 0.0 {
                0
            } else {
                // ceil(d / (r / BINS)) in 1..=BINS; the edge r * slot / BINS is ≥ d.
                ((d / radius[g] * BINS as f64).ceil() as usize).clamp(1, BINS)
            };
            counts[g * (BINS + 1) + slot] += 1;
        }
        Level {
            centres,
            radius,
            counts,
        }
    }

    /// A lower bound of `sum_p d(p, Y)²` over this cloud's points, `Y` the cloud of `to`.
    fn bound(&self, to: &NearestNeighborIndex<'_>) -> f64 {
        let mut sum = 0.0f64;
        for (g, centre) in self.centres.iter().enumerate() {
            // The true distance is at least the float32 one less a relative 1e-6 (an overflow
            // to infinity means at least the largest float32).
            let dist = (to.nearest(centre).0.min(f32::MAX) as f64).sqrt() * (1.0 - 1e-6);
            let counts = &self.counts[g * (BINS + 1)..(g + 1) * (BINS + 1)];
            sum += counts[0] as f64 * dist * dist;
            let width = self.radius[g] / BINS as f64 * (1.0 + 1e-9);
            for (b, &count) in counts[1..].iter().enumerate() {
                let gap = dist - width * (b + 1) as f64;
                if gap <= 0.0 {
                    break;
                }
                sum += count as f64 * gap * gap;
            }
        }
        sum
    }
}

/// A cloud ready for the search: its tree and its spread order.
struct Prepared<'a> {
    points: &'a [[f32; 3]],
    index: NearestNeighborIndex<'a>,
    order: Vec<u32>,
}

impl<'a> Prepared<'a> {
    fn new(points: &'a [[f32; 3]]) -> Self {
        Prepared {
            points,
            index: NearestNeighborIndex::new(points),
            order: spread_order(points.len()),
        }
    }
}

/// The coarse levels of a completion: the first 16, 64, 256, … points of its farthest point
/// sample as centres, as long as each centre has at least [`MIN_POINTS_PER_CENTRE`] points.
fn coarse_levels(points: &[[f32; 3]]) -> Vec<Level> {
    let mut sizes = Vec::new();
    let mut k = FIRST_LEVEL;
    while k * MIN_POINTS_PER_CENTRE <= points.len() {
        sizes.push(k);
        k *= LEVEL_GROWTH;
    }
    let Some(&most) = sizes.last() else {
        return Vec::new();
    };
    let sample = crate::fps::sample_unchecked(points, most, 0);
    sizes
        .iter()
        .map(|&k| Level::new(points, sample[..k].iter().map(|&i| points[i]).collect()))
        .collect()
}

/// The axis-aligned bounding box of clouds: (min, max) in float64.
fn bounding_box<'c>(clouds: impl Iterator<Item = &'c [[f32; 3]]>) -> ([f64; 3], [f64; 3]) {
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for p in clouds.flatten() {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a] as f64);
            hi[a] = hi[a].max(p[a] as f64);
        }
    }
    (lo, hi)
}

/// A truncated distance field of the completion C on a regular grid over all the clouds: a cell
/// holds a lower bound of the distance from its centre q to C, exact up to [`SPLAT_CELLS`]
/// cells away. For any point r, d(r, C) ≥ d(q, C) − |r − q| (triangle inequality), so a whole
/// reference gets a lower bound of its directed term towards C at a few float operations a
/// point. Every point of C writes its distance into the cells around it (a cube of
/// 2·[`SPLAT_CELLS`] + 1 cells a side); a cell no point reached is farther than
/// `SPLAT_CELLS` cells from all of C and keeps that distance as its bound.
struct DistanceGrid {
    origin: [f64; 3],
    cell: f64,
    dims: [usize; 3],
    /// Per axis, the float32 coordinate of every cell centre.
    centres: [Vec<f32>; 3],
    /// Per cell (x slowest), the lowered lower bound of the distance from its centre to C.
    distance: Vec<f64>,
}

impl DistanceGrid {
    /// The field of `completion` over the box `lo..hi` (which holds the completion), in at
    /// most about [`GRID_CELLS`] cubic cells, and cells no smaller than a third of the
    /// completion's point spacing (so the exact part reaches about as far as a point's
    /// neighbours).
    fn new(completion: &[[f32; 3]], lo: [f64; 3], hi: [f64; 3]) -> Self {
        let extent: [f64; 3] = std::array::from_fn(|a| (hi[a] - lo[a]).max(0.0));
        let longest = extent.iter().cloned().fold(0.0, f64::max);
        let cell = if longest > 0.0 {
            // Flat boxes count as 1/64 of the longest side thick, so the cells stay few.
            let volume: f64 = extent.iter().map(|e| e.max(longest / 64.0)).product();
            // The spacing of points on the surface of the completion's box.
            let (clo, chi) = bounding_box(std::iter::once(completion));
            let [x, y, z]: [f64; 3] = std::array::from_fn(|a| chi[a] - clo[a]);
            let spacing = (2.0 * (x * y + y * z + z * x) / completion.len() as f64).sqrt();
            (volume / GRID_CELLS as f64).cbrt().max(spacing / 3.0)
        } else {
            1.0
        };
        let dims: [usize; 3] = std::array::from_fn(|a| (extent[a] / cell).floor() as usize + 1);
        let centres = std::array::from_fn(|a| {
            (0..dims[a])
                .map(|i| (lo[a] + (i as f64 + 0.5) * cell) as f32)
                .collect::<Vec<f32>>()
        });
        let reach = SPLAT_CELLS as f64 * cell;
        let mut grid = DistanceGrid {
            origin: lo,
            cell,
            dims,
            centres,
            distance: vec![reach * (1.0 - 1e-6); dims.iter().product()],
        };
        grid.splat(completion, reach);
        grid
    }

    /// The index of the cell holding coordinate `x` on axis `a` (clamped to the grid), with
    /// `inverse` = 1 / cell. Rounding may pick a neighbouring cell: any cell gives a valid
    /// bound, since the bound uses that cell's own centre.
    #[inline(always)]
    fn axis_index(&self, a: usize, x: f64, inverse: f64) -> usize {
        // `as` saturates: negative values go to 0.
        (((x - self.origin[a]) * inverse) as usize).min(self.dims[a] - 1)
    }

    /// Lower every cell within `reach` (per axis) of a point of `completion` to the point's
    /// distance. A cell left out is more than `reach` + half a cell from the point on some
    /// axis: its initial value stays below that distance.
    fn splat(&mut self, completion: &[[f32; 3]], reach: f64) {
        let [dx, dy, dz] = self.dims;
        for c in completion {
            let c64 = c.map(f64::from);
            let range = |a: usize| {
                let from = ((c64[a] - reach - self.origin[a]) / self.cell).floor();
                let from = if from < 0.0 { 0 } else { from as usize };
                let to = ((c64[a] + reach - self.origin[a]) / self.cell).floor() as usize;
                from..=to.min(self.dims[a] - 1)
            };
            let (rx, ry, rz) = (range(0), range(1), range(2));
            for i in rx {
                let ex = self.centres[0][i] as f64 - c64[0];
                for j in ry.clone() {
                    let ey = self.centres[1][j] as f64 - c64[1];
                    let row = (i * dy + j) * dz;
                    let exy = ex * ex + ey * ey;
                    for k in rz.clone() {
                        let ez = self.centres[2][k] as f64 - c64[2];
                        // float64 from float32 coordinates: relative error ~1e-16, covered
                        // by the 1e-9 margin.
                        let d = (exy + ez * ez).sqrt() * (1.0 - 1e-9);
                        let slot = &mut self.distance[row + k];
                        if d < *slot {
                            *slot = d;
                        }
                    }
                }
            }
        }
        debug_assert!(dx * dy * dz == self.distance.len());
    }

    /// A lower bound of d(p, C)² (unsafe: lower it with [`safe`] before comparing).
    #[inline(always)]
    fn point_bound(&self, p: &[f32; 3], inverse: f64) -> f64 {
        let [_, dy, dz] = self.dims;
        let p64 = p.map(f64::from);
        let (i, j, k) = (
            self.axis_index(0, p64[0], inverse),
            self.axis_index(1, p64[1], inverse),
            self.axis_index(2, p64[2], inverse),
        );
        let ex = p64[0] - self.centres[0][i] as f64;
        let ey = p64[1] - self.centres[1][j] as f64;
        let ez = p64[2] - self.centres[2][k] as f64;
        let offset = (ex * ex + ey * ey + ez * ez).sqrt() * (1.0 + 1e-9);
        let gap = (self.distance[(i * dy + j) * dz + k] - offset).max(0.0);
        gap * gap
    }
}

/// The sum over the points of `from`, in its spread order, of the float32 squared distance
/// to the nearest point of `to`, added in float64; `None` as soon as `exceeds(k, partial)`
/// says so (asked every [`CHECK_EVERY`] points, `k` points in).
fn directed_sum(
    from: &Prepared<'_>,
    to: &Prepared<'_>,
    mut exceeds: impl FnMut(usize, f64) -> bool,
) -> Option<f64> {
    let mut sum = 0.0f64;
    for (k, &i) in from.order.iter().enumerate() {
        sum += to.index.nearest(&from.points[i as usize]).0 as f64;
        if (k + 1) % CHECK_EVERY == 0 && exceeds(k + 1, sum) {
            return None;
        }
    }
    Some(sum)
}

/// The CD-L2 of a pair from its two directed sums, as every caller computes it.
fn combine(c: &Prepared<'_>, r: &Prepared<'_>, there: f64, back: f64) -> f64 {
    let there = 0.0 + there * (1.0 / c.points.len() as f64);
    there + back * (1.0 / r.points.len() as f64)
}

/// The exact CD-L2 of a pair, or `None` as soon as it is known to exceed `bound`. `grid` is
/// the completion's distance field and `grid_total` its bound of the reference's points (the
/// unscaled sum), `there_bound` a (safe) lower bound of the completion → reference term.
///
/// The reference → completion sum comes first: besides its running sum, the points still to
/// come are bounded by the grid point by point, so a reference that cannot win is dropped
/// after a few of its points. Then the completion → reference sum, with the exact
/// reference → completion term added.
fn chamfer_bounded(
    c: &Prepared<'_>,
    r: &Prepared<'_>,
    grid: &DistanceGrid,
    grid_total: f64,
    there_bound: f64,
    bound: f64,
) -> Option<f64> {
    let inverse = 1.0 / grid.cell;
    let back_scale = 1.0 / r.points.len() as f64;
    // What the grid gives for the points not yet summed: its whole bound (`grid_total`, the
    // sum of the points' bounds) less the points done (rounding of the difference is far
    // inside BOUND_SHRINK's margin).
    let mut grid_done = 0.0f64;
    let mut done = 0;
    let back = directed_sum(r, c, |k, sum| {
        for &i in &r.order[done..k] {
            grid_done += grid.point_bound(&r.points[i as usize], inverse);
        }
        done = k;
        let rest = (grid_total - grid_done).max(0.0);
        there_bound + safe((sum + rest) * back_scale) > bound
    })?;
    let back_term = back * back_scale;
    let there_scale = 1.0 / c.points.len() as f64;
    let there = directed_sum(c, r, |_, sum| {
        there_bound.max(sum * there_scale) + back_term > bound
    })?;
    Some(combine(c, r, there, back))
}

/// The exact CD-L2 of a pair as the search computes it (its value is what
/// [`minimal_matching`] compares and returns): both directed sums in the clouds' spread
/// orders, each point's float32 squared distance added in float64.
pub fn chamfer_exact(completion: &[[f32; 3]], reference: &[[f32; 3]]) -> f64 {
    let (c, r) = (Prepared::new(completion), Prepared::new(reference));
    let there = directed_sum(&c, &r, |_, _| false).unwrap_or(f64::NAN);
    let back = directed_sum(&r, &c, |_, _| false).unwrap_or(f64::NAN);
    combine(&c, &r, there, back)
}

/// Lower a bound so that it cannot exceed the exact value through rounding.
fn safe(bound: f64) -> f64 {
    bound * BOUND_SHRINK - BOUND_SLACK
}

/// The grid's bound of the sum over `r`'s points (spread order) of d(p, C)², or `None` as
/// soon as its running value alone shows the pair's distance exceeds `bound`.
fn grid_sum(grid: &DistanceGrid, r: &Prepared<'_>, bound: f64) -> Option<f64> {
    let inverse = 1.0 / grid.cell;
    let scale = 1.0 / r.points.len() as f64;
    let mut sum = 0.0f64;
    for (k, &i) in r.order.iter().enumerate() {
        sum += grid.point_bound(&r.points[i as usize], inverse);
        if (k + 1) % CHECK_EVERY == 0 && safe(sum * scale) > bound {
            return None;
        }
    }
    Some(sum)
}

/// Points of a reference whose grid bounds estimate its distance, to order the references.
const PROBE: usize = 64;

/// For one completion: the smallest CD-L2 to any reference and that reference's index
/// (the lowest index among equal distances). `extent` bounds every reference.
fn nearest_reference(
    completion: &[[f32; 3]],
    references: &[Prepared<'_>],
    extent: ([f64; 3], [f64; 3]),
) -> (f64, u32) {
    let c = Prepared::new(completion);
    let levels = coarse_levels(completion);
    let (lo, hi) = bounding_box(std::iter::once(completion));
    let grid = DistanceGrid::new(
        completion,
        std::array::from_fn(|a| lo[a].min(extent.0[a])),
        std::array::from_fn(|a| hi[a].max(extent.1[a])),
    );
    // Visit the references nearest first by an estimate (the grid's bounds of a few spread
    // points, scaled up), so that a near-best distance is known early and the rest drop out
    // after a few grid look-ups each.
    let inverse = 1.0 / grid.cell;
    let mut ranked: Vec<(f64, u32)> = references
        .iter()
        .enumerate()
        .map(|(j, r)| {
            let probe = &r.order[..PROBE.min(r.order.len())];
            let sum: f64 = probe
                .iter()
                .map(|&i| grid.point_bound(&r.points[i as usize], inverse))
                .sum();
            (sum / probe.len() as f64, j as u32)
        })
        .collect();
    ranked.sort_by(|x, y| x.0.total_cmp(&y.0).then(x.1.cmp(&y.1)));
    let mut best = (f64::INFINITY, u32::MAX);
    // A reference is dropped only when a lower bound of its distance exceeds the best
    // distance: it cannot be the nearest, nor tie with it. Ties resolve to the lowest index
    // as with every pair.
    'references: for &(_, j) in &ranked {
        let r = &references[j as usize];
        let Some(grid_total) = grid_sum(&grid, r, best.0) else {
            continue;
        };
        let back = safe(grid_total / r.points.len() as f64);
        // Tighten with the completion → reference term's bounds, coarse to fine.
        let mut there = 0.0f64;
        for level in &levels {
            there = there.max(safe(level.bound(&r.index) / completion.len() as f64));
            if there + back > best.0 {
                continue 'references;
            }
        }
        if let Some(d) = chamfer_bounded(&c, r, &grid, grid_total, there, best.0) {
            if d < best.0 || (d == best.0 && j < best.1) {
                best = (d, j);
            }
        }
    }
    best
}

/// Minimal matching distance terms: for each completion, the smallest CD-L2 (sum of both mean
/// squared directed distances) to any reference cloud, and the index of that reference.
///
/// Exact: the same value as computing every pair, found with far fewer queries. Completions
/// run in parallel; every reference's tree is built once.
pub fn minimal_matching(
    completions: &[&[[f32; 3]]],
    references: &[&[[f32; 3]]],
) -> Result<Vec<(f64, u32)>> {
    if references.is_empty() {
        return Err(GeometryError::Empty { arg: "references" });
    }
    for (b, c) in completions.iter().enumerate() {
        validate_pair("completions", c, "references", references[0], b)?;
    }
    for (b, r) in references.iter().enumerate() {
        validate_pair("references", r, "completions", r, b)?;
    }
    let parallel = crate::parallel_allowed();
    let prepared: Vec<Prepared<'_>> = if parallel {
        references.par_iter().map(|r| Prepared::new(r)).collect()
    } else {
        references.iter().map(|r| Prepared::new(r)).collect()
    };
    let extent = bounding_box(references.iter().copied());
    Ok(if parallel {
        completions
            .par_iter()
            .map(|c| nearest_reference(c, &prepared, extent))
            .collect()
    } else {
        completions
            .iter()
            .map(|c| nearest_reference(c, &prepared, extent))
            .collect()
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn cloud(rng: &mut rand::rngs::StdRng, n: usize, scale: [f32; 3]) -> Vec<[f32; 3]> {
        (0..n)
            .map(|_| {
                [
                    rng.gen_range(-1.0..1.0) * scale[0],
                    rng.gen_range(-1.0..1.0) * scale[1],
                    rng.gen_range(-1.0..1.0) * scale[2],
                ]
            })
            .collect()
    }

    fn brute(c: &[[f32; 3]], r: &[[f32; 3]]) -> f64 {
        let (a, b) = crate::chamfer::chamfer_serial(c, r);
        a + b
    }

    #[test]
    fn pruned_search_equals_all_pairs() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        let refs: Vec<Vec<[f32; 3]>> = (0..40)
            .map(|k| {
                let s = 0.5 + 0.03 * k as f32;
                cloud(&mut rng, 300 + k, [s, 1.0, 2.0 - s])
            })
            .collect();
        let comps: Vec<Vec<[f32; 3]>> = (0..12)
            .map(|k| cloud(&mut rng, 200 + 7 * k, [0.6 + 0.07 * k as f32, 1.0, 1.3]))
            .collect();
        let r: Vec<&[[f32; 3]]> = refs.iter().map(|x| x.as_slice()).collect();
        let c: Vec<&[[f32; 3]]> = comps.iter().map(|x| x.as_slice()).collect();
        let got = minimal_matching(&c, &r).unwrap();
        for (k, comp) in comps.iter().enumerate() {
            let all: Vec<f64> = refs.iter().map(|x| brute(comp, x)).collect();
            let (j, best) = all
                .iter()
                .enumerate()
                .fold(
                    (0, f64::INFINITY),
                    |acc, (j, &d)| if d < acc.1 { (j, d) } else { acc },
                );
            assert_eq!(got[k].1 as usize, j);
            assert!((got[k].0 - best).abs() <= 1e-9 * best.max(1e-12));
        }
    }

    /// Every pair by [`chamfer_exact`]: the smallest distance, lowest index among ties.
    fn every_pair(comp: &[[f32; 3]], refs: &[Vec<[f32; 3]>]) -> (f64, u32) {
        let mut best = (f64::INFINITY, u32::MAX);
        for (j, r) in refs.iter().enumerate() {
            let d = chamfer_exact(comp, r);
            if d < best.0 || (d == best.0 && (j as u32) < best.1) {
                best = (d, j as u32);
            }
        }
        best
    }

    fn check_against_every_pair(comps: &[Vec<[f32; 3]>], refs: &[Vec<[f32; 3]>]) {
        let r: Vec<&[[f32; 3]]> = refs.iter().map(|x| x.as_slice()).collect();
        let c: Vec<&[[f32; 3]]> = comps.iter().map(|x| x.as_slice()).collect();
        let got = minimal_matching(&c, &r).unwrap();
        for (k, comp) in comps.iter().enumerate() {
            let want = every_pair(comp, refs);
            assert_eq!(got[k].1, want.1, "completion {k}");
            assert_eq!(got[k].0.to_bits(), want.0.to_bits(), "completion {k}");
        }
    }

    #[test]
    fn search_is_bit_identical_to_every_pair() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        // Near copies of the references, so the bounds must separate close candidates.
        let refs: Vec<Vec<[f32; 3]>> = (0..30)
            .map(|k| cloud(&mut rng, 400 + 13 * k, [1.0 + 0.01 * k as f32, 0.5, 0.3]))
            .collect();
        let comps: Vec<Vec<[f32; 3]>> = (0..8)
            .map(|k| {
                let base = &refs[(7 * k) % refs.len()];
                base.iter()
                    .map(|p| p.map(|x| x + rng.gen_range(-0.01..0.01)))
                    .collect()
            })
            .collect();
        check_against_every_pair(&comps, &refs);
    }

    #[test]
    fn ties_go_to_the_lowest_index() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(5);
        let car = cloud(&mut rng, 500, [1.0, 0.4, 0.3]);
        let other = cloud(&mut rng, 500, [1.2, 0.4, 0.3]);
        // identical references at 1, 3 and 4; a completion equal to them, one near them
        let refs = vec![other.clone(), car.clone(), other, car.clone(), car.clone()];
        let near: Vec<[f32; 3]> = car.iter().map(|p| [p[0] + 1e-3, p[1], p[2]]).collect();
        check_against_every_pair(&[car.clone(), near], &refs);
        let r: Vec<&[[f32; 3]]> = refs.iter().map(|x| x.as_slice()).collect();
        assert_eq!(
            minimal_matching(&[car.as_slice()], &r).unwrap()[0],
            (0.0, 1)
        );
    }

    #[test]
    fn far_tiny_flat_and_duplicate_clouds() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(9);
        let mut refs: Vec<Vec<[f32; 3]>> = (0..6)
            .map(|k| {
                let mut c = cloud(&mut rng, 200, [1.0, 1.0, 1.0]);
                c.iter_mut().for_each(|p| p[0] += 1000.0 * k as f32);
                c
            })
            .collect();
        refs.push(vec![[0.5, 0.5, 0.5]]);
        refs.push(vec![[0.5, 0.5, 0.5]; 300]);
        refs.push((0..300).map(|i| [i as f32 / 300.0, 0.0, 0.0]).collect());
        refs.push(
            cloud(&mut rng, 300, [1.0, 1.0, 0.0])
                .into_iter()
                .chain(std::iter::repeat_n([0.1, 0.2, 0.0], 200))
                .collect(),
        );
        let comps = vec![
            vec![[3000.0, 0.0, 0.0]],
            vec![[0.5, 0.5, 0.5]; 3],
            cloud(&mut rng, 250, [1.0, 1.0, 0.0]),
            (0..200).map(|i| [i as f32 / 200.0, 1e-3, 0.0]).collect(),
            cloud(&mut rng, 300, [0.2, 0.2, 0.2]),
            refs[3].clone(),
        ];
        check_against_every_pair(&comps, &refs);
        // the same sets at extreme scales: float32 rounding and underflow near the bounds
        for scale in [1e-18f32, 1e-6, 1e6, 1e14] {
            let f = |set: &[Vec<[f32; 3]>]| -> Vec<Vec<[f32; 3]>> {
                set.iter()
                    .map(|c| c.iter().map(|p| p.map(|x| x * scale)).collect())
                    .collect()
            };
            check_against_every_pair(&f(&comps), &f(&refs));
        }
    }

    #[test]
    fn bounds_stay_below_the_exact_terms() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(13);
        for trial in 0..20 {
            let scale = [1.0, 0.5 + 0.05 * trial as f32, 0.3];
            let c_pts = cloud(&mut rng, 300 + 40 * trial, scale);
            let r_pts = cloud(&mut rng, 500, [1.0, 0.5, 0.3 + 0.02 * trial as f32]);
            let (c, r) = (Prepared::new(&c_pts), Prepared::new(&r_pts));
            let there = directed_sum(&c, &r, |_, _| false).unwrap() / c_pts.len() as f64;
            let back = directed_sum(&r, &c, |_, _| false).unwrap() / r_pts.len() as f64;
            let (lo, hi) = bounding_box([c_pts.as_slice(), r_pts.as_slice()].into_iter());
            let grid = DistanceGrid::new(&c_pts, lo, hi);
            let grid_bound = safe(grid_sum(&grid, &r, f64::INFINITY).unwrap() / r_pts.len() as f64);
            assert!(grid_bound <= back, "{grid_bound} > {back}");
            assert!(grid_bound > 0.1 * back, "grid bound {grid_bound} of {back}");
            for level in coarse_levels(&c_pts) {
                let b = safe(level.bound(&r.index) / c_pts.len() as f64);
                assert!(b <= there, "{b} > {there}");
            }
        }
    }

    #[test]
    fn empty_references_are_refused() {
        let c = vec![[0.0f32; 3]; 4];
        let err = minimal_matching(&[c.as_slice()], &[]).unwrap_err();
        assert!(err.to_string().contains("references"));
    }

    #[test]
    fn spread_order_is_a_permutation() {
        let mut order = spread_order(1000);
        order.sort_unstable();
        assert_eq!(order, (0..1000).collect::<Vec<u32>>());
    }
}
