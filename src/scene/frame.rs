//! The immutable, render-ready scene at one time (STYLE.md §2, Tungsten's
//! `TraceableScene`): render-space triangles (world space less the render origin,
//! [`super::Scene::render_origin`]) split into static and dynamic sets with their
//! BVHs, punctual lights, emissive triangles ready for sampling, and the camera.

use std::sync::Arc;

use glam::{DMat3, DMat4, DVec3, Vec2, Vec3, Vec4};

use super::{Clip, Light, LightKind, Material, Primitive, Projection, Surfaces, Texture};
use crate::accel::{Accel, StaticBvh};
use crate::color::luminance;
use crate::geom::{
    Geometry, Motion, NO_ATTRIBUTES, Triangle, TriangleAttributes, TriangleShading,
    face_normal_area,
};

/// Static geometry and its BVH: evaluated and built once per render, shared by every frame.
#[derive(Clone)]
pub struct StaticSet {
    pub geometry: Arc<Geometry>,
    pub bvh: Arc<StaticBvh>,
    /// Bounding box of the static geometry (the unit box when there is none).
    pub bounds: (Vec3, Vec3),
    /// The world point that is render space's origin ([`super::Scene::render_origin`]):
    /// every position of a render — geometry, lights, camera, and what is kept across
    /// frames — is relative to it.
    pub origin: DVec3,
}

impl StaticSet {
    /// A static set whose render space is world space.
    pub fn new(geometry: Geometry) -> Self {
        Self::with_origin(geometry, DVec3::ZERO)
    }

    /// A static set of `geometry` already in the render space of `origin`.
    pub fn with_origin(geometry: Geometry, origin: DVec3) -> Self {
        let bvh = Arc::new(StaticBvh::build(&geometry));
        let mut lo = Vec3::splat(f32::MAX);
        let mut hi = Vec3::splat(f32::MIN);
        for t in &geometry.triangles {
            for v in [t.v0, t.v1, t.v2] {
                lo = lo.min(v.into());
                hi = hi.max(v.into());
            }
        }
        let bounds = if lo.x > hi.x {
            (Vec3::ZERO, Vec3::ONE)
        } else {
            (lo, hi)
        };
        StaticSet {
            geometry: Arc::new(geometry),
            bvh,
            bounds,
            origin,
        }
    }
}

impl Geometry {
    /// Appends a primitive transformed by `world` — or, when skinned, by its `joints`
    /// matrices (glTF §3.7.3: the mesh node's own transform is then ignored) — after
    /// applying morph `weights`, into render space: world positions are computed in f64 and
    /// `origin` (the render-space origin, see [`StaticSet::origin`]) is subtracted before
    /// they are rounded to f32.
    pub fn push_primitive(
        &mut self,
        p: &Primitive,
        world: DMat4,
        joints: Option<&[DMat4]>,
        weights: &[f32],
        prim: u32,
        origin: DVec3,
    ) {
        let n = p.positions.len();
        let mut pos = p.positions.clone();
        let mut nrm = p.normals.clone();
        for (w, target) in weights.iter().zip(&p.targets) {
            if *w == 0.0 {
                continue;
            }
            for (v, d) in pos.iter_mut().zip(&target.positions) {
                *v += *w * *d;
            }
            if let Some(nrm) = nrm.as_mut() {
                for (v, d) in nrm.iter_mut().zip(&target.normals) {
                    *v += *w * *d;
                }
            }
        }
        // Per-vertex matrix: skinning blends joint matrices by weight.
        let skin = |v: usize| -> DMat4 {
            match joints {
                Some(j) if v < p.joints.len() && v < p.weights.len() => {
                    let mut m = DMat4::ZERO;
                    for k in 0..4 {
                        let w = p.weights[v][k];
                        if w != 0.0 {
                            m += j
                                .get(p.joints[v][k] as usize)
                                .copied()
                                .unwrap_or(DMat4::IDENTITY)
                                * w as f64;
                        }
                    }
                    m
                }
                _ => world,
            }
        };
        let world_normals = DMat3::from_mat4(world).inverse().transpose();
        let mut wpos = Vec::with_capacity(n);
        let mut wnrm = Vec::with_capacity(n);
        let mut wtan = Vec::with_capacity(n);
        for v in 0..n {
            let m = if joints.is_some() { skin(v) } else { world };
            wpos.push((m.transform_point3(pos[v].as_dvec3()) - origin).as_vec3());
            if let Some(nrm) = &nrm {
                let nm = if joints.is_some() {
                    DMat3::from_mat4(m).inverse().transpose()
                } else {
                    world_normals
                };
                wnrm.push((nm * nrm[v].as_dvec3()).normalize_or_zero().as_vec3());
            }
            if let Some(t) = p.tangents.as_ref().and_then(|t| t.get(v)) {
                // Tangents are directions on the surface: transformed by the matrix itself;
                // a mirroring matrix flips the bitangent's handedness.
                let m3 = DMat3::from_mat4(m);
                let w = if m3.determinant() < 0.0 { -t.w } else { t.w };
                wtan.push(
                    (m3 * t.truncate().as_dvec3())
                        .normalize_or_zero()
                        .as_vec3()
                        .extend(w),
                );
            }
        }
        let mirrored = joints.is_none() && world.determinant() < 0.0;
        for t in p.indices.chunks_exact(3) {
            let mut idx = [t[0] as usize, t[1] as usize, t[2] as usize];
            if mirrored {
                idx.swap(1, 2);
            }
            let [a, b, c] = idx.map(|i| wpos[i]);
            let tri = Triangle {
                v0: a.into(),
                v1: b.into(),
                v2: c.into(),
            };
            let (ng, area) = face_normal_area(&tri);
            if !(area > 0.0) || !a.is_finite() || !b.is_finite() || !c.is_finite() {
                continue; // collapsed by a zero scale or a degenerate skin pose
            }
            let normals = idx.map(|i| match wnrm.get(i) {
                Some(v) if v.length_squared() > 0.5 => *v,
                _ => ng,
            });
            let uvs = idx.map(|i| {
                p.uvs
                    .as_ref()
                    .and_then(|u| u.get(i).copied())
                    .unwrap_or(Vec2::ZERO)
            });
            self.triangles.push(tri);
            let attributes = if p.colors.is_some() || !wtan.is_empty() {
                let color = |i: usize| {
                    p.colors
                        .as_ref()
                        .and_then(|c| c.get(i).copied())
                        .unwrap_or(Vec4::ONE)
                };
                let tangent = |i: usize| wtan.get(i).copied().unwrap_or(Vec4::ZERO);
                self.attributes.push(TriangleAttributes {
                    colors: idx.map(color),
                    tangents: idx.map(tangent),
                });
                (self.attributes.len() - 1) as u32
            } else {
                NO_ATTRIBUTES
            };
            self.shading.push(TriangleShading {
                normals,
                uvs,
                material: p.material as u32,
                prim,
                masked: p.masked,
                attributes,
            });
        }
    }
}

/// A pinhole or orthographic camera in render space.
#[derive(Debug, Clone, Copy)]
pub struct FrameCamera {
    pub origin: Vec3,
    pub right: Vec3,
    pub up: Vec3,
    /// Viewing direction (the camera's −Z).
    pub forward: Vec3,
    pub projection: Projection,
    pub aspect: f32,
    /// Camera rays see surfaces between these depths along `forward` only.
    pub clip: Clip,
    /// tan(yfov / 2) of a perspective projection, computed once (every camera ray uses it).
    tan_half_yfov: f32,
}

/// tan(yfov / 2) of a perspective projection; 0 for an orthographic one.
fn tan_half_yfov(projection: Projection) -> f32 {
    match projection {
        Projection::Perspective { yfov } => (0.5 * yfov).tan(),
        Projection::Orthographic { .. } => 0.0,
    }
}

/// A camera ray: it sees surfaces from `origin` (on the near plane) out to `tmax`.
#[derive(Debug, Clone, Copy)]
pub struct CameraRay {
    pub origin: Vec3,
    pub dir: Vec3,
    pub tmax: f32,
}

impl FrameCamera {
    /// Why a camera node with world matrix `world` can place no view, if it cannot: glTF
    /// 2.0 §3.10 makes the view matrix the inverse of the camera node's global transform,
    /// so every axis of it needs a non-zero, finite scale (a zero scale collapses the view
    /// and makes the far clip depth ∞ × 0), and the mean scale that the clip depths are
    /// multiplied by ([`Self::from_matrix`]) must stay a positive, finite f32. Non-uniform
    /// and mirroring scales place a view.
    pub fn placement_error(world: DMat4, clip: Clip) -> Option<String> {
        let (scale, rot, origin) = world.to_scale_rotation_translation();
        let s = (scale.abs().element_sum() / 3.0) as f32;
        let why = if !(world.is_finite() && scale.is_finite() && origin.is_finite()) {
            "is not finite"
        } else if !(scale.abs().min_element() > 0.0 && rot.is_finite()) {
            "is singular (an axis is scaled to zero)"
        } else if !(s > 0.0 && s.is_finite() && (clip.near * s).is_finite()) {
            "scales the clip depths out of f32's range"
        } else {
            return None;
        };
        Some(format!(
            "the camera's world transform (translation {:?}, scale {:?}) {why}, so it \
             places no view (glTF 2.0 §3.10: the view matrix is its inverse); give the \
             camera node and its ancestors a non-zero, finite scale",
            origin.to_array(),
            scale.to_array()
        ))
    }

    /// From a camera node's world matrix (scale removed: cameras look along −Z), in the
    /// render space whose origin is the world point `render_origin`. The clip depths are in
    /// the node's units, so they scale with the node's world scale as the scene does. The
    /// matrix must place a view ([`Self::placement_error`]: [`super::Scene::check_camera`]
    /// refuses a camera whose matrix does not at a frame it renders).
    pub fn from_matrix(
        world: DMat4,
        render_origin: DVec3,
        projection: Projection,
        clip: Clip,
        aspect: f32,
    ) -> Self {
        let (scale, rot, origin) = world.to_scale_rotation_translation();
        let rot = rot.as_quat();
        let s = (scale.abs().element_sum() / 3.0) as f32;
        FrameCamera {
            origin: (origin - render_origin).as_vec3(),
            right: rot * Vec3::X,
            up: rot * Vec3::Y,
            forward: rot * -Vec3::Z,
            projection,
            tan_half_yfov: tan_half_yfov(projection),
            aspect,
            clip: Clip {
                near: clip.near * s,
                far: clip.far * s,
            },
        }
    }

    /// The same camera with clip depths `clip`.
    pub fn with_clip(self, clip: Clip) -> Self {
        FrameCamera { clip, ..self }
    }

    pub fn look_at(position: Vec3, target: Vec3, up: Vec3, yfov: f32, aspect: f32) -> Self {
        let forward = (target - position).normalize();
        let right = forward.cross(up).normalize();
        FrameCamera {
            origin: position,
            right,
            up: right.cross(forward),
            forward,
            projection: Projection::Perspective { yfov },
            tan_half_yfov: tan_half_yfov(Projection::Perspective { yfov }),
            aspect,
            clip: Clip::default(),
        }
    }

    /// Ray through film position `(x, y)` in `[0, 1]²`, y down, from the near clip plane to
    /// the far one (glTF 2.0 §3.10: `znear`, `zfar` are depths along the view axis).
    pub fn ray(&self, x: f32, y: f32) -> CameraRay {
        let sx = 2.0 * x - 1.0;
        let sy = 1.0 - 2.0 * y;
        let (eye, dir) = match self.projection {
            Projection::Perspective { .. } => {
                let h = self.tan_half_yfov;
                let d = self.forward + self.right * (sx * h * self.aspect) + self.up * (sy * h);
                (self.origin, d.normalize())
            }
            Projection::Orthographic { ymag } => {
                let o =
                    self.origin + self.right * (sx * ymag * self.aspect) + self.up * (sy * ymag);
                (o, self.forward)
            }
        };
        // Distance along the ray per unit of depth.
        let per_depth = 1.0 / dir.dot(self.forward).max(f32::MIN_POSITIVE);
        let near = self.clip.near * per_depth;
        CameraRay {
            origin: eye + dir * near,
            dir,
            tmax: if self.clip.far.is_finite() {
                (self.clip.far * per_depth - near).max(0.0)
            } else {
                f32::INFINITY
            },
        }
    }

    /// Depth of `p` along the view axis (the `Z` AOV).
    pub fn depth(&self, p: Vec3) -> f32 {
        (p - self.origin).dot(self.forward)
    }
}

/// A punctual light in render space. `intensity` is colour × intensity: radiant intensity
/// (point, spot) or irradiance at normal incidence (directional).
#[derive(Debug, Clone, Copy)]
pub struct PunctualLight {
    pub kind: LightKind,
    pub position: Vec3,
    /// Direction the light points (its −Z); for directional lights, the light travels along it.
    pub direction: Vec3,
    pub intensity: Vec3,
    pub range: Option<f32>,
}

impl PunctualLight {
    /// The light of a node with world matrix `world`, in the render space whose origin is
    /// the world point `origin`.
    /// The light points along the node's −Z axis as `world` maps it, which a non-uniform
    /// scale above a rotated node turns (a decomposition into a rotation would not);
    /// [`crate::scene::Scene::check_lights`] refuses a node that maps it to zero. Range and
    /// intensity do not change with the node's scale (`KHR_lights_punctual`); the range is
    /// in the file's units, which the job's layer transform scales by `units` (the cube root
    /// of its determinant).
    pub fn new(l: &Light, world: DMat4, origin: DVec3, units: f32) -> Self {
        PunctualLight {
            kind: l.kind,
            position: (world.w_axis.truncate() - origin).as_vec3(),
            direction: world
                .transform_vector3(DVec3::NEG_Z)
                .normalize_or_zero()
                .as_vec3(),
            intensity: l.color * l.intensity,
            range: l.range.map(|r| r * units),
        }
    }
}

/// An emissive triangle, for sampling direct light.
#[derive(Debug, Clone, Copy)]
pub struct Emitter {
    pub motion: Motion,
    pub triangle: u32,
    pub area: f32,
    /// Emitted radiance averaged over the triangle (exact without an emissive texture):
    /// what its power, and so the probability of choosing it, is computed from.
    pub radiance: Vec3,
    pub double_sided: bool,
    /// Its radiance varies over it (its material has an emissive texture, or an alpha
    /// cut-out, whose removed parts emit nothing): the radiance at a point is
    /// [`FrameScene::emitted_radiance`], not [`Emitter::radiance`].
    pub varies: bool,
}

/// Samples per side of the stratified grid over which a textured or cut-out emitter's
/// radiance is averaged (8 × 8 = 64 points, uniform in area): the texture integrated over
/// the triangle for its power. Only selection probabilities depend on it; every estimate
/// reads the texture (and the cut-out) at its own point, so an inexact average adds noise,
/// never bias. An average of zero (light only between the points) keeps the triangle, with
/// the power of one point in 64 at the material's full emission: dropping it lost that
/// light.
pub const EMISSION_AVERAGE_GRID: u32 = 8;

/// Barycentrics (weights of `v1`, `v2`) of the uniform-area point `(u1, u2)` of a triangle
/// (Shirley's square-root parameterisation).
pub fn uniform_barycentric(u1: f32, u2: f32) -> Vec2 {
    let su = u1.sqrt();
    Vec2::new(su * (1.0 - u2), su * u2)
}

/// The radiance triangle `i` of `g`, of material `m`, emits at barycentrics `b`: its
/// emission there, or none where an alpha cut-out removes the surface.
fn emitted_at(m: &Material, g: &Geometry, i: usize, b: Vec2, textures: &[Texture]) -> Vec3 {
    let (uv, color) = Surfaces::uv_and_color(g, i, b);
    if m.opaque_at(uv, color, textures) {
        m.emission_at(uv, textures)
    } else {
        Vec3::ZERO
    }
}

/// Emissive triangles with a power-proportional discrete distribution.
#[derive(Debug, Clone, Default)]
pub struct Emitters {
    pub list: Vec<Emitter>,
    /// Cumulative, normalised power; `cdf[i]` is the probability of choosing `list[..=i]`.
    pub cdf: Vec<f32>,
    /// Index in `list` of each emissive triangle, by set and triangle.
    index: rustc_hash::FxHashMap<(Motion, u32), u32>,
}

impl Emitters {
    fn new(sets: [(&Geometry, Motion); 2], surfaces: &Surfaces) -> Self {
        let mut list = Vec::new();
        let mut power = Vec::new();
        for (g, motion) in sets {
            for (i, (t, s)) in g.triangles.iter().zip(&g.shading).enumerate() {
                let m = &surfaces.materials[s.material as usize];
                if !m.is_emissive() {
                    continue;
                }
                let varies = m.emissive_texture.is_some() || m.alpha_cutoff.is_some();
                let radiance = if varies {
                    let n = EMISSION_AVERAGE_GRID;
                    let mut sum = Vec3::ZERO;
                    for a in 0..n {
                        for b in 0..n {
                            let bc = uniform_barycentric(
                                (a as f32 + 0.5) / n as f32,
                                (b as f32 + 0.5) / n as f32,
                            );
                            sum += emitted_at(m, g, i, bc, &surfaces.textures);
                        }
                    }
                    let mean = sum / (n * n) as f32;
                    // Light between the grid's points still needs a chance to be chosen.
                    if mean.max_element() > 0.0 {
                        mean
                    } else {
                        m.emission / (n * n) as f32
                    }
                } else {
                    m.emission
                };
                let (_, area) = face_normal_area(t);
                let luminance = luminance(radiance).max(1e-30);
                // Power is used only in ratios: area × luminance × sides. Computed in f64 so
                // that kilometre-sized emitters do not overflow.
                power.push(area * luminance as f64 * if m.double_sided { 2.0 } else { 1.0 });
                list.push(Emitter {
                    motion,
                    triangle: i as u32,
                    area: area as f32,
                    radiance,
                    double_sided: m.double_sided,
                    varies,
                });
            }
        }
        let total: f64 = power.iter().sum();
        let mut acc = 0.0;
        let cdf = power
            .iter()
            .map(|p| {
                acc += p;
                (acc / total) as f32
            })
            .collect();
        let index = list
            .iter()
            .enumerate()
            .map(|(i, e)| ((e.motion, e.triangle), i as u32))
            .collect();
        Emitters { list, cdf, index }
    }

    /// The emitter on triangle `triangle` of set `motion` and the probability that
    /// [`Emitters::pick`] chooses it, if it is one.
    pub fn find(&self, motion: Motion, triangle: u32) -> Option<(&Emitter, f32)> {
        let &i = self.index.get(&(motion, triangle))?;
        let i = i as usize;
        let lo = if i == 0 { 0.0 } else { self.cdf[i - 1] };
        Some((&self.list[i], self.cdf[i] - lo))
    }

    /// Picks an emitter with probability proportional to its power: `(index, probability)`.
    pub fn pick(&self, u: f32) -> Option<(usize, f32)> {
        if self.list.is_empty() {
            return None;
        }
        let i = self
            .cdf
            .partition_point(|&c| c <= u)
            .min(self.list.len() - 1);
        let lo = if i == 0 { 0.0 } else { self.cdf[i - 1] };
        Some((i, self.cdf[i] - lo))
    }
}

/// Everything one frame needs to trace rays.
pub struct FrameScene {
    pub static_geometry: Arc<Geometry>,
    pub dynamic_geometry: Geometry,
    pub accel: Accel,
    pub lights: Vec<PunctualLight>,
    pub emitters: Emitters,
    pub camera: FrameCamera,
    /// The scene's materials and textures (normal maps, vertex colours and emissive textures
    /// are read where rays hit).
    pub surfaces: Surfaces,
    /// [`StaticSet::bounds`], computed once per render.
    static_bounds: (Vec3, Vec3),
}

impl FrameScene {
    /// Builds the dynamic BVH; the static set and its BVH are shared between frames.
    pub fn new(
        statics: &StaticSet,
        dynamic_geometry: Geometry,
        lights: Vec<PunctualLight>,
        camera: FrameCamera,
        surfaces: &Surfaces,
    ) -> Self {
        let accel = Accel::with_static(statics.bvh.clone(), &dynamic_geometry);
        let static_geometry = statics.geometry.clone();
        let emitters = Emitters::new(
            [
                (&static_geometry, Motion::Static),
                (&dynamic_geometry, Motion::Dynamic),
            ],
            surfaces,
        );
        FrameScene {
            static_geometry,
            dynamic_geometry,
            accel,
            lights,
            emitters,
            camera,
            surfaces: surfaces.clone(),
            static_bounds: statics.bounds,
        }
    }

    /// Radiance emitter `e` emits at barycentrics `b` of its triangle (the emissive texture
    /// read there, when it has one).
    pub fn emitted_radiance(&self, e: &Emitter, b: Vec2) -> Vec3 {
        if !e.varies {
            return e.radiance;
        }
        let g = self.geometry(e.motion);
        let i = e.triangle as usize;
        let m = &self.surfaces.materials[g.shading[i].material as usize];
        emitted_at(m, g, i, b, &self.surfaces.textures)
    }

    pub fn geometry(&self, motion: Motion) -> &Geometry {
        match motion {
            Motion::Static => &self.static_geometry,
            Motion::Dynamic => &self.dynamic_geometry,
        }
    }

    /// Bounding box of the static geometry (the unit box when there is none): the same in
    /// every frame.
    pub fn static_box(&self) -> (Vec3, Vec3) {
        self.static_bounds
    }

    /// Radius of the sphere around [`FrameScene::static_box`]: the unit of the relative
    /// distances in the settings (D_max, photon search radii).
    pub fn static_radius(&self) -> f32 {
        let (lo, hi) = self.static_box();
        (0.5 * (hi - lo).length()).max(f32::MIN_POSITIVE)
    }

    /// Largest absolute coordinate of any vertex: the scene's scale for error bounds.
    pub fn extent(&self) -> f32 {
        let m = |g: &Geometry| {
            g.triangles
                .iter()
                .map(|t| t.v0.abs().max(t.v1.abs()).max(t.v2.abs()).max_element())
                .fold(0.0f32, f32::max)
        };
        m(&self.static_geometry).max(m(&self.dynamic_geometry))
    }
}
