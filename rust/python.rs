//! The one binding module: every `#[pyfunction]` of `pfnet._core`.
//!
//! The functions here take batched, C-contiguous arrays (`pfnet.geometry` reshapes, converts and
//! checks shapes first, so its messages can name the user's shapes), borrow them without copying,
//! release the GIL while the Rust core works, and hand results back without copying.
//!
//! Every error they raise is a [`GeometryError`] converted in one place, the `From` impl below,
//! into the Python exception `pfnet.errors.GeometryError` (a `ValueError`).

use numpy::ndarray::{Array1, Array2, Array3};
use numpy::{
    Element, IntoPyArray, PyArray1, PyArray2, PyArray3, PyReadonlyArray, PyReadonlyArray1,
    PyReadonlyArray2, PyReadonlyArray3, PyUntypedArrayMethods,
};
use pyo3::prelude::*;
use rayon::prelude::*;

use crate::chamfer::{chamfer, chamfer_batch};
use crate::crop::{self, CropSize, Directions};
use crate::error::{check_finite, check_point_count, GeometryError, MAX_POINTS};
use crate::fps;
use crate::lzf;
use crate::nn::{validate_pair, NearestNeighborIndex};

/// Two arrays returned together: (partial, missing), (sq_dist, index), (pred_to_gt, gt_to_pred).
type Pair<'py, A, B> = (Bound<'py, A>, Bound<'py, B>);
type Split<'py, T> = Pair<'py, PyArray3<T>, PyArray3<T>>;
type Cloud<'a> = &'a [[f32; 3]];

mod exception {
    // `__module__` is the public home, `pfnet.errors`, which re-exports the class: tracebacks
    // print `pfnet.errors.GeometryError` and pickling (multiprocessing) finds the class there.
    pyo3::create_exception!(
        pfnet.errors,
        GeometryError,
        pyo3::exceptions::PyValueError,
        "Bad input to pfnet's geometry core: a shape, size, count or coordinate it cannot use. \
         A ValueError, so code that catches ValueError keeps working."
    );
}

/// The single conversion of the core's errors into Python exceptions.
impl From<GeometryError> for PyErr {
    fn from(err: GeometryError) -> PyErr {
        exception::GeometryError::new_err(err.to_string())
    }
}

/// `f` applied to every item, across the thread pool when there are several items and this
/// process may use it (see [`crate::parallel_allowed`]), else in order on this thread.
fn map_batch<I: Sync, R: Send>(items: &[I], f: impl Fn(usize, &I) -> R + Sync + Send) -> Vec<R> {
    if items.len() > 1 && crate::parallel_allowed() {
        items.par_iter().enumerate().map(|(i, x)| f(i, x)).collect()
    } else {
        items.iter().enumerate().map(|(i, x)| f(i, x)).collect()
    }
}

/// The values of a C-contiguous array, borrowed. `as_slice` alone also accepts Fortran order,
/// whose values it would hand over transposed.
fn c_order<'a, T: Element, D: numpy::ndarray::Dimension>(
    arg: &'static str,
    array: &'a PyReadonlyArray<'_, T, D>,
) -> Result<&'a [T], GeometryError> {
    if !array.is_c_contiguous() {
        return Err(GeometryError::NotContiguous { arg });
    }
    array
        .as_slice()
        .map_err(|_| GeometryError::NotContiguous { arg })
}

/// The clouds of a (B, N, 3) array as B slices of points.
fn clouds<'a, T: Element>(
    arg: &'static str,
    array: &'a PyReadonlyArray3<'_, T>,
) -> Result<Vec<&'a [[T; 3]]>, GeometryError> {
    rows_of_three(arg, "(B, N, 3)", array)
}

/// The B slices of 3-vectors of a C-contiguous array shaped `expected`, (B, _, 3).
fn rows_of_three<'a, T: Element>(
    arg: &'static str,
    expected: &'static str,
    array: &'a PyReadonlyArray3<'_, T>,
) -> Result<Vec<&'a [[T; 3]]>, GeometryError> {
    let shape = array.shape();
    let n = shape[1];
    if shape[2] != 3 {
        return Err(GeometryError::Shape {
            arg,
            expected,
            got: shape.to_vec(),
        });
    }
    if n == 0 {
        // Refused before a list of B empty clouds is built: an array of no values may claim any
        // B (np.zeros((2**40, 0, 3)) made the list's allocation abort the process).
        return match shape[0] {
            0 => Ok(Vec::new()),
            _ => Err(GeometryError::Empty { arg }),
        };
    }
    let (points, _) = c_order(arg, array)?.as_chunks::<3>();
    Ok(points.chunks(n).collect())
}

fn check_batches(
    arg: &'static str,
    na: usize,
    other: &'static str,
    nb: usize,
) -> Result<(), GeometryError> {
    if na != nb {
        return Err(GeometryError::Mismatch {
            arg,
            other,
            what: "batch size",
            sizes: (na, nb),
        });
    }
    Ok(())
}

/// Exact IFPS of every cloud of `points` (B, N, 3); returns int64 indices (B, n_samples).
#[pyfunction]
fn farthest_point_sample<'py>(
    py: Python<'py>,
    points: PyReadonlyArray3<'py, f32>,
    n_samples: usize,
    start_index: usize,
) -> PyResult<Bound<'py, PyArray2<i64>>> {
    let batch = clouds("points", &points)?;
    let b = batch.len();
    // Checked once for all clouds, and for a batch of none too: the output is (B, n_samples),
    // and a batch of no clouds with a huge n_samples made a shape that crashed numpy.
    fps::check_sizes(points.shape()[1], n_samples, start_index)?;
    let flat: Vec<i64> = py.detach(|| -> Result<Vec<i64>, GeometryError> {
        for (i, cloud) in batch.iter().enumerate() {
            check_finite("points", i, cloud)?;
        }
        // One cloud runs on one thread: splitting one IFPS per iteration loses (DESIGN.md §6).
        let rows = map_batch(&batch, |_, cloud| {
            fps::sample_unchecked(cloud, n_samples, start_index)
        });
        Ok(rows.into_iter().flatten().map(|i| i as i64).collect())
    })?;
    let out = Array2::from_shape_vec((b, n_samples), flat).expect("b * n_samples indices");
    Ok(out.into_pyarray(py))
}

/// Nearest reference point of every query point, per batch item.
#[pyfunction]
fn nearest_neighbors<'py>(
    py: Python<'py>,
    query: PyReadonlyArray3<'py, f32>,
    reference: PyReadonlyArray3<'py, f32>,
) -> PyResult<Pair<'py, PyArray2<f32>, PyArray2<i64>>> {
    let queries = clouds("query", &query)?;
    let references = clouds("reference", &reference)?;
    check_batches("query", queries.len(), "reference", references.len())?;
    let (b, q) = (queries.len(), query.shape()[1]);
    let (dist, index) = py.detach(|| -> Result<(Vec<f32>, Vec<u32>), GeometryError> {
        for (i, (qc, rc)) in queries.iter().zip(&references).enumerate() {
            validate_pair("query", qc, "reference", rc, i)?;
        }
        let pairs: Vec<(Cloud, Cloud)> = queries.into_iter().zip(references).collect();
        let rows = map_batch(&pairs, |_, (qc, rc)| {
            let mut dist = vec![0.0f32; q];
            let mut index = vec![0u32; q];
            NearestNeighborIndex::new(rc).query_into(qc, &mut dist, &mut index, b == 1);
            (dist, index)
        });
        let (dist, index): (Vec<Vec<f32>>, Vec<Vec<u32>>) = rows.into_iter().unzip();
        let (dist, index) = (dist.concat(), index.concat());
        Ok((dist, index))
    })?;
    let dist = Array2::from_shape_vec((b, q), dist).expect("b * q distances");
    let index = Array2::from_shape_vec((b, q), index.into_iter().map(i64::from).collect())
        .expect("b * q indices");
    Ok((dist.into_pyarray(py), index.into_pyarray(py)))
}

/// The two directed Chamfer terms of every (pred, gt) pair, float64 (B,) each.
#[pyfunction]
#[pyo3(name = "chamfer")]
fn chamfer_py<'py>(
    py: Python<'py>,
    pred: PyReadonlyArray3<'py, f32>,
    gt: PyReadonlyArray3<'py, f32>,
) -> PyResult<Pair<'py, PyArray1<f64>, PyArray1<f64>>> {
    let preds = clouds("pred", &pred)?;
    let gts = clouds("gt", &gt)?;
    check_batches("pred", preds.len(), "gt", gts.len())?;
    let terms = py.detach(|| -> Result<Vec<(f64, f64)>, GeometryError> {
        if preds.len() == 1 {
            return Ok(vec![chamfer(preds[0], gts[0])?]);
        }
        chamfer_batch(&preds, &gts)
    })?;
    let (p2g, g2p): (Vec<f64>, Vec<f64>) = terms.into_iter().unzip();
    Ok((
        Array1::from(p2g).into_pyarray(py),
        Array1::from(g2p).into_pyarray(py),
    ))
}

/// For every completion, the smallest CD-L2 to any reference cloud (R, M, 3) and that
/// reference's index: float64 (C,), int64 (C,) (KITTI's minimal matching distance). The
/// completions may differ in size: their points one after another (P, 3), and how many each
/// has (C,), so every reference's tree is built once for all of them.
#[pyfunction]
fn minimal_matching<'py>(
    py: Python<'py>,
    points: PyReadonlyArray2<'py, f32>,
    counts: Vec<usize>,
    references: PyReadonlyArray3<'py, f32>,
) -> PyResult<Pair<'py, PyArray1<f64>, PyArray1<i64>>> {
    let shape = points.shape();
    if shape[1] != 3 {
        let got = shape.to_vec();
        return Err(GeometryError::Shape {
            arg: "completions",
            expected: "(P, 3)",
            got,
        }
        .into());
    }
    let all = c_order("completions", &points)?.as_chunks::<3>().0;
    if counts.contains(&0) {
        return Err(GeometryError::Empty { arg: "completions" }.into());
    }
    let total = counts.iter().try_fold(0usize, |a, &n| a.checked_add(n));
    if total != Some(all.len()) {
        return Err(GeometryError::out_of_range(
            "counts",
            format!("must add up to the {} completion points", all.len()),
        )
        .into());
    }
    let mut comps = Vec::with_capacity(counts.len());
    let mut rest = all;
    for &n in &counts {
        let (cloud, tail) = rest.split_at(n);
        comps.push(cloud);
        rest = tail;
    }
    let refs = clouds("references", &references)?;
    let found = py.detach(|| crate::metrics::minimal_matching(&comps, &refs))?;
    let (dist, index): (Vec<f64>, Vec<i64>) = found.into_iter().map(|(d, j)| (d, j as i64)).unzip();
    Ok((
        Array1::from(dist).into_pyarray(py),
        Array1::from(index).into_pyarray(py),
    ))
}

/// Crop every cloud of a batch; `fill(i, cloud, kept, removed)` writes cloud `i`'s kept and
/// removed coordinates into buffers with one spare point each (see `crop::write_split`).
fn crop_batch<'py, T, F>(
    py: Python<'py>,
    points: &PyReadonlyArray3<'py, T>,
    n_missing: usize,
    fill: F,
) -> PyResult<Split<'py, T>>
where
    T: Element + Copy + Default + Send + Sync,
    F: Fn(usize, &[[T; 3]], &mut [T], &mut [T]) -> Result<(), GeometryError> + Send + Sync,
{
    let batch = clouds("points", points)?;
    let (b, n) = (batch.len(), points.shape()[1]);
    let (kept, removed) = ((n - n_missing) * 3, n_missing * 3);
    let crop_one = |(i, cloud): (usize, &&[[T; 3]])| -> Result<(Vec<T>, Vec<T>), GeometryError> {
        let mut partial = vec![T::default(); kept + 3];
        let mut missing = vec![T::default(); removed + 3];
        fill(i, cloud, &mut partial, &mut missing)?;
        partial.truncate(kept);
        missing.truncate(removed);
        Ok((partial, missing))
    };
    let (partial, missing) = py.detach(|| -> Result<(Vec<T>, Vec<T>), GeometryError> {
        if b == 1 {
            return crop_one((0, &batch[0]));
        }
        let parts: Vec<(Vec<T>, Vec<T>)> = map_batch(&batch, |i, cloud| crop_one((i, cloud)))
            .into_iter()
            .collect::<Result<_, _>>()?;
        let (partial, missing): (Vec<Vec<T>>, Vec<Vec<T>>) = parts.into_iter().unzip();
        Ok((partial.concat(), missing.concat()))
    })?;
    let partial = Array3::from_shape_vec((b, n - n_missing, 3), partial).expect("partial shape");
    let missing = Array3::from_shape_vec((b, n_missing, 3), missing).expect("missing shape");
    Ok((partial.into_pyarray(py), missing.into_pyarray(py)))
}

/// Check the sizes of a count crop before its output buffers are sized by them.
fn check_n_missing(points_shape: &[usize], n_missing: usize) -> Result<(), GeometryError> {
    check_point_count("points", points_shape[1])?;
    crop::check_count(n_missing, points_shape[1])
}

/// One viewpoint per cloud of a batch of `b`: a (b, 3) array.
fn viewpoint_rows(
    viewpoints: &PyReadonlyArray2<'_, f64>,
    b: usize,
) -> Result<Vec<[f64; 3]>, GeometryError> {
    let arg = "viewpoint";
    let shape = viewpoints.shape();
    if shape[1] != 3 {
        return Err(GeometryError::Shape {
            arg,
            expected: "(B, 3)",
            got: shape.to_vec(),
        });
    }
    check_batches("points", b, arg, shape[0])?;
    Ok(c_order(arg, viewpoints)?.as_chunks::<3>().0.to_vec())
}

macro_rules! crop_functions {
    ($count:ident, $radius:ident, $multi:ident, $t:ty) => {
        /// Remove the `n_missing` points nearest each cloud's viewpoint (B, 3).
        #[pyfunction]
        fn $count<'py>(
            py: Python<'py>,
            points: PyReadonlyArray3<'py, $t>,
            viewpoints: PyReadonlyArray2<'py, f64>,
            n_missing: usize,
        ) -> PyResult<Split<'py, $t>> {
            check_n_missing(points.shape(), n_missing)?;
            let rows = viewpoint_rows(&viewpoints, points.shape()[0])?;
            crop_batch(py, &points, n_missing, |i, cloud, kept, removed| {
                crop::crop_count_into(cloud, rows[i], n_missing, kept, removed)
                    .map_err(|e| with_batch(e, i))
            })
        }

        /// Remove every point within `radius` of `viewpoint` from one cloud (N, 3).
        #[pyfunction]
        fn $radius<'py>(
            py: Python<'py>,
            points: PyReadonlyArray2<'py, $t>,
            viewpoint: [f64; 3],
            radius: f64,
        ) -> PyResult<Pair<'py, PyArray2<$t>, PyArray2<$t>>> {
            let shape = points.shape();
            if shape[1] != 3 {
                let got = shape.to_vec();
                let expected = "(N, 3)";
                return Err(GeometryError::Shape {
                    arg: "points",
                    expected,
                    got,
                }
                .into());
            }
            let cloud = c_order("points", &points)?.as_chunks::<3>().0;
            let (partial, missing) = py.detach(|| {
                crop::crop_mask(cloud, viewpoint, CropSize::Radius(radius))
                    .map(|mask| crop::split_by_mask(cloud, &mask))
            })?;
            let to_array = |v: Vec<[$t; 3]>| {
                let rows = v.len();
                Array2::from_shape_vec((rows, 3), v.into_iter().flatten().collect())
                    .expect("rows * 3 coordinates")
                    .into_pyarray(py)
            };
            Ok((to_array(partial), to_array(missing)))
        }

        /// Remove `n_missing` points split among each cloud's K viewpoints (B, K, 3).
        #[pyfunction]
        fn $multi<'py>(
            py: Python<'py>,
            points: PyReadonlyArray3<'py, $t>,
            viewpoints: PyReadonlyArray3<'py, f64>,
            n_missing: usize,
        ) -> PyResult<Split<'py, $t>> {
            check_n_missing(points.shape(), n_missing)?;
            let centres = rows_of_three("viewpoints", "(B, K, 3)", &viewpoints)?;
            check_batches("points", points.shape()[0], "viewpoints", centres.len())?;
            crop_batch(py, &points, n_missing, |i, cloud, kept, removed| {
                let mask = crop::multi_region_mask(cloud, centres[i], n_missing)
                    .map_err(|e| with_batch(e, i))?;
                crop::write_split(cloud, &mask, kept, removed);
                Ok(())
            })
        }
    };
}

crop_functions!(crop_count_f32, crop_radius_f32, crop_multi_f32, f32);
crop_functions!(crop_count_f64, crop_radius_f64, crop_multi_f64, f64);

/// Put the batch index into a coordinate error raised inside a batch loop.
fn with_batch(err: GeometryError, batch: usize) -> GeometryError {
    match err {
        GeometryError::NonFinite { arg, point, .. } => {
            GeometryError::NonFinite { arg, batch, point }
        }
        GeometryError::Huge { arg, point, .. } => GeometryError::Huge { arg, batch, point },
        other => other,
    }
}

/// Seeded region centres for `batch` random crops: float64 (batch, n_regions, 3).
#[pyfunction]
fn random_centres<'py>(
    py: Python<'py>,
    seed: u64,
    batch: usize,
    n_regions: usize,
    directions: &str,
) -> PyResult<Bound<'py, PyArray3<f64>>> {
    let directions: Directions = directions.parse()?;
    // Checked here too: a batch of zero clouds never reaches `crop::random_centres`.
    crop::check_region_count(n_regions)?;
    // `batch` is any integer the caller gives: refuse what cannot be allocated instead of
    // letting the allocation panic (capacity overflow) or abort the process.
    let mut flat = Vec::new();
    let size = batch.checked_mul(n_regions * 3);
    if size.is_none_or(|size| flat.try_reserve_exact(size).is_err()) {
        return Err(GeometryError::out_of_range(
            "batch",
            format!("is too large: {batch} × {n_regions} centres do not fit in memory"),
        )
        .into());
    }
    for stream in 0..batch {
        let centres = crop::random_centres(seed, stream as u64, n_regions, directions)?;
        flat.extend(centres.into_iter().flatten());
    }
    let out = Array3::from_shape_vec((batch, n_regions, 3), flat).expect("centre shape");
    Ok(out.into_pyarray(py))
}

/// LZF `data` (PCD `binary_compressed`) expanded to exactly `size` bytes, as uint8 (size,).
#[pyfunction]
fn lzf_decompress<'py>(
    py: Python<'py>,
    data: PyReadonlyArray1<'py, u8>,
    size: usize,
) -> PyResult<Bound<'py, PyArray1<u8>>> {
    let input = c_order("data", &data)?;
    let out = py.detach(|| lzf::lzf_decompress(input, size))?;
    Ok(Array1::from_vec(out).into_pyarray(py))
}

#[pymodule]
fn _core(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(farthest_point_sample, m)?)?;
    m.add_function(wrap_pyfunction!(nearest_neighbors, m)?)?;
    m.add_function(wrap_pyfunction!(chamfer_py, m)?)?;
    m.add_function(wrap_pyfunction!(minimal_matching, m)?)?;
    m.add_function(wrap_pyfunction!(crop_count_f32, m)?)?;
    m.add_function(wrap_pyfunction!(crop_count_f64, m)?)?;
    m.add_function(wrap_pyfunction!(crop_radius_f32, m)?)?;
    m.add_function(wrap_pyfunction!(crop_radius_f64, m)?)?;
    m.add_function(wrap_pyfunction!(crop_multi_f32, m)?)?;
    m.add_function(wrap_pyfunction!(crop_multi_f64, m)?)?;
    m.add_function(wrap_pyfunction!(random_centres, m)?)?;
    m.add_function(wrap_pyfunction!(lzf_decompress, m)?)?;
    m.add("MAX_REGIONS", crop::MAX_REGIONS)?;
    m.add("MAX_COORDINATE", crate::error::MAX_COORDINATE)?;
    m.add("MAX_POINTS", MAX_POINTS)?;
    m.add(
        "GeometryError",
        m.py().get_type::<exception::GeometryError>(),
    )?;
    let viewpoints: Vec<f64> = crop::VIEWPOINTS.iter().flatten().copied().collect();
    m.add(
        "VIEWPOINTS",
        Array2::from_shape_vec((5, 3), viewpoints)
            .expect("5 viewpoints")
            .into_pyarray(m.py()),
    )?;
    Ok(())
}
