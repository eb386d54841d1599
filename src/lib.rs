//! anchorage: a batch renderer for animation. Photon mapping, final gathering and irradiance
//! caching made temporally coherent by anchors (Smyk, Kinuwaki, Ďurikovič, Myszkowski,
//! "Temporally Coherent Irradiance Caching for High Quality Animation Rendering").
//!
//! Stages, in data-flow order (DESIGN.md): [`job`] → [`scene`] (glTF layers, tags,
//! animation) → [`accel`] (static and dynamic BVHs) → [`render`] (shading) → [`output`]
//! (EXR, stats, preview), driven frame by frame by [`pipeline`].

// `!(x > 0.0)` is deliberate throughout: it rejects NaN as well as non-positive values.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

pub mod accel;
pub mod compare;
pub mod error;
pub mod gi;
pub mod inspect;
pub mod job;
pub mod output;
pub mod pipeline;
pub mod render;
pub mod sampling;
pub mod scene;

pub use error::{Error, Result};
