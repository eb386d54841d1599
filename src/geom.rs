//! The vocabulary every stage shares: the static/dynamic split of prims (the paper's §3),
//! render-space triangles with their shading data, and the directions sampled around a
//! normal.

use std::f32::consts::PI;

use std::sync::Arc;

use glam::{Vec2, Vec3, Vec3A, Vec4};
use serde::{Deserialize, Serialize};

pub use obvhs::triangle::Triangle;

/// Whether a prim may change between frames (the paper's static/dynamic objects, §3).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum Motion {
    Static,
    Dynamic,
}

/// Per-triangle shading data, parallel to [`Geometry::triangles`].
#[derive(Debug, Clone, Copy)]
pub struct TriangleShading {
    /// Vertex normals (the geometric normal where the mesh has none).
    pub normals: [Vec3; 3],
    pub uvs: [Vec2; 3],
    pub material: u32,
    /// Global prim (node) index: layers' nodes numbered one after another.
    pub prim: u32,
    /// The material cuts the surface out where its alpha is below a cutoff (glTF `alphaMode`
    /// `MASK`, and `BLEND` rendered as a cut-out): only hits on such triangles pay for the
    /// alpha test ([`Geometry::alpha_passes`]).
    pub masked: bool,
    /// Index into [`Geometry::attributes`], or [`NO_ATTRIBUTES`] for triangles whose mesh has
    /// neither vertex colours nor tangents.
    pub attributes: u32,
}

/// [`TriangleShading::attributes`] of a triangle without vertex colours or tangents.
pub const NO_ATTRIBUTES: u32 = u32::MAX;

/// Per-vertex data only some meshes carry, kept apart so that the common triangle stays small.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TriangleAttributes {
    /// Linear RGBA vertex colours (`COLOR_0`; white where the mesh has none).
    pub colors: [Vec4; 3],
    /// World-space tangents with the bitangent's sign in `w` (`TANGENT`); zero where the mesh
    /// has none, and tangents are then derived from the texture coordinates.
    pub tangents: [Vec4; 3],
}

/// Decides whether a hit on a masked triangle counts (glTF alpha cut-out). Implemented by
/// the scene's materials; geometry without one treats every triangle as opaque.
pub trait AlphaTest: Send + Sync + std::fmt::Debug {
    /// True where triangle `triangle` of `g` is opaque at barycentrics `b` (weights of its
    /// second and third vertices).
    fn opaque(&self, g: &Geometry, triangle: usize, b: Vec2) -> bool;
}

/// Render-space triangles (world space less the render origin, `Scene::render_origin`),
/// front faces counter-clockwise (mirroring transforms are undone).
#[derive(Debug, Clone, Default)]
pub struct Geometry {
    pub triangles: Vec<Triangle>,
    pub shading: Vec<TriangleShading>,
    /// Vertex colours and tangents of the triangles that have them.
    pub attributes: Vec<TriangleAttributes>,
    /// The alpha test of masked triangles; `None` makes every triangle opaque.
    pub alpha: Option<Arc<dyn AlphaTest>>,
}

impl Geometry {
    pub fn len(&self) -> usize {
        self.triangles.len()
    }

    pub fn is_empty(&self) -> bool {
        self.triangles.is_empty()
    }

    /// Asks the CPU to bring triangle `i`'s vertices and shading record into its cache, for
    /// a hit whose surface point is made soon (a hint; nothing where the CPU has none).
    #[inline]
    pub fn prefetch(&self, i: usize) {
        // Neither record spans more than two lines.
        if let (Some(t), Some(s)) = (self.triangles.get(i), self.shading.get(i)) {
            prefetch_value(t);
            prefetch_value(s);
        }
    }

    pub fn bytes(&self) -> usize {
        self.triangles.len() * (size_of::<Triangle>() + size_of::<TriangleShading>())
            + self.attributes.len() * size_of::<TriangleAttributes>()
    }

    /// Whether a ray hitting triangle `i` at barycentrics `b` stops there: always for opaque
    /// triangles (one flag read), else the alpha test.
    #[inline]
    pub fn alpha_passes(&self, i: usize, b: Vec2) -> bool {
        if !self.shading[i].masked {
            return true;
        }
        match &self.alpha {
            Some(a) => a.opaque(self, i, b),
            None => true,
        }
    }

    /// Triangle `i`'s vertex colours and tangents, if it has them.
    pub fn attributes_of(&self, i: usize) -> Option<&TriangleAttributes> {
        self.attributes.get(self.shading[i].attributes as usize)
    }
}

/// Asks the CPU to bring the cache line at `p` into its cache, for a read soon (a hint: `p`
/// need not point into anything; nothing where the CPU has no such instruction).
#[inline(always)]
pub fn prefetch_line<T>(p: *const T) {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: a prefetch reads nothing and faults on no address.
    unsafe {
        std::arch::x86_64::_mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>(p.cast());
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = p;
}

/// [`prefetch_line`] for the first and the last line of `*v`: all of a value that spans
/// at most two lines.
#[inline(always)]
pub fn prefetch_value<T>(v: &T) {
    let p: *const u8 = std::ptr::from_ref(v).cast();
    prefetch_line(p);
    prefetch_line(p.wrapping_add(size_of::<T>().max(1) - 1));
}

/// An orthonormal basis around `n` (Duff et al. 2017).
pub fn basis(n: Vec3) -> (Vec3, Vec3) {
    let s = 1.0f32.copysign(n.z);
    let a = -1.0 / (s + n.z);
    let b = n.x * n.y * a;
    (
        Vec3::new(1.0 + s * n.x * n.x * a, s * b, -s * n.x),
        Vec3::new(b, s + n.y * n.y * a, -n.y),
    )
}

/// Cosine-weighted direction around `n` from two uniform numbers.
pub fn cosine_direction(n: Vec3, u1: f32, u2: f32) -> Vec3 {
    let (t, b) = basis(n);
    let r = u1.sqrt();
    let phi = 2.0 * PI * u2;
    (t * (r * phi.cos()) + b * (r * phi.sin()) + n * (1.0 - u1).max(0.0).sqrt()).normalize()
}

pub fn uniform_sphere(u1: f32, u2: f32) -> Vec3 {
    let z = 1.0 - 2.0 * u1;
    let r = (1.0 - z * z).max(0.0).sqrt();
    let phi = 2.0 * PI * u2;
    Vec3::new(r * phi.cos(), r * phi.sin(), z)
}

/// Unit geometric normal (counter-clockwise front) and area of a triangle, computed in f64:
/// the f32 cross product of edges longer than ~1e9 or shorter than ~1e-9 overflows or
/// underflows when squared, which turned every triangle of a 1e10-scaled scene degenerate.
/// A zero normal and area for a degenerate triangle.
pub fn face_normal_area(t: &Triangle) -> (Vec3, f64) {
    let v = |p: Vec3A| Vec3::from(p).as_dvec3();
    let (a, b, c) = (v(t.v0), v(t.v1), v(t.v2));
    let n = (b - a).cross(c - a);
    let len = n.length();
    if !(len > 0.0) || !len.is_finite() {
        return (Vec3::ZERO, 0.0);
    }
    ((n / len).as_vec3(), 0.5 * len)
}

/// Helper for tests and tools: a triangle from three points.
pub fn triangle(a: Vec3, b: Vec3, c: Vec3) -> Triangle {
    Triangle {
        v0: Vec3A::from(a),
        v1: Vec3A::from(b),
        v2: Vec3A::from(c),
    }
}

/// Helper for tests: appends the quad `a b c d` (two triangles, flat normals facing along
/// (b − a) × (c − a), material 0, prim 0) to `g`.
#[cfg(test)]
pub fn push_quad(g: &mut Geometry, a: Vec3, b: Vec3, c: Vec3, d: Vec3) {
    for t in [triangle(a, b, c), triangle(a, c, d)] {
        let n = Vec3::from((t.v1 - t.v0).cross(t.v2 - t.v0)).normalize();
        g.triangles.push(t);
        g.shading.push(TriangleShading {
            normals: [n; 3],
            uvs: [Vec2::ZERO; 3],
            material: 0,
            prim: 0,
            masked: false,
            attributes: NO_ATTRIBUTES,
        });
    }
}
