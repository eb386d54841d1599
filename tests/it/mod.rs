mod anchors;
mod cli;
pub mod common;
mod gi;
mod gpu;
mod lighting;
mod python;
mod scenes;
mod tags;
