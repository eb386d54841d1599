//! Renders one variant over the job's frames, in memory, timing each frame.

use std::time::Instant;

use super::Variant;
use crate::error::Result;
use crate::integrator::FrameImage;
use crate::job::Job;
use crate::pipeline;
use crate::scene::Scene;
use crate::session::FrameState;
use crate::stats::FrameStats;

/// One variant's frames and their statistics, first frame first.
pub(super) struct Run {
    pub images: Vec<FrameImage>,
    /// Per frame; `timings_s.total` is the frame's wall-clock seconds.
    pub stats: Vec<FrameStats>,
    /// Hemisphere strata per cache record (`m·n`).
    pub strata_per_record: f64,
}

/// Renders every frame of `job` with the method, preset and setting of `v`. Every variant
/// renders the same frames with the same seeds.
pub(super) fn render(job: &Job, scene: &Scene, v: &Variant) -> Result<Run> {
    let mut job = job.clone();
    job.method.name = v.method;
    job.method.preset = v.preset;
    if let Some(s) = &v.setting {
        s.apply(&mut job);
    }
    let resources = pipeline::new_resources(&job, scene)?;
    let mut state = FrameState::default();
    let mut images = Vec::new();
    let mut stats = Vec::new();
    for f in job.frames.start..=job.frames.end {
        let t = Instant::now();
        let mut s = pipeline::new_stats(&job, f);
        let img = pipeline::render_frame(&job, scene, &resources, &mut state, f, &mut s)?;
        s.timings_s.total = t.elapsed().as_secs_f64();
        images.push(img);
        stats.push(s);
    }
    let [m, n] = job.method.params().cache.strata;
    Ok(Run {
        images,
        stats,
        strata_per_record: (m * n) as f64,
    })
}
