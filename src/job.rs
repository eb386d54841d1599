//! Job files: what to render and how. Config flows once (STYLE.md §3): the JSON file is
//! deserialised with unknown keys rejected ([`JobFile`]), command-line overrides are applied
//! in one place ([`Overrides`]), and the result is a validated, immutable [`Job`].
//!
//! The schema is published in `schemas/job.schema.json`; README.md documents every key and
//! its default.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use clap::ValueEnum;
use glam::{DMat4, DQuat, DVec3, EulerRot, Vec3};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use crate::anchor::AnchorParams;
use crate::error::{Error, Result};
use crate::geom::Motion;
use crate::integrator::{GiParams, Preset};
use crate::photon::GatherDirect;
use crate::scene::{CameraSpec, Clip, LayerDesc, LookAt, Scene, SceneDesc};
pub use crate::visibility::VisibilityChoice;

/// The job file as written on disk.
#[derive(Debug, Clone, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct JobFile {
    /// glTF layers composed into one scene, like USD references. At least one.
    pub scene: Vec<LayerFile>,
    /// Camera: a glTF camera node by name, or one given here. Default: the first glTF camera.
    #[serde(default)]
    pub camera: Option<CameraFile>,
    /// Image size in pixels, `[width, height]`, each 1..=16384. Default `[640, 360]`.
    #[serde(default = "default_resolution")]
    #[schemars(inner(range(min = 1, max = 16384)))]
    pub resolution: [u32; 2],
    /// Inclusive frame range. Default: frame 0 only.
    #[serde(default)]
    pub frames: Option<FrameRange>,
    /// Frames per second for frame ↔ time mapping. Default 24.
    #[serde(default = "default_fps")]
    #[schemars(extend("exclusiveMinimum" = 0))]
    pub fps: f64,
    /// The frame number at animation time 0 (Blender's exporter writes time 0 at its scene's
    /// start frame, usually 1). Default 0: frame `f` is at time `f / fps`.
    #[serde(default)]
    pub frame_offset: f64,
    /// Where frames go. Default: directory `render` beside the job file, name = job file stem.
    #[serde(default)]
    pub output: Option<OutputFile>,
    /// Seed of every random number. Default 0.
    #[serde(default)]
    pub seed: u32,
    /// Sampling settings.
    #[serde(default)]
    pub render: RenderSettings,
    /// Method settings (the global-illumination method and its parameters).
    #[serde(default)]
    pub method: MethodSettings,
}

impl JobFile {
    /// A job of one scene file with every default (`inspect SCENE.gltf`, the fuzzer).
    pub fn for_scene(path: PathBuf) -> JobFile {
        JobFile {
            scene: vec![LayerFile {
                path,
                transform: Default::default(),
                tags: Default::default(),
                animations: None,
            }],
            camera: None,
            resolution: default_resolution(),
            frames: None,
            fps: default_fps(),
            frame_offset: 0.0,
            output: None,
            seed: 0,
            render: Default::default(),
            method: Default::default(),
        }
    }
}

fn default_resolution() -> [u32; 2] {
    [640, 360]
}
fn default_fps() -> f64 {
    24.0
}

/// One glTF file in the composition.
#[derive(Debug, Clone, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct LayerFile {
    /// Path of the `.gltf` or `.glb`, relative to the job file.
    pub path: PathBuf,
    /// Transform applied to the whole layer (cameras and lights included).
    #[serde(default)]
    pub transform: TransformFile,
    /// Motion tags by node name; they win over tags in the file.
    #[serde(default)]
    pub tags: BTreeMap<String, Motion>,
    /// The animation clips that play, by name or as `animations[i]`. Default: all of them
    /// (with a warning where two drive the same property of a node: the first in the file
    /// wins). `[]` plays none.
    #[serde(default)]
    pub animations: Option<Vec<String>>,
}

/// A layer transform: scale, then rotation, then translation.
#[derive(Debug, Clone, Default, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct TransformFile {
    #[serde(default)]
    pub translation: Option<[f64; 3]>,
    /// Rotation as XYZ Euler angles in degrees.
    #[serde(default)]
    pub rotation_deg: Option<[f64; 3]>,
    /// Uniform scale (a number) or per-axis scale (three numbers).
    #[serde(default)]
    pub scale: Option<Scale>,
}

#[derive(Debug, Clone, Copy, Deserialize, JsonSchema)]
#[serde(untagged)]
pub enum Scale {
    Uniform(f64),
    Axes([f64; 3]),
}

impl TransformFile {
    /// In f64, like every world transform (a layer placed 1e6 from the origin keeps its
    /// sub-millimetre detail until the render-space origin is subtracted).
    pub fn matrix(&self) -> DMat4 {
        let t = self.translation.map(DVec3::from).unwrap_or(DVec3::ZERO);
        let r = self
            .rotation_deg
            .map(|[x, y, z]| {
                DQuat::from_euler(
                    EulerRot::XYZ,
                    x.to_radians(),
                    y.to_radians(),
                    z.to_radians(),
                )
            })
            .unwrap_or(DQuat::IDENTITY);
        let s = match self.scale {
            None => DVec3::ONE,
            Some(Scale::Uniform(s)) => DVec3::splat(s),
            Some(Scale::Axes(a)) => DVec3::from(a),
        };
        DMat4::from_scale_rotation_translation(s, r, t)
    }
}

/// Camera given in the job file.
#[derive(Debug, Clone, JsonSchema)]
#[serde(untagged)]
pub enum CameraFile {
    /// A glTF camera node by name (searched in layer order).
    Node(NodeCamera),
    /// A pinhole camera.
    LookAt(LookAtCamera),
}

/// [`CameraFile::Node`]: the name of a glTF camera node.
#[derive(Debug, Clone, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct NodeCamera {
    pub node: String,
}

/// [`CameraFile::LookAt`]: a pinhole camera placed by the job.
#[derive(Debug, Clone, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct LookAtCamera {
    pub position: [f64; 3],
    pub look_at: [f64; 3],
    #[serde(default = "default_up")]
    pub up: [f32; 3],
    /// Vertical field of view in degrees, in (0, 180).
    #[schemars(extend("exclusiveMinimum" = 0, "exclusiveMaximum" = 180))]
    pub yfov_deg: f32,
    /// Camera rays see nothing nearer than this depth along the view axis. Default 0.
    #[serde(default)]
    #[schemars(range(min = 0))]
    pub znear: f32,
    /// ... nor farther than this one. Default: no far plane.
    #[serde(default)]
    pub zfar: Option<f32>,
}

impl<'de> Deserialize<'de> for CameraFile {
    /// A camera with a `node` key names a node, any other is a look-at camera: deciding by
    /// the key, rather than trying each in turn, lets an error name the key at fault (a
    /// missing `yfov_deg`, an unknown `fov`) instead of saying that no kind matched.
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        use serde::de::Error as _;
        let v = serde_json::Value::deserialize(d)?;
        let camera = if v.get("node").is_some() {
            NodeCamera::deserialize(v).map(CameraFile::Node)
        } else {
            LookAtCamera::deserialize(v).map(CameraFile::LookAt)
        };
        camera.map_err(|e| D::Error::custom(format!("camera: {e}")))
    }
}

fn default_up() -> [f32; 3] {
    [0.0, 1.0, 0.0]
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct FrameRange {
    pub start: i32,
    pub end: i32,
}

#[derive(Debug, Clone, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct OutputFile {
    /// Output directory, relative to the job file. Default `render`.
    #[serde(default)]
    pub directory: Option<PathBuf>,
    /// File name stem: frames are `NAME.####.exr`. Default: the job file's stem.
    #[serde(default)]
    pub name: Option<String>,
    /// Exposure of the PNG previews in stops (`--exposure`): pixel values are scaled by
    /// 2^exposure before the sRGB curve. The EXRs stay in scene radiance. Default 0.
    #[serde(default)]
    #[schemars(range(min = -64, max = 64))]
    pub exposure: f32,
}

/// Sampling settings ([`RenderSettings::default`] gives the defaults).
#[derive(Debug, Clone, Copy, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct RenderSettings {
    /// Camera samples per pixel (box filter over the pixel). Default 16.
    #[schemars(range(min = 1, max = 65536))]
    pub samples_per_pixel: u32,
    /// Samples of the emissive-triangle lights per camera sample. Default 1.
    #[schemars(range(min = 1, max = 1024))]
    pub light_samples: u32,
    /// Where the anchor method's visibility detection runs (`--visibility`). Default auto.
    pub visibility: VisibilityChoice,
}

impl Default for RenderSettings {
    fn default() -> Self {
        RenderSettings {
            samples_per_pixel: 16,
            light_samples: 1,
            visibility: VisibilityChoice::Auto,
        }
    }
}

/// The global-illumination method (`--method` on the command line).
#[derive(
    Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema, clap::ValueEnum,
)]
#[serde(rename_all = "kebab-case")]
pub enum Method {
    /// The paper's anchors: temporally coherent final gathering (the default).
    #[default]
    Anchors,
    /// Emission and direct lighting only; no indirect light.
    Direct,
    /// Photon map + irradiance cache, every stratum re-gathered every frame (paper Table 1).
    BruteForce,
    /// As brute force, with irradiance precomputed at a quarter of the photons (Christensen 1999).
    Precomputed,
    /// Unbiased path tracing with next-event estimation: the reference.
    PathTrace,
}

impl Method {
    /// The method's name as the job file and the command line spell it.
    pub fn name(self) -> String {
        self.to_possible_value()
            .map(|v| v.get_name().to_string())
            .unwrap_or_default()
    }
}

/// Method settings: a preset, then any of its values overridden. Defaults are the
/// `production` preset's (README.md lists them with what each costs and buys).
#[derive(Debug, Clone, Copy, Default, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct MethodSettings {
    /// The method (`--method`). Default `anchors`.
    pub name: Method,
    /// The speed/accuracy preset whose values the keys below override. Default `production`.
    pub preset: Preset,
    /// Photons emitted per frame. Default: the preset's (50 000, 200 000, 800 000).
    #[schemars(range(min = 1, max = 100_000_000))]
    pub photons: Option<u32>,
    /// Photons per irradiance estimate. Default: the preset's (32, 64, 100).
    #[schemars(range(min = 1, max = 1000))]
    pub k: Option<u32>,
    /// No photon look-up (estimate, nearest photon, precomputed irradiance) reaches farther
    /// than this fraction of the static scene's bounding radius, so light does not leak
    /// through closed geometry; in (0, 1]. Default 0.05.
    #[schemars(extend("exclusiveMinimum" = 0, "maximum" = 1))]
    pub max_photon_radius: Option<f32>,
    /// Where a gather hit's direct light from punctual lights comes from: `photons` (the
    /// paper's: the photon map's estimate) or `shadow-rays` (a shadow ray to each punctual
    /// light from each gather hit and anchor; the photon map for the light that has
    /// bounced). Default `shadow-rays`.
    pub gather_direct: Option<GatherDirect>,
    /// `[M, N]`: θ × φ strata of the final gather, M·N rays per cache record. Default: the
    /// preset's (8×24, 12×36, 30×60).
    #[schemars(inner(range(min = 1, max = 256)))]
    pub strata: Option<[u32; 2]>,
    /// Ward's error threshold a, in (0, 2]. Default: the preset's (0.4, 0.25, 0.15).
    #[schemars(extend("exclusiveMinimum" = 0, "maximum" = 2))]
    pub error: Option<f32>,
    /// A record is valid out to a·R, clamped to at least this many pixel footprints
    /// (> 0, at most `max_spacing_px`). Default: the preset's (3, 2, 1.5).
    #[schemars(extend("exclusiveMinimum" = 0))]
    pub min_spacing_px: Option<f32>,
    /// ... and to at most this many. Default: the preset's (32, 24, 16).
    #[schemars(extend("exclusiveMinimum" = 0))]
    pub max_spacing_px: Option<f32>,
    /// Frames a cache record may go unused before it is removed. Default 2.
    pub max_age: Option<u32>,
    /// The paper's N (§4.3): a pixel read from more than this many cache records is
    /// crowded, and the least influential records there are removed (`weber_threshold`),
    /// each only while every pixel it serves keeps this many; 1..=64. Default 6.
    #[schemars(range(min = 1, max = 64))]
    pub weber_records: Option<u32>,
    /// A record in a crowded pixel is removed after the frame where its Weber fraction δ
    /// (§4.3, Equation 1: the sum over the pixels it serves of the relative change of each
    /// when it is left out) is below this; 0 keeps every record. Default 0.5.
    #[schemars(range(min = 0, max = 1000))]
    pub weber_threshold: Option<f32>,
    /// Neighbour clamping (Křivánek et al. 2006): a cache record's radius is at most a
    /// neighbouring record's plus this times their distance, so that records above a
    /// contact stop short of it; 0 turns it off. Default 2.
    #[schemars(range(min = 0, max = 1000))]
    pub neighbour_clamp: Option<f32>,
    /// After the first frame, a pixel centre counts as covered where a cache record made
    /// for an earlier frame that sees no dynamic prim is valid to this multiple of `error`,
    /// instead of getting a record of its own: fewer records as the camera moves, read to
    /// the shading's relaxed threshold (twice `error`); 1 places as densely as on the first
    /// frame. In [1, 2]. Default 2.
    #[schemars(range(min = 1, max = 2))]
    pub coverage_slack: Option<f32>,
    /// `path-trace` samples per pixel. Default: the preset's (64, 256, 1024).
    #[schemars(range(min = 1, max = 1_048_576))]
    pub path_samples: Option<u32>,
    /// `path-trace` maximum path length (Russian roulette ends most paths sooner). Default 64.
    #[schemars(range(min = 1, max = 1024))]
    pub path_depth: Option<u32>,
    /// Photon bounces at most (Russian roulette ends most photon paths sooner). Default 64.
    #[schemars(range(min = 1, max = 1024))]
    pub photon_bounces: Option<u32>,
    /// `path-trace`: how emissive triangles are sampled: `mis` (emitter and BRDF samples
    /// combined), `lights` or `brdf` alone (for checking; all three converge to the same
    /// image). Default `mis`.
    pub path_sampling: Option<crate::integrator::path::PathSampling>,
    /// Cached methods: how moderately glossy lobes (roughness from
    /// `glossy_specular_max_roughness` to `glossy_max_roughness`) gather their indirect light:
    /// `bucketing` (anchor bucketing, paper §5.1; `anchors` only, the other methods sample)
    /// or `importance` (reflection rays). Default `bucketing`.
    pub glossy_mode: Option<crate::integrator::cached::GlossyMode>,
    /// Cached methods: importance-sampled reflection rays per camera sample, for lobes
    /// narrower than `glossy_specular_max_roughness` (and for moderately glossy ones in
    /// `importance` mode). Default 2.
    #[schemars(range(max = 32))]
    pub glossy_rays: Option<u32>,
    /// `anchors`, bucketing: `[M, N]` θ × φ cells of the hemisphere at a moderately glossy
    /// pixel, each 1..=256. Default `[12, 48]`.
    #[schemars(inner(range(min = 1, max = 256)))]
    pub glossy_bucket_strata: Option<[u32; 2]>,
    /// `anchors`, bucketing: a cell's bucket keeps the anchors nearer than its depth ×
    /// (1 + this), in [0, 10]. Default 0.2.
    #[schemars(range(min = 0, max = 10))]
    pub glossy_bucket_offset: Option<f32>,
    /// Cached methods: below this roughness a glossy lobe is highly glossy and always gets
    /// reflection rays. Default 0.35.
    #[schemars(range(min = 0, max = 0.75))]
    pub glossy_specular_max_roughness: Option<f32>,
    /// Cached methods: lobes narrower than this roughness gather their indirect light at the
    /// pixel; wider ones are shaded from the irradiance cache, by its records' fit of the
    /// direction their light arrives from; in [0, 0.75]. Default 0.6.
    #[schemars(range(min = 0, max = 0.75))]
    pub glossy_max_roughness: Option<f32>,
    /// `anchors` settings (each key defaults as documented in README.md).
    pub anchors: Option<AnchorParams>,
}

impl MethodSettings {
    /// The preset with this file's overrides applied.
    pub fn params(&self) -> GiParams {
        let mut p = GiParams::preset(self.preset);
        if let Some(v) = self.photons {
            p.photons = v;
        }
        if let Some(v) = self.k {
            p.k = v;
        }
        if let Some(v) = self.max_photon_radius {
            p.max_photon_radius = v;
        }
        if let Some(v) = self.gather_direct {
            p.gather_direct = v;
        }
        if let Some(v) = self.strata {
            p.cache.strata = v;
        }
        if let Some(v) = self.error {
            p.cache.error = v;
        }
        if let Some(v) = self.min_spacing_px {
            p.cache.min_spacing_px = v;
        }
        if let Some(v) = self.max_spacing_px {
            p.cache.max_spacing_px = v;
        }
        if let Some(v) = self.max_age {
            p.cache.max_age = v;
        }
        if let Some(v) = self.weber_records {
            p.cache.weber_records = v;
        }
        if let Some(v) = self.weber_threshold {
            p.cache.weber_threshold = v;
        }
        if let Some(v) = self.neighbour_clamp {
            p.cache.neighbour_clamp = v;
        }
        if let Some(v) = self.coverage_slack {
            p.cache.coverage_slack = v;
        }
        if let Some(v) = self.path_samples {
            p.path_samples = v;
        }
        if let Some(v) = self.path_depth {
            p.path_depth = v;
        }
        if let Some(v) = self.photon_bounces {
            p.photon_bounces = v;
        }
        if let Some(v) = self.path_sampling {
            p.path_sampling = v;
        }
        if let Some(v) = self.glossy_rays {
            p.glossy.rays = v;
        }
        if let Some(v) = self.glossy_mode {
            p.glossy.mode = v;
        }
        if let Some(v) = self.glossy_specular_max_roughness {
            p.glossy.specular_max_roughness = v;
        }
        if let Some(v) = self.glossy_bucket_strata {
            p.glossy.bucket.strata = v;
        }
        if let Some(v) = self.glossy_bucket_offset {
            p.glossy.bucket.offset = v;
        }
        if let Some(v) = self.glossy_max_roughness {
            p.glossy.max_roughness = v;
        }
        if let Some(v) = self.anchors {
            p.anchors = v;
        }
        p
    }

    /// Checks every value; errors name `method.KEY` in the file at `path`.
    pub fn validate(&self, path: &Path) -> Result<()> {
        let p = self.params();
        let bad = |key: &str, msg: &str| {
            Err(Error::input(path, format!("method.{key}"), msg.to_string()))
        };
        if p.photons == 0 || p.photons > 100_000_000 {
            return bad("photons", "must be 1..=100000000");
        }
        if p.k == 0 || p.k > 1000 {
            return bad("k", "must be 1..=1000");
        }
        if !(p.max_photon_radius > 0.0 && p.max_photon_radius <= 1.0) {
            return bad(
                "max_photon_radius",
                "must be in (0, 1] (a fraction of the static scene's bounding radius)",
            );
        }
        if p.cache.strata.iter().any(|&s| s == 0 || s > 256) {
            return bad("strata", "must be two numbers in 1..=256");
        }
        if !(p.cache.error > 0.0 && p.cache.error <= 2.0) {
            return bad("error", "must be in (0, 2]");
        }
        if !(p.cache.min_spacing_px > 0.0
            && p.cache.min_spacing_px <= p.cache.max_spacing_px
            && p.cache.max_spacing_px.is_finite())
        {
            return bad("min_spacing_px", "must be > 0 and <= max_spacing_px");
        }
        if !(1..=64).contains(&p.cache.weber_records) {
            return bad("weber_records", "must be 1..=64");
        }
        if !(0.0..=1000.0).contains(&p.cache.weber_threshold) {
            return bad(
                "weber_threshold",
                "must be in [0, 1000] (0 keeps every record)",
            );
        }
        if !(0.0..=1000.0).contains(&p.cache.neighbour_clamp) {
            return bad(
                "neighbour_clamp",
                "must be in [0, 1000] (0 turns neighbour clamping off)",
            );
        }
        if !(1.0..=crate::cache::RELAXED).contains(&p.cache.coverage_slack) {
            return bad(
                "coverage_slack",
                "must be in [1, 2] (1: every frame places records as densely as the first)",
            );
        }
        if p.glossy.bucket.strata.iter().any(|&s| s == 0 || s > 256) {
            return bad("glossy_bucket_strata", "each must be 1..=256");
        }
        if !(0.0..=10.0).contains(&p.glossy.bucket.offset) {
            return bad("glossy_bucket_offset", "must be in [0, 10]");
        }
        if p.glossy.rays > 32 {
            return bad("glossy_rays", "must be 0..=32");
        }
        if !(0.0..=p.glossy.max_roughness).contains(&p.glossy.specular_max_roughness) {
            return bad(
                "glossy_specular_max_roughness",
                "must be in [0, glossy_max_roughness]",
            );
        }
        if !(0.0..=crate::integrator::MIS_ROUGHNESS).contains(&p.glossy.max_roughness) {
            return bad(
                "glossy_max_roughness",
                "must be in [0, 0.75] (glossy rays rely on the direct light's BRDF samples there)",
            );
        }
        if p.path_samples == 0 || p.path_samples > 1 << 20 {
            return bad("path_samples", "must be 1..=1048576");
        }
        if p.path_depth == 0 || p.path_depth > 1024 {
            return bad("path_depth", "must be 1..=1024");
        }
        if p.photon_bounces == 0 || p.photon_bounces > 1024 {
            return bad("photon_bounces", "must be 1..=1024");
        }
        let a = p.anchors;
        if !(a.d_max > 0.0 && a.d_max <= 1.0) {
            return bad(
                "anchors.d_max",
                "must be in (0, 1] (a fraction of the scene radius)",
            );
        }
        if a.d_max_absolute
            .is_some_and(|d| !(d > 0.0 && d.is_finite()))
        {
            return bad(
                "anchors.d_max_absolute",
                "must be a positive distance in scene units",
            );
        }
        if !(a.photon_radius > 0.0 && a.photon_radius <= 1.0) {
            return bad("anchors.photon_radius", "must be in (0, 1]");
        }
        if !(-1.0..=1.0).contains(&a.normal_cos) || !(a.albedo_tolerance >= 0.0) {
            return bad(
                "anchors.normal_cos",
                "normal_cos must be in [-1, 1] and albedo_tolerance >= 0",
            );
        }
        if !(a.rebalance >= 1.0 && a.importons_per_pixel > 0.0 && a.importons_per_pixel <= 16.0) {
            return bad(
                "anchors.rebalance",
                "rebalance must be >= 1 and importons_per_pixel in (0, 16]",
            );
        }
        if a.k_scale.is_some_and(|s| !(s > 0.0 && s <= 64.0)) {
            return bad("anchors.k_scale", "must be in (0, 64]");
        }
        Ok(())
    }
}

/// Command-line overrides, applied to the job file in one place ([`Job::load`]).
#[derive(Debug, Clone, Default)]
pub struct Overrides {
    pub frames: Option<FrameRange>,
    pub out_dir: Option<PathBuf>,
    pub method: Option<Method>,
    pub visibility: Option<VisibilityChoice>,
    /// Preview exposure in stops.
    pub exposure: Option<f32>,
}

/// A validated job: paths resolved, ranges checked.
#[derive(Debug, Clone)]
pub struct Job {
    pub path: PathBuf,
    pub layers: Vec<LayerDesc>,
    pub camera: Option<CameraSpec>,
    pub width: u32,
    pub height: u32,
    pub frames: FrameRange,
    pub fps: f64,
    pub frame_offset: f64,
    pub out_dir: PathBuf,
    pub name: String,
    /// Preview exposure in stops ([`OutputFile::exposure`]).
    pub exposure: f32,
    pub seed: u32,
    pub render: RenderSettings,
    pub method: MethodSettings,
}

impl Job {
    /// Reads, validates and applies `overrides` to the job file at `path`.
    pub fn load(path: &Path, overrides: &Overrides) -> Result<Job> {
        let text = read_job_text(path)?;
        let file: JobFile = serde_json::from_str(&text).map_err(|e| json_error(path, &text, &e))?;
        Job::from_file(path, file, overrides)
    }

    /// Validates an already-parsed job file; `path` locates relative paths and names errors.
    pub fn from_file(path: &Path, file: JobFile, overrides: &Overrides) -> Result<Job> {
        let base = path.parent().unwrap_or(Path::new("."));
        if file.scene.is_empty() {
            return Err(Error::input(
                path,
                "scene",
                "at least one scene layer is required",
            ));
        }
        let [width, height] = file.resolution;
        if width == 0 || height == 0 || width > 16384 || height > 16384 {
            return Err(Error::input(
                path,
                "resolution",
                format!("must be 1..=16384 pixels each, got {width}x{height}"),
            ));
        }
        // Frame times are f32 seconds: half a frame must be one.
        if !(file.fps.is_finite() && file.fps > 0.0 && ((0.5 / file.fps) as f32).is_finite()) {
            return Err(Error::input(
                path,
                "fps",
                format!(
                    "must be > 0 with half a frame's seconds finite in f32, got {:e}",
                    file.fps
                ),
            ));
        }
        if !file.frame_offset.is_finite() {
            return Err(Error::input(path, "frame_offset", "must be finite"));
        }
        let frames = overrides
            .frames
            .or(file.frames)
            .unwrap_or(FrameRange { start: 0, end: 0 });
        if frames.end < frames.start {
            return Err(Error::input(
                path,
                "frames",
                format!("end {} is before start {}", frames.end, frames.start),
            ));
        }
        let count = i64::from(frames.end) - i64::from(frames.start) + 1;
        if count > MAX_FRAMES {
            return Err(Error::input(
                path,
                "frames",
                format!("{count} frames in one job; at most {MAX_FRAMES} (split the shot)"),
            ));
        }
        let render = render_settings(path, file.render, overrides)?;
        let mut method = file.method;
        if let Some(m) = overrides.method {
            method.name = m;
        }
        method.validate(path)?;
        let layers = layers(path, base, &file.scene)?;
        let camera = file.camera.map(|c| camera(path, c)).transpose()?;
        let (out_dir, name, exposure) = output(path, base, file.output, overrides)?;
        Ok(Job {
            path: path.to_path_buf(),
            layers,
            camera,
            width,
            height,
            frames,
            fps: file.fps,
            frame_offset: file.frame_offset,
            out_dir,
            name,
            exposure,
            seed: file.seed,
            render,
            method,
        })
    }

    /// What [`Scene::load`] reads for this job.
    pub fn scene_desc(&self) -> SceneDesc<'_> {
        SceneDesc {
            file: &self.path,
            layers: &self.layers,
            camera: self.camera.as_ref(),
        }
    }

    /// Loads the job's scene (layers, tags, camera) and checks the frame range against its
    /// animation: everything a render needs.
    pub fn load_scene(&self) -> Result<Scene> {
        let scene = Scene::load(&self.scene_desc())?;
        if let Some((t0, t1)) = scene.time_range() {
            let half = (0.5 / self.fps) as f32;
            for (key, f) in [
                ("frames.start", self.frames.start),
                ("frames.end", self.frames.end),
            ] {
                let t = self.time_of(f);
                if t < t0 - half || t > t1 + half {
                    let (first, last) = self.frames_in(t0, t1);
                    return Err(Error::input(
                        &self.path,
                        key,
                        format!(
                            "frame {f} (t = {t:.4} s at {} fps, frame_offset {}) is outside the animation, which spans t = {t0:.4}..{t1:.4} s (frames {first:.0}..{last:.0})",
                            self.fps, self.frame_offset,
                        ),
                    ));
                }
            }
        }
        let frames = (self.frames.start..=self.frames.end).map(|f| (f, self.time_of(f)));
        scene.check_camera(frames.clone())?;
        scene.check_lights(frames)?;
        crate::output::protect_inputs(std::iter::once(self.path.as_path()).chain(scene.files()));
        Ok(scene)
    }

    /// Loads the layers and resolves tags without requiring a camera (`inspect`).
    pub fn load_scene_layers(&self) -> Result<Scene> {
        Scene::load_layers(&self.scene_desc())
    }

    /// Animation time in seconds of `frame`.
    pub fn time_of(&self, frame: i32) -> f32 {
        ((frame as f64 - self.frame_offset) / self.fps) as f32
    }

    /// First and last whole frame whose times lie in `[t0, t1]`, with a thousandth of a frame
    /// of slack for key times stored as f32 (Blender writes frame 1 at 1/24 s).
    pub fn frames_in(&self, t0: f32, t1: f32) -> (f64, f64) {
        let frame = |t: f32| t as f64 * self.fps + self.frame_offset;
        // `+ 0.0` turns a negative zero into zero for display.
        (
            (frame(t0) - 1e-3).ceil() + 0.0,
            (frame(t1) + 1e-3).floor() + 0.0,
        )
    }

    /// Path of a frame's EXR; its stats and preview share the stem.
    pub fn frame_path(&self, frame: i32, ext: &str) -> PathBuf {
        self.out_dir
            .join(format!("{}.{:04}.{ext}", self.name, frame))
    }
}

/// `render` with the command line's `--visibility` applied, checked.
fn render_settings(
    path: &Path,
    file: RenderSettings,
    overrides: &Overrides,
) -> Result<RenderSettings> {
    let mut rs = file;
    if let Some(v) = overrides.visibility {
        rs.visibility = v;
    }
    if rs.samples_per_pixel == 0 || rs.samples_per_pixel > 65536 {
        return Err(Error::input(
            path,
            "render.samples_per_pixel",
            "must be 1..=65536",
        ));
    }
    if rs.light_samples == 0 || rs.light_samples > 1024 {
        return Err(Error::input(
            path,
            "render.light_samples",
            "must be 1..=1024",
        ));
    }
    Ok(rs)
}

/// The layers with their paths resolved against `base` and their transforms checked.
fn layers(path: &Path, base: &Path, scene: &[LayerFile]) -> Result<Vec<LayerDesc>> {
    scene
        .iter()
        .enumerate()
        .map(|(i, l)| {
            let m = l.transform.matrix();
            if !m.is_finite() || !(m.determinant().abs() > 0.0) {
                return Err(Error::input(
                    path,
                    format!("scene[{i}].transform"),
                    "must be finite and invertible",
                ));
            }
            Ok(LayerDesc {
                path: base.join(&l.path),
                transform: m,
                tags: l.tags.clone(),
                animations: l.animations.clone(),
            })
        })
        .collect()
}

/// The job's camera, checked: a node name, or a pinhole camera that can look somewhere.
fn camera(path: &Path, c: CameraFile) -> Result<CameraSpec> {
    let (position, look_at, up, yfov_deg, znear, zfar) = match c {
        CameraFile::Node(NodeCamera { node }) => return Ok(CameraSpec::Node(node)),
        CameraFile::LookAt(LookAtCamera {
            position,
            look_at,
            up,
            yfov_deg,
            znear,
            zfar,
        }) => (
            DVec3::from(position),
            DVec3::from(look_at),
            Vec3::from(up),
            yfov_deg,
            znear,
            zfar.unwrap_or(f32::INFINITY),
        ),
    };
    if !(znear.is_finite() && znear >= 0.0) {
        return Err(Error::input(path, "camera.znear", "must be finite and ≥ 0"));
    }
    if zfar.is_nan() || zfar <= znear {
        return Err(Error::input(
            path,
            "camera.zfar",
            "must be greater than znear",
        ));
    }
    if !(position.is_finite() && look_at.is_finite() && up.is_finite())
        || (look_at - position).length() == 0.0
    {
        return Err(Error::input(
            path,
            "camera",
            "position and look_at must differ",
        ));
    }
    if !(look_at - position).length().is_finite() {
        return Err(Error::input(
            path,
            "camera.position",
            "lies too far from look_at: their distance overflows",
        ));
    }
    if (look_at - position)
        .normalize()
        .as_vec3()
        .cross(up.normalize_or_zero())
        .length()
        < 1e-6
    {
        return Err(Error::input(
            path,
            "camera.up",
            "must not be parallel to the view",
        ));
    }
    if !(yfov_deg > 0.0 && yfov_deg < 180.0) {
        return Err(Error::input(path, "camera.yfov_deg", "must be in (0, 180)"));
    }
    Ok(CameraSpec::LookAt(LookAt {
        position,
        look_at,
        up,
        yfov: yfov_deg.to_radians(),
        clip: Clip {
            near: znear,
            far: zfar,
        },
    }))
}

/// Most frames one job renders (about 70 minutes at 24 fps): shots beyond it are split.
pub const MAX_FRAMES: i64 = 100_000;

/// Largest job file read: job files are small; this stops `/dev/zero` or a wrong path to a
/// huge file from being read into memory.
const MAX_JOB_BYTES: u64 = 16 << 20;

/// Longest `output.name`, in bytes: the temporary names add about 30 to it, and file names
/// are limited to 255 bytes.
const MAX_NAME_BYTES: usize = 200;

/// The job file's text: a regular file of at most [`MAX_JOB_BYTES`] (a FIFO, a device or a
/// directory is refused before it is opened: [`crate::scene::gltf::open_limited`]).
fn read_job_text(path: &Path) -> Result<String> {
    use std::io::Read;
    let fail = |m: String| Error::input(path, "file", m);
    let (f, _) = crate::scene::gltf::open_limited(path, "file", MAX_JOB_BYTES)?;
    let mut text = String::new();
    f.take(MAX_JOB_BYTES + 1)
        .read_to_string(&mut text)
        .map_err(|e| fail(format!("cannot read job file: {e}")))?;
    if text.len() as u64 > MAX_JOB_BYTES {
        return Err(fail(format!(
            "larger than {} MiB: not a job file",
            MAX_JOB_BYTES >> 20
        )));
    }
    Ok(text)
}

/// The output directory (`--out` wins), the frames' file name stem and the preview exposure
/// (`--exposure` wins).
fn output(
    path: &Path,
    base: &Path,
    file: Option<OutputFile>,
    overrides: &Overrides,
) -> Result<(PathBuf, String, f32)> {
    let out = file.unwrap_or(OutputFile {
        directory: None,
        name: None,
        exposure: 0.0,
    });
    let exposure = overrides.exposure.unwrap_or(out.exposure);
    if !(-64.0..=64.0).contains(&exposure) {
        let key = if overrides.exposure.is_some() {
            "--exposure"
        } else {
            "output.exposure"
        };
        return Err(Error::input(path, key, "must be in [-64, 64] stops"));
    }
    let out_dir = match &overrides.out_dir {
        Some(d) => d.clone(),
        None => base.join(out.directory.unwrap_or_else(|| PathBuf::from("render"))),
    };
    let name = match out.name {
        Some(n) => n,
        None => path
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| "frame".into()),
    };
    if name.is_empty()
        || name == "."
        || name == ".."
        || name.contains(['/', '\\'])
        || name.chars().any(char::is_control)
    {
        return Err(Error::input(
            path,
            "output.name",
            "must be a plain file name (no path separators or control characters)",
        ));
    }
    if name.len() > MAX_NAME_BYTES {
        return Err(Error::input(
            path,
            "output.name",
            format!("{} bytes long; at most {MAX_NAME_BYTES}", name.len()),
        ));
    }
    Ok((out_dir, name, exposure))
}

/// A JSON error with the key path where serde stopped and the offending line (Tungsten-style):
/// serde's message without its own "at line L column C", and of a long line (a job written
/// on one line) the [`EXCERPT_CHARS`] characters either side of the column.
fn json_error(path: &Path, text: &str, e: &serde_json::Error) -> Error {
    let (line, column) = (e.line(), e.column());
    let message = e.to_string();
    let message = message
        .strip_suffix(&format!(" at line {line} column {column}"))
        .unwrap_or(&message);
    let full = text.lines().nth(line.saturating_sub(1)).unwrap_or("");
    let chars: Vec<char> = full.chars().collect();
    // serde_json counts the column in bytes.
    let at = full
        .char_indices()
        .take_while(|&(byte, _)| byte < column.saturating_sub(1))
        .count();
    let (from, to) = (
        at.saturating_sub(EXCERPT_CHARS),
        (at + EXCERPT_CHARS).min(chars.len()),
    );
    let excerpt: String = chars[from..to].iter().collect();
    let excerpt = format!(
        "{}{}{}",
        if from > 0 { "…" } else { "" },
        if from > 0 {
            excerpt.as_str()
        } else {
            excerpt.trim_start()
        },
        if to < chars.len() { "…" } else { "" }
    );
    Error::input(
        path,
        format!("line {line}, column {column}"),
        format!("{message}\n    {}", excerpt.trim_end()),
    )
}

/// How many characters of the offending line a job-file error shows either side of the
/// column ([`json_error`]).
const EXCERPT_CHARS: usize = 60;

/// The JSON Schema of job files (`schemas/job.schema.json`), generated from [`JobFile`].
pub fn schema() -> schemars::Schema {
    let mut s = schemars::schema_for!(JobFile);
    s.insert("$id".into(), "anchorage/job.schema.json".into());
    s.insert("title".into(), "anchorage job file".into());
    s
}
