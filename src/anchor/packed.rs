//! The compact anchor of §3: 18 bytes here against the paper's 22. The position is
//! quantised to 21 bits per axis inside the static scene's bounding box (relative, so
//! equally fine at any scene scale: 36 m Sponza → 17 µm), the normal octahedron-encoded in
//! two bytes, L_i in RGBE (Ward's shared exponent: 2^−128..2^127, 8-bit mantissa relative
//! to the brightest channel, so intensities from 1e−6 to 1e6 and beyond survive) and the
//! albedo as three sRGB-encoded bytes.

use glam::Vec3;
use serde::{Deserialize, Serialize};

use crate::color::{
    oct_decode_table, oct_encode, rgbe_decode, rgbe_encode, srgb_encode, srgb8_to_linear,
};

/// A compact anchor.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[repr(C)]
pub struct Anchor {
    /// Quantised position: 3 × 21 bits in a u64, stored as four u16 (alignment 2).
    position: [u16; 4],
    normal: [u8; 2],
    /// L_i in RGBE.
    irradiance: [u8; 4],
    /// Albedo, sRGB-encoded.
    albedo: [u8; 3],
    /// Liveness: 0 = free slot (ids of live anchors are stable).
    live: u8,
}

/// Maps positions inside the static scene's box to 21-bit integers and back.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Quantizer {
    lo: Vec3,
    step: Vec3,
}

const QMAX: f32 = ((1u32 << 21) - 1) as f32;

impl Quantizer {
    pub fn new(lo: Vec3, hi: Vec3) -> Self {
        let extent = (hi - lo).max(Vec3::splat(f32::MIN_POSITIVE));
        // Pad by a step so that points on the box's faces stay inside.
        let lo = lo - extent / QMAX;
        let step = extent * (1.0 + 2.0 / QMAX) / QMAX;
        Quantizer { lo, step }
    }

    fn encode(&self, p: Vec3) -> u64 {
        let q = ((p - self.lo) / self.step)
            .round()
            .clamp(Vec3::ZERO, Vec3::splat(QMAX));
        (q.x as u64) | (q.y as u64) << 21 | (q.z as u64) << 42
    }

    fn decode(&self, v: u64) -> Vec3 {
        let m = (1u64 << 21) - 1;
        let q = Vec3::new((v & m) as f32, (v >> 21 & m) as f32, (v >> 42 & m) as f32);
        self.lo + q * self.step
    }

    /// Per-axis bound on the distance between a point and its decoded position.
    pub fn error(&self) -> Vec3 {
        0.5 * self.step
    }

    /// Largest distance between a point and its decoded position.
    pub fn max_error(&self) -> f32 {
        0.5 * self.step.length()
    }
}

impl Anchor {
    pub fn new(
        q: &Quantizer,
        position: Vec3,
        normal: Vec3,
        albedo: Vec3,
        irradiance: Vec3,
    ) -> Self {
        let p = q.encode(position);
        Anchor {
            position: [
                p as u16,
                (p >> 16) as u16,
                (p >> 32) as u16,
                (p >> 48) as u16,
            ],
            normal: oct_encode(normal),
            irradiance: rgbe_encode(irradiance),
            albedo: [
                srgb_encode(albedo.x),
                srgb_encode(albedo.y),
                srgb_encode(albedo.z),
            ],
            live: 1,
        }
    }

    pub fn position(&self, q: &Quantizer) -> Vec3 {
        let p = self.position;
        q.decode(p[0] as u64 | (p[1] as u64) << 16 | (p[2] as u64) << 32 | (p[3] as u64) << 48)
    }

    pub fn normal(&self) -> Vec3 {
        oct_decode_table(self.normal)
    }

    pub fn albedo(&self) -> Vec3 {
        Vec3::new(
            srgb8_to_linear(self.albedo[0]),
            srgb8_to_linear(self.albedo[1]),
            srgb8_to_linear(self.albedo[2]),
        )
    }

    pub fn irradiance(&self) -> Vec3 {
        rgbe_decode(self.irradiance)
    }

    pub fn set_irradiance(&mut self, e: Vec3) {
        self.irradiance = rgbe_encode(e);
    }

    /// Sets the albedo (a material edit, `integrator::anchors::refresh_albedo`).
    pub fn set_albedo(&mut self, albedo: Vec3) {
        self.albedo = [
            srgb_encode(albedo.x),
            srgb_encode(albedo.y),
            srgb_encode(albedo.z),
        ];
    }

    /// Radiance leaving the anchor: albedo × L_i / π.
    pub fn radiance(&self) -> Vec3 {
        self.albedo() * self.irradiance() * std::f32::consts::FRAC_1_PI
    }

    pub fn is_live(&self) -> bool {
        self.live != 0
    }
}

impl Anchor {
    /// Frees the anchor's slot.
    pub(super) fn kill(&mut self) {
        self.live = 0;
    }
}

impl Quantizer {
    /// Size of one quantisation step per axis.
    pub fn step(&self) -> Vec3 {
        self.step
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::color::{rgbe_decode, rgbe_encode};

    #[test]
    fn anchors_fit_in_twenty_bytes() {
        assert!(size_of::<Anchor>() <= 20, "{}", size_of::<Anchor>());
    }

    #[test]
    fn rgbe_round_trips_from_tiny_to_huge() {
        for v in [1e-30f32, 1e-6, 0.3, 1.0, 7.5, 1e6, 1e30] {
            let c = Vec3::new(v, 0.5 * v, 0.25 * v);
            let d = rgbe_decode(rgbe_encode(c));
            assert!(
                ((d - c).abs() / c.max_element()).max_element() < 1.0 / 128.0,
                "{c} -> {d}"
            );
        }
        assert_eq!(rgbe_decode(rgbe_encode(Vec3::ZERO)), Vec3::ZERO);
    }

    #[test]
    fn positions_keep_relative_precision_at_any_scale() {
        for s in [1e-3f32, 1.0, 1e4] {
            let q = Quantizer::new(Vec3::splat(-10.0 * s), Vec3::splat(30.0 * s));
            let p = Vec3::new(1.234, -5.678, 29.9) * s;
            let a = Anchor::new(&q, p, Vec3::Y, Vec3::splat(0.5), Vec3::ONE);
            assert!(
                (a.position(&q) - p).length() <= q.max_error() * 1.01,
                "scale {s}"
            );
            assert!(q.max_error() < 40.0 * s * 1e-6);
        }
    }

    #[test]
    fn normals_and_albedo_survive_encoding() {
        for n in [
            Vec3::X,
            -Vec3::Y,
            Vec3::new(0.3, -0.5, 0.8).normalize(),
            Vec3::new(-0.6, 0.1, -0.79).normalize(),
        ] {
            let q = Quantizer::new(Vec3::ZERO, Vec3::ONE);
            let a = Anchor::new(&q, Vec3::ZERO, n, Vec3::new(0.73, 0.05, 0.5), Vec3::ONE);
            assert!(a.normal().dot(n) > 0.9995, "{n} -> {}", a.normal());
            assert!(
                (a.albedo() - Vec3::new(0.73, 0.05, 0.5))
                    .abs()
                    .max_element()
                    < 0.004
            );
        }
    }
}
