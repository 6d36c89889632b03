//! Viewpoint cropping: the partial clouds of PF-Net's training and test protocol.
//!
//! A crop removes the points nearest a viewpoint (the authors' five centres are
//! [`VIEWPOINTS`]), either a fixed number of them or all within a radius. Distances are computed
//! in float64 from the input coordinates; ties go to the lowest index. Both outputs keep the
//! input's relative point order. A cloud may hold at most [`MAX_POINTS`](crate::error::MAX_POINTS)
//! points (candidate lists and histogram counts are `u32`); every public function here checks it.

use crate::error::{check_finite, check_point_count, GeometryError, Result, MAX_COORDINATE};

/// The authors' five crop centres (PF-Net code, `choice` in `Train_PFNet.py`).
pub const VIEWPOINTS: [[f64; 3]; 5] = [
    [1.0, 0.0, 0.0],
    [0.0, 0.0, 1.0],
    [1.0, 0.0, 1.0],
    [-1.0, 0.0, 0.0],
    [-1.0, 1.0, 0.0],
];

/// How a crop chooses the points to remove.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum CropSize {
    /// The `n` points nearest the viewpoint.
    Count(usize),
    /// Every point within this Euclidean distance of the viewpoint.
    Radius(f64),
}

#[inline(always)]
fn sq_dist_f64<T: Copy + Into<f64>>(p: &[T; 3], v: &[f64; 3]) -> f64 {
    let dx = p[0].into() - v[0];
    let dy = p[1].into() - v[1];
    let dz = p[2].into() - v[2];
    dx * dx + dy * dy + dz * dz
}

fn check_viewpoint(viewpoint: &[f64; 3]) -> Result<()> {
    if viewpoint.iter().all(|c| c.is_finite()) {
        Ok(())
    } else {
        Err(GeometryError::out_of_range(
            "viewpoint",
            format!("must be finite, got {viewpoint:?}"),
        ))
    }
}

pub(crate) fn check_count(n_missing: usize, n: usize) -> Result<()> {
    if n_missing >= n {
        return Err(GeometryError::out_of_range(
            "n_missing",
            format!("must be smaller than the number of points ({n}), got {n_missing}"),
        ));
    }
    Ok(())
}

/// `true` for every point the crop removes. Validates its input.
pub fn crop_mask<T: Copy + Into<f64>>(
    points: &[[T; 3]],
    viewpoint: [f64; 3],
    size: CropSize,
) -> Result<Vec<bool>> {
    check_point_count("points", points.len())?;
    check_viewpoint(&viewpoint)?;
    match size {
        CropSize::Count(n_missing) => {
            check_count(n_missing, points.len())?;
            let mut mask = vec![false; points.len()];
            let keys = cloud_keys(points, viewpoint)?;
            mark_nearest(&keys, None, n_missing, &mut mask);
            Ok(mask)
        }
        CropSize::Radius(radius) => {
            // The count path checks coordinates as it computes its keys; this one must too
            // (it once returned NaN points in the partial cloud).
            check_finite("points", 0, points)?;
            if !(radius.is_finite() && radius >= 0.0) {
                return Err(GeometryError::out_of_range(
                    "radius",
                    format!("must be a finite non-negative number, got {radius}"),
                ));
            }
            let r2 = radius * radius;
            Ok(points
                .iter()
                .map(|p| sq_dist_f64(p, &viewpoint) <= r2)
                .collect())
        }
    }
}

/// Sortable keys of the squared distances to `viewpoint` (finite distances are >= +0, so their
/// bit patterns order like the values), computed in one pass with their minimum and maximum.
/// `None` if a distance is not finite or a coordinate is beyond [`MAX_COORDINATE`] (the caller
/// then names the offending point).
struct DistanceKeys {
    keys: Vec<u64>,
    lo: u64,
    hi: u64,
}

thread_local! {
    /// A per-thread key buffer reused across crops: a fresh 16k-point buffer is large enough
    /// for the allocator to map new pages on every call, and the page faults cost as much as
    /// the whole selection.
    static KEY_BUFFER: std::cell::RefCell<Vec<u64>> = const { std::cell::RefCell::new(Vec::new()) };
}

impl Drop for DistanceKeys {
    fn drop(&mut self) {
        let keys = std::mem::take(&mut self.keys);
        KEY_BUFFER.with(|b| {
            let mut b = b.borrow_mut();
            if keys.capacity() > b.capacity() {
                *b = keys;
            }
        });
    }
}

fn distance_keys<'a, T: Copy + Into<f64> + 'a>(
    points: impl Iterator<Item = &'a [T; 3]>,
    viewpoint: [f64; 3],
) -> Option<DistanceKeys> {
    let mut keys = KEY_BUFFER.with(|b| std::mem::take(&mut *b.borrow_mut()));
    keys.clear();
    let mut all_finite = true;
    let mut largest = 0.0f64;
    let (mut lo, mut hi) = (u64::MAX, 0);
    keys.extend(points.map(|p| {
        let d = sq_dist_f64(p, &viewpoint);
        all_finite &= d.is_finite();
        let [x, y, z] = p.map(|c| c.into().abs());
        largest = largest.max(x).max(y).max(z);
        let k = d.to_bits();
        lo = lo.min(k);
        hi = hi.max(k);
        k
    }));
    let keys = DistanceKeys { keys, lo, hi };
    (all_finite && largest <= MAX_COORDINATE).then_some(keys)
}

/// Keys of a cloud, or the error naming its first non-finite point.
fn cloud_keys<T: Copy + Into<f64>>(points: &[[T; 3]], viewpoint: [f64; 3]) -> Result<DistanceKeys> {
    match distance_keys(points.iter(), viewpoint) {
        Some(keys) => Ok(keys),
        None => {
            check_finite("points", 0, points)?;
            // Finite coordinates whose squared distance overflows float64.
            Err(GeometryError::out_of_range(
                "points",
                "are too large: squared distances to the viewpoint overflow float64",
            ))
        }
    }
}

/// The predicate, fed the keys in index order, that says which points a count crop removes.
///
/// The count-th smallest distance is the threshold: every point below it is removed, and of the
/// points exactly at it, the lowest indices until `count` are reached. The predicate has no
/// branches: the comparisons are unpredictable for points in random order.
fn removal_rule(keys: &DistanceKeys, count: usize) -> impl FnMut(u64) -> bool {
    let (threshold, below) = kth_smallest(keys, count - 1);
    let ties = count - below;
    let mut seen = 0;
    move |k: u64| {
        let at = k == threshold;
        let removed = (k < threshold) | (at & (seen < ties));
        seen += usize::from(at);
        removed
    }
}

/// Crop one cloud by count straight into flat output buffers (see [`write_split`] for their
/// sizes): the fast path of the bindings, with no intermediate mask.
pub fn crop_count_into<T: Copy + Into<f64>>(
    points: &[[T; 3]],
    viewpoint: [f64; 3],
    n_missing: usize,
    kept: &mut [T],
    removed: &mut [T],
) -> Result<()> {
    check_point_count("points", points.len())?;
    check_viewpoint(&viewpoint)?;
    check_count(n_missing, points.len())?;
    let keys = cloud_keys(points, viewpoint)?;
    if n_missing == 0 {
        kept[..points.len() * 3].copy_from_slice(points.as_flattened());
        return Ok(());
    }
    let mut take = removal_rule(&keys, n_missing);
    let (mut k, mut r) = (0, 0);
    for (p, &key) in points.iter().zip(&keys.keys) {
        let m = take(key);
        kept[k..k + 3].copy_from_slice(p);
        removed[r..r + 3].copy_from_slice(p);
        r += 3 * usize::from(m);
        k += 3 * usize::from(!m);
    }
    Ok(())
}

/// Mark in `mask` the `count` points with the smallest `keys` (ties: lowest index). `keys[j]`
/// belongs to point `candidates[j]`, or to point `j` when `candidates` is `None`.
fn mark_nearest(keys: &DistanceKeys, candidates: Option<&[u32]>, count: usize, mask: &mut [bool]) {
    if count == 0 {
        return;
    }
    let mut take = removal_rule(keys, count);
    let keys = &keys.keys;
    match candidates {
        None => mask.iter_mut().zip(keys).for_each(|(m, &k)| *m = take(k)),
        Some(c) => c
            .iter()
            .zip(keys)
            .for_each(|(&i, &k)| mask[i as usize] = take(k)),
    }
}

/// The `k`-th smallest (0-based) of `keys` by radix selection: a histogram over the current
/// key range narrows it 2048-fold per pass, and a small bucket is finished by sorting. Two or
/// three linear passes instead of a comparison-based select (which was 4x slower at 16k points).
fn kth_smallest(keys: &DistanceKeys, mut k: usize) -> (u64, usize) {
    const BITS: u32 = 11;
    let (mut lo, mut hi) = (keys.lo, keys.hi);
    let keys = &keys.keys;
    // How many keys lie below `lo` (always below the answer).
    let mut below = 0;
    let mut hist = vec![0u32; 1 << BITS];
    let mut first_pass = true;
    loop {
        if lo == hi {
            return (lo, below);
        }
        let shift = (64 - (hi - lo).leading_zeros()).saturating_sub(BITS);
        hist.fill(0);
        if first_pass {
            // Every key is in range: no filter, and four interleaved counters per bucket so
            // that repeated buckets do not serialise on one memory location.
            let mut quad = [[0u32; 4]; 1 << BITS];
            let chunks = keys.chunks_exact(4);
            for &x in chunks.remainder() {
                quad[((x - lo) >> shift) as usize][0] += 1;
            }
            for c in chunks {
                for (lane, &x) in c.iter().enumerate() {
                    quad[((x - lo) >> shift) as usize][lane] += 1;
                }
            }
            for (h, q) in hist.iter_mut().zip(&quad) {
                *h = q.iter().sum();
            }
            first_pass = false;
        } else {
            for &x in keys {
                if x >= lo && x <= hi {
                    hist[((x - lo) >> shift) as usize] += 1;
                }
            }
        }
        let mut bucket = 0;
        while k >= hist[bucket] as usize {
            k -= hist[bucket] as usize;
            below += hist[bucket] as usize;
            bucket += 1;
        }
        let bucket_lo = lo + ((bucket as u64) << shift);
        let bucket_hi = hi.min(bucket_lo + ((1u64 << shift) - 1));
        if hist[bucket] <= 256 {
            let mut small: Vec<u64> = keys
                .iter()
                .copied()
                .filter(|&x| x >= bucket_lo && x <= bucket_hi)
                .collect();
            let value = *small.select_nth_unstable(k).1;
            return (value, below + small.iter().filter(|&&x| x < value).count());
        }
        (lo, hi) = (bucket_lo, bucket_hi);
    }
}

/// Remove `n_missing` points split among several viewpoints: region `k` takes the points nearest
/// `viewpoints[k]` among those not yet removed; the counts differ by at most one, the earlier
/// regions taking the remainder.
pub fn multi_region_mask<T: Copy + Into<f64>>(
    points: &[[T; 3]],
    viewpoints: &[[f64; 3]],
    n_missing: usize,
) -> Result<Vec<bool>> {
    check_point_count("points", points.len())?;
    if viewpoints.is_empty() {
        return Err(GeometryError::Empty { arg: "viewpoints" });
    }
    if viewpoints.len() > MAX_REGIONS {
        return Err(GeometryError::out_of_range(
            "viewpoints",
            format!(
                "holds {} regions, more than the {MAX_REGIONS} a crop may remove",
                viewpoints.len()
            ),
        ));
    }
    check_finite("points", 0, points)?;
    for v in viewpoints {
        check_viewpoint(v)?;
    }
    check_count(n_missing, points.len())?;
    let mut mask = vec![false; points.len()];
    let k = viewpoints.len();
    for (region, v) in viewpoints.iter().enumerate() {
        let count = n_missing / k + usize::from(region < n_missing % k);
        let remaining: Vec<u32> = (0..points.len() as u32)
            .filter(|&i| !mask[i as usize])
            .collect();
        let keys =
            distance_keys(remaining.iter().map(|&i| &points[i as usize]), *v).ok_or_else(|| {
                GeometryError::out_of_range(
                    "points",
                    "are too large: squared distances to a viewpoint overflow float64",
                )
            })?;
        mark_nearest(&keys, Some(&remaining), count, &mut mask);
    }
    Ok(mask)
}

/// Where random crops put their centres.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Directions {
    /// One of the authors' five [`VIEWPOINTS`] (distinct ones for several regions, up to five).
    Viewpoints,
    /// Uniformly distributed on the unit sphere.
    Sphere,
}

impl std::str::FromStr for Directions {
    type Err = GeometryError;

    /// `"viewpoints"` or `"sphere"`, as `pfnet.geometry.random_crop` spells them.
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "viewpoints" => Ok(Directions::Viewpoints),
            "sphere" => Ok(Directions::Sphere),
            other => Err(GeometryError::out_of_range(
                "directions",
                format!("must be 'viewpoints' or 'sphere', got {other:?}"),
            )),
        }
    }
}

/// SplitMix64: a tiny, well-mixed generator, so seeded crops are the same on every platform.
struct SplitMix64(u64);

impl SplitMix64 {
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    fn next_f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    fn below(&mut self, n: usize) -> usize {
        (self.next_f64() * n as f64) as usize % n
    }
}

/// The most regions one crop may remove. The paper crops one region and the command line at
/// most five; more than a few dozen is scattered point removal, not missing regions. Each
/// region is selected by a pass over the points still present, so a crop costs O(K·N): 256
/// regions on 65,536 points take about 0.3 s, where the earlier bound, 65,536 regions, took
/// 36 s for one cloud. (It also bounds the centres' memory: a request for 2^61 regions
/// panicked on the allocation before a bound existed.)
pub const MAX_REGIONS: usize = 256;

/// Reject a region count outside `[1, MAX_REGIONS]`.
pub fn check_region_count(n_regions: usize) -> Result<()> {
    if n_regions == 0 || n_regions > MAX_REGIONS {
        return Err(GeometryError::out_of_range(
            "n_regions",
            format!("must be in [1, {MAX_REGIONS}], got {n_regions}"),
        ));
    }
    Ok(())
}

/// The region centres a seeded random crop uses (`stream` separates the clouds of a batch).
pub fn random_centres(
    seed: u64,
    stream: u64,
    n_regions: usize,
    directions: Directions,
) -> Result<Vec<[f64; 3]>> {
    check_region_count(n_regions)?;
    let mut rng = SplitMix64(seed ^ stream.wrapping_mul(0xD1B5_4A32_D192_ED03));
    match directions {
        Directions::Viewpoints => {
            if n_regions > VIEWPOINTS.len() {
                return Err(GeometryError::out_of_range(
                    "n_regions",
                    format!("must be at most 5 with directions='viewpoints', got {n_regions}"),
                ));
            }
            // Partial Fisher-Yates: distinct viewpoints.
            let mut order = [0, 1, 2, 3, 4];
            for i in 0..n_regions {
                let j = i + rng.below(order.len() - i);
                order.swap(i, j);
            }
            Ok(order[..n_regions].iter().map(|&i| VIEWPOINTS[i]).collect())
        }
        Directions::Sphere => Ok((0..n_regions)
            .map(|_| {
                // Archimedes: z uniform in [-1, 1] and a uniform angle give a uniform sphere point.
                let z = 2.0 * rng.next_f64() - 1.0;
                let phi = std::f64::consts::TAU * rng.next_f64();
                let r = (1.0 - z * z).max(0.0).sqrt();
                [r * phi.cos(), r * phi.sin(), z]
            })
            .collect()),
    }
}

/// Split `points` by `mask` into (kept, removed), each in input order.
pub fn split_by_mask<T: Copy>(points: &[[T; 3]], mask: &[bool]) -> (Vec<[T; 3]>, Vec<[T; 3]>) {
    let removed = mask.iter().filter(|&&m| m).count();
    let mut partial = Vec::with_capacity(points.len() - removed);
    let mut missing = Vec::with_capacity(removed);
    for (p, &m) in points.iter().zip(mask) {
        if m {
            missing.push(*p);
        } else {
            partial.push(*p);
        }
    }
    (partial, missing)
}

/// Write the coordinates of the kept and the removed points, in input order, into two flat
/// buffers (3 values per point), each with room for one more point than it receives: every
/// point is written to both and only one cursor advances, which avoids a branch per point.
pub fn write_split<T: Copy>(points: &[[T; 3]], mask: &[bool], kept: &mut [T], removed: &mut [T]) {
    let (mut k, mut r) = (0, 0);
    for (p, &m) in points.iter().zip(mask) {
        kept[k..k + 3].copy_from_slice(p);
        removed[r..r + 3].copy_from_slice(p);
        r += 3 * usize::from(m);
        k += 3 * usize::from(!m);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn line(n: usize) -> Vec<[f32; 3]> {
        (0..n).map(|i| [i as f32, 0.0, 0.0]).collect()
    }

    #[test]
    fn removes_the_nearest_points_and_keeps_order() {
        let points = line(10);
        let mask = crop_mask(&points, [9.5, 0.0, 0.0], CropSize::Count(3)).unwrap();
        let (partial, missing) = split_by_mask(&points, &mask);
        assert_eq!(
            missing,
            vec![[7.0, 0.0, 0.0], [8.0, 0.0, 0.0], [9.0, 0.0, 0.0]]
        );
        assert_eq!(partial, points[..7].to_vec());
    }

    #[test]
    fn ties_go_to_the_lowest_index() {
        // Points 0 and 2 are both at distance 1 from the viewpoint at x = 1.
        let points = line(3);
        let mask = crop_mask(&points, [1.0, 0.0, 0.0], CropSize::Count(2)).unwrap();
        assert_eq!(mask, vec![true, true, false]);
        let same = vec![[0.0f64; 3]; 6];
        let mask = crop_mask(&same, [1.0, 0.0, 0.0], CropSize::Count(4)).unwrap();
        assert_eq!(mask, vec![true, true, true, true, false, false]);
    }

    #[test]
    fn radix_selection_matches_sorting() {
        let mut state = 99u64;
        for n in [1usize, 2, 7, 300, 5000] {
            let keys: Vec<u64> = (0..n)
                .map(|i| {
                    state = state.wrapping_mul(6364136223846793005).wrapping_add(1);
                    if i % 3 == 0 {
                        42.0
                    } else {
                        (state >> 20) as f64
                    }
                    .to_bits()
                })
                .collect();
            let mut sorted = keys.clone();
            sorted.sort_unstable();
            let keys = DistanceKeys {
                lo: *sorted.first().unwrap(),
                hi: *sorted.last().unwrap(),
                keys,
            };
            for k in [0, n / 2, n - 1] {
                let (value, below) = kth_smallest(&keys, k);
                assert_eq!(value, sorted[k], "n={n} k={k}");
                assert_eq!(below, sorted.iter().filter(|&&x| x < value).count());
            }
        }
    }

    #[test]
    fn radius_is_inclusive() {
        let mask = crop_mask(&line(5), [0.0, 0.0, 0.0], CropSize::Radius(2.0)).unwrap();
        assert_eq!(mask, vec![true, true, true, false, false]);
    }

    #[test]
    fn multi_region_splits_the_count() {
        let points = line(20);
        let mask = multi_region_mask(&points, &[[-1.0, 0.0, 0.0], [30.0, 0.0, 0.0]], 5).unwrap();
        let removed: Vec<usize> = (0..20).filter(|&i| mask[i]).collect();
        assert_eq!(removed, vec![0, 1, 2, 18, 19]);
    }

    #[test]
    fn random_centres_are_seeded_and_distinct() {
        let a = random_centres(7, 3, 3, Directions::Viewpoints).unwrap();
        assert_eq!(a, random_centres(7, 3, 3, Directions::Viewpoints).unwrap());
        assert!(a[0] != a[1] && a[1] != a[2] && a[0] != a[2]);
        for c in random_centres(1, 0, 50, Directions::Sphere).unwrap() {
            let norm = (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt();
            assert!((norm - 1.0).abs() < 1e-12);
        }
        assert!(random_centres(1, 0, 6, Directions::Viewpoints).is_err());
        assert!(random_centres(1, 0, 0, Directions::Sphere).is_err());
        assert!(random_centres(1, 0, MAX_REGIONS + 1, Directions::Sphere).is_err());
    }

    #[test]
    fn directions_parse_their_python_names() {
        assert_eq!("sphere".parse(), Ok(Directions::Sphere));
        assert_eq!("viewpoints".parse(), Ok(Directions::Viewpoints));
        let err = "up".parse::<Directions>().unwrap_err();
        assert_eq!(
            err.to_string(),
            "directions must be 'viewpoints' or 'sphere', got \"up\""
        );
    }

    #[test]
    fn empty_clouds_are_refused_by_every_crop() {
        let empty: [[f32; 3]; 0] = [];
        let expected = Err(GeometryError::Empty { arg: "points" });
        assert_eq!(crop_mask(&empty, [0.0; 3], CropSize::Count(0)), expected);
        assert_eq!(crop_mask(&empty, [0.0; 3], CropSize::Radius(1.0)), expected);
        assert_eq!(multi_region_mask(&empty, &[[0.0; 3]], 0), expected);
        assert_eq!(
            crop_count_into(&empty, [0.0; 3], 0, &mut [], &mut []),
            Err(GeometryError::Empty { arg: "points" })
        );
    }

    #[test]
    fn multi_region_refuses_more_regions_than_the_bound() {
        let views = vec![[1.0, 0.0, 0.0]; MAX_REGIONS + 1];
        let err = multi_region_mask(&line(8), &views, 2)
            .unwrap_err()
            .to_string();
        assert!(err.contains("more than the 256"), "{err}");
        assert!(multi_region_mask(&line(8), &views[..MAX_REGIONS], 2).is_ok());
    }

    #[test]
    fn rejects_bad_counts() {
        let err = crop_mask(&line(4), [0.0; 3], CropSize::Count(4)).unwrap_err();
        assert!(err
            .to_string()
            .contains("n_missing must be smaller than the number of points (4)"));
        assert!(crop_mask(&line(4), [0.0; 3], CropSize::Radius(-1.0)).is_err());
        assert!(crop_mask(&line(4), [f64::NAN, 0.0, 0.0], CropSize::Count(1)).is_err());
    }
}
