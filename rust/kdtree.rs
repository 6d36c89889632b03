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
//! it prunes with the point of the cell closest to the query: its float64 distance is an exact
//! lower bound on the float64 distance of every point of the cell (see [`Nearest::may_hold`]).
//!
//! A cell can be much larger than its points: on a line or plane oblique to the axes, a leaf's
//! cell stays open along the line or plane, and a small cluster far from the rest of the cloud
//! has a cell reaching across the gap. Pruning by cells alone then visits O(n) leaves per query
//! (audit 9, G2: 54 s for the Chamfer distance of 1M points along x = y = z). So a node whose
//! points are much thinner along some oblique direction than along the axes (from the moments of
//! its points, merged up the tree), or much smaller than its cell, also keeps a [`Hull`]: an
//! oriented box along the principal axes of its points, or its tight box. Where both children
//! of a node have one, the search visits the child with the nearer hull first. Tight boxes alone
//! are not enough on an oblique plane: a query at distance h from the plane is within reach of
//! every box whose corner comes within h, about h / (leaf size) leaves, so O(√n); an oriented box
//! of a patch of the plane is flat and the search visits a handful of leaves. On spread clouds
//! almost no node has a hull and the search is the plain one.
//!
//! The answer is the point with the smallest float64 squared distance computed from the float32
//! coordinates, `dx*dx + dy*dy + dz*dz` in that order; among equal ones the lowest item. Callers
//! see that distance rounded to float32, which never decreases along that order. Pruning is exact
//! for it: cells bound the float64 distance exactly, hulls lowered by a relative
//! [`F64_RELATIVE_ERROR`] for rounding ([`Hull::lower`]), and a leaf's points are first compared
//! in float32 against a cutoff that no point able to come first exceeds ([`Nearest::cutoff`]).
//!
//! The tree used to rank in float32 first (ties to the float64 nearest), which made a query far
//! from a plane or line oblique to the axes cost O(n): a float32 squared distance carries a
//! relative error of about 6·10⁻⁸, so at height H above a patch of size about 1 every point
//! within about 2.5·10⁻⁴·H of the query's foot tied with the best, and the hulls, whose bound is
//! not exact in float32, could not exclude any of them (audit K1: 100k points at H = 10³, 21 s).
//! In float64, with the hulls' margin of 2⁻⁴⁸, the band is about 10⁻⁷·H wide: a few leaves at
//! H = 10³, about a hundred along a line at 10⁵; it covers a unit patch again at about 10⁷.

use std::ops::Range;

/// Most points in a leaf; leaves hold between half this and this many.
const LEAF_SIZE: usize = 16;

/// Subtrees of at least this many points are built on two threads.
const PARALLEL_MIN_BUILD: usize = 1 << 13;

/// How much [`Hull::lower`] is lowered, relatively, so that it stays below the float64 distance
/// of every point of its node: the rounding of both (twelve operations of 2⁻⁵³) rounded up.
const F64_RELATIVE_ERROR: f64 = 1.0 / (1u64 << 48) as f64;

/// The margins of the leaf scan's float32 prefilter ([`Nearest::cutoff`]): relative, above the
/// float32 rounding of a squared distance (five operations of 2⁻²⁴) and the float64 one, and
/// absolute, above the underflow of its three squares (2⁻¹⁵⁰ each).
const PREFILTER_RELATIVE: f64 = 1.0 / (1u64 << 20) as f64;
const PREFILTER_UNDERFLOW: f64 = 1.0 / (1u128 << 126) as f64 / (1u64 << 20) as f64;

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

    /// The point of the box closest to `q`.
    #[inline]
    fn closest(&self, q: &[f32; 3]) -> [f32; 3] {
        [0, 1, 2].map(|d| q[d].max(self.lo[d]).min(self.hi[d]))
    }
}

/// An internal node: points with `coordinate[axis] < value` lie left, `> value` right, equal
/// ones on either side. `tag` holds `axis` in its two low bits, [`HAS_HULL`] when the node
/// has a [`Hull`] and [`CHILD_HULLS`] when both its children have one.
#[derive(Clone, Copy, Default)]
struct Split {
    value: f32,
    tag: u32,
}

const AXIS_MASK: u32 = 3;
const HAS_HULL: u32 = 4;
/// Both children are internal nodes with hulls.
const CHILD_HULLS: u32 = 8;

/// The relative error bound of `u · (p − c)` in float64 for `|u|` ≤ 1 + 2⁻⁴⁰: about
/// 4·2⁻⁵³·Σ|pₖ − cₖ|, doubled and rounded up.
const HULL_ERROR: f64 = 1.0 / (1u64 << 49) as f64;

/// An oriented bounding box of a node's points, kept for the nodes whose cell is a poor bound:
/// flat or thin nodes oblique to the axes (a patch of an oblique plane or line), whose box along
/// their principal axes is much thinner than their cell, and nodes much smaller than their cell
/// (a small cluster far from the rest), with the coordinate axes.
///
/// `axes` are nearly orthonormal; along each, every point `p` of the node satisfies
/// `lo ≤ axis · (p − centre) ≤ hi` exactly (the bounds are widened by the rounding of the
/// float64 products). A query `q` then lies at least `dist(axis · (q − centre), [lo, hi])` from
/// the node along each axis, less the rounding of that product, and the squared distance from `q`
/// to any point is at least the sum of these squares times `shrink`, which bounds
/// 1 / ‖axes‖₂² (so that axes that are not exactly orthonormal still give a lower bound) and
/// takes off [`F64_RELATIVE_ERROR`] for rounding (see [`Hull::lower`]).
#[derive(Clone)]
struct Hull {
    centre: [f64; 3],
    axes: [[f64; 3]; 3],
    lo: [f64; 3],
    hi: [f64; 3],
    shrink: f64,
    /// With the coordinate axes, the box itself, for the exact bound of [`Nearest::may_hold`].
    tight: Option<Bounds>,
}

impl Hull {
    /// Around `entries`, with `axes` (rows, nearly orthonormal).
    fn new(entries: &[Entry], centre: [f64; 3], axes: [[f64; 3]; 3]) -> Self {
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for e in entries {
            let w = [0, 1, 2].map(|d| f64::from(e.point[d]) - centre[d]);
            let err = HULL_ERROR * (w[0].abs() + w[1].abs() + w[2].abs());
            for i in 0..3 {
                let t = dot(&axes[i], &w);
                lo[i] = lo[i].min(t - err);
                hi[i] = hi[i].max(t + err);
            }
        }
        // The centre is the points' mean, so `lo ≤ 0 ≤ hi` up to its rounding; exactly so (see
        // `Hull::lower`).
        let (lo, hi) = (lo.map(|l| l.min(0.0)), hi.map(|h| h.max(0.0)));
        // ‖U‖₂² ≤ ‖U Uᵀ‖∞, each Gram entry computed within a few 2⁻⁵³.
        let gram_row = |i: usize| (0..3).map(move |j| dot(&axes[i], &axes[j]).abs() + 1e-15);
        let norm = (0..3).map(|i| gram_row(i).sum::<f64>()).fold(0.0, f64::max);
        Hull {
            centre,
            axes,
            lo,
            hi,
            shrink: (1.0 - F64_RELATIVE_ERROR) / norm,
            tight: (axes == IDENTITY).then(|| Bounds::of(entries)),
        }
    }

    /// Whether the node may hold a point that comes before `best`, given `lower` =
    /// [`Hull::lower`]`(q64)`.
    #[inline]
    fn admits(&self, best: &Nearest, q: &[f32; 3], q64: &[f64; 3], lower: f64) -> bool {
        best.may_hold(lower)
            && self
                .tight
                .as_ref()
                .is_none_or(|tight| best.may_hold(sq_dist_f64(q64, &tight.closest(q))))
    }

    /// A lower bound on the float64 squared distance ([`sq_dist_f64`]) from `q` to every point
    /// of the node, rounding included.
    ///
    /// Along an axis the exact product lies within `err` / 4 of `t`, so the computed gap is at
    /// most the exact gap less 3/4 of `err` plus the rounding of `lo − t` (or `t − hi`); that is
    /// below 2⁻⁵³·|t| (`lo ≤ 0 ≤ hi`, so where positive it is at most |t|), itself below `err`
    /// / 16; and the subtraction of `err` rounds by a relative 2⁻⁵³. So the computed bound is at
    /// most the exact one times (1 + 2⁻⁵³)⁷ (the gaps, their squares, the sum, `shrink` and its
    /// division), and a point's float64 distance at least its exact one times (1 − 2⁻⁵³)⁵:
    /// `shrink`'s [`F64_RELATIVE_ERROR`] covers both.
    #[inline]
    fn lower(&self, q: &[f64; 3]) -> f64 {
        let w = [0, 1, 2].map(|d| q[d] - self.centre[d]);
        let err = HULL_ERROR * (w[0].abs() + w[1].abs() + w[2].abs());
        let mut sum = 0.0;
        for i in 0..3 {
            let t = dot(&self.axes[i], &w);
            let gap = ((self.lo[i] - t).max(t - self.hi[i]) - err).max(0.0);
            sum += gap * gap;
        }
        sum * self.shrink
    }
}

const IDENTITY: [[f64; 3]; 3] = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];

#[inline]
fn dot(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// The count, mean and scatter matrix (sum of outer products of deviations) of a node's points,
/// merged up the tree.
#[derive(Clone, Copy)]
struct Moments {
    n: f64,
    mean: [f64; 3],
    scatter: [[f64; 3]; 3],
}

impl Moments {
    fn of(entries: &[Entry]) -> Self {
        let n = entries.len() as f64;
        let mut mean = [0.0; 3];
        for e in entries {
            for (m, &c) in mean.iter_mut().zip(&e.point) {
                *m += f64::from(c);
            }
        }
        mean = mean.map(|m| m / n);
        let mut scatter = [[0.0; 3]; 3];
        for e in entries {
            let w = [0, 1, 2].map(|d| f64::from(e.point[d]) - mean[d]);
            for a in 0..3 {
                for b in 0..3 {
                    scatter[a][b] += w[a] * w[b];
                }
            }
        }
        Moments { n, mean, scatter }
    }

    /// Of the union of two disjoint sets (Chan, Golub and LeVeque).
    fn merge(&self, other: &Moments) -> Self {
        let n = self.n + other.n;
        let delta = [0, 1, 2].map(|d| other.mean[d] - self.mean[d]);
        let mean = [0, 1, 2].map(|d| self.mean[d] + delta[d] * (other.n / n));
        let weight = self.n * other.n / n;
        let mut scatter = [[0.0; 3]; 3];
        for a in 0..3 {
            for b in 0..3 {
                scatter[a][b] =
                    self.scatter[a][b] + other.scatter[a][b] + delta[a] * delta[b] * weight;
            }
        }
        Moments { n, mean, scatter }
    }

    /// Whether the points are much thinner along some direction than along every coordinate
    /// axis: some pair of coordinates nearly correlated, or the scatter matrix nearly singular
    /// against its diagonal (Hadamard's inequality makes the ratio at most 1).
    fn oblique_thin(&self) -> bool {
        let s = &self.scatter;
        let pairs = [(0, 1), (0, 2), (1, 2)];
        let correlated = pairs.iter().any(|&(a, b)| {
            s[a][b] * s[a][b] > 0.9 * (s[a][a] * s[b][b]) && s[a][a] * s[b][b] > 0.0
        });
        let diagonal = s[0][0] * s[1][1] * s[2][2];
        let det = s[0][0] * (s[1][1] * s[2][2] - s[1][2] * s[1][2])
            - s[0][1] * (s[0][1] * s[2][2] - s[1][2] * s[0][2])
            + s[0][2] * (s[0][1] * s[1][2] - s[1][1] * s[0][2]);
        correlated || (diagonal > 0.0 && det < 0.1 * diagonal)
    }
}

/// The principal axes of a symmetric 3×3 matrix (cyclic Jacobi), as rows made orthonormal by
/// Gram–Schmidt; the coordinate axes if that fails.
fn principal_axes(mut a: [[f64; 3]; 3]) -> [[f64; 3]; 3] {
    let identity = IDENTITY;
    // Columns of `v` are the eigenvectors.
    let mut v = identity;
    for _ in 0..16 {
        let off = a[0][1] * a[0][1] + a[0][2] * a[0][2] + a[1][2] * a[1][2];
        let diag = a[0][0] * a[0][0] + a[1][1] * a[1][1] + a[2][2] * a[2][2];
        // Also stops on NaN.
        if off.partial_cmp(&(1e-30 * diag)) != Some(std::cmp::Ordering::Greater) {
            break;
        }
        for (p, q) in [(0, 1), (0, 2), (1, 2)] {
            if a[p][q] == 0.0 {
                continue;
            }
            let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
            let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
            let t = if theta == 0.0 { 1.0 } else { t };
            let c = 1.0 / (t * t + 1.0).sqrt();
            let s = t * c;
            for row in &mut a {
                let (akp, akq) = (row[p], row[q]);
                row[p] = c * akp - s * akq;
                row[q] = s * akp + c * akq;
            }
            let (row_p, row_q) = (a[p], a[q]);
            a[p] = [0, 1, 2].map(|k| c * row_p[k] - s * row_q[k]);
            a[q] = [0, 1, 2].map(|k| s * row_p[k] + c * row_q[k]);
            for row in &mut v {
                let (vp, vq) = (row[p], row[q]);
                row[p] = c * vp - s * vq;
                row[q] = s * vp + c * vq;
            }
        }
    }
    let mut axes = [0, 1, 2].map(|i| [v[0][i], v[1][i], v[2][i]]);
    for i in 0..3 {
        for j in 0..i {
            let along = dot(&axes[i], &axes[j]);
            axes[i] = [0, 1, 2].map(|d| axes[i][d] - along * axes[j][d]);
        }
        let norm = dot(&axes[i], &axes[i]).sqrt();
        if norm.partial_cmp(&0.5) != Some(std::cmp::Ordering::Greater) {
            return identity;
        }
        axes[i] = axes[i].map(|x| x / norm);
    }
    axes
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

/// The squared distance in float32, for the leaf scan's prefilter.
#[inline]
fn sq_dist_f32(q: &[f32; 3], r: &[f32; 3]) -> f32 {
    let (dx, dy, dz) = (q[0] - r[0], q[1] - r[1], q[2] - r[2]);
    dx * dx + dy * dy + dz * dz
}

/// The squared distance in float64 from float32 coordinates, `dx*dx + dy*dy + dz*dz` in that
/// order: the distance that ranks the points.
#[inline]
fn sq_dist_f64(q: &[f64; 3], r: &[f32; 3]) -> f64 {
    let (dx, dy, dz) = (
        q[0] - f64::from(r[0]),
        q[1] - f64::from(r[1]),
        q[2] - f64::from(r[2]),
    );
    dx * dx + dy * dy + dz * dz
}

/// The best answer so far of one query.
struct Nearest {
    /// Its float64 squared distance.
    sq_dist: f64,
    item: u32,
    /// [`Nearest::cutoff`] of `sq_dist`.
    cutoff: f32,
}

impl Nearest {
    const NONE: Nearest = Nearest {
        sq_dist: f64::INFINITY,
        item: u32::MAX,
        cutoff: f32::INFINITY,
    };

    /// The largest float32 squared distance `dx*dx + dy*dy + dz*dz` of a point whose float64
    /// one is at most `sq_dist`, so that a leaf scan can skip, in float32, the points that
    /// cannot come first.
    ///
    /// For the exact squared distance D of a point, the float32 distance (five operations, each
    /// rounded by a relative 2⁻²⁴, a square also by an absolute 2⁻¹⁵⁰ when it underflows;
    /// differences and sums that underflow are exact) is at most D·(1 + 2⁻²⁴)⁵ + 2⁻¹⁴⁸, and the
    /// float64 distance (no underflow: squares of float32 differences are above 2⁻²⁹⁸) at least
    /// D·(1 − 2⁻⁵³)⁵. A point at float64 distance at most `sq_dist` thus has a float32 distance
    /// at most `sq_dist`·(1 + 5.1·2⁻²⁴) + 2⁻¹⁴⁸. The cutoff, `sq_dist`·(1 + 2⁻²⁰) + 2⁻¹⁴⁶
    /// rounded to float64 and then to float32 (a relative 2⁻²⁴, or an absolute 2⁻¹⁵⁰ among
    /// subnormals), stays above that. Coordinates are within ±1e18
    /// ([`crate::error::MAX_COORDINATE`]), so no distance overflows; with no answer yet the
    /// cutoff is infinite.
    #[inline]
    fn cutoff(sq_dist: f64) -> f32 {
        (sq_dist * (1.0 + PREFILTER_RELATIVE) + PREFILTER_UNDERFLOW) as f32
    }

    /// Whether a node all of whose points are at least `lower` from the query (float64 squared
    /// distance) may hold a point that comes before the best so far (an equal distance may come
    /// first by its item).
    ///
    /// For a box, the float64 distance of its point closest to the query is an exact `lower`:
    /// the float64 distance of a point only grows with each |q − r| (every rounded operation is
    /// monotonic and symmetric), so no point of the box has a smaller one. An exact bound
    /// matters when a query is far from a small node and its points' distances differ only in
    /// the last bits. For a hull, [`Hull::lower`].
    #[inline]
    fn may_hold(&self, lower: f64) -> bool {
        lower <= self.sq_dist
    }

    /// Take the point `r` of `item` if it comes first.
    #[inline]
    fn offer(&mut self, q: &[f64; 3], r: &[f32; 3], item: u32) {
        let d = sq_dist_f64(q, r);
        if (d, item) < (self.sq_dist, self.item) {
            *self = Nearest {
                sq_dist: d,
                item,
                cutoff: Self::cutoff(d),
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
    /// By internal node, its hull if its `Split` has [`HAS_HULL`].
    hulls: Vec<Option<Box<Hull>>>,
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
        let mut hulls: Vec<Option<Box<Hull>>> = vec![None; splits.len()];
        let mut leaves = vec![Leaf::default(); 1usize << levels];
        let mut nodes = Nodes {
            splits: &mut splits,
            hulls: &mut hulls,
            leaves: &mut leaves,
        };
        build(&mut entries, &mut nodes, bounds, parallel);
        KdTree {
            bounds,
            splits,
            hulls,
            leaves,
        }
    }

    /// The float32 squared distance to, and item of, the first point of `q` in the order of the
    /// module documentation.
    #[inline]
    pub fn nearest(&self, q: &[f32; 3]) -> (f32, u32) {
        let mut best = Nearest::NONE;
        let q64 = q.map(f64::from);
        let closest = self.bounds.closest(q);
        self.search(0, self.splits.len(), 0, q, &q64, closest, false, &mut best);
        // Below 1.2e37 (MAX_COORDINATE): no overflow.
        (best.sq_dist as f32, best.item)
    }

    /// Search the subtree at internal node `node` (`span` internal nodes; none for a leaf) whose
    /// leaves start at `leaf`, the query's side first. `closest` is the point of the subtree's
    /// cell closest to the query; the caller has checked that cell against `best`, and the
    /// node's hull too if `hull_checked`.
    #[allow(clippy::too_many_arguments)]
    fn search(
        &self,
        node: usize,
        span: usize,
        leaf: usize,
        q: &[f32; 3],
        q64: &[f64; 3],
        closest: [f32; 3],
        hull_checked: bool,
        best: &mut Nearest,
    ) {
        if span == 0 {
            self.scan(&self.leaves[leaf], q, q64, best);
            return;
        }
        let Split { value, tag } = self.splits[node];
        if tag & (HAS_HULL | CHILD_HULLS) != 0 {
            let split = Split { value, tag };
            self.search_hulls(node, span, leaf, q, q64, closest, hull_checked, split, best);
            return;
        }
        let axis = (tag & AXIS_MASK) as usize;
        let half = span / 2;
        let left = (node + 1, leaf);
        let right = (node + 1 + half, leaf + half + 1);
        let (near, far) = if q[axis] < value {
            (left, right)
        } else {
            (right, left)
        };
        self.search(near.0, half, near.1, q, q64, closest, false, best);
        // The near child's cell has the same point closest to the query as this one; the far
        // child's has `value` along `axis`.
        let mut far_closest = closest;
        far_closest[axis] = value;
        if best.may_hold(sq_dist_f64(q64, &far_closest)) {
            self.search(far.0, half, far.1, q, q64, far_closest, false, best);
        }
    }

    /// [`Self::search`] at a node with a hull or whose children have hulls (out of line, to keep
    /// the common path small): check the node's hull unless `hull_checked`, and visit the
    /// child with the nearer hull first when both have one.
    #[allow(clippy::too_many_arguments)]
    #[inline(never)]
    fn search_hulls(
        &self,
        node: usize,
        span: usize,
        leaf: usize,
        q: &[f32; 3],
        q64: &[f64; 3],
        closest: [f32; 3],
        hull_checked: bool,
        Split { value, tag }: Split,
        best: &mut Nearest,
    ) {
        if tag & HAS_HULL != 0 && !hull_checked {
            if let Some(hull) = &self.hulls[node] {
                if !hull.admits(best, q, q64, hull.lower(q64)) {
                    return;
                }
            }
        }
        let axis = (tag & AXIS_MASK) as usize;
        let half = span / 2;
        let left = (node + 1, leaf);
        let right = (node + 1 + half, leaf + half + 1);
        let (near, far) = if q[axis] < value {
            (left, right)
        } else {
            (right, left)
        };
        let mut far_closest = closest;
        far_closest[axis] = value;
        if tag & CHILD_HULLS != 0 {
            if let (Some(near_hull), Some(far_hull)) = (&self.hulls[near.0], &self.hulls[far.0]) {
                // On an oblique line or plane the query's side of the split may lie far from its
                // nearest points.
                let near_lower = near_hull.lower(q64);
                let far_lower = far_hull.lower(q64);
                let mut order = [
                    (near, closest, near_hull, near_lower),
                    (far, far_closest, far_hull, far_lower),
                ];
                if far_lower.max(sq_dist_f64(q64, &far_closest)) < near_lower {
                    order.swap(0, 1);
                }
                for ((child, child_leaf), child_closest, hull, lower) in order {
                    if best.may_hold(sq_dist_f64(q64, &child_closest))
                        && hull.admits(best, q, q64, lower)
                    {
                        self.search(child, half, child_leaf, q, q64, child_closest, true, best);
                    }
                }
                return;
            }
        }
        self.search(near.0, half, near.1, q, q64, closest, false, best);
        if best.may_hold(sq_dist_f64(q64, &far_closest)) {
            self.search(far.0, half, far.1, q, q64, far_closest, false, best);
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

    /// Offer `best` the points of `leaf`: their float32 distances, computed together, skip
    /// those that cannot come first ([`Nearest::cutoff`]); the others are ranked in float64.
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
            any |= dk <= best.cutoff;
        }
        if any {
            for k in 0..LEAF_SIZE {
                if d[k] <= best.cutoff {
                    best.offer(q64, &[xs[k], ys[k], zs[k]], leaf.items[k]);
                }
            }
        }
    }
}

/// The parts of a subtree: its internal nodes and their hulls in pre-order, and its leaves.
struct Nodes<'a> {
    splits: &'a mut [Split],
    hulls: &'a mut [Option<Box<Hull>>],
    leaves: &'a mut [Leaf],
}

impl Nodes<'_> {
    /// This node's split and hull, and the left and right subtrees.
    #[allow(clippy::type_complexity)]
    fn split(&mut self) -> (&mut Split, &mut Option<Box<Hull>>, Nodes<'_>, Nodes<'_>) {
        let half = self.splits.len() / 2;
        let (split, splits) = self.splits.split_first_mut().expect("an internal node");
        let (hull, hulls) = self.hulls.split_first_mut().expect("an internal node");
        let (left_splits, right_splits) = splits.split_at_mut(half);
        let (left_hulls, right_hulls) = hulls.split_at_mut(half);
        let (left_leaves, right_leaves) = self.leaves.split_at_mut(half + 1);
        (
            split,
            hull,
            Nodes {
                splits: left_splits,
                hulls: left_hulls,
                leaves: left_leaves,
            },
            Nodes {
                splits: right_splits,
                hulls: right_hulls,
                leaves: right_leaves,
            },
        )
    }
}

/// Order `entries` as the subtree over them, filling its internal nodes (pre-order), their
/// hulls and its leaves; `cell` is the subtree's cell. Returns the moments of its points.
fn build(entries: &mut [Entry], nodes: &mut Nodes, cell: Bounds, parallel: bool) -> Moments {
    if nodes.splits.is_empty() {
        let leaf = &mut nodes.leaves[0];
        for (k, e) in entries.iter().enumerate() {
            for d in 0..3 {
                leaf.coords[d][k] = e.point[d];
            }
            leaf.items[k] = e.item;
        }
        return Moments::of(entries);
    }
    let tight = Bounds::of(entries);
    let axis = tight.widest();
    let split_here = parallel && entries.len() >= PARALLEL_MIN_BUILD;
    let mid = entries.len() / 2;
    entries.select_nth_unstable_by(mid, |a, b| a.point[axis].total_cmp(&b.point[axis]));
    let value = entries[mid].point[axis];
    let (mut left_cell, mut right_cell) = (cell, cell);
    left_cell.hi[axis] = value;
    right_cell.lo[axis] = value;
    let (split, hull, mut left_nodes, mut right_nodes) = nodes.split();
    let (left, right) = entries.split_at_mut(mid);
    let (l, r) = if split_here {
        rayon::join(
            || build(left, &mut left_nodes, left_cell, parallel),
            || build(right, &mut right_nodes, right_cell, parallel),
        )
    } else {
        (
            build(left, &mut left_nodes, left_cell, false),
            build(right, &mut right_nodes, right_cell, false),
        )
    };
    let moments = l.merge(&r);
    let axes = if moments.oblique_thin() {
        Some(principal_axes(moments.scatter))
    } else if loose(&cell, &tight) {
        Some(IDENTITY)
    } else {
        None
    };
    let has_hull = |nodes: &Nodes| nodes.hulls.first().is_some_and(Option::is_some);
    let child_hulls = has_hull(&left_nodes) && has_hull(&right_nodes);
    *split = Split {
        value,
        tag: axis as u32
            | if axes.is_some() { HAS_HULL } else { 0 }
            | if child_hulls { CHILD_HULLS } else { 0 },
    };
    *hull = axes.map(|axes| Box::new(Hull::new(entries, moments.mean, axes)));
    moments
}

/// Whether the tight box of a node's points leaves a quarter of its cell's largest extent empty
/// along some axis (a small cluster far from the rest; on spread clouds, almost never).
fn loose(cell: &Bounds, tight: &Bounds) -> bool {
    let extent = |b: &Bounds, d: usize| f64::from(b.hi[d]) - f64::from(b.lo[d]);
    let largest = (0..3).map(|d| extent(cell, d)).fold(0.0, f64::max);
    (0..3).any(|d| extent(cell, d) - extent(tight, d) > 0.25 * largest)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{rngs::StdRng, Rng, SeedableRng};

    #[test]
    fn hulls_bound_the_distance_to_their_points_from_below() {
        let mut rng = StdRng::seed_from_u64(3);
        for scale in [1e-30f32, 1e-3, 1.0, 1e6, 1e17] {
            let direction: [f32; 3] = [0, 1, 2].map(|_| rng.gen_range(-1.0..1.0));
            let entries: Vec<Entry> = (0..64)
                .map(|i| {
                    let (t, s) = (rng.gen_range(-1.0f32..1.0), rng.gen_range(-1.0f32..1.0));
                    let point = [0, 1, 2]
                        .map(|d| scale * (t * direction[d] + 1e-3 * s * (d as f32 - 1.0) + 0.5));
                    Entry { point, item: i }
                })
                .collect();
            let moments = Moments::of(&entries);
            for axes in [principal_axes(moments.scatter), IDENTITY] {
                let hull = Hull::new(&entries, moments.mean, axes);
                for _ in 0..200 {
                    let q = [0, 1, 2].map(|_| scale * rng.gen_range(-2.0f32..3.0));
                    let q64 = q.map(f64::from);
                    let nearest = entries
                        .iter()
                        .map(|e| sq_dist_f64(&q64, &e.point))
                        .fold(f64::INFINITY, f64::min);
                    assert!(hull.lower(&q64) <= nearest, "scale {scale}");
                }
            }
        }
    }

    #[test]
    fn oblique_lines_and_planes_get_oriented_hulls_and_spread_clouds_almost_none() {
        let mut rng = StdRng::seed_from_u64(4);
        let n = 20_000;
        let build = |points: Vec<[f32; 3]>| {
            let entries = points
                .into_iter()
                .enumerate()
                .map(|(i, point)| Entry {
                    point,
                    item: i as u32,
                })
                .collect();
            let tree = KdTree::new(entries, false);
            tree.hulls.iter().filter(|h| h.is_some()).count() as f64 / tree.hulls.len() as f64
        };
        let plane = (0..n)
            .map(|_| {
                let (a, b) = (rng.gen_range(0.0f32..1.0), rng.gen_range(0.0f32..1.0));
                [a, b, 1.0 - a - b]
            })
            .collect();
        let spread = (0..n)
            .map(|_| [0, 1, 2].map(|_| rng.gen_range(0.0f32..1.0)))
            .collect();
        assert!(build(plane) > 0.99);
        let spread = build(spread);
        assert!(spread < 0.05, "{spread}");
    }
}
