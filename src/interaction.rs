//! Where light meets a surface: the shading point a ray finds ([`SurfacePoint`]), tracing,
//! and direct light from every light with shadow rays through the surface's BRDF
//! ([`direct_light`], with multiple importance sampling of emitters and the BRDF). Every
//! method builds on these, at camera hits and at final-gather hits alike.
//!
//! Units: pixel values are radiance in the scene's light units (glTF: candela for point and
//! spot lights, lux for directional lights, nits for emission), so a point light of
//! intensity `I` over a white Lambertian plane (`KHR_materials_specular.specularFactor` 0)
//! gives `I·cosθ/(π r²)`.

use glam::{Vec2, Vec3, Vec4};

use crate::accel::{
    Hit, SHADOW_EPSILON, barycentric, gamma, hit_point, interpolate, lanes4, offset_ray_origin,
};
use crate::bsdf::{Bsdf, Lobes};
use crate::geom::{Geometry, face_normal_area};
use crate::sampling::Sampler;
use crate::scene::frame::uniform_barycentric;
use crate::scene::material::NormalMap;
use crate::scene::{CameraRay, FrameScene, LightKind, Material, PunctualLight, Texture};

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
    /// Geometric normal on the side the ray came from: ray offsets and side tests use it.
    pub ng: Vec3,
    /// Shading normal — interpolated vertex normal, perturbed by the material's normal map —
    /// on the same side as `ng`: cosines and sampled directions use it.
    pub ns: Vec3,
    /// `TEXCOORD_0` at the hit.
    pub uv: Vec2,
    /// Linear RGBA vertex colour (`COLOR_0`) at the hit; white without one. (An array, not
    /// a `Vec4`: a `Vec4` would align the point to 16 bytes, and the gather holds millions.)
    pub color: [f32; 4],
    /// Per-component bound on the error of `position` (pbrt-v4 §6.8.5): rays leave from
    /// beyond it ([`Self::spawn`]).
    pub error: Vec3,
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
        // The point from its barycentrics with an error bound; a ray in the triangle's
        // plane (no barycentrics) falls back to `origin + t·dir` with the bound of its
        // three roundings.
        let hp = hit_point(tri, origin, dir).unwrap_or_else(|| {
            let position = origin + dir * hit.t;
            let b = barycentric(tri, position);
            crate::accel::HitPoint {
                position,
                error: (origin.abs() + (dir * hit.t).abs()) * gamma(3),
                b: Vec3::new(1.0 - b.x - b.y, b.x, b.y),
            }
        });
        let (w, b) = (hp.b.x, Vec2::new(hp.b.y, hp.b.z));
        let (n, _) = face_normal_area(tri);
        let front = n.dot(dir) < 0.0;
        let ng = if front { n } else { -n };
        let nv =
            (sh.normals[0] * w + sh.normals[1] * b.x + sh.normals[2] * b.y).normalize_or_zero();
        let nv = if nv == Vec3::ZERO { n } else { nv };
        let uv = sh.uvs[0] * w + sh.uvs[1] * b.x + sh.uvs[2] * b.y;
        let (_, color) = crate::scene::Surfaces::uv_and_color(g, hit.triangle as usize, b);
        let surfaces = &frame.surfaces;
        let mapped = surfaces
            .materials
            .get(sh.material as usize)
            .and_then(|m| m.normal_texture)
            .and_then(|map| normal_mapped(g, hit.triangle as usize, nv, uv, b, &map, surfaces));
        // Oriented like `ng`, as the vertex normal is (glTF's frame is the file's normal's,
        // so where vertex normals oppose the winding the mapped normal is turned with
        // them); a mapped normal on the far side of the geometric one falls back to the
        // interpolated normal.
        let flip = nv.dot(ng) < 0.0;
        let orient = |v: Vec3| if flip { -v } else { v };
        let ns = match mapped.map(orient) {
            Some(m) if m.dot(ng) > 0.0 => m,
            _ => orient(nv),
        };
        SurfacePoint {
            position: hp.position,
            ng,
            ns,
            uv,
            color: color.to_array(),
            error: hp.error,
            material: sh.material,
            front,
            hit,
        }
    }

    /// Origin for rays leaving on the ray's side of the surface (pbrt-v4's
    /// `OffsetRayOrigin` along the geometric normal).
    pub fn spawn(&self) -> Vec3 {
        offset_ray_origin(self.position, self.error, self.ng, self.ng)
    }

    /// A shadow ray from here to `target`, a point with error bound `target_error` on a
    /// surface with geometric normal `target_n` (pbrt-v4's `SpawnRayTo`): both ends leave
    /// their surface's error box towards each other, and the ray stops [`SHADOW_EPSILON`]
    /// short of the far end. `None` if the ends coincide.
    pub fn spawn_to(&self, target: Vec3, target_error: Vec3, target_n: Vec3) -> Option<Segment> {
        Segment::between(
            (self.position, self.error, self.ng),
            (target, target_error, target_n),
        )
    }

    /// The reflectance photon look-ups and final-gather hits shade with, treating the surface
    /// as Lambertian: the BRDF's hemispherical albedo, both lobes
    /// ([`Bsdf::hemispherical_albedo`]; the base colour for a pure Lambertian). A glossy hit
    /// seen by a gather ray reflects the right amount of light, spread evenly.
    pub fn albedo(&self, m: Materials) -> Vec3 {
        self.bsdf(m)
            .hemispherical_albedo()
            .sum()
            .clamp(Vec3::ZERO, Vec3::ONE)
    }

    /// The BRDF here ([`crate::bsdf`]).
    pub fn bsdf(&self, m: Materials) -> Bsdf {
        m.materials[self.material as usize].bsdf(self.uv, Vec4::from_array(self.color), m.textures)
    }

    /// The normal the BRDF is evaluated about for light leaving towards `wo`: the shading
    /// normal, or the geometric one where `wo` lies below the shading normal's horizon
    /// (interpolated and mapped normals can tilt past the viewer).
    pub fn shading_normal(&self, wo: Vec3) -> Vec3 {
        if self.ns.dot(wo) > 0.0 {
            self.ns
        } else {
            self.ng
        }
    }

    /// Emitted radiance towards the ray's origin (emissive texture included).
    pub fn emission(&self, m: Materials) -> Vec3 {
        let mat = &m.materials[self.material as usize];
        if self.front || mat.double_sided {
            mat.emission_at(self.uv, m.textures)
        } else {
            Vec3::ZERO
        }
    }
}

/// The shading normal of a normal-mapped hit (glTF 2.0 §3.9.3, `normalTexture`), in the
/// orientation of the vertex normal `nv`: the tangent-space normal read at `uv` taken to
/// world space by the frame (T, B, nv). T is the interpolated `TANGENT` orthogonalised
/// against `nv`, B = (nv × T)·w with w the tangent's handedness; without tangents, T is the
/// triangle's ∂p/∂u and w makes B point along −∂p/∂v (glTF's v runs down the image, the
/// map's +Y up), both in the map's transformed UVs. `None` where no frame exists (UVs
/// without area, a degenerate texel): the vertex normal is used.
fn normal_mapped(
    g: &Geometry,
    i: usize,
    nv: Vec3,
    uv: Vec2,
    b: Vec2,
    map: &NormalMap,
    surfaces: &crate::scene::Surfaces,
) -> Option<Vec3> {
    let n_ts = map.normal(&surfaces.textures, uv)?;
    let w0 = 1.0 - b.x - b.y;
    let given = g.attributes_of(i).and_then(|a| {
        let t = a.tangents[0] * w0 + a.tangents[1] * b.x + a.tangents[2] * b.y;
        (t.truncate().length_squared() > 0.0).then(|| {
            let sign = if a.tangents[0].w < 0.0 { -1.0 } else { 1.0 };
            (t.truncate(), sign)
        })
    });
    let (t, sign) = match given {
        Some(t) => t,
        None => {
            let tri = &g.triangles[i];
            let sh = &g.shading[i];
            let uvs = sh.uvs.map(|u| map.texture.transform.apply(u));
            let (e1, e2) = (Vec3::from(tri.v1 - tri.v0), Vec3::from(tri.v2 - tri.v0));
            let (d1, d2) = (uvs[1] - uvs[0], uvs[2] - uvs[0]);
            let det = d1.x * d2.y - d2.x * d1.y;
            if !(det.abs() > 0.0) {
                return None;
            }
            let dpdu = (e1 * d2.y - e2 * d1.y) / det;
            let dpdv = (e2 * d1.x - e1 * d2.x) / det;
            let sign = if nv.cross(dpdu).dot(-dpdv) < 0.0 {
                -1.0
            } else {
                1.0
            };
            (dpdu, sign)
        }
    };
    let t = (t - nv * nv.dot(t)).normalize_or_zero();
    if t == Vec3::ZERO || !t.is_finite() {
        return None;
    }
    let bt = nv.cross(t) * sign;
    let n = (t * n_ts.x + bt * n_ts.y + nv * n_ts.z).normalize_or_zero();
    (n != Vec3::ZERO && n.is_finite()).then_some(n)
}

/// A shadow ray between two surface points ([`SurfacePoint::spawn_to`]).
#[derive(Debug, Clone, Copy)]
pub struct Segment {
    pub origin: Vec3,
    /// Unit direction.
    pub dir: Vec3,
    /// Distance between the two offset ends.
    pub length: f32,
    /// Where the occlusion test stops.
    pub tmax: f32,
}

impl Segment {
    /// The shadow ray from a point `from` to a point `to` on surfaces, each given as
    /// (position, error bound, geometric normal) ([`SurfacePoint::spawn_to`]). `None` if
    /// the ends coincide.
    pub fn between(from: (Vec3, Vec3, Vec3), to: (Vec3, Vec3, Vec3)) -> Option<Segment> {
        let (position, error, ng) = from;
        let (target, target_error, target_n) = to;
        let origin = offset_ray_origin(position, error, ng, target - position);
        let end = offset_ray_origin(target, target_error, target_n, origin - target);
        Segment::from_ends(origin, end)
    }

    /// The shadow ray from a point `from` on a surface (as in [`Segment::between`]) to a
    /// point `target` known exactly, which is not offset: [`Segment::between`] with a zero
    /// error bound at `target` (whose offset is zero along any finite normal), without
    /// computing the offset.
    pub fn to_exact(from: (Vec3, Vec3, Vec3), target: Vec3) -> Option<Segment> {
        let (position, error, ng) = from;
        let origin = offset_ray_origin(position, error, ng, target - position);
        Segment::from_ends(origin, target)
    }

    fn from_ends(origin: Vec3, end: Vec3) -> Option<Segment> {
        let d = end - origin;
        let length = d.length();
        (length > 0.0 && length.is_finite()).then(|| Segment {
            origin,
            dir: d / length,
            length,
            tmax: length * (1.0 - SHADOW_EPSILON),
        })
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

/// A film position (in `[0, 1]²`, y down) and, where it is known without tracing, what its
/// camera ray hits ([`camera_hits4`]).
pub type FilmPosition = ((f32, f32), Option<Option<Hit>>);

/// The camera rays through up to four film positions (each in `[0, 1]²`, y down) and what
/// they hit, traced together ([`crate::accel::Accel::closest4_rays`]: one walk of the tree
/// for four rays that run close together); each hit is the one [`camera_hit`] finds. A
/// position that comes with its hit (`Some`: a logged render's, [`camera_hit`]'s `known`) is
/// not traced.
pub fn camera_hits4(
    frame: &FrameScene,
    film: [Option<FilmPosition>; 4],
) -> [Option<(CameraRay, Option<Hit>)>; 4] {
    let rays = lanes4(|i| film[i].map(|((x, y), known)| (frame.camera.ray(x, y), known)));
    let traced = frame.accel.closest4_rays(
        &frame.static_geometry,
        &frame.dynamic_geometry,
        lanes4(|i| match rays[i] {
            Some((r, None)) => Some((r.origin, r.dir, r.tmax)),
            _ => None,
        }),
    );
    lanes4(|i| rays[i].map(|(r, known)| (r, known.unwrap_or(traced[i]))))
}

/// [`camera_hits4`] for every position of `film`, four at a time.
pub fn camera_hits(frame: &FrameScene, film: &[(f32, f32)]) -> Vec<(CameraRay, Option<Hit>)> {
    let mut out = Vec::with_capacity(film.len());
    for four in film.chunks(4) {
        let four = std::array::from_fn(|i| four.get(i).map(|&f| (f, None)));
        out.extend(camera_hits4(frame, four).into_iter().flatten());
    }
    out
}

/// What the camera sees at every pixel centre of a frame: traced once, in parallel, four
/// neighbouring pixels at a time ([`camera_hits`]), for the three passes that look there
/// (cache placement, the lookup points, the shading pass).
pub struct PixelCentres {
    width: u32,
    height: u32,
    hits: Vec<Option<Hit>>,
}

impl PixelCentres {
    /// The pixel centres of a `width` × `height` image of `frame`.
    pub fn trace(frame: &FrameScene, width: u32, height: u32) -> Self {
        use rayon::prelude::*;
        let film: Vec<(f32, f32)> = (0..height)
            .flat_map(|y| (0..width).map(move |x| Self::film(width, height, x, y)))
            .collect();
        let hits = film
            .par_chunks(64)
            .flat_map_iter(|chunk| camera_hits(frame, chunk).into_iter().map(|(_, h)| h))
            .collect();
        PixelCentres {
            width,
            height,
            hits,
        }
    }

    /// The film position of pixel (x, y)'s centre.
    fn film(width: u32, height: u32, x: u32, y: u32) -> (f32, f32) {
        (
            (x as f32 + 0.5) / width as f32,
            (y as f32 + 0.5) / height as f32,
        )
    }

    /// What pixel (x, y)'s centre ray hit.
    pub fn hit(&self, x: u32, y: u32) -> Option<Hit> {
        self.hits[(y * self.width + x) as usize]
    }

    /// The surface point pixel (x, y)'s centre ray hit ([`camera_hit`]'s).
    pub fn point(&self, frame: &FrameScene, x: u32, y: u32) -> Option<SurfacePoint> {
        let (fx, fy) = Self::film(self.width, self.height, x, y);
        let r = frame.camera.ray(fx, fy);
        self.hit(x, y)
            .map(|h| SurfacePoint::new(frame, h, r.origin, r.dir))
    }

    /// The image size the centres were traced for.
    pub fn size(&self) -> (u32, u32) {
        (self.width, self.height)
    }
}

/// The surface the camera sees through film position `(x, y)` (in `[0, 1]²`, y down), between
/// its clip planes, and the camera ray's direction.
pub fn trace_camera(frame: &FrameScene, x: f32, y: f32) -> (Vec3, Option<SurfacePoint>) {
    let (dir, _, sp) = camera_hit(frame, x, y, None);
    (dir, sp)
}

/// [`trace_camera`], and the hit itself, which a later render of the same view of the same
/// geometry may pass back as `known` instead of tracing the ray again
/// ([`crate::integrator::replay`]).
pub fn camera_hit(
    frame: &FrameScene,
    x: f32,
    y: f32,
    known: Option<Option<Hit>>,
) -> (Vec3, Option<Hit>, Option<SurfacePoint>) {
    let r = frame.camera.ray(x, y);
    let hit = known.unwrap_or_else(|| {
        frame.accel.closest(
            &frame.static_geometry,
            &frame.dynamic_geometry,
            r.origin,
            r.dir,
            r.tmax,
        )
    });
    (
        r.dir,
        hit,
        hit.map(|h| SurfacePoint::new(frame, h, r.origin, r.dir)),
    )
}

/// A shading point's shadow rays: counted, traced, and logged or answered from a log where
/// one is kept ([`crate::integrator::replay`]: watch mode's relight, whose geometry is the
/// logged render's); with them, the point's logged emitter samples ([`EmitterSample`]),
/// which [`direct_light`] reads back as far as [`Reuse`] allows, and logs afresh. A logged answer is used only for the ray it was logged for: the ray
/// cast in the same place of the sequence, with the same origin, direction and length (a
/// light that moved, or an emitter picked differently, casts other rays, which are traced).
pub struct ShadowRays<'a> {
    /// Shadow rays cast, traced or answered from the log.
    pub cast: &'a mut u64,
    /// Answers logged by an earlier render, in the order their rays were cast
    /// ([`ShadowRays::entry`]).
    known: &'a [u64],
    next: usize,
    /// Where this render's answers are logged.
    log: Option<&'a mut Vec<u64>>,
    /// The emitter samples an earlier render logged at this point, and what of them holds.
    known_emitters: &'a [EmitterSample],
    reuse: Reuse,
    /// Where this render's emitter samples are logged.
    emitter_log: Option<&'a mut Vec<EmitterSample>>,
}

/// What of a logged [`EmitterSample`] a relight may use where its emitter pick is the
/// logged one (the same emitter, with the same probability).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Reuse {
    /// Nothing: the sample is computed afresh.
    #[default]
    None,
    /// The surface is the logged one (its shading normal, the direction to the sampled
    /// point and the geometric factor), but its BRDF may differ: the BRDF is evaluated again.
    Surface,
    /// The BRDF too: only the emitter's emission is read again.
    Brdf,
}

/// One emitter sample of [`direct_light`] as a relight reads it back (watch mode's log,
/// [`crate::integrator::replay`]): the emitter picked and its probability, how far the
/// sample got, the direction and geometric factor, the BRDF value, where on the emitter,
/// and its shadow ray's log entry. 64 bytes.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct EmitterSample {
    /// The emitter's index (low 29 bits), the stage reached (bits 30–31: [`STAGE_GEOMETRY`],
    /// [`STAGE_BRDF`], [`STAGE_SHADOW`]) and whether the light was weighted against a BRDF
    /// sample (bit 29).
    packed: u32,
    p_pick: f32,
    wi: Vec3,
    /// cos θx cos θy (area / r²) / p_pick × the MIS weight.
    scale: f32,
    f: Lobes,
    bc: glam::Vec2,
    shadow: u64,
}

const _: () = assert!(size_of::<EmitterSample>() == 64);

/// Stopped before the BRDF: facing away, or degenerate.
const STAGE_GEOMETRY: u32 = 0;
/// Stopped at a BRDF value of zero (no shadow ray).
const STAGE_BRDF: u32 = 1;
/// A shadow ray was cast (`shadow` is its entry).
const STAGE_SHADOW: u32 = 2;
const MIS_BIT: u32 = 1 << 29;
const EMITTER_MASK: u32 = MIS_BIT - 1;

impl EmitterSample {
    fn new(emitter: usize, p_pick: f32, mis: bool) -> Self {
        EmitterSample {
            packed: (emitter as u32 & EMITTER_MASK) | if mis { MIS_BIT } else { 0 },
            p_pick,
            ..Default::default()
        }
    }

    fn stage(&self) -> u32 {
        self.packed >> 30
    }

    fn at(mut self, stage: u32) -> Self {
        self.packed = (self.packed & !(3 << 30)) | (stage << 30);
        self
    }

    /// Whether it was logged for the pick `(emitter, p_pick)` under `sampling`.
    fn is_pick(&self, emitter: usize, p_pick: f32, mis: bool) -> bool {
        emitter < EMITTER_MASK as usize
            && self.packed & EMITTER_MASK == emitter as u32
            && self.p_pick.to_bits() == p_pick.to_bits()
            && (self.packed & MIS_BIT != 0) == mis
    }

    /// Inverts the logged shadow ray's answer. For the test that a relight reads them.
    #[doc(hidden)]
    pub fn invert_shadow(&mut self) {
        if self.stage() == STAGE_SHADOW {
            self.shadow ^= 1;
        }
    }

    /// Sets every logged BRDF value to zero. For the test that a relight reads them.
    #[doc(hidden)]
    pub fn clear_brdf(&mut self) {
        self.f = Lobes::ZERO;
    }
}

impl<'a> ShadowRays<'a> {
    /// Traces every ray, counting them in `cast`.
    pub fn traced(cast: &'a mut u64) -> Self {
        ShadowRays {
            cast,
            known: &[],
            next: 0,
            log: None,
            known_emitters: &[],
            reuse: Reuse::None,
            emitter_log: None,
        }
    }

    /// Answers from `known` where it holds the same ray, traces the others, and logs every
    /// answer in `log`.
    pub fn logged(cast: &'a mut u64, known: &'a [u64], log: Option<&'a mut Vec<u64>>) -> Self {
        ShadowRays {
            cast,
            known,
            next: 0,
            log,
            known_emitters: &[],
            reuse: Reuse::None,
            emitter_log: None,
        }
    }

    /// The same, where an earlier render logged the point's emitter samples `known` (used as
    /// `reuse` allows) and this one logs its own into `log`.
    pub fn with_emitters(
        self,
        known: &'a [EmitterSample],
        reuse: Reuse,
        log: Option<&'a mut Vec<EmitterSample>>,
    ) -> Self {
        ShadowRays {
            known_emitters: known,
            reuse,
            emitter_log: log,
            ..self
        }
    }

    /// A logged shadow ray's answer, for the same ray cast again: counted, logged, and
    /// the known answers' place moved past it as [`ShadowRays::occluded`] does.
    fn replay(&mut self, entry: u64) -> bool {
        *self.cast += 1;
        self.next += 1;
        if let Some(log) = self.log.as_deref_mut() {
            log.push(entry);
        }
        entry & 1 == 1
    }

    fn log_emitter(&mut self, e: EmitterSample) {
        if let Some(log) = self.emitter_log.as_deref_mut() {
            log.push(e);
        }
    }

    /// Whether something blocks the ray `o + t·dir`, `0 < t < tmax`.
    fn occluded(&mut self, frame: &FrameScene, o: Vec3, dir: Vec3, tmax: f32) -> bool {
        self.occluded_entry(frame, o, dir, tmax) & 1 == 1
    }

    /// [`ShadowRays::occluded`], as its log entry (0 | the answer where nothing is logged).
    fn occluded_entry(&mut self, frame: &FrameScene, o: Vec3, dir: Vec3, tmax: f32) -> u64 {
        *self.cast += 1;
        let trace = || {
            frame.accel.occluded(
                &frame.static_geometry,
                &frame.dynamic_geometry,
                o,
                dir,
                tmax,
            )
        };
        if self.log.is_none() && self.known.is_empty() {
            return u64::from(trace());
        }
        let key = Self::entry(o, dir, tmax, false);
        let answer = match self.known.get(self.next) {
            Some(&e) if e | 1 == key | 1 => e & 1 == 1,
            _ => trace(),
        };
        self.next += 1;
        let entry = key | u64::from(answer);
        if let Some(log) = self.log.as_deref_mut() {
            log.push(entry);
        }
        entry
    }

    /// A log entry: a 63-bit hash of the ray's bits (origin, direction, length), the answer
    /// in the lowest bit. Two different rays share a hash with probability 2⁻⁶³.
    fn entry(o: Vec3, dir: Vec3, tmax: f32, occluded: bool) -> u64 {
        let mut h = 0x243f_6a88_85a3_08d3u64;
        for w in [o.x, o.y, o.z, dir.x, dir.y, dir.z, tmax].map(f32::to_bits) {
            h = (h ^ u64::from(w)).wrapping_mul(0x9e37_79b9_7f4a_7c15);
            h ^= h >> 29;
        }
        (h & !1) | u64::from(occluded)
    }
}

/// Light from one punctual light at `x`, shadow ray included (`KHR_lights_punctual`): the
/// direction towards it and the irradiance it gives a surface facing it; `None` where it is
/// blocked, out of range or behind the surface.
fn punctual_incident(
    frame: &FrameScene,
    x: &SurfacePoint,
    l: &PunctualLight,
    shadow: &mut ShadowRays,
) -> Option<(Vec3, Vec3)> {
    punctual_incident_from(frame, x.spawn(), x.ns, x.ng, l, shadow)
}

/// The light of one punctual light, shadow ray included, at a point known by its shadow
/// rays' origin `o` (already off its surface) and its shading and geometric normals: the
/// direction towards the light and the irradiance it gives a surface facing it.
pub fn punctual_incident_from(
    frame: &FrameScene,
    o: Vec3,
    ns: Vec3,
    ng: Vec3,
    l: &PunctualLight,
    shadow: &mut ShadowRays,
) -> Option<(Vec3, Vec3)> {
    let (wi, dist, e) = match l.kind {
        LightKind::Directional => (-l.direction, f32::INFINITY, l.intensity),
        LightKind::Point | LightKind::Spot { .. } => {
            let d = l.position - o;
            let r2 = d.length_squared();
            let r = r2.sqrt();
            if !(r > 0.0) || l.range.is_some_and(|range| r > range) {
                return None;
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
    if ns.dot(wi) <= 0.0 || ng.dot(wi) <= 0.0 || e == Vec3::ZERO {
        return None;
    }
    if shadow.occluded(frame, o, wi, dist) {
        return None;
    }
    Some((wi, e))
}

/// The power heuristic with exponent 2 (Veach 1997) for a sample whose strategy had density
/// `a` against another strategy's `b` (each already multiplied by its sample count).
#[inline]
pub fn power_heuristic(a: f32, b: f32) -> f32 {
    if !(a > 0.0) {
        return 0.0;
    }
    let r = b / a;
    if !r.is_finite() {
        return 0.0;
    }
    1.0 / (1.0 + r * r)
}

/// The solid-angle density with which one emitter sample from `x` picks the point `y` that a
/// ray from `x` along `dir` found at `distance`, on emitter triangle `y.hit` (0 if it is not
/// an emitter): the pick probability × r² / (area × |cos θy|).
pub fn emitter_pdf(frame: &FrameScene, y: &SurfacePoint, dir: Vec3, distance: f32) -> f32 {
    let Some((em, p_pick)) = frame.emitters.find(y.hit.motion, y.hit.triangle) else {
        return 0.0;
    };
    let cos_y = y.ng.dot(dir).abs();
    if !(cos_y > 0.0 && em.area > 0.0) {
        return 0.0;
    }
    // r²/area first: scale-free, so neither tiny nor huge scenes leave f32's range.
    p_pick * (distance / em.area.sqrt()).powi(2) / cos_y
}

/// How the direct light of emissive triangles is estimated.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LightSampling {
    /// Emitter samples only.
    Lights,
    /// Emitter samples and one BRDF sample, combined by multiple importance sampling.
    Mis,
}

/// Direct light `x` reflects towards `wo` through `bsdf`, by lobe: punctual lights exactly,
/// emissive triangles by `n` QMC samples (`sampler` indices `index·n ..`, dimensions
/// `dim..dim+3`). With [`LightSampling::Mis`] each emitter sample is weighted by the power
/// heuristic against one BRDF sample, which the caller adds ([`brdf_sampled_emission`] at a
/// camera hit, the path's next vertex in the path tracer).
#[allow(clippy::too_many_arguments)]
pub fn direct_light(
    frame: &FrameScene,
    x: &SurfacePoint,
    wo: Vec3,
    bsdf: &Bsdf,
    sampler: &Sampler,
    (index, n, dim): (u32, u32, u32),
    sampling: LightSampling,
    shadow: &mut ShadowRays,
) -> Lobes {
    let ns = x.shading_normal(wo);
    let mut out = Lobes::ZERO;
    for l in &frame.lights {
        if let Some((wi, e)) = punctual_incident(frame, x, l, shadow) {
            out += bsdf.eval(ns, wo, wi).scale(e * ns.dot(wi).max(0.0));
        }
    }
    if frame.emitters.list.is_empty() || n == 0 {
        return out;
    }
    let mut area = Lobes::ZERO;
    let mis = sampling == LightSampling::Mis;
    for j in 0..n {
        let i = index * n + j;
        let Some((k, p_pick)) = frame.emitters.pick(sampler.get(i, dim)) else {
            break;
        };
        let em = &frame.emitters.list[k];
        // A relight's logged sample of the same pick: what `reuse` allows is read back.
        let known = shadow
            .known_emitters
            .get(j as usize)
            .filter(|e| e.is_pick(k, p_pick, mis));
        let reuse = match (known, shadow.reuse) {
            (Some(_), Reuse::Surface) if mis => Reuse::None,
            (Some(_), r) => r,
            (None, _) => Reuse::None,
        };
        if let (Some(&e), Reuse::Surface | Reuse::Brdf) = (known, reuse) {
            let f = match (e.stage(), reuse) {
                (STAGE_GEOMETRY, _) => Lobes::ZERO,
                (_, Reuse::Brdf) => e.f,
                _ => bsdf.eval(ns, wo, e.wi),
            };
            match e.stage() {
                STAGE_GEOMETRY => {
                    shadow.log_emitter(e);
                    continue;
                }
                _ if f.sum() == Vec3::ZERO => {
                    shadow.log_emitter(EmitterSample { f, ..e }.at(STAGE_BRDF));
                    continue;
                }
                STAGE_SHADOW => {
                    shadow.log_emitter(EmitterSample { f, ..e });
                    if !shadow.replay(e.shadow) {
                        let l_e = frame.emitted_radiance(em, e.bc);
                        area += f.scale(l_e * e.scale);
                    }
                    continue;
                }
                // The BRDF was zero there and is not now: the shadow ray was never cast.
                _ => {}
            }
        }
        let mut logged = EmitterSample::new(k, p_pick, mis);
        let g = frame.geometry(em.motion);
        let tri = &g.triangles[em.triangle as usize];
        // Uniform point on the triangle (Shirley's square-root parameterisation), with the
        // error bound of its interpolation (pbrt-v4 §6.8.5).
        let [u1, u2] = sampler.get2(i, dim + 1);
        let su = u1.sqrt();
        let (y, y_error) = interpolate(tri, Vec3::new(1.0 - su, su * (1.0 - u2), su * u2));
        let bc = uniform_barycentric(u1, u2);
        let (ny, _) = face_normal_area(tri);
        let Some(seg) = x.spawn_to(y, y_error, ny) else {
            shadow.log_emitter(logged);
            continue;
        };
        let (r, wi) = (seg.length, seg.dir);
        let cos_x = ns.dot(wi);
        let cos_y = -ny.dot(wi);
        let cos_y = if em.double_sided { cos_y.abs() } else { cos_y };
        if cos_x <= 0.0 || cos_y <= 0.0 || x.ng.dot(wi) <= 0.0 || !(r > 0.0) {
            shadow.log_emitter(logged);
            continue;
        }
        let f = bsdf.eval(ns, wo, wi);
        logged = EmitterSample {
            wi,
            bc,
            f,
            ..logged
        };
        if f.sum() == Vec3::ZERO {
            shadow.log_emitter(logged.at(STAGE_BRDF));
            continue;
        }
        let entry = shadow.occluded_entry(frame, seg.origin, wi, seg.tmax);
        logged = EmitterSample {
            shadow: entry,
            ..logged.at(STAGE_SHADOW)
        };
        if entry & 1 == 1 {
            // A relight that reads this sample back finds the same ray blocked: it needs
            // no factor.
            shadow.log_emitter(logged);
            continue;
        }
        // L_e f cosθx cosθy / r² / pdf_area, pdf_area = p_pick / area. Ordered so that
        // neither tiny nor huge scenes leave f32's range: area / r² is scale-free.
        let ratio = (em.area.sqrt() / r).powi(2);
        let weight = match sampling {
            LightSampling::Lights => 1.0,
            LightSampling::Mis => {
                let p_light = n as f32 * p_pick / (ratio * cos_y);
                power_heuristic(p_light, bsdf.pdf(ns, wo, wi))
            }
        };
        let scale = cos_x * cos_y * ratio / p_pick * weight;
        shadow.log_emitter(EmitterSample { scale, ..logged });
        let l_e = frame.emitted_radiance(em, bc);
        area += f.scale(l_e * scale);
    }
    out + area.scale(Vec3::splat(1.0 / n as f32))
}

/// The BRDF-sampled half of [`LightSampling::Mis`] at `x`: one direction drawn from `bsdf`
/// with `u`; if its ray meets an emitter, the emission it reflects towards `wo`, weighted by
/// the power heuristic against `n_light` emitter samples. Counts the ray in `rays`.
#[allow(clippy::too_many_arguments)]
pub fn brdf_sampled_emission(
    frame: &FrameScene,
    m: Materials,
    x: &SurfacePoint,
    wo: Vec3,
    bsdf: &Bsdf,
    u: [f32; 3],
    n_light: u32,
    rays: &mut u64,
) -> Lobes {
    if frame.emitters.list.is_empty() {
        return Lobes::ZERO;
    }
    let ns = x.shading_normal(wo);
    let Some(s) = bsdf.sample(ns, wo, u) else {
        return Lobes::ZERO;
    };
    if x.ng.dot(s.wi) <= 0.0 {
        return Lobes::ZERO;
    }
    *rays += 1;
    let o = x.spawn();
    let Some(h) = frame.accel.closest(
        &frame.static_geometry,
        &frame.dynamic_geometry,
        o,
        s.wi,
        f32::INFINITY,
    ) else {
        return Lobes::ZERO;
    };
    if frame.emitters.find(h.motion, h.triangle).is_none() {
        return Lobes::ZERO;
    }
    let y = SurfacePoint::new(frame, h, o, s.wi);
    let l_e = y.emission(m);
    if l_e == Vec3::ZERO {
        return Lobes::ZERO;
    }
    let p_light = n_light as f32 * emitter_pdf(frame, &y, s.wi, h.t);
    let w = power_heuristic(s.pdf, p_light);
    s.f.scale(l_e * (ns.dot(s.wi) / s.pdf * w))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::accel::canonical;

    #[test]
    fn a_segment_to_an_exact_point_is_one_between_with_no_error_there() {
        let mut state = 3u32;
        let mut next = || {
            state = crate::sampling::hash(&[state]);
            state as f32 / u32::MAX as f32 * 2.0 - 1.0
        };
        for i in 0..20_000 {
            let scale = [1e-3, 1.0, 1e6][i % 3];
            let mut v = || Vec3::new(next(), next(), next());
            let (p, target) = (v() * scale, v() * scale);
            let error = v().abs() * scale * 1e-6;
            let (ng, target_n) = (v().normalize_or(Vec3::Z), v().normalize_or(Vec3::Y));
            let (Some(a), Some(b)) = (
                Segment::to_exact((p, error, ng), target),
                Segment::between((p, error, ng), (target, Vec3::ZERO, target_n)),
            ) else {
                panic!("{p} to {target}: no segment");
            };
            // The ray that runs is the same to the bit (a zero's sign aside, which the
            // trace's canonical direction drops).
            let bits = |v: Vec3| v.to_array().map(f32::to_bits);
            assert_eq!(bits(a.origin), bits(b.origin));
            assert_eq!(
                bits(canonical(a.dir)),
                bits(canonical(b.dir)),
                "{p} to {target}"
            );
            assert_eq!(a.tmax.to_bits(), b.tmax.to_bits());
            assert_eq!(a.length.to_bits(), b.length.to_bits());
        }
    }
}
