//! Materials as the algorithm needs them (DESIGN.md, Scene conventions): glTF
//! metallic-roughness reduced to a Lambertian albedo (base colour factor × base colour
//! texture), emission (factor × `KHR_materials_emissive_strength`), and roughness/metallic
//! kept for the glossy lobe of the paper's §5.

use glam::{Vec2, Vec3, Vec4};

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

/// A base colour texture reference.
#[derive(Debug, Clone, Copy)]
pub struct TextureRef {
    /// Index into the scene's texture list.
    pub texture: usize,
    /// Which UV set (`TEXCOORD_n`) it reads; only set 0 is carried, others are rejected.
    pub wrap: [Wrap; 2],
}

#[derive(Debug, Clone)]
pub struct Material {
    pub name: String,
    /// Base colour factor (linear RGBA).
    pub base_color: Vec4,
    pub base_color_texture: Option<TextureRef>,
    /// Emitted radiance: emissive factor × emissive strength.
    pub emission: Vec3,
    /// Emission from both faces (glTF `doubleSided`), else from the front face only.
    pub double_sided: bool,
    pub roughness: f32,
    pub metallic: f32,
}

impl Default for Material {
    /// glTF's default material: white, fully rough, non-metallic, single-sided.
    fn default() -> Self {
        Material {
            name: "default".into(),
            base_color: Vec4::ONE,
            base_color_texture: None,
            emission: Vec3::ZERO,
            double_sided: false,
            roughness: 1.0,
            metallic: 1.0,
        }
    }
}

impl Material {
    /// Lambertian albedo at texture coordinate `uv`, clamped to [0, 1] for energy conservation.
    pub fn albedo(&self, uv: Vec2, textures: &[Texture]) -> Vec3 {
        let mut c = self.base_color;
        if let Some(t) = self.base_color_texture {
            c *= textures[t.texture].sample(uv, t.wrap);
        }
        c.truncate().clamp(Vec3::ZERO, Vec3::ONE)
    }

    pub fn is_emissive(&self) -> bool {
        self.emission.max_element() > 0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
