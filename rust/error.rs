//! The one error type of the geometry core. Python bindings convert it once, at the boundary.

use std::fmt;

/// Why a geometry call rejected its input. Every variant names the argument at fault.
#[derive(Debug, Clone, PartialEq)]
pub enum GeometryError {
    /// A cloud with no points.
    Empty { arg: &'static str },
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
    /// A count or index outside its allowed range.
    OutOfRange { arg: &'static str, message: String },
    /// Two arguments whose sizes do not agree.
    Mismatch { message: String },
}

impl GeometryError {
    pub(crate) fn out_of_range(arg: &'static str, message: impl Into<String>) -> Self {
        GeometryError::OutOfRange {
            arg,
            message: message.into(),
        }
    }
}

impl fmt::Display for GeometryError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            GeometryError::Empty { arg } => {
                write!(f, "{arg} is empty: a cloud needs at least one point")
            }
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
            GeometryError::Mismatch { message } => write!(f, "{message}"),
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
