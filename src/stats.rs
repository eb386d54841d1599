//! The stats JSON written beside each frame (`schemas/stats.schema.json`, generated from
//! these types): the paper's Table 1 rows as per-stage timings, counts of what was traced
//! and stored, and memory.

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// Per-stage seconds of the frame's wall time (`schemas/stats.schema.json`). Stages that
/// run one after another are wall-clock spans; the parallel shading pass of the cached
/// methods is split among `direct_lighting`, `cache_interpolation`, `final_gathering`,
/// `irradiance_estimation` and `camera_rays` in proportion to the thread seconds its
/// workers spent at each (per row, summed over threads), so the rows are seconds per frame
/// that add up to about `total` (the rest: the static BVH, output, and what little lies
/// between the spans).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct Timings {
    /// Evaluating animation, skinning and morphing of dynamic prims.
    pub scene_evaluation: f64,
    /// Evaluating static prims and building their BVH (first frame of a render only).
    pub static_bvh: f64,
    pub dynamic_bvh: f64,
    /// The paper's Table 1 rows: photon tracing, irradiance estimation (photon lookups at
    /// gather hits, or precomputation; for `anchors` the L_i of anchors, new and
    /// re-estimated), final gathering (tracing gather rays) and cache interpolation
    /// (shading from the cache, glossy bucketing and reflection rays included). Pixel
    /// samples no record covers gather on the spot: their rays count as final gathering,
    /// their photon look-ups (`anchors`: anchor searches) as irradiance estimation, not as
    /// interpolation. Zero for methods without that stage.
    pub photon_tracing: f64,
    pub irradiance_estimation: f64,
    /// `anchors`: linking the gather hits of new records and re-shot strata to anchors
    /// (Pseudocode 1: each hit's nearest photon, the search among the anchors with the tests
    /// of §3.1 and its shadow ray, new anchors made where none passes). In the paper's
    /// Table 1 it would fall under final gathering (Pseudocode 2 attaches each stratum as
    /// its ray is shot); here it is a row of its own, apart from the rays.
    #[serde(default)]
    pub attachment: f64,
    /// The cached methods: integrating each record's strata into its irradiance, gradients
    /// and directional fit (`anchors`: and its dominant anchor), for new records and those
    /// whose strata changed. In the paper's Table 1 it would fall under final gathering
    /// (Pseudocode 2 reads each stratum's L_i in its loop over the strata); here it is a
    /// row of its own, so that final gathering is the rays' tracing.
    #[serde(default)]
    pub integration: f64,
    /// The cached methods: deciding where new records go — tracing the pixel centres and
    /// the camera samples' lookup points, testing which of them the cache covers, and
    /// adding the new records to its grids with their radii clamped by their neighbours'
    /// (not their gathers, which count in the rows above).
    #[serde(default)]
    pub placement: f64,
    /// The cached methods' bookkeeping between the stages: dropping expired records,
    /// assembling the film, the Weber rule's tally and removals (§4.3); `anchors` also
    /// counts the strata that link each anchor and collects or rebalances the anchors.
    #[serde(default)]
    pub upkeep: f64,
    pub final_gathering: f64,
    pub cache_interpolation: f64,
    /// Detecting strata that may see dynamic prims (`anchors`, paper §3.2).
    pub visibility: f64,
    /// Answering anchor bucketing's hemisphere depth queries (`anchors` with glossy
    /// surfaces, paper §5.1), where `visibility` runs. Not part of `cache_interpolation`.
    #[serde(default)]
    pub depth_maps: f64,
    /// Direct light at camera hits (for `path-trace`: the whole path tracing).
    pub direct_lighting: f64,
    /// The cached methods' shading pass, besides the rows above: tracing the camera rays
    /// (each pixel's centre and its samples) with their surface points, and the film's
    /// bookkeeping. Zero for `path-trace` and `direct`, whose `direct_lighting` holds them.
    #[serde(default)]
    pub camera_rays: f64,
    pub output: f64,
    pub total: f64,
}

#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct Counts {
    pub triangles_static: u64,
    pub triangles_dynamic: u64,
    pub punctual_lights: u64,
    pub emissive_triangles: u64,
    pub pixels: u64,
    pub camera_rays: u64,
    /// Shadow rays of the direct light at camera hits, and the BRDF-sampled rays of direct
    /// light at glossy camera hits. Those that `method.gather_direct` `shadow-rays` casts
    /// from gather hits and anchors count in `gather_shadow_rays`.
    pub shadow_rays: u64,
    /// Cached methods with `method.gather_direct` `shadow-rays`: the shadow rays cast from
    /// gather hits and anchors to the punctual lights (their time is irradiance
    /// estimation's). 0 by photons.
    #[serde(default)]
    pub gather_shadow_rays: u64,
    /// Glossy reflection rays traced at camera hits (cached methods).
    #[serde(default)]
    pub glossy_rays: u64,
    /// Photons stored this frame.
    pub photons: u64,
    /// Irradiance cache records in use this frame.
    pub caches: u64,
    /// `anchors`: spot records among `caches` — records made at camera samples that no
    /// other record covers, read only by such samples — and those made this frame (the
    /// others were made for earlier frames' samples and are read again).
    #[serde(default)]
    pub caches_spot: u64,
    #[serde(default)]
    pub caches_spot_made: u64,
    /// Records the Weber rule (paper §4.3; `method.weber_threshold`) removes after this
    /// frame: they had the least influence on pixels read from more than
    /// `method.weber_records` records.
    #[serde(default)]
    pub caches_retired: u64,
    /// Final-gather rays traced this frame, those of `uncached_samples` included.
    pub rays_shot: u64,
    /// Pixel samples no cache record (spot records included) covered, gathered on the spot.
    pub uncached_samples: u64,
    /// Final-gather rays traced this frame by records that existed before it (for
    /// `anchors`, the re-shot strata; for brute force, every stratum of every record).
    pub rays_reshot: u64,
    /// `anchors`: strata the visibility test (paper §3.2) flagged as possibly seeing a
    /// dynamic prim this frame. Of those, only the ones whose own ray meets a dynamic prim
    /// before its static hit are re-shot; `rays_reshot` adds the strata whose ray met one
    /// last frame.
    #[serde(default)]
    pub strata_flagged: u64,
    /// `anchors`: anchors whose irradiance was estimated again this frame.
    pub anchors_reestimated: u64,
    /// Live anchors, and anchors created this frame (`anchors`).
    pub anchors: u64,
    pub anchors_created: u64,
}

/// Live anchors by how many strata link them (the paper's Figure 8).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, JsonSchema)]
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

#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, JsonSchema)]
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
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct FrameStats {
    pub frame: i32,
    /// Animation time of the frame in seconds.
    pub time: f32,
    pub method: String,
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

/// The JSON Schema of the stats files (`schemas/stats.schema.json`), generated from
/// [`FrameStats`].
pub fn schema() -> schemars::Schema {
    let mut s = schemars::schema_for!(FrameStats);
    s.insert("$id".into(), "anchorage/stats.schema.json".into());
    s.insert(
        "title".into(),
        "anchorage per-frame stats (NAME.####.json)".into(),
    );
    s
}
