//! metricdeform: deform triangle meshes so that demanded lengths, areas and
//! volumes hold exactly, with the shape as close to the input as it can be
//! (Jin, Zhang, Wang: *Deformation with Enforced Metrics on Length, Area and
//! Volume*).
//!
//! # Example
//!
//! A unit cube's surface asked for eight times its volume, and nothing else,
//! becomes the cube scaled by 2:
//!
//! ```
//! use metricdeform::{deform, Demand, Mesh, Options, Problem};
//!
//! let positions = [
//!     [0., 0., 0.], [1., 0., 0.], [1., 1., 0.], [0., 1., 0.],
//!     [0., 0., 1.], [1., 0., 1.], [1., 1., 1.], [0., 1., 1.],
//! ];
//! let triangles = [
//!     [0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
//!     [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7],
//! ];
//! let mesh = Mesh::from_arrays(&positions, &triangles)?;
//! let problem = Problem::new(mesh, "cube", &[Demand::volume().scale(8.0)], &[], &[])?;
//! let result = deform(&problem, &Options::default())?;
//!
//! assert!(result.report.satisfied);
//! let volume = &result.report.constraints[0];
//! assert!((volume.result - 8.0).abs() < 8.0 * 1e-5);
//! // Every edge doubled: the cube scaled by 2.
//! let edge = result.positions[1] - result.positions[0];
//! assert!((edge.length() - 2.0).abs() < 1e-3);
//! # Ok::<(), metricdeform::Error>(())
//! ```
//!
//! # Where each step of the paper lives
//!
//! | module | what | paper |
//! |---|---|---|
//! | [`mesh`] | the mesh; [`mesh::io`] reading and writing, [`mesh::topology`], [`mesh::validate`] | |
//! | [`job`] | the job file (TOML/JSON): one front end that builds a [`Problem`] | |
//! | [`selection`] | curves and regions on the input surface | Sec. 3.1 |
//! | [`metrics`] | length, area, volume, their gradients and scale-factor polynomials | Eqs. 9-14 |
//! | [`problem`] | demands, handles and curvature regions resolved on the mesh | |
//! | [`scale_factors`] | per-face scale factors | Eq. 3 |
//! | [`shape`] | the shape energy and its system; handles; curvature targets | Eqs. 4-7, 19, 21 |
//! | [`anderson`] | acceleration of the scale-driven iteration | |
//! | [`constrained_step`] | one linearly constrained Newton step by the Schur complement | Eqs. 15-18 |
//! | [`fine_tune`] | the metrics as hard constraints | Eq. 8 |
//! | [`pipeline`] | Eq. 3 and Eq. 7 iterated, then the fine-tune; backends | Sec. 2.4 |
//! | [`run`] | a whole run in memory: [`deform`] and [`measure`] | |
//! | [`report`] | the JSON report and the stdout table | |
//! | [`distortion`], [`render`], [`output`], [`memory`] | per-face fields, pictures, atomic output, memory probes | |

// Index loops read as the paper's sums (`for i in 0..n { s[i] ... }`).
#![allow(clippy::needless_range_loop)]

pub mod anderson;
pub mod constrained_step;
pub mod distortion;
pub mod error;
pub mod fine_tune;
pub mod job;
pub mod memory;
pub mod mesh;
pub mod metrics;
pub mod ordered;
pub mod output;
pub mod pipeline;
pub mod problem;
pub mod render;
pub mod report;
pub mod run;
pub mod scale_factors;
pub mod selection;
pub mod shape;

pub use error::{Error, Result};
pub use mesh::Mesh;
pub use pipeline::{choose_backend, Options, SolverBackend};
pub use problem::{Curvature, Demand, Handle, Metric, Problem, Target};
pub use run::{deform, measure, Deformation};
pub use selection::{Curve, FacePoint, Region};
