//! pfnet's geometry core: exact iterative farthest point sampling, KD-tree nearest neighbours and
//! Chamfer metrics, and viewpoint cropping; plus LZF decompression for the PCD reader. The
//! modules are plain Rust (no Python types); the `python` feature adds the one binding module
//! that exposes them as `pfnet._core`.
//!
//! Every entry point checks its input and returns [`GeometryError`] instead of panicking
//! ([`NearestNeighborIndex::new`] expects a checked cloud); a cloud may hold at most
//! [`MAX_POINTS`] (2³² − 1) points, with coordinates up to ±[`MAX_COORDINATE`].

pub mod chamfer;
pub mod crop;
pub mod error;
pub mod fps;
mod kdtree;
pub mod lzf;
pub mod metrics;
pub mod nn;

#[cfg(feature = "python")]
mod python;

/// Whether this process may use rayon's thread pool.
///
/// A process forked after the pool started (a DataLoader worker under Linux's default `fork`
/// start method) inherits the pool's bookkeeping but not its threads, so parallel work would
/// wait forever. The first call records the process id; a call from another process (a fork
/// child) gets `false`, and the caller then runs sequentially.
pub fn parallel_allowed() -> bool {
    static POOL_OWNER: std::sync::OnceLock<u32> = std::sync::OnceLock::new();
    *POOL_OWNER.get_or_init(std::process::id) == std::process::id()
}

pub use chamfer::{chamfer, chamfer_batch};
pub use crop::{
    crop_mask, multi_region_mask, random_centres, split_by_mask, CropSize, Directions, VIEWPOINTS,
};
pub use error::{GeometryError, MAX_COORDINATE, MAX_POINTS};
pub use fps::{farthest_point_sample, farthest_point_sample_naive};
pub use lzf::lzf_decompress;
pub use metrics::minimal_matching;
pub use nn::{nearest_neighbors, nearest_neighbors_naive, NearestNeighborIndex};
