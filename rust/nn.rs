//! Exact nearest neighbours with a KD-tree of our own ([`crate::kdtree`]), which stays fast on
//! collinear and planar clouds, far queries and clouds too small or too spread for float32.

use std::collections::hash_map::{Entry, HashMap};
use std::hash::{BuildHasherDefault, Hasher};
use std::marker::PhantomData;
use std::ops::Range;

use rayon::prelude::*;

use crate::error::{check_finite, check_point_count, Result};
use crate::kdtree::{self, KdTree};

/// Below this many queries a single thread answers faster than a split across the pool.
const PARALLEL_MIN_QUERIES: usize = 4096;

/// A KD-tree over a reference cloud, answering nearest-one queries.
///
/// The answer is the reference point with the smallest float64 squared distance from the float32
/// coordinates, `dx*dx + dy*dy + dz*dz`; among equal ones the lowest index. The tree holds each
/// distinct point once: copies of one point all tie, so a cloud of 100,000 of them made every
/// query scan them all (17 s for 100k identical points against 9 ms for 40k random ones).
/// Duplicates map back to their lowest index.
pub struct NearestNeighborIndex<'a> {
    tree: KdTree,
    /// With duplicates: by reference index, how many copies the point has there (its first).
    copies: Option<Vec<u32>>,
    /// The index may borrow the reference cloud again in the future; callers already keep it.
    reference: PhantomData<&'a [[f32; 3]]>,
}

/// A fast, deterministic hasher for the bit patterns of coordinates (std's SipHash is several
/// times slower here and its DoS resistance buys nothing for points).
#[derive(Default)]
struct PointHasher(u64);

impl Hasher for PointHasher {
    fn finish(&self) -> u64 {
        self.0
    }
    fn write(&mut self, bytes: &[u8]) {
        // A key's three coordinates arrive as one 12-byte slice: hash them a word at a time.
        for word in bytes.chunks(4) {
            let mut padded = [0; 4];
            padded[..word.len()].copy_from_slice(word);
            self.write_u32(u32::from_le_bytes(padded));
        }
    }
    fn write_usize(&mut self, _length: usize) {
        // Only the length prefix of the fixed-size key arrives here; it tells nothing.
    }
    fn write_u32(&mut self, value: u32) {
        self.0 = (self.0.rotate_left(5) ^ u64::from(value)).wrapping_mul(0x51_7c_c1_b7_27_22_0a_95);
    }
}

/// The distinct points of `reference`, as points and the first index of each, and by index
/// of a first copy, the number of copies; or `None` if all differ.
fn distinct_points(reference: &[[f32; 3]]) -> Option<Distinct> {
    // +0.0 turns -0.0 into 0.0, so equal coordinates have equal bits.
    let key = |p: &[f32; 3]| p.map(|c| (c + 0.0).to_bits());
    let mut first: HashMap<[u32; 3], u32, BuildHasherDefault<PointHasher>> =
        HashMap::with_capacity_and_hasher(reference.len(), BuildHasherDefault::default());
    let mut points = Vec::new();
    let mut original = Vec::new();
    // Made at the first duplicate; only the entries of first copies are ever read.
    let mut copies: Option<Vec<u32>> = None;
    for (i, p) in reference.iter().enumerate() {
        match first.entry(key(p)) {
            Entry::Vacant(slot) => {
                slot.insert(i as u32);
                points.push(*p);
                original.push(i as u32);
            }
            Entry::Occupied(slot) => {
                copies.get_or_insert_with(|| vec![1; reference.len()])[*slot.get() as usize] += 1;
            }
        }
    }
    copies.map(|copies| (points, original, copies))
}

type Distinct = (Vec<[f32; 3]>, Vec<u32>, Vec<u32>);

impl<'a> NearestNeighborIndex<'a> {
    /// Build the tree; `reference` must be non-empty, finite and hold at most
    /// [`MAX_POINTS`](crate::error::MAX_POINTS) points, as [`nearest_neighbors`] checks (indices
    /// are `u32`).
    pub fn new(reference: &'a [[f32; 3]]) -> Self {
        let (entries, copies) = match distinct_points(reference) {
            None => (
                reference
                    .iter()
                    .enumerate()
                    .map(|(i, &point)| kdtree::Entry {
                        point,
                        item: i as u32,
                    })
                    .collect(),
                None,
            ),
            Some((points, original, copies)) => (
                points
                    .into_iter()
                    .zip(original)
                    .map(|(point, item)| kdtree::Entry { point, item })
                    .collect(),
                Some(copies),
            ),
        };
        NearestNeighborIndex {
            tree: KdTree::new(entries, crate::parallel_allowed()),
            copies,
            reference: PhantomData,
        }
    }

    /// Squared distance to, and index of, the nearest reference point of `q`. The distance is
    /// `dx*dx + dy*dy + dz*dz` in float64, in that order, rounded to float32, so every caller
    /// sees the same value.
    #[inline]
    pub fn nearest(&self, q: &[f32; 3]) -> (f32, u32) {
        self.tree.nearest(q)
    }

    /// How many leaves the tree has; [`Self::points`] takes a range of them.
    pub fn leaf_count(&self) -> usize {
        self.tree.leaf_count()
    }

    /// The distinct reference points in `leaves`, in the tree's order (neighbours in space come
    /// together, so answering them one after another keeps another tree's leaves in cache), each
    /// with its number of copies in the reference cloud.
    pub fn points(&self, leaves: Range<usize>) -> impl Iterator<Item = ([f32; 3], u32)> + '_ {
        self.tree.points(leaves).map(|(point, item)| {
            let copies = self.copies.as_ref().map_or(1, |c| c[item as usize]);
            (point, copies)
        })
    }

    /// Answer every query into `sq_dist`/`index`; in parallel when `parallel` and there are many.
    pub fn query_into(
        &self,
        queries: &[[f32; 3]],
        sq_dist: &mut [f32],
        index: &mut [u32],
        parallel: bool,
    ) {
        let answer = |(q, (d, i)): (&[f32; 3], (&mut f32, &mut u32))| {
            (*d, *i) = self.nearest(q);
        };
        if parallel && queries.len() >= PARALLEL_MIN_QUERIES && crate::parallel_allowed() {
            let chunk = 1024;
            queries
                .par_chunks(chunk)
                .zip(
                    sq_dist
                        .par_chunks_mut(chunk)
                        .zip(index.par_chunks_mut(chunk)),
                )
                .for_each(|(q, (d, i))| {
                    q.iter()
                        .zip(d.iter_mut().zip(i.iter_mut()))
                        .for_each(answer)
                });
        } else {
            queries
                .iter()
                .zip(sq_dist.iter_mut().zip(index.iter_mut()))
                .for_each(answer);
        }
    }
}

/// Check a (query, reference) pair of clouds for emptiness, more than
/// [`MAX_POINTS`](crate::error::MAX_POINTS) points and non-finite values.
pub(crate) fn validate_pair(
    query_arg: &'static str,
    query: &[[f32; 3]],
    reference_arg: &'static str,
    reference: &[[f32; 3]],
    batch: usize,
) -> Result<()> {
    check_point_count(query_arg, query.len())?;
    check_point_count(reference_arg, reference.len())?;
    check_finite(query_arg, batch, query)?;
    check_finite(reference_arg, batch, reference)
}

/// For every query point, the squared distance to and index of its nearest reference point.
/// Each cloud may hold at most [`MAX_POINTS`](crate::error::MAX_POINTS) points.
pub fn nearest_neighbors(
    query: &[[f32; 3]],
    reference: &[[f32; 3]],
) -> Result<(Vec<f32>, Vec<u32>)> {
    validate_pair("query", query, "reference", reference, 0)?;
    let mut sq_dist = vec![0.0; query.len()];
    let mut index = vec![0; query.len()];
    NearestNeighborIndex::new(reference).query_into(query, &mut sq_dist, &mut index, true);
    Ok((sq_dist, index))
}

/// Brute-force reference, in the index's order: the smallest float64 squared distance from the
/// float32 coordinates (`dx*dx + dy*dy + dz*dz`), the lowest index among equal ones; the
/// distance rounded to float32. Used by tests.
pub fn nearest_neighbors_naive(query: &[[f32; 3]], reference: &[[f32; 3]]) -> (Vec<f32>, Vec<u32>) {
    query
        .iter()
        .map(|q| {
            let mut best = (f64::INFINITY, 0u32);
            for (i, r) in reference.iter().enumerate() {
                let [dx, dy, dz] = [0, 1, 2].map(|d| f64::from(q[d]) - f64::from(r[d]));
                let d = dx * dx + dy * dy + dz * dz;
                if d < best.0 {
                    best = (d, i as u32);
                }
            }
            (best.0 as f32, best.1)
        })
        .unzip()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::error::GeometryError;
    use rand::{rngs::StdRng, Rng, SeedableRng};

    fn cloud(n: usize, seed: u64, grid: bool) -> Vec<[f32; 3]> {
        let mut rng = StdRng::seed_from_u64(seed);
        (0..n)
            .map(|_| {
                if grid {
                    [0, 1, 2].map(|_| rng.gen_range(0..4) as f32)
                } else {
                    [0, 1, 2].map(|_| rng.gen_range(-1.0f32..1.0))
                }
            })
            .collect()
    }

    #[test]
    fn matches_brute_force_distances() {
        for (nq, nr, grid) in [
            (1, 1, false),
            (500, 3000, false),
            (6000, 700, false),
            (900, 900, true),
        ] {
            let (q, r) = (cloud(nq, 1, grid), cloud(nr, 2, grid));
            let (d, i) = nearest_neighbors(&q, &r).unwrap();
            let (dn, i_naive) = nearest_neighbors_naive(&q, &r);
            assert_eq!((&d, &i), (&dn, &i_naive), "nq={nq} nr={nr} grid={grid}");
            for (k, qq) in q.iter().enumerate() {
                let rr = r[i[k] as usize];
                let [dx, dy, dz] = [0, 1, 2].map(|a| f64::from(qq[a]) - f64::from(rr[a]));
                assert_eq!((dx * dx + dy * dy + dz * dz) as f32, d[k]);
            }
        }
    }

    #[test]
    fn duplicates_are_answered_with_their_lowest_index() {
        let mut r = vec![[0.5f32, 0.5, 0.5]; 5000];
        r.extend(cloud(300, 3, false));
        r.extend(vec![[-0.0f32, 0.25, 1.0]; 4000]);
        r.push([0.0, 0.25, 1.0]); // equal to the -0.0 copies
        let q = cloud(700, 4, false);
        let (d, i) = nearest_neighbors(&q, &r).unwrap();
        let (dn, i_naive) = nearest_neighbors_naive(&q, &r);
        assert_eq!((&d, &i), (&dn, &i_naive));
        for &index in &i {
            // a point with copies is always named by its first copy
            let first = r.iter().position(|p| *p == r[index as usize]).unwrap();
            assert_eq!(index as usize, first);
        }
        let all_same = vec![[1.0f32, 2.0, 3.0]; 100_000];
        let (d, i) = nearest_neighbors(&all_same, &all_same).unwrap();
        assert!(d.iter().all(|&x| x == 0.0) && i.iter().all(|&x| x == 0));
    }

    type Cloud = Vec<[f32; 3]>;

    /// Degenerate layouts that made kiddo's tree quadratic (issue 14), and the oblique lines and
    /// planes and far tiny clusters on which cells alone pruned too little (audit 9, G2): name,
    /// reference, queries.
    fn degenerate_layouts(n: usize) -> Vec<(&'static str, Cloud, Cloud)> {
        let random = cloud(n, 5, false);
        let t: Vec<f32> = (0..n).map(|i| i as f32 / n as f32).collect();
        let collinear: Vec<[f32; 3]> = t.iter().map(|&x| [x, 0.0, 0.0]).collect();
        let diagonal: Vec<[f32; 3]> = t.iter().map(|&x| [x, 2.0 * x, -0.5 * x]).collect();
        let planar: Vec<[f32; 3]> = random.iter().map(|p| [p[0], p[1], 0.25]).collect();
        let scaled =
            |s: f32| -> Vec<[f32; 3]> { random.iter().map(|p| p.map(|c| c * s)).collect() };
        let far = random.iter().map(|p| p.map(|c| c + 100.0)).collect();
        let mut subnormal_and_huge = scaled(1e-40);
        subnormal_and_huge[n / 2] = [1e17, 0.0, 0.0];
        let mut mixed = scaled(1e-30);
        mixed.extend(scaled(1e17).into_iter().take(n / 4));
        let shifted = |c: &[[f32; 3]], by: f32| -> Vec<[f32; 3]> {
            c.iter().map(|p| p.map(|v| v + by)).collect()
        };
        let cube = cloud(n, 12, false);
        let x_eq_y_eq_z: Vec<[f32; 3]> = t.iter().map(|&x| [x, x, x]).collect();
        let noisy_diagonal = cloud(n, 13, false)
            .iter()
            .zip(&t)
            .map(|(p, &x)| p.map(|c| x + 0.01 * c))
            .collect();
        let oblique_plane: Vec<[f32; 3]> = random
            .iter()
            .map(|p| [p[0], p[1], 1.0 - p[0] - p[1]])
            .collect();
        let tilted_plane: Vec<[f32; 3]> = random
            .iter()
            .map(|p| [p[0], p[1], 0.3 * p[0] + 0.7 * p[1]])
            .collect();
        let far_clusters: Vec<[f32; 3]> = random
            .iter()
            .enumerate()
            .map(|(i, p)| p.map(|c| c * 1e-6 + if i % 2 == 0 { 0.0 } else { 1.0 }))
            .collect();
        let clusters_far_apart: Vec<[f32; 3]> = random
            .iter()
            .enumerate()
            .map(|(i, p)| p.map(|c| c * 1e-6 + if i % 2 == 0 { 0.0 } else { 1e6 }))
            .collect();
        let far_cube = cube.iter().map(|p| p.map(|c| (c + 1.0) * 5e5)).collect();
        // K1: queries far above a tilted plane or away from a tilted line, where every point
        // near the query's foot ties in float32 (each height in turn; negative ones below).
        let unit = |v: [f32; 3]| v.map(|c| c / (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt());
        let normal = unit([0.3, 0.7, -1.0]);
        let far_above_plane = |heights: &[f32]| -> Cloud {
            cloud(n, 14, false)
                .iter()
                .enumerate()
                .map(|(i, p)| {
                    let foot = [p[0], p[1], 0.3 * p[0] + 0.7 * p[1]];
                    let h = heights[i % heights.len()];
                    [0, 1, 2].map(|d| foot[d] + h * normal[d])
                })
                .collect()
        };
        let direction = unit([1.0, 0.6, 0.3]);
        let tilted_line: Vec<[f32; 3]> = t.iter().map(|&x| direction.map(|c| x * c)).collect();
        let far_from_line = |heights: &[f32]| -> Cloud {
            cloud(n, 15, false)
                .iter()
                .enumerate()
                .map(|(i, p)| {
                    // p less its part along the line, as a unit vector: a direction across it
                    let along = p[0] * direction[0] + p[1] * direction[1] + p[2] * direction[2];
                    let across = unit([0, 1, 2].map(|d| p[d] - along * direction[d]));
                    let foot = 0.5 * (p[0] + 1.0);
                    let h = heights[i % heights.len()];
                    [0, 1, 2].map(|d| foot * direction[d] + h * across[d])
                })
                .collect()
        };
        let mixed_heights = [1.0, 1e3, -1e5, 30.0, 1e5, -1e3];
        let k1 = [
            (
                "tilted plane, queries 1e3 above",
                "tilted line, queries 1e3 away",
                &[1e3][..],
            ),
            (
                "tilted plane, queries 1e5 above",
                "tilted line, queries 1e5 away",
                &[1e5][..],
            ),
            (
                "tilted plane, queries 1 to 1e5 above and below",
                "tilted line, queries 1 to 1e5 away",
                &mixed_heights[..],
            ),
        ];
        let mut layouts = Vec::new();
        for (plane_name, line_name, heights) in k1 {
            layouts.push((plane_name, tilted_plane.clone(), far_above_plane(heights)));
            layouts.push((line_name, tilted_line.clone(), far_from_line(heights)));
        }
        layouts.extend([
            (
                "oblique line, noisy queries",
                x_eq_y_eq_z.clone(),
                noisy_diagonal,
            ),
            ("oblique line, queries in a cube", x_eq_y_eq_z, cube.clone()),
            (
                "oblique plane, queries in a cube",
                oblique_plane.clone(),
                cube.clone(),
            ),
            (
                "oblique plane, queries on it",
                oblique_plane.clone(),
                oblique_plane,
            ),
            (
                "tilted plane, queries in a cube",
                tilted_plane,
                cube.clone(),
            ),
            ("far tiny clusters, queries in a cube", far_clusters, cube),
            (
                "tiny clusters 1e6 apart, queries between",
                clusters_far_apart,
                far_cube,
            ),
            ("collinear", collinear.clone(), collinear.clone()),
            (
                "collinear, queries off the line",
                collinear.clone(),
                cloud(n, 6, false),
            ),
            ("diagonal", diagonal.clone(), shifted(&diagonal, 1e-3)),
            ("planar", planar.clone(), planar.clone()),
            ("far queries", random.clone(), far),
            ("underflowing squares", scaled(1e-25), scaled(1e-25)),
            (
                "underflowing, other queries",
                scaled(1e-25),
                cloud(n, 7, false)
                    .iter()
                    .map(|p| p.map(|c| c * 1e-25))
                    .collect(),
            ),
            (
                "subnormal cluster and a huge point",
                subnormal_and_huge.clone(),
                subnormal_and_huge,
            ),
            ("tiny and huge", mixed.clone(), shifted(&mixed, 1e-30)),
            (
                "grid with ties",
                cloud(n, 8, true),
                shifted(&cloud(n, 9, true), 0.5),
            ),
        ]);
        layouts
    }

    #[test]
    fn degenerate_layouts_match_brute_force() {
        for (name, reference, query) in degenerate_layouts(2000) {
            let answer = nearest_neighbors(&query, &reference).unwrap();
            assert_eq!(
                answer,
                nearest_neighbors_naive(&query, &reference),
                "{name}"
            );
        }
    }

    #[test]
    fn random_clouds_match_brute_force() {
        let (q, r) = (cloud(3000, 10, false), cloud(5000, 11, false));
        let answer = nearest_neighbors(&q, &r).unwrap();
        assert_eq!(answer, nearest_neighbors_naive(&q, &r));
    }

    #[test]
    fn a_cloud_far_too_small_for_float32_squares_answers_each_point_with_itself() {
        // Every float32 distance is 0, so the float64 distance decides: each point is its own
        // nearest, as scipy answers in float64.
        let tiny: Vec<[f32; 3]> = cloud(50_000, 12, false)
            .iter()
            .map(|p| p.map(|c| c * 1e-25))
            .collect();
        let (d, i) = nearest_neighbors(&tiny, &tiny).unwrap();
        assert!(d.iter().all(|&x| x == 0.0));
        assert!(i.iter().enumerate().all(|(k, &x)| x as usize == k));
    }

    #[test]
    fn rejects_empty_and_non_finite() {
        let r = cloud(5, 0, false);
        assert_eq!(
            nearest_neighbors(&[], &r).unwrap_err(),
            GeometryError::Empty { arg: "query" }
        );
        assert_eq!(
            nearest_neighbors(&r, &[]).unwrap_err(),
            GeometryError::Empty { arg: "reference" }
        );
        let mut bad = r.clone();
        bad[2][0] = f32::INFINITY;
        assert!(nearest_neighbors(&r, &bad)
            .unwrap_err()
            .to_string()
            .contains("reference"));
    }
}
