//! Materials as the algorithm needs them (DESIGN.md, Scene conventions): glTF
//! metallic-roughness ([`Material::bsdf`]: base colour factor × base colour texture ×
//! `COLOR_0`, metallic and roughness factors × `metallicRoughnessTexture`, the dielectric
//! specular factor of `KHR_materials_specular`), alpha cut-out (`alphaMode` `MASK`; `BLEND`
//! as a cut-out at 0.5), normal maps, emission (factor × emissive texture ×
//! `KHR_materials_emissive_strength`), and `KHR_texture_transform` on every texture.
//!
//! [`Surfaces`] is the scene's material and texture list shared by every frame; it is also
//! the [`AlphaTest`] the BVH traversal asks about hits on masked triangles, so that camera,
//! shadow, photon, final-gather and path rays all pass through cut-out parts alike.

use std::sync::Arc;

use glam::{Vec2, Vec3, Vec4};

use crate::bsdf::Bsdf;
use crate::geom::{AlphaTest, Geometry};

/// Texture wrap modes (glTF `sampler.wrapS/wrapT`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Wrap {
    Repeat,
    MirroredRepeat,
    ClampToEdge,
}

impl Wrap {
    /// Maps a texel coordinate to `0..n`.
    fn apply(self, i: i64, n: i64) -> usize {
        let r = match self {
            Wrap::Repeat => i.rem_euclid(n),
            Wrap::ClampToEdge => i.clamp(0, n - 1),
            Wrap::MirroredRepeat => {
                let m = i.rem_euclid(2 * n);
                if m < n { m } else { 2 * n - 1 - m }
            }
        };
        r as usize
    }
}

/// A decoded texture in linear RGBA (colour textures are sRGB-decoded on load).
#[derive(Debug, Clone)]
pub struct Texture {
    pub width: u32,
    pub height: u32,
    pub texels: Vec<Vec4>,
}

impl Texture {
    /// Bilinear lookup at `uv` (glTF convention: origin top-left, v down).
    pub fn sample(&self, uv: Vec2, wrap: [Wrap; 2]) -> Vec4 {
        let (w, h) = (self.width as i64, self.height as i64);
        let x = uv.x * self.width as f32 - 0.5;
        let y = uv.y * self.height as f32 - 0.5;
        if !(x.is_finite() && y.is_finite()) {
            return self.texels[0];
        }
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = (x - x0, y - y0);
        // Clamp to a range where i64 arithmetic cannot overflow; wrap handles the rest.
        let (x0, y0) = (x0.clamp(-1e9, 1e9) as i64, y0.clamp(-1e9, 1e9) as i64);
        let texel = |i: i64, j: i64| {
            let (i, j) = (wrap[0].apply(i, w), wrap[1].apply(j, h));
            self.texels[j * self.width as usize + i]
        };
        let top = texel(x0, y0).lerp(texel(x0 + 1, y0), fx);
        let bottom = texel(x0, y0 + 1).lerp(texel(x0 + 1, y0 + 1), fx);
        top.lerp(bottom, fy)
    }
}

/// A `KHR_texture_transform`: `uv' = T · R · S · uv` with the extension's translation
/// (`offset`), rotation (radians, counter-clockwise in UV space) and scale, stored as the
/// 2×3 matrix `[a b c; d e f]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct UvTransform([f32; 6]);

impl UvTransform {
    pub const IDENTITY: UvTransform = UvTransform([1.0, 0.0, 0.0, 0.0, 1.0, 0.0]);

    /// The extension's matrix: translation × rotation × scale.
    pub fn new(offset: Vec2, rotation: f32, scale: Vec2) -> Self {
        let (s, c) = rotation.sin_cos();
        UvTransform([
            c * scale.x,
            s * scale.y,
            offset.x,
            -s * scale.x,
            c * scale.y,
            offset.y,
        ])
    }

    pub fn is_finite(&self) -> bool {
        self.0.iter().all(|v| v.is_finite())
    }

    #[inline]
    pub fn apply(&self, uv: Vec2) -> Vec2 {
        let m = &self.0;
        Vec2::new(
            m[0] * uv.x + m[1] * uv.y + m[2],
            m[3] * uv.x + m[4] * uv.y + m[5],
        )
    }
}

/// A material's reference to a texture: which, how it wraps and its UV transform.
#[derive(Debug, Clone, Copy)]
pub struct TextureRef {
    /// Index into the scene's texture list.
    pub texture: usize,
    pub wrap: [Wrap; 2],
    /// `KHR_texture_transform` (identity without it). Every texture reads `TEXCOORD_0`; a
    /// texture that names another set is read from set 0 with a warning on load.
    pub transform: UvTransform,
}

impl TextureRef {
    /// The texture's value at the surface's `TEXCOORD_0` coordinate `uv`.
    #[inline]
    pub fn sample(&self, textures: &[Texture], uv: Vec2) -> Vec4 {
        textures[self.texture].sample(self.transform.apply(uv), self.wrap)
    }
}

/// A tangent-space normal map (glTF `normalTexture`): linear RGB, `scale` multiplying the
/// X and Y components.
#[derive(Debug, Clone, Copy)]
pub struct NormalMap {
    pub texture: TextureRef,
    pub scale: f32,
}

impl NormalMap {
    /// The tangent-space normal at `uv` (+X along the tangent, +Y along the bitangent, +Z
    /// out of the surface), unit length; `None` where the texel is degenerate.
    pub fn normal(&self, textures: &[Texture], uv: Vec2) -> Option<Vec3> {
        let c = self.texture.sample(textures, uv).truncate() * 2.0 - Vec3::ONE;
        let n = Vec3::new(c.x * self.scale, c.y * self.scale, c.z);
        let n = n.normalize_or_zero();
        (n != Vec3::ZERO).then_some(n)
    }
}

#[derive(Debug, Clone)]
pub struct Material {
    pub name: String,
    /// Base colour factor (linear RGBA).
    pub base_color: Vec4,
    pub base_color_texture: Option<TextureRef>,
    /// Where alpha below this is cut out (glTF `alphaCutoff` for `MASK`, 0.5 for `BLEND`);
    /// `None` for opaque materials (`OPAQUE`, alpha ignored).
    pub alpha_cutoff: Option<f32>,
    /// Tangent-space normal map (`normalTexture`).
    pub normal_texture: Option<NormalMap>,
    /// Emitted radiance: emissive factor × emissive strength (× the emissive texture).
    pub emission: Vec3,
    /// Emissive texture (sRGB-decoded), multiplying [`Material::emission`].
    pub emissive_texture: Option<TextureRef>,
    /// Emission from both faces (glTF `doubleSided`), else from the front face only.
    pub double_sided: bool,
    /// `pbrMetallicRoughness.roughnessFactor` and `metallicFactor`.
    pub roughness: f32,
    pub metallic: f32,
    /// Roughness in G, metallic in B (linear), multiplying the factors.
    pub metallic_roughness_texture: Option<TextureRef>,
    /// Dielectric specular factor (`KHR_materials_specular.specularFactor`, 1 without it).
    pub specular: f32,
}

impl Default for Material {
    /// glTF's default material: white, fully rough, fully metallic (the specification's
    /// defaults for `roughnessFactor` and `metallicFactor`), single-sided.
    fn default() -> Self {
        Material {
            name: "default".into(),
            base_color: Vec4::ONE,
            base_color_texture: None,
            alpha_cutoff: None,
            normal_texture: None,
            emission: Vec3::ZERO,
            emissive_texture: None,
            double_sided: false,
            roughness: 1.0,
            metallic: 1.0,
            metallic_roughness_texture: None,
            specular: 1.0,
        }
    }
}

impl Material {
    /// Base colour (linear RGBA) at texture coordinate `uv` with vertex colour `color`:
    /// factor × texture × `COLOR_0` (glTF 2.0 §3.9.2).
    pub fn base_color_at(&self, uv: Vec2, color: Vec4, textures: &[Texture]) -> Vec4 {
        let mut c = self.base_color * color;
        if let Some(t) = self.base_color_texture {
            c *= t.sample(textures, uv);
        }
        c
    }

    /// Lambertian albedo at texture coordinate `uv` with vertex colour `color`, clamped to
    /// [0, 1] for energy conservation.
    pub fn albedo(&self, uv: Vec2, color: Vec4, textures: &[Texture]) -> Vec3 {
        self.base_color_at(uv, color, textures)
            .truncate()
            .clamp(Vec3::ZERO, Vec3::ONE)
    }

    /// The BRDF at texture coordinate `uv` with vertex colour `color` (glTF 2.0 Appendix B,
    /// [`crate::bsdf`]).
    pub fn bsdf(&self, uv: Vec2, color: Vec4, textures: &[Texture]) -> Bsdf {
        let (mut roughness, mut metallic) = (self.roughness, self.metallic);
        if let Some(t) = self.metallic_roughness_texture {
            let v = t.sample(textures, uv);
            roughness *= v.y;
            metallic *= v.z;
        }
        Bsdf::new(
            self.base_color_at(uv, color, textures).truncate(),
            metallic,
            roughness,
            self.specular,
        )
    }

    /// Whether the surface is there at `uv` with vertex colour `color`: alpha (factor ×
    /// texture × `COLOR_0`) at or above the cutoff, or the material is opaque.
    pub fn opaque_at(&self, uv: Vec2, color: Vec4, textures: &[Texture]) -> bool {
        match self.alpha_cutoff {
            None => true,
            Some(cutoff) => {
                let mut a = self.base_color.w * color.w;
                if let Some(t) = self.base_color_texture {
                    a *= t.sample(textures, uv).w;
                }
                a >= cutoff
            }
        }
    }

    /// Emitted radiance at `uv`: [`Material::emission`] × the emissive texture.
    pub fn emission_at(&self, uv: Vec2, textures: &[Texture]) -> Vec3 {
        match self.emissive_texture {
            Some(t) => self.emission * t.sample(textures, uv).truncate(),
            None => self.emission,
        }
    }

    pub fn is_emissive(&self) -> bool {
        self.emission.max_element() > 0.0
    }
}

/// The scene's materials (index 0 is glTF's default material) and textures, shared by every
/// frame and by both geometry sets as their [`AlphaTest`].
#[derive(Debug, Clone)]
pub struct Surfaces {
    pub materials: Arc<[Material]>,
    pub textures: Arc<[Texture]>,
}

impl Default for Surfaces {
    /// glTF's default material alone.
    fn default() -> Self {
        Surfaces {
            materials: Arc::from(vec![Material::default()]),
            textures: Arc::from(Vec::new()),
        }
    }
}

impl Surfaces {
    /// Texture coordinate and vertex colour of triangle `i` of `g` at barycentrics `b`.
    pub fn uv_and_color(g: &Geometry, i: usize, b: Vec2) -> (Vec2, Vec4) {
        let sh = &g.shading[i];
        let w = 1.0 - b.x - b.y;
        let uv = sh.uvs[0] * w + sh.uvs[1] * b.x + sh.uvs[2] * b.y;
        let color = g.attributes_of(i).map_or(Vec4::ONE, |a| {
            a.colors[0] * w + a.colors[1] * b.x + a.colors[2] * b.y
        });
        (uv, color)
    }
}

impl AlphaTest for Surfaces {
    fn opaque(&self, g: &Geometry, triangle: usize, b: Vec2) -> bool {
        let (uv, color) = Surfaces::uv_and_color(g, triangle, b);
        match self.materials.get(g.shading[triangle].material as usize) {
            Some(m) => m.opaque_at(uv, color, &self.textures),
            None => true,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The extension's own example: offset (0, 1), rotation π/2, scale 0.5 "utilizes only
    /// the lower left quadrant of the source image, rotated clockwise 90°" (UV's v runs
    /// down the image, so the lower left quadrant is u ∈ [0, ½], v ∈ [½, 1]). The opposite
    /// rotation sign maps the unit square to u ∈ [−½, 0], v ∈ [1, 1½], outside the image.
    #[test]
    fn texture_transform_matches_the_extensions_example() {
        let t = UvTransform::new(
            Vec2::new(0.0, 1.0),
            std::f32::consts::FRAC_PI_2,
            Vec2::splat(0.5),
        );
        for uv in [[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0], [0.3, 0.7]] {
            let p = t.apply(Vec2::from(uv));
            assert!(
                (-1e-6..=0.5 + 1e-6).contains(&p.x) && (0.5 - 1e-6..=1.0 + 1e-6).contains(&p.y),
                "{uv:?} -> {p}"
            );
        }
        // Corners: the image's lower left (0, 1) is where uv (0, 0) lands.
        assert!(t.apply(Vec2::ZERO).distance(Vec2::new(0.0, 1.0)) < 1e-6);
    }

    #[test]
    fn wrap_modes_map_into_range() {
        assert_eq!(Wrap::Repeat.apply(-1, 4), 3);
        assert_eq!(Wrap::Repeat.apply(5, 4), 1);
        assert_eq!(Wrap::ClampToEdge.apply(-3, 4), 0);
        assert_eq!(Wrap::ClampToEdge.apply(9, 4), 3);
        assert_eq!(Wrap::MirroredRepeat.apply(4, 4), 3);
        assert_eq!(Wrap::MirroredRepeat.apply(-1, 4), 0);
        assert_eq!(Wrap::MirroredRepeat.apply(8, 4), 0);
    }

    /// `KHR_texture_transform` is T · R · S with R turning (1, 0) towards (0, −1) — the
    /// direction the Khronos TextureTransformTest model checks (as three.js and
    /// cesium-native apply it) — scale first, offset last.
    #[test]
    fn texture_transform_scales_then_rotates_then_offsets() {
        let t = UvTransform::new(
            Vec2::new(0.5, 0.25),
            std::f32::consts::FRAC_PI_2,
            Vec2::new(2.0, 3.0),
        );
        let p = t.apply(Vec2::new(1.0, 0.0));
        assert!((p - Vec2::new(0.5, -1.75)).length() < 1e-6, "{p}");
        let p = t.apply(Vec2::new(0.0, 1.0));
        assert!((p - Vec2::new(3.5, 0.25)).length() < 1e-6, "{p}");
        assert_eq!(
            UvTransform::IDENTITY.apply(Vec2::new(0.3, 0.7)),
            Vec2::new(0.3, 0.7)
        );
    }

    #[test]
    fn bilinear_sample_of_a_checker_centre_averages() {
        let t = Texture {
            width: 2,
            height: 1,
            texels: vec![Vec4::ZERO, Vec4::ONE],
        };
        let c = t.sample(Vec2::new(0.5, 0.5), [Wrap::ClampToEdge; 2]);
        assert!((c.x - 0.5).abs() < 1e-6);
        let c = t.sample(Vec2::new(0.25, 0.5), [Wrap::ClampToEdge; 2]);
        assert_eq!(c.x, 0.0);
    }
}
