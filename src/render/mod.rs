//! Shading pixels: camera rays, surface interactions and direct lighting from every light
//! with shadow rays. The global-illumination methods of the paper build on
//! [`SurfacePoint`] and [`direct_irradiance`], which they also need at final-gather hits.
//!
//! Units: pixel values are radiance in the scene's light units (glTF: candela for point and
//! spot lights, lux for directional lights, nits for emission), so a point light of
//! intensity `I` over a white Lambertian plane gives `I·cosθ/(π r²)`.

use glam::{Vec2, Vec3};
use rayon::prelude::*;

use crate::accel::{Hit, barycentric, offset_of};
use crate::job::RenderSettings;
use crate::sampling::Sampler;
use crate::scene::{FrameScene, LightKind, Material, PunctualLight, Texture};

/// What the renderer needs of the scene's materials.
#[derive(Clone, Copy)]
pub struct Materials<'a> {
    pub materials: &'a [Material],
    pub textures: &'a [Texture],
}

/// A shading point on a surface, oriented towards the incoming ray.
#[derive(Debug, Clone, Copy)]
pub struct SurfacePoint {
    pub position: Vec3,
    /// Geometric normal on the side the ray came from.
    pub ng: Vec3,
    /// Interpolated shading normal, on the same side as `ng`.
    pub ns: Vec3,
    pub uv: Vec2,
    /// Distance to move ray origins off this surface.
    pub offset: f32,
    pub material: u32,
    /// True if the ray hit the front (counter-clockwise) face.
    pub front: bool,
    pub hit: Hit,
}

impl SurfacePoint {
    pub fn new(frame: &FrameScene, hit: Hit, origin: Vec3, dir: Vec3) -> Self {
        let g = frame.geometry(hit.motion);
        let tri = &g.triangles[hit.triangle as usize];
        let sh = &g.shading[hit.triangle as usize];
        let position = origin + dir * hit.t;
        let b = barycentric(tri, position);
        let w = 1.0 - b.x - b.y;
        let n = Vec3::from((tri.v1 - tri.v0).cross(tri.v2 - tri.v0)).normalize_or_zero();
        let front = n.dot(dir) < 0.0;
        let ng = if front { n } else { -n };
        let ns =
            (sh.normals[0] * w + sh.normals[1] * b.x + sh.normals[2] * b.y).normalize_or_zero();
        let ns = if ns.dot(ng) < 0.0 { -ns } else { ns };
        let ns = if ns == Vec3::ZERO { ng } else { ns };
        SurfacePoint {
            position,
            ng,
            ns,
            uv: sh.uvs[0] * w + sh.uvs[1] * b.x + sh.uvs[2] * b.y,
            offset: offset_of(tri),
            material: sh.material,
            front,
            hit,
        }
    }

    /// Origin for rays leaving on the ray's side of the surface.
    pub fn spawn(&self) -> Vec3 {
        self.position + self.ng * self.offset
    }

    pub fn albedo(&self, m: Materials) -> Vec3 {
        m.materials[self.material as usize].albedo(self.uv, m.textures)
    }

    /// Emitted radiance towards the ray's origin.
    pub fn emission(&self, m: Materials) -> Vec3 {
        let mat = &m.materials[self.material as usize];
        if self.front || mat.double_sided {
            mat.emission
        } else {
            Vec3::ZERO
        }
    }
}

/// The surface the ray `o + t·d` meets first, if any.
pub fn trace(frame: &FrameScene, o: Vec3, d: Vec3) -> Option<SurfacePoint> {
    frame
        .accel
        .closest(
            &frame.static_geometry,
            &frame.dynamic_geometry,
            o,
            d,
            f32::INFINITY,
        )
        .map(|h| SurfacePoint::new(frame, h, o, d))
}

/// Irradiance at `x` from one punctual light, shadow ray included (`KHR_lights_punctual`).
fn punctual_irradiance(
    frame: &FrameScene,
    x: &SurfacePoint,
    l: &PunctualLight,
    shadow_rays: &mut u64,
) -> Vec3 {
    let o = x.spawn();
    let (wi, dist, e) = match l.kind {
        LightKind::Directional => (-l.direction, f32::INFINITY, l.intensity),
        LightKind::Point | LightKind::Spot { .. } => {
            let d = l.position - o;
            let r2 = d.length_squared();
            let r = r2.sqrt();
            if !(r > 0.0) || l.range.is_some_and(|range| r > range) {
                return Vec3::ZERO;
            }
            let wi = d / r;
            let mut e = l.intensity / r2;
            if let LightKind::Spot { inner, outer } = l.kind {
                // The extension's smooth cone falloff between the outer and inner angles.
                let cd = l.direction.dot(-wi);
                let (co, ci) = (outer.cos(), inner.cos());
                let s = ((cd - co) / (ci - co).max(1e-4)).clamp(0.0, 1.0);
                e *= s * s;
            }
            (wi, r * (1.0 - 1e-6), e)
        }
    };
    let cos = x.ns.dot(wi);
    if cos <= 0.0 || x.ng.dot(wi) <= 0.0 || e == Vec3::ZERO {
        return Vec3::ZERO;
    }
    *shadow_rays += 1;
    if frame
        .accel
        .occluded(&frame.static_geometry, &frame.dynamic_geometry, o, wi, dist)
    {
        return Vec3::ZERO;
    }
    e * cos
}

/// Irradiance at `x` from all lights: punctual lights exactly, emissive triangles by
/// `n` QMC samples (`sampler` indices `index·n ..`, dimensions `dim..dim+3`).
pub fn direct_irradiance(
    frame: &FrameScene,
    x: &SurfacePoint,
    sampler: &Sampler,
    index: u32,
    n: u32,
    dim: u32,
    shadow_rays: &mut u64,
) -> Vec3 {
    let mut e = Vec3::ZERO;
    for l in &frame.lights {
        e += punctual_irradiance(frame, x, l, shadow_rays);
    }
    if frame.emitters.list.is_empty() {
        return e;
    }
    let o = x.spawn();
    let mut area = Vec3::ZERO;
    for j in 0..n {
        let i = index * n + j;
        let Some((k, p_pick)) = frame.emitters.pick(sampler.get(i, dim)) else {
            break;
        };
        let em = &frame.emitters.list[k];
        let g = frame.geometry(em.motion);
        let tri = &g.triangles[em.triangle as usize];
        // Uniform point on the triangle (Shirley's square-root parameterisation).
        let [u1, u2] = sampler.get2(i, dim + 1);
        let su = u1.sqrt();
        let y = Vec3::from(tri.v0 * (1.0 - su) + tri.v1 * (su * (1.0 - u2)) + tri.v2 * (su * u2));
        let ny = Vec3::from((tri.v1 - tri.v0).cross(tri.v2 - tri.v0)).normalize_or_zero();
        let d = y - o;
        let r2 = d.length_squared();
        if !(r2 > 0.0) {
            continue;
        }
        let r = r2.sqrt();
        let wi = d / r;
        let cos_x = x.ns.dot(wi);
        let cos_y = -ny.dot(wi);
        let cos_y = if em.double_sided { cos_y.abs() } else { cos_y };
        if cos_x <= 0.0 || cos_y <= 0.0 || x.ng.dot(wi) <= 0.0 {
            continue;
        }
        *shadow_rays += 1;
        let tmax = r - 2.0 * offset_of(tri);
        if tmax > 0.0
            && frame
                .accel
                .occluded(&frame.static_geometry, &frame.dynamic_geometry, o, wi, tmax)
        {
            continue;
        }
        // E = L_e cosθx cosθy / r² / pdf_area, pdf_area = p_pick / area. Ordered so that
        // neither tiny nor huge scenes leave f32's range: (area / r²) is scale-free.
        area += em.radiance * (cos_x * cos_y * (em.area / r2) / p_pick);
    }
    e + area / n as f32
}

/// The AOVs of one frame, row-major, top row first.
#[derive(Debug, Clone, Default)]
pub struct FrameImage {
    pub width: u32,
    pub height: u32,
    /// Premultiplied RGBA: emission + direct (+ indirect, later), alpha = coverage.
    pub beauty: Vec<[f32; 4]>,
    pub direct: Vec<[f32; 3]>,
    /// Light reflected at least twice (final gather or path tracing); zero for `direct`.
    pub indirect: Vec<[f32; 3]>,
    /// Camera-space depth along the view axis of the nearest hit; `f32::MAX` where nothing is hit.
    pub depth: Vec<f32>,
    /// Cached methods only (else `None`): `anchor_id` and `reshoot` AOVs, see [`Pixel`].
    pub anchor_id: Option<Vec<u32>>,
    pub reshoot: Option<Vec<f32>>,
}

impl FrameImage {
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
}

/// One pixel's AOVs.
#[derive(Debug, Clone, Copy, Default)]
pub struct Pixel {
    pub beauty: [f32; 4],
    pub direct: [f32; 3],
    pub indirect: [f32; 3],
    pub depth: f32,
    /// Cached methods: id + 1 of the anchor feeding the first hit's dominant record (0: none).
    pub anchor_id: u32,
    /// Cached methods: weighted fraction of the contributing strata re-traced this frame.
    pub reshoot: f32,
}

/// Sums a pixel's samples: emission, direct and indirect radiance, coverage and depth.
#[derive(Debug, Clone, Copy)]
pub struct Accumulator {
    emission: Vec3,
    direct: Vec3,
    indirect: Vec3,
    hits: f32,
    depth: f32,
    anchor: Option<u32>,
    reshoot: f32,
    cached: f32,
}

impl Default for Accumulator {
    fn default() -> Self {
        Accumulator {
            emission: Vec3::ZERO,
            direct: Vec3::ZERO,
            indirect: Vec3::ZERO,
            hits: 0.0,
            depth: f32::MAX,
            anchor: None,
            reshoot: 0.0,
            cached: 0.0,
        }
    }
}

impl Accumulator {
    /// A camera sample that hit a surface at view-axis `depth`.
    pub fn hit(&mut self, depth: f32, emission: Vec3, direct: Vec3, indirect: Vec3) {
        self.hits += 1.0;
        self.depth = self.depth.min(depth);
        self.emission += emission;
        self.direct += direct;
        self.indirect += indirect;
    }

    /// Adds radiance to a sample already counted by [`Accumulator::hit`].
    pub fn add(&mut self, direct: Vec3, indirect: Vec3) {
        self.direct += direct;
        self.indirect += indirect;
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
        let (e, d, i) = (f(self.emission), f(self.direct), f(self.indirect));
        let b = e + d + i;
        Pixel {
            beauty: [b.x, b.y, b.z, self.hits * inv],
            direct: d.to_array(),
            indirect: i.to_array(),
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
    let rows: Vec<(Vec<Pixel>, S)> = (0..height)
        .into_par_iter()
        .map(|y| {
            let mut state = S::default();
            let row = (0..width).map(|x| shade(x, y, &mut state)).collect();
            (row, state)
        })
        .collect();
    let n = (width * height) as usize;
    let mut img = FrameImage {
        width,
        height,
        beauty: Vec::with_capacity(n),
        direct: Vec::with_capacity(n),
        indirect: Vec::with_capacity(n),
        depth: Vec::with_capacity(n),
        anchor_id: Some(Vec::with_capacity(n)),
        reshoot: Some(Vec::with_capacity(n)),
    };
    let mut states = Vec::with_capacity(height as usize);
    let (mut ids, mut reshoot) = (Vec::with_capacity(n), Vec::with_capacity(n));
    for (row, state) in rows {
        for p in row {
            img.beauty.push(p.beauty);
            img.direct.push(p.direct);
            img.indirect.push(p.indirect);
            img.depth.push(p.depth);
            ids.push(p.anchor_id);
            reshoot.push(p.reshoot);
        }
        states.push(state);
    }
    img.anchor_id = Some(ids);
    img.reshoot = Some(reshoot);
    (img, states)
}

impl RenderCounts {
    pub fn sum<'a>(all: impl IntoIterator<Item = &'a RenderCounts>) -> RenderCounts {
        all.into_iter()
            .fold(RenderCounts::default(), |a, c| RenderCounts {
                camera_rays: a.camera_rays + c.camera_rays,
                shadow_rays: a.shadow_rays + c.shadow_rays,
            })
    }
}

/// Renders emission and direct lighting (`method: direct`).
pub fn render_direct(
    frame: &FrameScene,
    m: Materials,
    settings: &RenderSettings,
    width: u32,
    height: u32,
    seed: u32,
    frame_number: i32,
) -> (FrameImage, RenderCounts) {
    let spp = settings.samples_per_pixel;
    let (img, rows) = render_rows(width, height, |x, y, counts: &mut RenderCounts| {
        let sampler = Sampler::new(seed, frame_number, 0, y * width + x);
        let mut acc = Accumulator::default();
        for s in 0..spp {
            let [jx, jy] = sampler.get2(s, 0);
            let (o, d) = frame.camera.ray(
                (x as f32 + jx) / width as f32,
                (y as f32 + jy) / height as f32,
            );
            counts.camera_rays += 1;
            let Some(sp) = trace(frame, o, d) else {
                continue;
            };
            let hit = sp.hit;
            let e = direct_irradiance(
                frame,
                &sp,
                &sampler,
                s,
                settings.light_samples,
                2,
                &mut counts.shadow_rays,
            );
            acc.hit(
                hit.t * d.dot(frame.camera.forward),
                sp.emission(m),
                sp.albedo(m) * std::f32::consts::FRAC_1_PI * e,
                Vec3::ZERO,
            );
        }
        acc.finish(spp)
    });
    let mut img = img;
    img.drop_cache_aovs();
    (img, RenderCounts::sum(&rows))
}
