//! pfnet's geometry core: exact iterative farthest point sampling, KD-tree nearest neighbours and
//! Chamfer metrics, and viewpoint cropping. The modules are plain Rust (no Python types); the
//! `python` feature adds the one binding module that exposes them as `pfnet._core`.

pub mod chamfer;
pub mod crop;
pub mod error;
pub mod fps;
pub mod nn;

#[cfg(feature = "python")]
mod python;

pub use chamfer::{chamfer, chamfer_batch};
pub use crop::{
    crop_mask, multi_region_mask, random_centres, split_by_mask, CropSize, Directions, VIEWPOINTS,
};
pub use error::GeometryError;
pub use fps::{farthest_point_sample, farthest_point_sample_naive};
pub use nn::{nearest_neighbors, nearest_neighbors_naive, NearestNeighborIndex};
