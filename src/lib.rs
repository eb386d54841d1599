//! anchorage: a batch renderer for animation. Photon mapping, final gathering and irradiance
//! caching made temporally coherent by anchors (Smyk, Kinuwaki, Ďurikovič, Myszkowski,
//! "Temporally Coherent Irradiance Caching for High Quality Animation Rendering").
//!
//! Modules by pipeline stage, each importing only those listed before it (DESIGN.md, Data
//! flow):
//!
//! - leaves: [`error`], [`geom`] (the shared vocabulary), [`color`] (colour and compact
//!   encodings), [`sampling`] (named sample streams);
//! - [`accel`]: the static and dynamic BVHs;
//! - [`scene`]: glTF layers, tags, animation, and the per-frame scene [`scene::FrameScene`];
//! - [`interaction`]: surface points, tracing and direct light;
//! - the paper's stages: [`photon`] (photon maps, §4.2), [`anchor`] (anchors, Pseudocode 1,
//!   §3), [`cache`] (irradiance cache records and strata, §4.1), [`visibility`] (strata that
//!   see dynamic prims, §3.2);
//! - [`integrator`]: the one pixel loop and the methods, Pseudocode 2 among them;
//! - [`session`]: the state a frame hands to the next;
//! - [`job`], [`stats`], [`output`], [`checkpoint`] (the state on disk), [`pipeline`] (the
//!   frame loop), [`inspect`],
//!   [`compare`], [`farm`] (chunked farm jobs) and [`watch`] (re-render on change), driven
//!   by the thin `main`.

// `!(x > 0.0)` is deliberate throughout: it rejects NaN as well as non-positive values.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

pub mod accel;
pub mod anchor;
pub mod bsdf;
pub mod budget;
pub mod cache;
pub mod checkpoint;
pub mod color;
pub mod compare;
pub mod error;
pub mod farm;
pub mod geom;
pub mod inspect;
pub mod integrator;
pub mod interaction;
pub mod job;
pub mod output;
pub mod photon;
pub mod pipeline;
pub mod sampling;
pub mod scene;
pub mod session;
pub mod stats;
pub mod visibility;
pub mod watch;

pub use error::{Error, Result};
