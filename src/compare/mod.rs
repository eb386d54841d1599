//! `anchorage compare`: measures the speed/accuracy trade of methods and presets on one job
//! (DESIGN.md, Speed versus accuracy). Every method renders the same frames with the same
//! seeds; each is scored against a reference method by
//!
//! - seconds per frame (median of the frames' totals),
//! - RMS relative error in %: `100·sqrt(Σ(m − r)² / Σ r²)` over the beauty's RGB, averaged
//!   over frames,
//! - temporal flicker in %: the mean absolute frame-to-frame change of the method's beauty
//!   over pixels where the reference does not change (coverage equal, depth within 1 % in
//!   both frames), relative to the reference's mean there. A moving camera leaves few such
//!   pixels: the report says how many were compared.
//!
//! The last two again on the `indirect` AOV alone, where the methods differ most.
//!
//! Output: a table on stdout, `compare.json`, and `compare.png` / `compare.svg` (both
//! errors against time).
//!
//! The stages, one file each: [`plan`] (flags → variants and reference), `run` (render a
//! variant), `score` (error, flicker, Table 1 seconds), `table` (the text tables), `plot`.

pub mod plan;
mod plot;
mod run;
pub mod score;
mod table;

use std::path::{Path, PathBuf};

pub use plan::{Plan, Setting, Variant};
pub use score::{Aov, Report, Score, Table1, flicker_pct, rms_error_pct};
pub use table::table;

use crate::error::Result;
use crate::job::Job;
use crate::output;
use crate::scene::Scene;

/// Renders the reference and every variant of `plan` over the job's frames and scores them.
pub fn run(job: &Job, scene: &Scene, plan: &Plan) -> Result<Report> {
    let reference = run::render(job, scene, &plan.reference)?;
    let mut results = Vec::new();
    for v in &plan.variants {
        let r = run::render(job, scene, v)?;
        results.push(score::score(v, &r, &reference));
    }
    Ok(score::report(job, &plan.reference, &reference, results))
}

/// Writes `compare.json`, `compare.png` and `compare.svg` into `dir`; returns their paths.
pub fn write(dir: &Path, r: &Report) -> Result<[PathBuf; 3]> {
    output::check_output_dir(dir)?;
    let json = dir.join("compare.json");
    output::write_json(&json, r)?;
    let [png, svg] = plot::write(dir, r)?;
    Ok([json, png, svg])
}
