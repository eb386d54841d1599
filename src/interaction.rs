//! Where light meets a surface: the shading point a ray finds ([`SurfacePoint`]), tracing,
//! and direct light from every light with shadow rays ([`direct_irradiance`]). Every
//! method builds on these, at camera hits and at final-gather hits alike.
//!
//! Units: pixel values are radiance in the scene's light units (glTF: candela for point and
//! spot lights, lux for directional lights, nits for emission), so a point light of
//! intensity `I` over a white Lambertian plane gives `I·cosθ/(π r²)`.

use glam::{Vec2, Vec3};

use crate::accel::{
    Hit, SHADOW_EPSILON, barycentric, gamma, hit_point, interpolate, offset_ray_origin,
};
use crate::geom::face_normal_area;
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
        let ns =
            (sh.normals[0] * w + sh.normals[1] * b.x + sh.normals[2] * b.y).normalize_or_zero();
        let ns = if ns.dot(ng) < 0.0 { -ns } else { ns };
        let ns = if ns == Vec3::ZERO { ng } else { ns };
        SurfacePoint {
            position: hp.position,
            ng,
            ns,
            uv: sh.uvs[0] * w + sh.uvs[1] * b.x + sh.uvs[2] * b.y,
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
        let origin = offset_ray_origin(self.position, self.error, self.ng, target - self.position);
        let end = offset_ray_origin(target, target_error, target_n, origin - target);
        let d = end - origin;
        let length = d.length();
        (length > 0.0 && length.is_finite()).then(|| Segment {
            origin,
            dir: d / length,
            length,
            tmax: length * (1.0 - SHADOW_EPSILON),
        })
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
    let mut area = Vec3::ZERO;
    for j in 0..n {
        let i = index * n + j;
        let Some((k, p_pick)) = frame.emitters.pick(sampler.get(i, dim)) else {
            break;
        };
        let em = &frame.emitters.list[k];
        let g = frame.geometry(em.motion);
        let tri = &g.triangles[em.triangle as usize];
        // Uniform point on the triangle (Shirley's square-root parameterisation), with the
        // error bound of its interpolation (pbrt-v4 §6.8.5).
        let [u1, u2] = sampler.get2(i, dim + 1);
        let su = u1.sqrt();
        let (y, y_error) = interpolate(tri, Vec3::new(1.0 - su, su * (1.0 - u2), su * u2));
        let (ny, _) = face_normal_area(tri);
        let Some(seg) = x.spawn_to(y, y_error, ny) else {
            continue;
        };
        let (r, wi) = (seg.length, seg.dir);
        let r2 = r * r;
        if !(r2 > 0.0) {
            continue;
        }
        let cos_x = x.ns.dot(wi);
        let cos_y = -ny.dot(wi);
        let cos_y = if em.double_sided { cos_y.abs() } else { cos_y };
        if cos_x <= 0.0 || cos_y <= 0.0 || x.ng.dot(wi) <= 0.0 {
            continue;
        }
        *shadow_rays += 1;
        if frame.accel.occluded(
            &frame.static_geometry,
            &frame.dynamic_geometry,
            seg.origin,
            wi,
            seg.tmax,
        ) {
            continue;
        }
        // E = L_e cosθx cosθy / r² / pdf_area, pdf_area = p_pick / area. Ordered so that
        // neither tiny nor huge scenes leave f32's range: (area / r²) is scale-free.
        area += em.radiance * (cos_x * cos_y * (em.area / r2) / p_pick);
    }
    e + area / n as f32
}
