mod cli;
pub mod common;
mod lighting;
mod python;
mod scenes;
mod tags;
