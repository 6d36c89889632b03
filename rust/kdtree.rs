//! A KD-tree for exact nearest-one queries in 3-D that stays near O(log n) per query on
//! degenerate clouds (not when a query is equidistant from most points, e.g. the centre of a
//! sphere of points, which no KD-tree prunes).
//!
//! It replaces kiddo's `ImmutableKdTree`, which is fast on well-spread clouds but went quadratic
//! on three kinds of plausible input (issue 14):
//! - it splits x, y, z in turn, so on a collinear cloud two levels in three split nothing;
//! - on crossing a splitting plane it adds `(new_offset − old_offset)²` to its lower bound,
//!   not `new_offset² − old_offset²`, so for a query far from the cloud the bound stays near the
//!   first plane's distance and almost nothing is pruned;
//! - it bounds in float32, where the squared distances of a cloud scaled by 1e-25 are all 0: every
//!   cell ties with the best answer and is visited.
//!
//! This tree splits each node at the median of its widest extent, so its depth is ⌈log₂(n/16)⌉
//! whatever the layout. Its cells are the cloud's bounding box cut by the splitting planes, and
//! it prunes with the squared distance from the query to the cell, kept per axis and summed in
//! float64 (which neither underflows nor overflows for float32 coordinates).
//!
//! The answer is defined by the float32 distance callers see, `dx*dx + dy*dy + dz*dz` in that
//! order: the point with the smallest one; among equal float32 distances the nearest in float64;
//! then the lowest item. Pruning is exact for that order (see [`Nearest::may_improve`]).

use std::ops::Range;

/// Most points in a leaf; leaves hold between half this and this many.
const LEAF_SIZE: usize = 16;

/// Subtrees of at least this many points are built on two threads.
const PARALLEL_MIN_BUILD: usize = 1 << 13;

/// Bounds on float32 rounding, used to turn a float64 distance into a lower bound on the float32
/// one. The float32 distance takes five rounded operations, each with relative error at most
/// 2⁻²⁴ (5·2⁻²⁴ < 2⁻²⁰ leaves room for the float64 errors, about 2⁻⁵⁰), and each of its three
/// squares may underflow by at most 2⁻¹⁵⁰ (3·2⁻¹⁵⁰ < 2⁻¹⁴⁷).
const F32_RELATIVE_ERROR: f64 = 1.0 / (1u64 << 20) as f64;
const F32_UNDERFLOW: f64 = 1.0 / (1u128 << 127) as f64 / (1u64 << 20) as f64;

/// The relative error of a float64 squared distance or box distance (a few 2⁻⁵³), rounded up.
const F64_RELATIVE_ERROR: f64 = 1.0 / (1u64 << 45) as f64;

/// A point of the tree and the item it answers with.
#[derive(Clone, Copy)]
pub(crate) struct Entry {
    pub point: [f32; 3],
    pub item: u32,
}

/// A bounding box.
#[derive(Clone, Copy)]
struct Bounds {
    lo: [f32; 3],
    hi: [f32; 3],
}

impl Bounds {
    fn of(entries: &[Entry]) -> Self {
        let mut b = Bounds {
            lo: [f32::INFINITY; 3],
            hi: [f32::NEG_INFINITY; 3],
        };
        // Comparisons rather than f32::min/max, whose NaN handling costs here (there is no NaN).
        for e in entries {
            for d in 0..3 {
                let c = e.point[d];
                b.lo[d] = if c < b.lo[d] { c } else { b.lo[d] };
                b.hi[d] = if c > b.hi[d] { c } else { b.hi[d] };
            }
        }
        b
    }

    /// The axis of the largest extent (in float64: `hi − lo` of huge coordinates is exact).
    fn widest(&self) -> usize {
        let extent = |d: usize| f64::from(self.hi[d]) - f64::from(self.lo[d]);
        (1..3).fold(0, |w, d| if extent(d) > extent(w) { d } else { w })
    }

    /// Per axis, the distance from `q` to the box (0 inside it).
    fn offsets(&self, q: &[f64; 3]) -> [f64; 3] {
        [0, 1, 2].map(|d| {
            (f64::from(self.lo[d]) - q[d])
                .max(q[d] - f64::from(self.hi[d]))
                .max(0.0)
        })
    }
}

/// An internal node: points with `coordinate[axis] < value` lie left, `> value` right, equal
/// ones on either side.
#[derive(Clone, Copy, Default)]
struct Split {
    value: f32,
    axis: u32,
}

/// A leaf's points by axis, padded with NaN (whose distance compares false with everything) so
/// that every leaf is scanned in fixed-size, vectorisable loops.
#[derive(Clone, Copy)]
struct Leaf {
    coords: [[f32; LEAF_SIZE]; 3],
    items: [u32; LEAF_SIZE],
}

impl Default for Leaf {
    fn default() -> Self {
        Leaf {
            coords: [[f32::NAN; LEAF_SIZE]; 3],
            items: [u32::MAX; LEAF_SIZE],
        }
    }
}

/// The squared distance in float32, in the plain order every caller uses.
#[inline]
fn sq_dist_f32(q: &[f32; 3], r: &[f32; 3]) -> f32 {
    let (dx, dy, dz) = (q[0] - r[0], q[1] - r[1], q[2] - r[2]);
    dx * dx + dy * dy + dz * dz
}

#[inline]
fn sq_dist_f64(q: &[f64; 3], r: &[f32; 3]) -> f64 {
    let (dx, dy, dz) = (
        q[0] - f64::from(r[0]),
        q[1] - f64::from(r[1]),
        q[2] - f64::from(r[2]),
    );
    dx * dx + dy * dy + dz * dz
}

#[inline]
fn norm2(offsets: &[f64; 3]) -> f64 {
    offsets[0] * offsets[0] + offsets[1] * offsets[1] + offsets[2] * offsets[2]
}

/// The best answer so far of one query.
struct Nearest {
    sq_dist: f32,
    sq_dist_f64: f64,
    item: u32,
}

impl Nearest {
    /// Whether a cell `lower` away from the query (float64 squared distance) may hold a point
    /// that comes before the best so far.
    ///
    /// Every point of the cell is at least `lower` away up to float64 rounding, so its float32
    /// distance is at least `lower_f32` below; it can come first only with a smaller float32
    /// distance, or an equal one and a float64 distance no larger than the best's.
    #[inline]
    fn may_improve(&self, lower: f64) -> bool {
        let best = f64::from(self.sq_dist);
        let lower_f32 = (lower * (1.0 - F32_RELATIVE_ERROR) - F32_UNDERFLOW).max(0.0);
        lower_f32 < best
            || (lower_f32 <= best && lower * (1.0 - F64_RELATIVE_ERROR) <= self.sq_dist_f64)
    }

    /// Take the point `r` of `item`, at float32 distance `d` no larger than the best's, if it
    /// comes first.
    #[inline]
    fn offer(&mut self, d: f32, q: &[f64; 3], r: &[f32; 3], item: u32) {
        let d64 = sq_dist_f64(q, r);
        if d < self.sq_dist || (d64, item) < (self.sq_dist_f64, self.item) {
            *self = Nearest {
                sq_dist: d,
                sq_dist_f64: d64,
                item,
            };
        }
    }
}

/// A balanced KD-tree. Every leaf lies the same number of splits below the root; a node of `len`
/// points gives its left child the first `len / 2`. `splits` holds the internal nodes in
/// pre-order (a node, its left subtree, its right subtree), `leaves` the leaves left to right.
pub(crate) struct KdTree {
    bounds: Bounds,
    splits: Vec<Split>,
    leaves: Vec<Leaf>,
}

impl KdTree {
    /// Build over `entries` (non-empty, finite coordinates).
    pub fn new(mut entries: Vec<Entry>, parallel: bool) -> Self {
        let mut levels = 0;
        while entries.len() > LEAF_SIZE << levels {
            levels += 1;
        }
        let bounds = Bounds::of(&entries);
        let mut splits = vec![Split::default(); (1usize << levels) - 1];
        let mut leaves = vec![Leaf::default(); 1usize << levels];
        build(&mut entries, &mut splits, &mut leaves, parallel);
        KdTree {
            bounds,
            splits,
            leaves,
        }
    }

    /// The float32 squared distance to, and item of, the first point of `q` in the order of the
    /// module documentation.
    #[inline]
    pub fn nearest(&self, q: &[f32; 3]) -> (f32, u32) {
        let mut best = Nearest {
            sq_dist: f32::INFINITY,
            sq_dist_f64: f64::INFINITY,
            item: u32::MAX,
        };
        let q64 = q.map(f64::from);
        let offsets = self.bounds.offsets(&q64);
        self.search(0, self.splits.len(), 0, q, &q64, offsets, &mut best);
        (best.sq_dist, best.item)
    }

    /// Search the subtree at internal node `node` (`span` internal nodes; none for a leaf) whose
    /// leaves start at `leaf`, the query's side first. `offsets` are the per-axis distances from
    /// the query to the subtree's cell, and the caller has checked that cell against `best`.
    #[allow(clippy::too_many_arguments)]
    fn search(
        &self,
        node: usize,
        span: usize,
        leaf: usize,
        q: &[f32; 3],
        q64: &[f64; 3],
        offsets: [f64; 3],
        best: &mut Nearest,
    ) {
        if span == 0 {
            self.scan(&self.leaves[leaf], q, q64, best);
            return;
        }
        let Split { value, axis } = self.splits[node];
        let (axis, value) = (axis as usize, f64::from(value));
        let half = span / 2;
        let left = (node + 1, leaf);
        let right = (node + 1 + half, leaf + half + 1);
        let (near, far) = if q64[axis] < value {
            (left, right)
        } else {
            (right, left)
        };
        // The near child's cell is as far from the query as this one.
        self.search(near.0, half, near.1, q, q64, offsets, best);
        // The far child's cell is `|q − value|` away along `axis`.
        let gap = (q64[axis] - value).abs();
        let far_offsets = [0, 1, 2].map(|d| if d == axis { gap } else { offsets[d] });
        if best.may_improve(norm2(&far_offsets)) {
            self.search(far.0, half, far.1, q, q64, far_offsets, best);
        }
    }

    /// How many leaves the tree has.
    pub fn leaf_count(&self) -> usize {
        self.leaves.len()
    }

    /// The points of `leaves`, leaf by leaf (so neighbours in space come together), each with
    /// its item.
    pub fn points(&self, leaves: Range<usize>) -> impl Iterator<Item = ([f32; 3], u32)> + '_ {
        self.leaves[leaves].iter().flat_map(|leaf| {
            let [xs, ys, zs] = &leaf.coords;
            (0..LEAF_SIZE)
                .take_while(|&k| leaf.items[k] != u32::MAX)
                .map(move |k| ([xs[k], ys[k], zs[k]], leaf.items[k]))
        })
    }

    #[inline]
    fn scan(&self, leaf: &Leaf, q: &[f32; 3], q64: &[f64; 3], best: &mut Nearest) {
        let [xs, ys, zs] = &leaf.coords;
        let mut d = [0.0f32; LEAF_SIZE];
        for k in 0..LEAF_SIZE {
            d[k] = sq_dist_f32(q, &[xs[k], ys[k], zs[k]]);
        }
        // NaN (padding) compares false.
        let mut any = false;
        for &dk in &d {
            any |= dk <= best.sq_dist;
        }
        if any {
            for k in 0..LEAF_SIZE {
                if d[k] <= best.sq_dist {
                    best.offer(d[k], q64, &[xs[k], ys[k], zs[k]], leaf.items[k]);
                }
            }
        }
    }
}

/// Order `entries` as the subtree over them, filling its internal nodes `splits` (pre-order)
/// and its `leaves`.
fn build(entries: &mut [Entry], splits: &mut [Split], leaves: &mut [Leaf], parallel: bool) {
    if splits.is_empty() {
        let leaf = &mut leaves[0];
        for (k, e) in entries.iter().enumerate() {
            for d in 0..3 {
                leaf.coords[d][k] = e.point[d];
            }
            leaf.items[k] = e.item;
        }
        return;
    }
    let axis = Bounds::of(entries).widest();
    let split_here = parallel && entries.len() >= PARALLEL_MIN_BUILD;
    let mid = entries.len() / 2;
    entries.select_nth_unstable_by(mid, |a, b| a.point[axis].total_cmp(&b.point[axis]));
    splits[0] = Split {
        value: entries[mid].point[axis],
        axis: axis as u32,
    };
    let (left, right) = entries.split_at_mut(mid);
    let half = splits.len() / 2;
    let (left_splits, right_splits) = splits[1..].split_at_mut(half);
    let (left_leaves, right_leaves) = leaves.split_at_mut(half + 1);
    if split_here {
        rayon::join(
            || build(left, left_splits, left_leaves, parallel),
            || build(right, right_splits, right_leaves, parallel),
        );
    } else {
        build(left, left_splits, left_leaves, false);
        build(right, right_splits, right_leaves, false);
    }
}
