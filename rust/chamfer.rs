//! The two directed terms of the Chamfer distance (PF-Net, Eq. 1), accumulated in float64.

use rayon::prelude::*;

use crate::error::Result;
use crate::nn::{validate_pair, NearestNeighborIndex};

/// Leaves per block of a directed term (about a thousand points): blocks are summed separately,
/// then in order, so the parallel and serial sums are the same number.
const LEAVES_PER_BLOCK: usize = 64;

/// Mean over the cloud of `from` (all `count` points, copies included) of the squared distance
/// to the nearest point of `to` (one directed term). The points are taken in `from`'s tree order,
/// so consecutive queries meet the same leaves of `to`.
fn directed(
    from: &NearestNeighborIndex<'_>,
    count: usize,
    to: &NearestNeighborIndex<'_>,
    parallel: bool,
) -> f64 {
    let block = |b: usize| -> f64 {
        let leaves = b * LEAVES_PER_BLOCK..((b + 1) * LEAVES_PER_BLOCK).min(from.leaf_count());
        from.points(leaves)
            .map(|(q, copies)| f64::from(to.nearest(&q).0) * f64::from(copies))
            .sum()
    };
    let blocks = from.leaf_count().div_ceil(LEAVES_PER_BLOCK);
    let sums: Vec<f64> = if parallel {
        (0..blocks).into_par_iter().map(block).collect()
    } else {
        (0..blocks).map(block).collect()
    };
    sums.iter().sum::<f64>() / count as f64
}

/// `(pred_to_gt, gt_to_pred)`: mean squared distance from each prediction point to the ground
/// truth, and the reverse. Uses all cores for large clouds. Each cloud may hold at most
/// [`MAX_POINTS`](crate::error::MAX_POINTS) points.
pub fn chamfer(pred: &[[f32; 3]], gt: &[[f32; 3]]) -> Result<(f64, f64)> {
    validate_pair("pred", pred, "gt", gt, 0)?;
    let large = pred.len() + gt.len() >= 8192;
    if !large || !crate::parallel_allowed() {
        return Ok(chamfer_serial(pred, gt));
    }
    // Build both trees at once, then query each direction with all threads.
    let (pred_index, gt_index) = rayon::join(
        || NearestNeighborIndex::new(pred),
        || NearestNeighborIndex::new(gt),
    );
    Ok((
        directed(&pred_index, pred.len(), &gt_index, true),
        directed(&gt_index, gt.len(), &pred_index, true),
    ))
}

/// One pair on one thread (used inside batch-parallel loops).
pub(crate) fn chamfer_serial(pred: &[[f32; 3]], gt: &[[f32; 3]]) -> (f64, f64) {
    let gt_index = NearestNeighborIndex::new(gt);
    let pred_index = NearestNeighborIndex::new(pred);
    (
        directed(&pred_index, pred.len(), &gt_index, false),
        directed(&gt_index, gt.len(), &pred_index, false),
    )
}

/// A batch of pairs, one pair per task across the thread pool.
pub fn chamfer_batch(preds: &[&[[f32; 3]]], gts: &[&[[f32; 3]]]) -> Result<Vec<(f64, f64)>> {
    for (b, (p, g)) in preds.iter().zip(gts).enumerate() {
        validate_pair("pred", p, "gt", g, b)?;
    }
    if !crate::parallel_allowed() {
        return Ok(preds
            .iter()
            .zip(gts)
            .map(|(p, g)| chamfer_serial(p, g))
            .collect());
    }
    Ok(preds
        .par_iter()
        .zip(gts.par_iter())
        .map(|(p, g)| chamfer_serial(p, g))
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nn::nearest_neighbors_naive;

    fn naive(pred: &[[f32; 3]], gt: &[[f32; 3]]) -> (f64, f64) {
        let mean = |d: Vec<f32>| d.iter().map(|&x| x as f64).sum::<f64>() / d.len() as f64;
        (
            mean(nearest_neighbors_naive(pred, gt).0),
            mean(nearest_neighbors_naive(gt, pred).0),
        )
    }

    #[test]
    fn matches_naive_and_is_zero_for_identical_clouds() {
        let a: Vec<[f32; 3]> = (0..5000)
            .map(|i| [(i as f32).sin(), (i as f32 * 0.37).cos(), i as f32 * 1e-4])
            .collect();
        let b: Vec<[f32; 3]> = a.iter().map(|p| [p[0] + 0.01, p[1], p[2] * 2.0]).collect();
        assert_eq!(chamfer(&a, &a).unwrap(), (0.0, 0.0));
        let (x, y) = chamfer(&a, &b[..3000]).unwrap();
        let (nx, ny) = naive(&a, &b[..3000]);
        assert!((x - nx).abs() <= 1e-12 * nx.max(1.0) && (y - ny).abs() <= 1e-12 * ny.max(1.0));
        let batch = chamfer_batch(&[&a[..100], &b[..7]], &[&b[..50], &a[..9]]).unwrap();
        assert_eq!(batch[0], chamfer(&a[..100], &b[..50]).unwrap());
        assert_eq!(batch[1], chamfer(&b[..7], &a[..9]).unwrap());
    }

    #[test]
    fn one_point_each_is_the_squared_distance() {
        assert_eq!(
            chamfer(&[[0.0, 0.0, 0.0]], &[[1.0, 2.0, 2.0]]).unwrap(),
            (9.0, 9.0)
        );
    }
}
