//! The render loop over a job's frames (DESIGN.md, Data flow): evaluate the scene at the
//! frame's time, build the dynamic BVH, shade, write the AOVs and the stats. The static set
//! and its BVH are built once, before the first frame.

use std::io::IsTerminal;
use std::path::PathBuf;
use std::time::Instant;

use crate::anchor::BYTES_PER_ANCHOR;
use crate::cache::Stratum;
use crate::checkpoint;
use crate::error::{Error, Result};
use crate::integrator::cached::{self, CachedMethod, CachedState};
use crate::integrator::path::PathTracer;
use crate::integrator::replay::{DirectKeys, ShadingLog};
use crate::integrator::{FrameContext, FrameImage, direct, path};
use crate::interaction::Materials;
use crate::job::{FrameRange, Job, Method};
use crate::output;
use crate::scene::{Scene, StaticSet};
use crate::session::{FrameState, Resources};
use crate::stats::{AnchorReuse, Counts, FrameStats, Memory, Timings};
use crate::visibility::{self, CpuVisibility};

/// How frames are reported while rendering.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Progress {
    /// A progress bar when stderr is a terminal, else one log line per frame (farm logs).
    Auto,
    Quiet,
}

#[derive(Debug, Clone)]
pub struct RenderOptions {
    pub preview: bool,
    pub progress: Progress,
    pub state: StateOptions,
}

/// Where a render's state comes from and goes to: checkpoints and farm chunks (DESIGN.md,
/// Shot state).
#[derive(Debug, Clone, Default)]
pub struct StateOptions {
    /// Start from this checkpoint: the state after the frame before the first one rendered.
    pub resume: Option<PathBuf>,
    /// Render up to this many frames before the range, without writing them, so that the
    /// range starts from a warm state (a farm chunk that runs in parallel with the others).
    /// Never before the animation's first frame.
    pub warmup: u32,
    /// Write checkpoints to this directory ([`checkpoint::state_path`]).
    pub out: Option<PathBuf>,
    /// ...after every `every`-th frame of the range (1: every frame) and after its last.
    pub every: u32,
}

impl StateOptions {
    /// Whether the state after `frame` of `range` is written.
    fn writes_after(&self, frame: i32, range: FrameRange) -> bool {
        let every = i64::from(self.every.max(1));
        self.out.is_some()
            && (frame == range.end || (i64::from(frame) - i64::from(range.start) + 1) % every == 0)
    }
}

/// The first frame a render of `job` renders: the range's start, or earlier by the warm-up,
/// but not before the animation's first frame.
pub fn first_frame(job: &Job, scene: &Scene, warmup: u32) -> i32 {
    let start = job.frames.start;
    let earliest = i64::from(start) - i64::from(warmup);
    let earliest = match scene.time_range() {
        Some((t0, t1)) => earliest.max(job.frames_in(t0, t1).0 as i64),
        None => earliest,
    };
    earliest.clamp(i64::from(i32::MIN), i64::from(start)) as i32
}

/// Renders one frame in memory: the AOVs and the stats (no files written). `state` carries
/// the cache and anchors from frame to frame.
pub fn render_frame(
    job: &Job,
    scene: &Scene,
    resources: &Resources,
    state: &mut FrameState,
    frame: i32,
    stats: &mut FrameStats,
) -> Result<FrameImage> {
    render_frame_with(
        job,
        scene,
        resources,
        state,
        frame,
        stats,
        cached::Refresh::default(),
        None,
    )
}

/// [`render_frame`] with what watch mode knows about the state ([`cached::Refresh`]) and
/// where it keeps the frame's shading log ([`ShadingLog`]: the cached methods log their
/// shading pass's rays and direct light there, with `keys`, and a relight replays the log
/// it finds).
#[allow(clippy::too_many_arguments)] // render_frame's, and what watch mode keeps
pub fn render_frame_with(
    job: &Job,
    scene: &Scene,
    resources: &Resources,
    state: &mut FrameState,
    frame: i32,
    stats: &mut FrameStats,
    refresh: cached::Refresh,
    log: Option<(&mut ShadingLog, &DirectKeys)>,
) -> Result<FrameImage> {
    let aspect = job.width as f32 / job.height as f32;
    let (fs, et) = scene.evaluate(job.time_of(frame), aspect, &resources.statics);
    stats.timings_s.scene_evaluation = et.animation;
    stats.timings_s.dynamic_bvh = et.dynamic_bvh;
    let ctx = FrameContext {
        scene: &fs,
        materials: Materials {
            materials: &scene.materials,
            textures: &scene.textures,
        },
        width: job.width,
        height: job.height,
        seed: job.seed,
        frame,
    };
    let start = Instant::now();
    let params = job.method.params();
    let rs = &job.render;
    let cached = match job.method.name {
        Method::Direct | Method::PathTrace => None,
        Method::BruteForce => Some(CachedMethod::BruteForce),
        Method::Precomputed => Some(CachedMethod::Precomputed),
        Method::Anchors => Some(CachedMethod::Anchors),
    };
    let (mut img, rc) = match (job.method.name, cached) {
        (_, Some(method)) => {
            let state = CachedState {
                cache: &mut state.cache,
                anchors: &mut state.anchors,
                keys: log.as_ref().map(|l| l.1),
                log: log.map(|l| l.0),
            };
            let (img, rc, gs) = cached::render(
                &ctx,
                state,
                &params,
                method,
                resources.visibility.as_ref(),
                rs.samples_per_pixel,
                rs.light_samples,
                refresh,
            )
            .map_err(|e| Error::Render(format!("frame {frame}: {e}")))?;
            let t = &mut stats.timings_s;
            t.photon_tracing = gs.photon_tracing;
            t.irradiance_estimation = gs.irradiance_estimation;
            t.attachment = gs.attachment;
            t.integration = gs.integration;
            t.placement = gs.placement;
            t.upkeep = gs.upkeep;
            t.final_gathering = gs.final_gathering;
            t.cache_interpolation = gs.cache_interpolation;
            t.depth_maps = gs.depth_maps;
            t.direct_lighting = gs.direct_lighting;
            t.camera_rays = gs.camera_rays;
            let c = &mut stats.counts;
            c.photons = gs.photons;
            c.caches = gs.caches;
            c.caches_spot = gs.caches_spot;
            c.caches_spot_made = gs.caches_spot_made;
            c.rays_shot = gs.rays_shot;
            c.uncached_samples = gs.uncached_samples;
            c.gather_shadow_rays = gs.gather_shadow_rays;
            c.caches_retired = gs.caches_retired;
            c.rays_reshot = gs.rays_shot - gs.uncached_rays;
            if let Some(a) = &gs.anchors {
                stats.visibility = Some(resources.visibility.name());
                c.anchors = a.anchors;
                c.anchors_created = a.anchors_created;
                c.anchors_reestimated = a.anchors_reestimated;
                c.rays_reshot = a.rays_reshot;
                c.strata_flagged = a.strata_flagged;
                stats.timings_s.visibility = a.visibility_s;
                stats.anchor_reuse = Some(AnchorReuse {
                    one: a.reuse_histogram[0],
                    two_to_10: a.reuse_histogram[1],
                    eleven_to_100: a.reuse_histogram[2],
                    hundred_one_to_1000: a.reuse_histogram[3],
                    over_1000: a.reuse_histogram[4],
                });
                stats.memory.bytes_per_anchor = BYTES_PER_ANCHOR as u64;
                stats.memory.anchors_bytes = a.anchors * BYTES_PER_ANCHOR as u64;
            }
            let strata = params.cache.strata[0] * params.cache.strata[1];
            stats.memory.bytes_per_stratum = size_of::<Stratum>() as u64;
            stats.memory.strata_bytes = c.caches * strata as u64 * size_of::<Stratum>() as u64;
            (img, rc)
        }
        (Method::PathTrace, None) => {
            let tracer = PathTracer {
                depth: params.path_depth,
                light_samples: rs.light_samples,
                sampling: params.path_sampling,
            };
            let r = path::render(&ctx, params.path_samples, &tracer);
            stats.timings_s.direct_lighting = start.elapsed().as_secs_f64();
            r
        }
        (_, None) => {
            let r = direct::render(&ctx, rs.samples_per_pixel, rs.light_samples);
            stats.timings_s.direct_lighting = start.elapsed().as_secs_f64();
            r
        }
    };
    if scene.emission_scale != 1.0 {
        img.unscale(scene.emission_scale);
    }
    let c = &mut stats.counts;
    c.triangles_static = fs.static_geometry.len() as u64;
    c.triangles_dynamic = fs.dynamic_geometry.len() as u64;
    c.punctual_lights = fs.lights.len() as u64;
    c.emissive_triangles = fs.emitters.list.len() as u64;
    c.pixels = job.width as u64 * job.height as u64;
    c.camera_rays = rc.camera_rays;
    c.shadow_rays = rc.shadow_rays;
    c.glossy_rays = rc.glossy_rays;
    let mem = &mut stats.memory;
    mem.geometry_static_bytes = fs.static_geometry.bytes() as u64;
    mem.geometry_dynamic_bytes = fs.dynamic_geometry.bytes() as u64;
    mem.bvh_static_bytes = resources.statics.bvh.bytes() as u64;
    mem.bvh_dynamic_bytes = fs.accel.dynamic_bytes() as u64;
    mem.image_bytes = c.pixels * 8 * 4;
    Ok(img)
}

/// The resources of a render of `job`: the static set with its BVH and, for the anchor
/// method, the visibility implementation that `render.visibility` chooses.
pub fn new_resources(job: &Job, scene: &Scene) -> Result<Resources> {
    with_statics(job, scene.statics())
}

/// [`new_resources`] around a static set already built.
fn with_statics(job: &Job, statics: StaticSet) -> Result<Resources> {
    let visibility = if job.method.name == Method::Anchors {
        visibility::gpu::choose(job.render.visibility).map_err(|e| Error::Render(e.to_string()))?
    } else {
        Box::new(CpuVisibility)
    };
    Ok(Resources {
        statics,
        visibility,
    })
}

/// Stats of `frame` with every number zero.
pub fn new_stats(job: &Job, frame: i32) -> FrameStats {
    FrameStats {
        frame,
        time: job.time_of(frame),
        method: job.method.name.name(),
        visibility: None,
        resolution: [job.width, job.height],
        samples_per_pixel: match job.method.name {
            Method::PathTrace => job.method.params().path_samples,
            _ => job.render.samples_per_pixel,
        },
        timings_s: Timings::default(),
        counts: Counts::default(),
        memory: Memory::default(),
        anchor_reuse: None,
    }
}

/// A preview with more than this fraction of its pixels clipped gets a warning (once).
const CLIPPED_WARNING: f32 = 0.2;

/// A frame's files under their final names.
pub struct WrittenFrame {
    pub exr: PathBuf,
    /// The fraction of the preview's pixels that clip and the exposure that would fit them
    /// (`None` without a preview).
    pub preview_fit: Option<output::PreviewExposure>,
}

/// Writes one frame atomically: the stats JSON, the optional PNG preview and the EXR are
/// staged under temporary names and renamed together, the EXR last (an EXR under its final
/// name means a whole frame). `stats.timings_s.output` is filled in before the stats are
/// written.
pub fn write_frame(
    job: &Job,
    frame: i32,
    img: &FrameImage,
    stats: &mut FrameStats,
    preview: bool,
) -> Result<WrittenFrame> {
    let t_out = Instant::now();
    let exr = job.frame_path(frame, "exr");
    let staged_exr = output::stage_exr(&exr, img)?;
    let mut files = Vec::new();
    let mut preview_fit = None;
    if preview {
        let (png, fit) = output::stage_png(&job.frame_path(frame, "png"), img, job.exposure)?;
        files.push(png);
        preview_fit = Some(fit);
    }
    stats.timings_s.output = t_out.elapsed().as_secs_f64();
    stats.timings_s.total += stats.timings_s.output;
    files.insert(
        0,
        output::stage_json(&job.frame_path(frame, "json"), stats)?,
    );
    files.push(staged_exr);
    output::commit(files)?;
    Ok(WrittenFrame { exr, preview_fit })
}

/// Renders every frame of the job and writes EXR, stats JSON and (optionally) PNG per frame.
/// The output directory is checked before the first frame renders.
pub fn render_job(job: &Job, scene: &Scene, opts: RenderOptions) -> Result<Vec<FrameStats>> {
    let so = &opts.state;
    let hash = match (&so.resume, &so.out) {
        (None, None) => None,
        _ => Some(checkpoint::job_hash(job, scene)?),
    };
    // No frame's files, nor a state written, may replace an input.
    let exts: &[&str] = if opts.preview {
        &["exr", "json", "png"]
    } else {
        &["exr", "json"]
    };
    output::refuse_inputs(
        "output",
        (job.frames.start..=job.frames.end)
            .flat_map(|f| exts.iter().map(move |e| job.frame_path(f, e)))
            .chain(so.out.iter().flat_map(|d| {
                (job.frames.start..=job.frames.end).map(|f| checkpoint::state_path(d, job, f))
            })),
    )?;
    // The state to resume from is read, and refused, before any directory is made.
    let resumed = match (&so.resume, hash) {
        (Some(path), Some(hash)) => {
            let p = job.method.params();
            let strata = (p.cache.strata[0] * p.cache.strata[1]) as usize;
            let (after, resumed) = checkpoint::read(path, hash, strata)?;
            if i64::from(after) + 1 != i64::from(job.frames.start) {
                return Err(Error::input(
                    path,
                    "frame",
                    format!(
                        "is the state after frame {after}; the range starts at frame {}, which \
                         needs the state after frame {}",
                        job.frames.start,
                        i64::from(job.frames.start) - 1
                    ),
                ));
            }
            Some(resumed)
        }
        _ => None,
    };
    // Every directory checked before any is made.
    output::check_output_dir_unmade(&job.out_dir)?;
    if let Some(dir) = &so.out {
        output::check_output_dir_unmade(dir)?;
    }
    output::check_output_dir(&job.out_dir)?;
    if let Some(dir) = &so.out {
        output::check_output_dir(dir)?;
    }
    // The static set's time is the stats' `static_bvh`; the adapter probe is not in it.
    let start = Instant::now();
    let statics = scene.statics();
    let static_time = start.elapsed().as_secs_f64();
    let resources = with_statics(job, statics)?;
    let (mut state, first) = match resumed {
        Some(state) => (state, job.frames.start),
        None => (FrameState::default(), first_frame(job, scene, so.warmup)),
    };
    let frames: Vec<i32> = (first..=job.frames.end).collect();
    let bar = (opts.progress == Progress::Auto && std::io::stderr().is_terminal()).then(|| {
        let b = indicatif::ProgressBar::new(frames.len() as u64);
        b.set_style(
            indicatif::ProgressStyle::with_template(
                "{elapsed_precise} [{bar:40}] {pos}/{len} frames, eta {eta} {msg}",
            )
            .expect("valid template")
            .progress_chars("=> "),
        );
        b
    });
    let mut all = Vec::new();
    let mut warned_clipping = false;
    for (i, &frame) in frames.iter().enumerate() {
        let t0 = Instant::now();
        let mut stats = new_stats(job, frame);
        if i == 0 {
            stats.timings_s.static_bvh = static_time;
        }
        let img = render_frame(job, scene, &resources, &mut state, frame, &mut stats)?;
        stats.timings_s.total = t0.elapsed().as_secs_f64() + stats.timings_s.static_bvh;
        if frame < job.frames.start {
            // A warm-up frame: its state is what counts.
            match &bar {
                Some(b) => b.inc(1),
                None if opts.progress == Progress::Auto => eprintln!(
                    "anchorage: warm-up frame {frame} ({}/{}) {:.2} s, {} gather rays (not written)",
                    i + 1,
                    frames.len(),
                    stats.timings_s.total,
                    stats.counts.rays_shot,
                ),
                None => {}
            }
            continue;
        }
        let written = write_frame(job, frame, &img, &mut stats, opts.preview)?;
        // After the frame: a checkpoint never names a frame that is not on disk.
        if let (Some(dir), Some(hash)) = (&so.out, hash)
            && so.writes_after(frame, job.frames)
        {
            checkpoint::write(
                &checkpoint::state_path(dir, job, frame),
                hash,
                frame,
                &state,
            )?;
        }
        if let Some(fit) = written.preview_fit
            && fit.clipped > CLIPPED_WARNING
            && !warned_clipping
        {
            warned_clipping = true;
            let msg = format!(
                "anchorage: warning: {:.0} % of frame {frame}'s preview clips at exposure \
                 {:+}; --exposure {:+} puts its 99th-percentile luminance at white (the \
                 EXRs are unaffected)",
                100.0 * fit.clipped,
                job.exposure,
                fit.suggested
            );
            match &bar {
                Some(b) => b.println(msg),
                None if opts.progress == Progress::Auto => eprintln!("{msg}"),
                None => {}
            }
        }
        match &bar {
            Some(b) => {
                b.set_message(format!("frame {frame}: {:.2} s", stats.timings_s.total));
                b.inc(1);
            }
            None if opts.progress == Progress::Auto => eprintln!(
                "anchorage: frame {frame} ({}/{}) {:.2} s, {} camera rays, {} shadow rays at camera hits, {} at gather hits and anchors, {} gather rays, {} caches -> {}",
                i + 1,
                frames.len(),
                stats.timings_s.total,
                stats.counts.camera_rays,
                stats.counts.shadow_rays,
                stats.counts.gather_shadow_rays,
                stats.counts.rays_shot,
                stats.counts.caches,
                written.exr.display()
            ),
            None => {}
        }
        all.push(stats);
    }
    if let Some(b) = bar {
        b.finish();
    }
    Ok(all)
}
