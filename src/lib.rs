//! metricdeform: deform triangle meshes so that demanded lengths, areas and volumes
//! hold exactly (Jin, Zhang, Wang: *Deformation with Enforced Metrics on Length, Area
//! and Volume*).

pub mod anderson;
pub mod constrained_step;
pub mod distortion;
pub mod error;
pub mod fine_tune;
pub mod job;
pub mod memory;
pub mod mesh;
pub mod metrics;
pub mod output;
pub mod pipeline;
pub mod problem;
pub mod render;
pub mod report;
pub mod scale_factors;
pub mod selection;
pub mod shape;

pub use error::{Error, Result};
pub use mesh::Mesh;
