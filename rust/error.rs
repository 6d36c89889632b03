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
            GeometryError::OutOfRange { arg, message } => write!(f, "{arg} {message}"),
            GeometryError::Mismatch { message } => write!(f, "{message}"),
        }
    }
}

impl std::error::Error for GeometryError {}

pub type Result<T> = std::result::Result<T, GeometryError>;

/// Reject clouds with NaN or infinite coordinates; `batch` is only used in the message.
pub fn check_finite<T: Copy + Into<f64>>(
    arg: &'static str,
    batch: usize,
    points: &[[T; 3]],
) -> Result<()> {
    match points
        .iter()
        .position(|p| !p.iter().all(|&c| c.into().is_finite()))
    {
        Some(point) => Err(GeometryError::NonFinite { arg, batch, point }),
        None => Ok(()),
    }
}
