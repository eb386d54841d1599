//! The film: one frame's AOVs, the per-pixel accumulation of camera samples, and the
//! parallel row loop that fills it in an order independent of the thread count.

use glam::Vec3;
use rayon::prelude::*;

use crate::bsdf::Lobes;

/// The AOVs of one frame, row-major, top row first.
#[derive(Debug, Clone, Default)]
pub struct FrameImage {
    pub width: u32,
    pub height: u32,
    /// Premultiplied RGBA: emission + direct (+ indirect, later), alpha = coverage.
    pub beauty: Vec<[f32; 4]>,
    /// Light reflected once, towards the camera: `diffuse_direct + glossy_direct`.
    pub direct: Vec<[f32; 3]>,
    /// Light reflected at least twice (final gather or path tracing); zero for `direct`:
    /// `diffuse_indirect + glossy_indirect`.
    pub indirect: Vec<[f32; 3]>,
    /// `direct` and `indirect` by the lobe of the camera hit's BRDF that reflected them
    /// towards the camera ([`crate::bsdf::Lobes`]), as Blender names its passes.
    pub diffuse_direct: Vec<[f32; 3]>,
    pub glossy_direct: Vec<[f32; 3]>,
    pub diffuse_indirect: Vec<[f32; 3]>,
    pub glossy_indirect: Vec<[f32; 3]>,
    /// Camera-space depth along the view axis of the nearest hit; `f32::MAX` where nothing is hit.
    pub depth: Vec<f32>,
    /// Cached methods only (else `None`): `anchor_id` and `reshoot` AOVs, see [`Pixel`].
    pub anchor_id: Option<Vec<u32>>,
    pub reshoot: Option<Vec<f32>>,
    /// Per pixel, the variance of the pixel's mean: the sample variance of its camera
    /// samples divided by their number, for the beauty's RGB and the `indirect` RGB (as
    /// Mitsuba 3 keeps beside its reference images). The samples are scrambled-QMC points,
    /// not independent ones, so this is the variance a Monte Carlo estimate with as many
    /// samples would have: for the smooth integrands of rendering an upper bound in practice.
    /// In memory only (statistical image tests); not written to the EXR.
    pub variance: PixelVariance,
}

/// [`FrameImage::variance`]: per pixel, the variance of the mean of the beauty and of the
/// `indirect` AOV, RGB.
#[derive(Debug, Clone, Default)]
pub struct PixelVariance {
    pub beauty: Vec<[f32; 3]>,
    pub indirect: Vec<[f32; 3]>,
}

impl FrameImage {
    /// Divides the radiance AOVs by `scale` (a power of two: exactly), and the variances by
    /// its square, each held to f32's largest value: the image of a scene whose emission was
    /// multiplied by `scale` ([`crate::scene::Scene::emission_scale`]), at the scene's own
    /// level. Depth and the cache AOVs do not depend on the light.
    pub fn unscale(&mut self, scale: f32) {
        let by = |v: f32, s: f64| {
            let q = f64::from(v) / s;
            if q > f64::from(f32::MAX) {
                f32::MAX
            } else {
                q as f32
            }
        };
        let s = f64::from(scale);
        for p in &mut self.beauty {
            for v in &mut p[..3] {
                *v = by(*v, s);
            }
        }
        for aov in [
            &mut self.direct,
            &mut self.indirect,
            &mut self.diffuse_direct,
            &mut self.glossy_direct,
            &mut self.diffuse_indirect,
            &mut self.glossy_indirect,
        ] {
            for v in aov.iter_mut().flatten() {
                *v = by(*v, s);
            }
        }
        for v in [&mut self.variance.beauty, &mut self.variance.indirect] {
            for v in v.iter_mut().flatten() {
                *v = by(*v, s * s);
            }
        }
    }

    /// Drops the cache AOVs (for methods without a cache).
    pub fn drop_cache_aovs(&mut self) {
        self.anchor_id = None;
        self.reshoot = None;
    }
}

#[derive(Debug, Clone, Copy, Default)]
pub struct RenderCounts {
    pub camera_rays: u64,
    pub shadow_rays: u64,
    /// Glossy reflection rays traced at camera hits (cached methods).
    pub glossy_rays: u64,
}

/// One pixel's AOVs.
#[derive(Debug, Clone, Copy, Default)]
pub struct Pixel {
    pub beauty: [f32; 4],
    pub direct: [f32; 3],
    pub indirect: [f32; 3],
    pub diffuse_direct: [f32; 3],
    pub glossy_direct: [f32; 3],
    pub diffuse_indirect: [f32; 3],
    pub glossy_indirect: [f32; 3],
    pub depth: f32,
    /// Cached methods: id + 1 of the anchor feeding the first hit's dominant record (0: none).
    pub anchor_id: u32,
    /// Cached methods: weighted fraction of the contributing strata re-traced this frame.
    pub reshoot: f32,
    /// Variance of the mean of the beauty and of the indirect RGB ([`FrameImage::variance`]).
    pub beauty_var: [f32; 3],
    pub indirect_var: [f32; 3],
}

/// Sums a pixel's samples: emission, direct and indirect radiance, coverage and depth.
#[derive(Debug, Clone, Copy)]
pub struct Accumulator {
    emission: Vec3,
    direct: Lobes,
    indirect: Lobes,
    hits: f32,
    depth: f32,
    anchor: Option<u32>,
    reshoot: f32,
    cached: f32,
    /// Sums of squares of each camera sample's beauty and indirect radiance.
    beauty_sq: glam::DVec3,
    indirect_sq: glam::DVec3,
}

impl Default for Accumulator {
    fn default() -> Self {
        Accumulator {
            emission: Vec3::ZERO,
            direct: Lobes::ZERO,
            indirect: Lobes::ZERO,
            hits: 0.0,
            depth: f32::MAX,
            anchor: None,
            reshoot: 0.0,
            cached: 0.0,
            beauty_sq: glam::DVec3::ZERO,
            indirect_sq: glam::DVec3::ZERO,
        }
    }
}

impl Accumulator {
    /// A camera sample that hit a surface at view-axis `depth`.
    pub fn hit(&mut self, depth: f32, emission: Vec3, direct: Lobes, indirect: Lobes) {
        self.hits += 1.0;
        self.depth = self.depth.min(depth);
        self.emission += emission;
        self.direct += direct;
        self.indirect += indirect;
    }

    /// Adds radiance to a sample already counted by [`Accumulator::hit`].
    pub fn add(&mut self, direct: Lobes, indirect: Lobes) {
        self.direct += direct;
        self.indirect += indirect;
    }

    /// The beauty and indirect radiance summed so far, to be handed to
    /// [`Accumulator::end_sample`] once the next camera sample has been shaded.
    pub fn begin_sample(&self) -> (Vec3, Vec3) {
        (
            self.emission + self.direct.sum() + self.indirect.sum(),
            self.indirect.sum(),
        )
    }

    /// Ends a camera sample begun with `begun` ([`Accumulator::begin_sample`]): its radiance
    /// enters the per-pixel variance.
    pub fn end_sample(&mut self, begun: (Vec3, Vec3)) {
        let (b, i) = self.begin_sample();
        let (db, di) = ((b - begun.0).as_dvec3(), (i - begun.1).as_dvec3());
        self.beauty_sq += db * db;
        self.indirect_sq += di * di;
    }

    /// Records what the cache gave a sample: the anchor id (kept from the first sample) and
    /// the fraction of its strata re-traced this frame.
    pub fn note_cache(&mut self, anchor_id: u32, reshoot: f32) {
        self.anchor.get_or_insert(anchor_id);
        self.reshoot += reshoot;
        self.cached += 1.0;
    }

    /// The box-filtered pixel over `spp` samples (misses count as black, transparent).
    /// A non-finite sum (which no valid input produces) becomes black rather than poisoning
    /// compositing.
    pub fn finish(&self, spp: u32) -> Pixel {
        let inv = 1.0 / spp as f32;
        let f = |v: Vec3| {
            let v = v * inv;
            if v.is_finite() { v } else { Vec3::ZERO }
        };
        let (dd, gd) = (f(self.direct.diffuse), f(self.direct.glossy));
        let (di, gi) = (f(self.indirect.diffuse), f(self.indirect.glossy));
        let (e, d, i) = (f(self.emission), dd + gd, di + gi);
        let b = e + d + i;
        // Sample variance of the samples (misses are samples of zero), over their number.
        let var = |sq: glam::DVec3, mean: Vec3| -> [f32; 3] {
            if spp < 2 {
                return [0.0; 3];
            }
            let n = f64::from(spp);
            let m = mean.as_dvec3();
            let v = ((sq - m * m * n) / (n - 1.0)).max(glam::DVec3::ZERO) / n;
            if v.is_finite() {
                v.as_vec3().to_array()
            } else {
                [0.0; 3]
            }
        };
        Pixel {
            beauty_var: var(self.beauty_sq, b),
            indirect_var: var(self.indirect_sq, i),
            beauty: [b.x, b.y, b.z, self.hits * inv],
            direct: d.to_array(),
            indirect: i.to_array(),
            diffuse_direct: dd.to_array(),
            glossy_direct: gd.to_array(),
            diffuse_indirect: di.to_array(),
            glossy_indirect: gi.to_array(),
            depth: self.depth,
            anchor_id: self.anchor.unwrap_or(0),
            reshoot: if self.cached > 0.0 {
                self.reshoot / self.cached
            } else {
                0.0
            },
        }
    }
}

/// Renders every pixel with `shade(x, y, row_state)` in parallel rows, joined in order, so
/// the image does not depend on the thread count. Returns the image and each row's state.
pub fn render_rows<S: Default + Send>(
    width: u32,
    height: u32,
    shade: impl Fn(u32, u32, &mut S) -> Pixel + Sync,
) -> (FrameImage, Vec<S>) {
    assemble(width, height, shade_rows(width, 0..height, shade))
}

/// The pixels of rows `rows` with `shade(x, y, row_state)`, rows in parallel, in order.
pub fn shade_rows<S: Default + Send>(
    width: u32,
    rows: std::ops::Range<u32>,
    shade: impl Fn(u32, u32, &mut S) -> Pixel + Sync,
) -> Vec<(Vec<Pixel>, S)> {
    rows.into_par_iter()
        .map(|y| {
            let mut state = S::default();
            let row = (0..width).map(|x| shade(x, y, &mut state)).collect();
            (row, state)
        })
        .collect()
}

/// The image of all `height` rows from [`shade_rows`] (top row first) and each row's state.
pub fn assemble<S>(width: u32, height: u32, rows: Vec<(Vec<Pixel>, S)>) -> (FrameImage, Vec<S>) {
    let n = (width * height) as usize;
    let mut img = FrameImage {
        width,
        height,
        beauty: Vec::with_capacity(n),
        direct: Vec::with_capacity(n),
        indirect: Vec::with_capacity(n),
        diffuse_direct: Vec::with_capacity(n),
        glossy_direct: Vec::with_capacity(n),
        diffuse_indirect: Vec::with_capacity(n),
        glossy_indirect: Vec::with_capacity(n),
        depth: Vec::with_capacity(n),
        anchor_id: Some(Vec::with_capacity(n)),
        reshoot: Some(Vec::with_capacity(n)),
        variance: PixelVariance {
            beauty: Vec::with_capacity(n),
            indirect: Vec::with_capacity(n),
        },
    };
    let mut states = Vec::with_capacity(height as usize);
    let (mut ids, mut reshoot) = (Vec::with_capacity(n), Vec::with_capacity(n));
    for (row, state) in rows {
        for p in row {
            img.beauty.push(p.beauty);
            img.direct.push(p.direct);
            img.indirect.push(p.indirect);
            img.diffuse_direct.push(p.diffuse_direct);
            img.glossy_direct.push(p.glossy_direct);
            img.diffuse_indirect.push(p.diffuse_indirect);
            img.glossy_indirect.push(p.glossy_indirect);
            img.depth.push(p.depth);
            ids.push(p.anchor_id);
            reshoot.push(p.reshoot);
            img.variance.beauty.push(p.beauty_var);
            img.variance.indirect.push(p.indirect_var);
        }
        states.push(state);
    }
    img.anchor_id = Some(ids);
    img.reshoot = Some(reshoot);
    (img, states)
}

impl AsMut<RenderCounts> for RenderCounts {
    fn as_mut(&mut self) -> &mut RenderCounts {
        self
    }
}

impl RenderCounts {
    pub fn sum<'a>(all: impl IntoIterator<Item = &'a RenderCounts>) -> RenderCounts {
        all.into_iter()
            .fold(RenderCounts::default(), |a, c| RenderCounts {
                camera_rays: a.camera_rays + c.camera_rays,
                shadow_rays: a.shadow_rays + c.shadow_rays,
                glossy_rays: a.glossy_rays + c.glossy_rays,
            })
    }
}
