//! metricdeform: deform triangle meshes so that demanded lengths, areas and volumes
//! hold exactly (Jin, Zhang, Wang: *Deformation with Enforced Metrics on Length, Area
//! and Volume*).

pub mod error;
pub mod io;
pub mod job;
pub mod mesh;
pub mod selection;
pub mod topology;
pub mod validate;

pub use error::{Error, Result};
pub mod anderson;
pub use mesh::Mesh;
pub mod deform;
pub mod distortion;
pub mod metrics;
pub mod output;
pub mod render;
pub mod report;
pub mod scale_factors;
pub mod schur;
pub mod shape;
