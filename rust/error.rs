//! The one error type of the geometry core. Python bindings convert it once, at the boundary
//! (`impl From<GeometryError> for PyErr` in `python.rs`), into `pfnet.errors.GeometryError`, a
//! `ValueError`.

use std::fmt;

/// Why a geometry call rejected its input. Every variant names the argument at fault.
#[derive(Debug, Clone, PartialEq)]
pub enum GeometryError {
    /// A cloud with no points.
    Empty { arg: &'static str },
    /// A cloud with more than [`MAX_POINTS`] points.
    TooManyPoints { arg: &'static str, points: usize },
    /// A coordinate that is NaN or infinite.
    NonFinite {
        arg: &'static str,
        batch: usize,
        point: usize,
    },
    /// A coordinate so large that squared distances would overflow float32.
    Huge {
        arg: &'static str,
        batch: usize,
        point: usize,
    },
    /// A count, index or option outside its allowed values.
    OutOfRange { arg: &'static str, message: String },
    /// An array whose shape is not the one the call needs (`expected` as in NumPy, "(B, N, 3)").
    Shape {
        arg: &'static str,
        expected: &'static str,
        got: Vec<usize>,
    },
    /// An array that is not C-contiguous (the bindings borrow arrays without copying them).
    NotContiguous { arg: &'static str },
    /// Two arguments whose sizes (`what`: "batch size", ...) do not agree.
    Mismatch {
        arg: &'static str,
        other: &'static str,
        what: &'static str,
        sizes: (usize, usize),
    },
    /// Encoded data (`arg`: "LZF data") that cannot be decoded; `offset` is the input byte at
    /// fault.
    Corrupt {
        arg: &'static str,
        offset: usize,
        message: String,
    },
}

impl GeometryError {
    pub(crate) fn out_of_range(arg: &'static str, message: impl Into<String>) -> Self {
        GeometryError::OutOfRange {
            arg,
            message: message.into(),
        }
    }
}

/// A shape written as NumPy writes it: `(2, 5)`, `(3,)`, `()`.
fn numpy_shape(shape: &[usize]) -> String {
    match shape {
        [one] => format!("({one},)"),
        _ => {
            let dims: Vec<String> = shape.iter().map(usize::to_string).collect();
            format!("({})", dims.join(", "))
        }
    }
}

impl fmt::Display for GeometryError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            GeometryError::Empty { arg } => {
                write!(f, "{arg} is empty: a cloud needs at least one point")
            }
            GeometryError::TooManyPoints { arg, points } => write!(
                f,
                "{arg} has {points} points per cloud, more than the {MAX_POINTS} (2^32 - 1) \
                 that one cloud may hold: point indices are 32-bit"
            ),
            GeometryError::NonFinite { arg, batch, point } => write!(
                f,
                "{arg} contains NaN or infinite coordinates (first at batch {batch}, point {point})"
            ),
            GeometryError::Huge { arg, batch, point } => write!(
                f,
                "{arg} has a coordinate beyond ±{MAX_COORDINATE:e} (first at batch {batch}, \
                 point {point}): squared distances would overflow float32; scale the cloud down"
            ),
            GeometryError::OutOfRange { arg, message } => write!(f, "{arg} {message}"),
            GeometryError::Shape { arg, expected, got } => {
                write!(
                    f,
                    "{arg} must have shape {expected}, got {}",
                    numpy_shape(got)
                )
            }
            GeometryError::NotContiguous { arg } => write!(f, "{arg} must be C-contiguous"),
            GeometryError::Mismatch {
                arg,
                other,
                what,
                sizes: (a, b),
            } => write!(
                f,
                "{arg} and {other} must have the same {what}, got {a} and {b}"
            ),
            GeometryError::Corrupt {
                arg,
                offset,
                message,
            } => write!(f, "{arg} is corrupt at byte {offset}: {message}"),
        }
    }
}

impl std::error::Error for GeometryError {}

pub type Result<T> = std::result::Result<T, GeometryError>;

/// The largest coordinate magnitude accepted. Two points within ±1e18 are at most
/// 2·√3·1e18 apart, so a squared distance stays below 1.2e37, under float32's 3.4e38: every
/// kernel computes exactly what it would for smaller clouds instead of returning `inf` or a
/// meaningless sample (a cloud ×1e20 made farthest point sampling return index 0 four times).
pub const MAX_COORDINATE: f64 = 1e18;

/// The most points one cloud may hold, `u32::MAX` (4,294,967,295). The kernels store point
/// indices and counts as `u32` (half the memory of `usize`): the sampling tree's order and node
/// ranges, the nearest-neighbour tree's items, the crop's candidate lists and histogram. Every
/// public entry point checks its clouds against this bound ([`check_point_count`]) before any of
/// those casts. A batch may hold any number of clouds.
pub const MAX_POINTS: usize = u32::MAX as usize;

/// Reject a cloud of `points` points that is empty or larger than [`MAX_POINTS`].
pub fn check_point_count(arg: &'static str, points: usize) -> Result<()> {
    if points == 0 {
        return Err(GeometryError::Empty { arg });
    }
    if points > MAX_POINTS {
        return Err(GeometryError::TooManyPoints { arg, points });
    }
    Ok(())
}

/// Reject clouds with NaN, infinite or huge coordinates; `batch` is only used in the message.
pub fn check_finite<T: Copy + Into<f64>>(
    arg: &'static str,
    batch: usize,
    points: &[[T; 3]],
) -> Result<()> {
    for (point, p) in points.iter().enumerate() {
        for &c in p {
            let c: f64 = c.into();
            if !c.is_finite() {
                return Err(GeometryError::NonFinite { arg, batch, point });
            }
            if c.abs() > MAX_COORDINATE {
                return Err(GeometryError::Huge { arg, batch, point });
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn point_counts_from_one_to_u32_max_are_accepted() {
        for n in [1, 2, 1 << 31, MAX_POINTS - 1, MAX_POINTS] {
            assert_eq!(check_point_count("points", n), Ok(()), "n={n}");
        }
        assert_eq!(MAX_POINTS, 4_294_967_295);
    }

    #[test]
    #[cfg(target_pointer_width = "64")]
    fn empty_and_over_u32_clouds_are_refused_with_their_size() {
        assert_eq!(
            check_point_count("gt", 0),
            Err(GeometryError::Empty { arg: "gt" })
        );
        // No cloud is allocated: the check sees only the length.
        for n in [MAX_POINTS + 1, 1 << 33, usize::MAX] {
            let err = check_point_count("reference", n).unwrap_err();
            assert_eq!(
                err,
                GeometryError::TooManyPoints {
                    arg: "reference",
                    points: n
                }
            );
            let message = err.to_string();
            assert!(
                message.starts_with(&format!("reference has {n} points")),
                "{message}"
            );
            assert!(message.contains("4294967295 (2^32 - 1)"), "{message}");
        }
    }

    #[test]
    fn messages_name_the_argument_and_numpy_shapes() {
        let shape = |got: Vec<usize>| GeometryError::Shape {
            arg: "points",
            expected: "(B, N, 3)",
            got,
        };
        assert_eq!(
            shape(vec![2, 5, 4]).to_string(),
            "points must have shape (B, N, 3), got (2, 5, 4)"
        );
        assert_eq!(
            shape(vec![7]).to_string(),
            "points must have shape (B, N, 3), got (7,)"
        );
        assert_eq!(
            GeometryError::NotContiguous { arg: "viewpoint" }.to_string(),
            "viewpoint must be C-contiguous"
        );
        let mismatch = GeometryError::Mismatch {
            arg: "pred",
            other: "gt",
            what: "batch size",
            sizes: (4, 3),
        };
        assert_eq!(
            mismatch.to_string(),
            "pred and gt must have the same batch size, got 4 and 3"
        );
    }
}
