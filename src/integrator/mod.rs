//! The integrators: how each method turns a frame's scene into pixels (DESIGN.md, Methods).
//!
//! One pixel loop serves them all ([`render_pixels`]): per pixel, camera samples jittered
//! over the pixel from the camera stream, a camera ray each, and the method's [`Shade`] at
//! every hit, accumulated into the AOVs of [`film`]. The methods:
//!
//! - [`direct`]: emission and direct light only.
//! - [`path`]: unbiased path tracing with next-event estimation, the reference.
//! - [`cached`]: photon map + irradiance cache, shading from the cache. Its prepare phase is
//!   the method's: `brute-force` re-gathers every stratum of every record each frame and
//!   estimates radiance at each gather hit from the k nearest photons (the paper's Table 1,
//!   left column); `precomputed` reads irradiance precomputed at a quarter of the photons
//!   (Christensen 1999, the paper's Figure 7); `anchors` is [`anchors`], the paper's method
//!   (§3–§4.3, Pseudocode 2).
//!
//! All share seeds, the photon sequence and the cache placement, so they compare like for
//! like.

pub mod anchors;
pub mod bucket;
pub mod cached;
pub mod direct;
pub mod film;
pub mod path;
pub mod replay;

use clap::ValueEnum;
use glam::Vec3;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use crate::accel::Hit;
use crate::anchor::AnchorParams;
use crate::bsdf::{Bsdf, Lobes};
use crate::cache::CacheParams;
use crate::interaction::{
    LightSampling, Materials, ShadowRays, SurfacePoint, brdf_sampled_emission, direct_light,
};
use crate::photon::GatherDirect;
use crate::sampling::{Dims, Sampler, Stream};
use crate::scene::{CameraRay, FrameScene};
pub use film::{Accumulator, FrameImage, Pixel, PixelVariance, RenderCounts};

/// Settings of the photon-mapping methods ([`GiParams::preset`] gives the presets).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct GiParams {
    /// Photons emitted per frame.
    pub photons: u32,
    /// Photons in each irradiance estimate.
    pub k: u32,
    /// Photon bounces at most. Russian roulette ends most paths long before; the cap only
    /// matters for near-white scenes, where a low one darkens the indirect light.
    pub photon_bounces: u32,
    /// No photon look-up reaches farther than this fraction of the static scene's bounding
    /// radius ([`crate::photon::PhotonMap::max_radius`]). Default 0.05 in every preset.
    pub max_photon_radius: f32,
    /// Where gather hits' direct light from punctual lights comes from. Default
    /// [`GatherDirect::ShadowRays`] in every preset.
    pub gather_direct: GatherDirect,
    pub cache: CacheParams,
    /// `anchors`: anchor density and reuse heuristics.
    pub anchors: AnchorParams,
    /// `path-trace`: samples per pixel and maximum path length.
    pub path_samples: u32,
    pub path_depth: u32,
    /// `path-trace`: which strategies light emissive triangles.
    pub path_sampling: path::PathSampling,
    /// Cached methods: the glossy lobe's indirect light at camera hits.
    pub glossy: cached::GlossyParams,
}

/// Named speed/accuracy presets.
#[derive(
    Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema, ValueEnum,
)]
#[serde(rename_all = "kebab-case")]
#[value(rename_all = "kebab-case")]
pub enum Preset {
    /// Fast previews: few photons, coarse caches.
    Draft,
    /// The default: the balance the README's measurements recommend.
    #[default]
    Production,
    /// The paper's 1,800 gather rays per record.
    Final,
}

impl Preset {
    /// The preset's name as the job file and the command line spell it.
    pub fn name(self) -> String {
        self.to_possible_value()
            .map(|v| v.get_name().to_string())
            .unwrap_or_default()
    }
}

/// Default bounce cap of photons and of path-traced paths in every preset. Russian roulette
/// keeps the mean path short; at albedo 0.8 a cap of 12 would drop 0.8¹² ≈ 7 % of the
/// indirect light, a cap of 64 drops 6·10⁻⁷.
pub const DEPTH: u32 = 64;

/// Default of [`GiParams::max_photon_radius`]: well above the k-nearest radius where photons
/// are not rare, well below the size of a room in a house.
pub const MAX_PHOTON_RADIUS: f32 = 0.05;

impl GiParams {
    pub fn preset(p: Preset) -> Self {
        let cache = CacheParams::default();
        match p {
            Preset::Draft => GiParams {
                photons: 50_000,
                k: 32,
                photon_bounces: DEPTH,
                max_photon_radius: MAX_PHOTON_RADIUS,
                gather_direct: GatherDirect::ShadowRays,
                cache: CacheParams {
                    strata: [8, 24],
                    error: 0.4,
                    min_spacing_px: 3.0,
                    max_spacing_px: 32.0,
                    ..cache
                },
                anchors: AnchorParams::default(),
                path_samples: 64,
                path_depth: DEPTH,
                path_sampling: path::PathSampling::Mis,
                glossy: cached::GlossyParams::default(),
            },
            Preset::Production => GiParams {
                photons: 200_000,
                k: 64,
                photon_bounces: DEPTH,
                max_photon_radius: MAX_PHOTON_RADIUS,
                gather_direct: GatherDirect::ShadowRays,
                cache,
                anchors: AnchorParams::default(),
                path_samples: 256,
                path_depth: DEPTH,
                path_sampling: path::PathSampling::Mis,
                glossy: cached::GlossyParams::default(),
            },
            Preset::Final => GiParams {
                photons: 800_000,
                k: 100,
                photon_bounces: DEPTH,
                max_photon_radius: MAX_PHOTON_RADIUS,
                gather_direct: GatherDirect::ShadowRays,
                cache: CacheParams {
                    strata: [30, 60],
                    error: 0.15,
                    min_spacing_px: 1.5,
                    max_spacing_px: 16.0,
                    ..cache
                },
                anchors: AnchorParams::default(),
                path_samples: 1024,
                path_depth: DEPTH,
                path_sampling: path::PathSampling::Mis,
                glossy: cached::GlossyParams::default(),
            },
        }
    }
}

/// The frame a method renders: the scene at the frame's time, its materials, the image and
/// the numbers every random number derives from.
#[derive(Clone, Copy)]
pub struct FrameContext<'a> {
    pub scene: &'a FrameScene,
    pub materials: Materials<'a>,
    pub width: u32,
    pub height: u32,
    pub seed: u32,
    pub frame: i32,
}

/// Dimensions of the camera stream ([`Stream::Camera`]): the first two jitter the sample in
/// the pixel; a method's shading takes the following ones from [`shading_dims`].
const DIM_JITTER: u32 = 0;

/// The camera stream's dimensions from the first one a method's shading may use.
pub fn shading_dims() -> Dims {
    let mut d = Dims::new();
    d.take(DIM_JITTER + 2);
    d
}

/// A camera sample that met a surface.
pub struct CameraHit<'a> {
    /// The pixel's sample stream and this sample's index in it.
    pub sampler: &'a Sampler,
    pub sample: u32,
    /// The camera ray's direction.
    pub dir: Vec3,
    pub sp: SurfacePoint,
}

impl CameraHit<'_> {
    /// Depth along the camera's view axis (the `Z` AOV).
    pub fn depth(&self, ctx: &FrameContext) -> f32 {
        ctx.scene.camera.depth(self.sp.position)
    }

    /// The hit's BRDF.
    pub fn bsdf(&self, ctx: &FrameContext) -> Bsdf {
        self.sp.bsdf(ctx.materials)
    }

    /// Direction towards the camera.
    pub fn wo(&self) -> Vec3 {
        -self.dir
    }

    /// Direct light the hit reflects towards the camera through its BRDF, by lobe: punctual
    /// lights exactly, emissive triangles by `light_samples` emitter samples, combined with
    /// one BRDF sample by multiple importance sampling where the BRDF has a glossy lobe
    /// narrower than [`MIS_ROUGHNESS`] (there emitter samples alone miss the highlight).
    /// Casts its shadow rays through `shadow`, and counts the BRDF sample's ray there too.
    pub fn direct_light(
        &self,
        ctx: &FrameContext,
        bsdf: &Bsdf,
        light_samples: u32,
        shadow: &mut ShadowRays,
    ) -> Lobes {
        let mut dims = shading_dims();
        let (dim_light, dim_brdf) = (dims.take(3), dims.take(3));
        let mis = bsdf.has_glossy() && bsdf.roughness < MIS_ROUGHNESS;
        let sampling = if mis {
            LightSampling::Mis
        } else {
            LightSampling::Lights
        };
        let mut l = direct_light(
            ctx.scene,
            &self.sp,
            self.wo(),
            bsdf,
            self.sampler,
            (self.sample, light_samples, dim_light),
            sampling,
            shadow,
        );
        if mis {
            let u = [
                self.sampler.get(self.sample, dim_brdf),
                self.sampler.get(self.sample, dim_brdf + 1),
                self.sampler.get(self.sample, dim_brdf + 2),
            ];
            l += brdf_sampled_emission(
                ctx.scene,
                ctx.materials,
                &self.sp,
                self.wo(),
                bsdf,
                u,
                light_samples,
                shadow.cast,
            );
        }
        l
    }
}

/// Below this roughness the direct light of emissive triangles at camera hits adds a BRDF
/// sample by multiple importance sampling.
pub const MIS_ROUGHNESS: f32 = 0.75;

/// Dimensions a camera hit's direct light uses from [`shading_dims`]: three for emitter
/// samples, three for the BRDF sample.
pub const DIRECT_DIMS: u32 = 6;

/// What a method does with the camera samples of one pixel: its shade phase.
pub trait Shade: Sync {
    /// State of one row of pixels (counters, timings, what the row used).
    type Row: Default + Send + AsMut<RenderCounts>;
    /// State of one pixel, set up before its first sample.
    type Pixel;

    fn begin_pixel(&self, ctx: &FrameContext, row: &mut Self::Row, x: u32, y: u32) -> Self::Pixel;

    /// Camera sample `s`'s hit as [`render_pixel_rows`] found it ([`pixel_camera_hits`]):
    /// a method that keeps camera hits logs it here.
    fn log_camera_hit(&self, _row: &mut Self::Row, _hit: Option<Hit>) {}

    /// The hit of camera sample `s` of pixel (x, y) where it is known without tracing (a
    /// logged render's, [`replay`]).
    fn known_camera_hit(
        &self,
        _ctx: &FrameContext,
        _sample: (u32, u32, u32),
    ) -> Option<Option<Hit>> {
        None
    }

    /// Shades one camera hit into `acc`.
    fn sample(
        &self,
        ctx: &FrameContext,
        pixel: &mut Self::Pixel,
        row: &mut Self::Row,
        hit: &CameraHit,
        acc: &mut Accumulator,
    );
}

/// The camera stream of pixel (x, y) in this frame.
pub fn pixel_sampler(ctx: &FrameContext, x: u32, y: u32) -> Sampler {
    Sampler::new(ctx.seed, ctx.frame, Stream::Camera, y * ctx.width + x)
}

/// The rays of camera samples `0..spp` of pixel (x, y), each jittered over the pixel from
/// its stream `sampler` ([`pixel_sampler`]), and what each hit: `known(s)` where it gives
/// one, else traced, four samples of the pixel at a time
/// ([`crate::interaction::camera_hits4`]). The hits are those of each ray traced alone.
pub fn pixel_camera_hits(
    ctx: &FrameContext,
    sampler: &Sampler,
    (x, y): (u32, u32),
    spp: u32,
    known: impl Fn(u32) -> Option<Option<Hit>>,
) -> Vec<(CameraRay, Option<Hit>)> {
    let film = |s: u32| {
        let [jx, jy] = sampler.get2(s, DIM_JITTER);
        (
            (x as f32 + jx) / ctx.width as f32,
            (y as f32 + jy) / ctx.height as f32,
        )
    };
    let mut out = Vec::with_capacity(spp as usize);
    for first in (0..spp).step_by(4) {
        let four = std::array::from_fn(|i| {
            let s = first + i as u32;
            (s < spp).then(|| (film(s), known(s)))
        });
        out.extend(
            crate::interaction::camera_hits4(ctx.scene, four)
                .into_iter()
                .flatten(),
        );
    }
    out
}

/// The pixel loop every method shares: `spp` box-filtered camera samples per pixel, rows in
/// parallel, the image independent of the thread count. Returns the image and each row's
/// state.
pub fn render_pixels<S: Shade>(
    ctx: &FrameContext,
    spp: u32,
    method: &S,
) -> (FrameImage, Vec<S::Row>) {
    film::assemble(
        ctx.width,
        ctx.height,
        render_pixel_rows(ctx, spp, method, 0..ctx.height),
    )
}

/// [`render_pixels`] for the rows `rows` only: each row's pixels and state, in order (a
/// method that prepares work per band of rows joins them with [`film::assemble`]).
pub fn render_pixel_rows<S: Shade>(
    ctx: &FrameContext,
    spp: u32,
    method: &S,
    rows: std::ops::Range<u32>,
) -> Vec<(Vec<Pixel>, S::Row)> {
    let w = ctx.width;
    film::shade_rows(w, rows, |x, y, row: &mut S::Row| {
        let sampler = pixel_sampler(ctx, x, y);
        let mut acc = Accumulator::default();
        let mut pixel = method.begin_pixel(ctx, row, x, y);
        let cameras = pixel_camera_hits(ctx, &sampler, (x, y), spp, |s| {
            method.known_camera_hit(ctx, (x, y, s))
        });
        for (s, (ray, hit)) in (0..spp).zip(cameras) {
            method.log_camera_hit(row, hit);
            let sp = hit.map(|h| SurfacePoint::new(ctx.scene, h, ray.origin, ray.dir));
            row.as_mut().camera_rays += 1;
            let Some(sp) = sp else {
                continue;
            };
            let hit = CameraHit {
                sampler: &sampler,
                sample: s,
                dir: ray.dir,
                sp,
            };
            let begun = acc.begin_sample();
            method.sample(ctx, &mut pixel, row, &hit, &mut acc);
            acc.end_sample(begun);
        }
        acc.finish(spp)
    })
}
