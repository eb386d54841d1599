//! The render loop over a job's frames (DESIGN.md, Data flow): evaluate the scene at the
//! frame's time, build the dynamic BVH, shade, write the AOVs and the stats. The static set
//! and its BVH are built once, before the first frame.

use std::io::IsTerminal;
use std::time::Instant;

use serde::Serialize;

use crate::error::{Error, Result};
use crate::gi::{self, Session};
use crate::job::{Job, Method};
use crate::output;
use crate::render::{self, FrameImage, Materials};
use crate::scene::{Scene, StaticSet};

/// Per-stage wall-clock seconds (`schemas/stats.schema.json`).
#[derive(Debug, Clone, Default, Serialize)]
pub struct Timings {
    /// Evaluating animation, skinning and morphing of dynamic prims.
    pub scene_evaluation: f64,
    /// Evaluating static prims and building their BVH (first frame of a render only).
    pub static_bvh: f64,
    pub dynamic_bvh: f64,
    /// The paper's Table 1 rows: photon tracing, irradiance estimation (photon lookups at
    /// gather hits, or precomputation), final gathering (tracing gather rays) and cache
    /// interpolation (shading from the cache). Zero for methods without that stage.
    pub photon_tracing: f64,
    pub irradiance_estimation: f64,
    pub final_gathering: f64,
    pub cache_interpolation: f64,
    /// Detecting strata that may see dynamic prims (`anchors`, paper §3.2).
    pub visibility: f64,
    /// Direct light at camera hits (for `path-trace`: the whole path tracing).
    pub direct_lighting: f64,
    pub output: f64,
    pub total: f64,
}

#[derive(Debug, Clone, Default, Serialize)]
pub struct Counts {
    pub triangles_static: u64,
    pub triangles_dynamic: u64,
    pub punctual_lights: u64,
    pub emissive_triangles: u64,
    pub pixels: u64,
    pub camera_rays: u64,
    pub shadow_rays: u64,
    /// Photons stored this frame.
    pub photons: u64,
    /// Irradiance cache records in use this frame.
    pub caches: u64,
    /// Final-gather rays traced this frame.
    pub rays_shot: u64,
    /// Pixel samples no cache record covered, gathered on the spot.
    pub uncached_samples: u64,
    /// Final-gather rays traced this frame by records that existed before it (for
    /// `anchors`, the re-shot strata; for brute force, every stratum of every record).
    pub rays_reshot: u64,
    /// `anchors`: anchors whose irradiance was estimated again this frame.
    pub anchors_reestimated: u64,
    /// Live anchors, and anchors created this frame (`anchors`).
    pub anchors: u64,
    pub anchors_created: u64,
}

/// Live anchors by how many strata link them (the paper's Figure 8).
#[derive(Debug, Clone, Default, Serialize)]
pub struct AnchorReuse {
    #[serde(rename = "1")]
    pub one: u64,
    #[serde(rename = "2-10")]
    pub two_to_10: u64,
    #[serde(rename = "11-100")]
    pub eleven_to_100: u64,
    #[serde(rename = "101-1000")]
    pub hundred_one_to_1000: u64,
    #[serde(rename = ">1000")]
    pub over_1000: u64,
}

#[derive(Debug, Clone, Default, Serialize)]
pub struct Memory {
    pub geometry_static_bytes: u64,
    pub geometry_dynamic_bytes: u64,
    pub bvh_static_bytes: u64,
    pub bvh_dynamic_bytes: u64,
    pub image_bytes: u64,
    /// Cached methods: bytes of one stratum and of all strata; `anchors`: of one anchor and
    /// of all anchors.
    pub bytes_per_stratum: u64,
    pub strata_bytes: u64,
    pub bytes_per_anchor: u64,
    pub anchors_bytes: u64,
}

/// The stats JSON written beside each frame.
#[derive(Debug, Clone, Serialize)]
pub struct FrameStats {
    pub frame: i32,
    /// Animation time of the frame in seconds.
    pub time: f32,
    pub method: &'static str,
    /// `anchors` only: the visibility implementation that ran.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub visibility: Option<String>,
    pub resolution: [u32; 2],
    pub samples_per_pixel: u32,
    pub timings_s: Timings,
    pub counts: Counts,
    pub memory: Memory,
    /// `anchors` only.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub anchor_reuse: Option<AnchorReuse>,
}

/// How frames are reported while rendering.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Progress {
    /// A progress bar when stderr is a terminal, else one log line per frame (farm logs).
    Auto,
    Quiet,
}

#[derive(Debug, Clone, Copy)]
pub struct RenderOptions {
    pub preview: bool,
    pub progress: Progress,
}

/// Renders one frame in memory: the AOVs and the stats (no files written). `session` carries
/// the irradiance cache from frame to frame.
pub fn render_frame(
    job: &Job,
    scene: &Scene,
    statics: &StaticSet,
    session: &mut Session,
    frame: i32,
    stats: &mut FrameStats,
) -> Result<FrameImage> {
    let t = job.time_of(frame);
    let start = Instant::now();
    let dynamic = scene.geometry(t, crate::scene::Motion::Dynamic);
    stats.timings_s.scene_evaluation = start.elapsed().as_secs_f64();
    let start = Instant::now();
    let fs = crate::scene::FrameScene::new(
        statics,
        dynamic,
        scene.lights(t),
        scene.camera_at(t, job.width as f32 / job.height as f32),
        &scene.materials,
    );
    stats.timings_s.dynamic_bvh = start.elapsed().as_secs_f64();
    let m = Materials {
        materials: &scene.materials,
        textures: &scene.textures,
    };
    let start = Instant::now();
    let params = job.method.params();
    let rs = &job.render;
    let (img, rc) = match job.method.name {
        Method::Direct => {
            let r = render::render_direct(&fs, m, rs, job.width, job.height, job.seed, frame);
            stats.timings_s.direct_lighting = start.elapsed().as_secs_f64();
            r
        }
        Method::BruteForce | Method::Precomputed | Method::Anchors => {
            let pre = match job.method.name {
                Method::Precomputed => gi::CachedMethod::Precomputed,
                Method::Anchors => gi::CachedMethod::Anchors,
                _ => gi::CachedMethod::BruteForce,
            };
            let (img, rc, gs) = gi::render_cached(
                &fs,
                m,
                session,
                &params,
                pre,
                rs.samples_per_pixel,
                rs.light_samples,
                job.width,
                job.height,
                job.seed,
                frame,
            )
            .map_err(|e| Error::Render(format!("frame {frame}: {e}")))?;
            let t = &mut stats.timings_s;
            t.photon_tracing = gs.photon_tracing;
            t.irradiance_estimation = gs.irradiance_estimation;
            t.final_gathering = gs.final_gathering;
            t.cache_interpolation = gs.cache_interpolation;
            t.direct_lighting = gs.direct_lighting;
            let c = &mut stats.counts;
            c.photons = gs.photons;
            c.caches = gs.caches;
            c.rays_shot = gs.rays_shot;
            c.uncached_samples = gs.uncached_samples;
            c.rays_reshot = gs.rays_shot;
            if let Some(a) = &gs.anchors {
                stats.visibility = Some(match &session.visibility {
                    Some(v) => v.name(),
                    None => gi::visibility::Visibility::name(&gi::visibility::CpuVisibility),
                });
                c.anchors = a.anchors;
                c.anchors_created = a.anchors_created;
                c.anchors_reestimated = a.anchors_reestimated;
                c.rays_reshot = a.rays_reshot;
                stats.timings_s.visibility = a.visibility_s;
                stats.anchor_reuse = Some(AnchorReuse {
                    one: a.reuse_histogram[0],
                    two_to_10: a.reuse_histogram[1],
                    eleven_to_100: a.reuse_histogram[2],
                    hundred_one_to_1000: a.reuse_histogram[3],
                    over_1000: a.reuse_histogram[4],
                });
                stats.memory.bytes_per_anchor = gi::anchors::BYTES_PER_ANCHOR as u64;
                stats.memory.anchors_bytes = a.anchors * gi::anchors::BYTES_PER_ANCHOR as u64;
            }
            stats.memory.bytes_per_stratum = size_of::<gi::cache::Stratum>() as u64;
            stats.memory.strata_bytes = c.caches
                * (job.method.params().cache.strata[0] * job.method.params().cache.strata[1])
                    as u64
                * size_of::<gi::cache::Stratum>() as u64;
            (img, rc)
        }
        Method::PathTrace => {
            let r = gi::path_trace(
                &fs,
                m,
                params.path_samples,
                params.path_depth,
                rs.light_samples,
                job.width,
                job.height,
                job.seed,
                frame,
            );
            stats.timings_s.direct_lighting = start.elapsed().as_secs_f64();
            r
        }
    };
    let c = &mut stats.counts;
    c.triangles_static = fs.static_geometry.len() as u64;
    c.triangles_dynamic = fs.dynamic_geometry.len() as u64;
    c.punctual_lights = fs.lights.len() as u64;
    c.emissive_triangles = fs.emitters.list.len() as u64;
    c.pixels = job.width as u64 * job.height as u64;
    c.camera_rays = rc.camera_rays;
    c.shadow_rays = rc.shadow_rays;
    let mem = &mut stats.memory;
    mem.geometry_static_bytes = fs.static_geometry.bytes() as u64;
    mem.geometry_dynamic_bytes = fs.dynamic_geometry.bytes() as u64;
    mem.bvh_static_bytes = statics.bvh.bytes() as u64;
    mem.bvh_dynamic_bytes = fs.accel.dynamic_bytes() as u64;
    mem.image_bytes = c.pixels * 8 * 4;
    Ok(img)
}

/// A session for `job`: empty caches and, for the anchor method, the visibility
/// implementation that `render.visibility` chooses.
pub fn new_session(job: &Job) -> Result<Session> {
    let mut session = Session::default();
    if job.method.name == Method::Anchors {
        session.visibility = gi::gpu::choose(job.render.visibility).map_err(Error::Render)?;
    }
    Ok(session)
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

/// Renders every frame of the job and writes EXR, stats JSON and (optionally) PNG per frame.
/// The output directory is checked before the first frame renders.
pub fn render_job(job: &Job, scene: &Scene, opts: RenderOptions) -> Result<Vec<FrameStats>> {
    output::check_output_dir(&job.out_dir)?;
    let start = Instant::now();
    let statics = scene.statics();
    let static_time = start.elapsed().as_secs_f64();
    let frames: Vec<i32> = (job.frames.start..=job.frames.end).collect();
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
    let mut session = new_session(job)?;
    for (i, &frame) in frames.iter().enumerate() {
        let t0 = Instant::now();
        let mut stats = new_stats(job, frame);
        if i == 0 {
            stats.timings_s.static_bvh = static_time;
        }
        let img = render_frame(job, scene, &statics, &mut session, frame, &mut stats)?;
        let t_out = Instant::now();
        let exr = job.frame_path(frame, "exr");
        output::write_exr(&exr, &img)?;
        if opts.preview {
            output::write_png(&job.frame_path(frame, "png"), &img)?;
        }
        stats.timings_s.output = t_out.elapsed().as_secs_f64();
        stats.timings_s.total = t0.elapsed().as_secs_f64() + stats.timings_s.static_bvh;
        output::write_json(&job.frame_path(frame, "json"), &stats)?;
        match &bar {
            Some(b) => {
                b.set_message(format!("frame {frame}: {:.2} s", stats.timings_s.total));
                b.inc(1);
            }
            None if opts.progress == Progress::Auto => eprintln!(
                "anchorage: frame {frame} ({}/{}) {:.2} s, {} camera rays, {} shadow rays, {} gather rays, {} caches -> {}",
                i + 1,
                frames.len(),
                stats.timings_s.total,
                stats.counts.camera_rays,
                stats.counts.shadow_rays,
                stats.counts.rays_shot,
                stats.counts.caches,
                exr.display()
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
