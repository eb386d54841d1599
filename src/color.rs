//! Colour and the compact encodings of stored values: sRGB transfer, luminance, Ward's RGBE
//! for irradiance and octahedral unit vectors (the paper's §3 compact anchors).

use glam::{Vec2, Vec3};

/// sRGB electro-optical transfer function (IEC 61966-2-1), 8-bit code value → linear.
pub fn srgb_to_linear(c: f32) -> f32 {
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

/// [`srgb_to_linear`] of an 8-bit code value `c` / 255, from a table (anchors decode their
/// albedo at every stratum that reads them).
pub fn srgb8_to_linear(c: u8) -> f32 {
    static TABLE: std::sync::LazyLock<[f32; 256]> =
        std::sync::LazyLock::new(|| std::array::from_fn(|c| srgb_to_linear(c as f32 / 255.0)));
    TABLE[c as usize]
}

/// Rec. 709 luminance of a linear RGB colour.
pub fn luminance(c: Vec3) -> f32 {
    c.dot(Vec3::new(0.2126, 0.7152, 0.0722))
}

/// Ward's RGBE: a shared 8-bit exponent and three 8-bit mantissas.
pub fn rgbe_encode(c: Vec3) -> [u8; 4] {
    let c = c.max(Vec3::ZERO);
    let m = c.max_element();
    if !(m > 1e-38) || !m.is_finite() {
        return [0; 4];
    }
    let e = m.log2().floor() as i32 + 1; // m < 2^e
    let e = e.clamp(-127, 128);
    let scale = 256.0 / 2f32.powi(e);
    let q = |v: f32| (v * scale).floor().min(255.0) as u8;
    [q(c.x), q(c.y), q(c.z), (e + 127) as u8]
}

pub fn rgbe_decode(v: [u8; 4]) -> Vec3 {
    if v == [0; 4] {
        return Vec3::ZERO;
    }
    let f = 2f32.powi(v[3] as i32 - 127 - 8);
    Vec3::new(v[0] as f32 + 0.5, v[1] as f32 + 0.5, v[2] as f32 + 0.5) * f
}

/// Octahedral normal encoding in two bytes.
pub fn oct_encode(n: Vec3) -> [u8; 2] {
    let n = n / (n.x.abs() + n.y.abs() + n.z.abs()).max(f32::MIN_POSITIVE);
    let p = if n.z >= 0.0 {
        Vec2::new(n.x, n.y)
    } else {
        Vec2::new(
            (1.0 - n.y.abs()) * n.x.signum(),
            (1.0 - n.x.abs()) * n.y.signum(),
        )
    };
    let q = |v: f32| ((v * 0.5 + 0.5) * 255.0).round().clamp(0.0, 255.0) as u8;
    [q(p.x), q(p.y)]
}

/// [`oct_decode`] from a table of every code (768 KiB, made at first use): anchors decode
/// their normal at each of attachment's reuse tests (§3.1), where reading the anchor and
/// decoding its normal (a square root and a division) took 8 % of step 1's samples in a
/// profile of Sponza's frame 1.
pub fn oct_decode_table(e: [u8; 2]) -> Vec3 {
    static TABLE: std::sync::LazyLock<Box<[Vec3]>> = std::sync::LazyLock::new(|| {
        (0..=u16::MAX)
            .map(|c| oct_decode(c.to_le_bytes()))
            .collect()
    });
    TABLE[usize::from(u16::from_le_bytes(e))]
}

pub fn oct_decode(e: [u8; 2]) -> Vec3 {
    let p = Vec2::new(
        e[0] as f32 / 255.0 * 2.0 - 1.0,
        e[1] as f32 / 255.0 * 2.0 - 1.0,
    );
    let z = 1.0 - p.x.abs() - p.y.abs();
    let (x, y) = if z >= 0.0 {
        (p.x, p.y)
    } else {
        (
            (1.0 - p.y.abs()) * p.x.signum(),
            (1.0 - p.x.abs()) * p.y.signum(),
        )
    };
    Vec3::new(x, y, z).normalize_or_zero()
}

/// A linear value in [0, 1] as an sRGB-encoded byte.
pub fn srgb_encode(v: f32) -> u8 {
    let v = v.clamp(0.0, 1.0);
    let s = if v <= 0.003_130_8 {
        12.92 * v
    } else {
        1.055 * v.powf(1.0 / 2.4) - 0.055
    };
    (s * 255.0).round() as u8
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_normal_table_holds_every_codes_decode() {
        for code in 0..=u16::MAX {
            let e = code.to_le_bytes();
            assert_eq!(
                oct_decode_table(e).to_array().map(f32::to_bits),
                oct_decode(e).to_array().map(f32::to_bits),
                "{e:?}"
            );
        }
    }

    #[test]
    fn srgb_decoding_matches_reference_points() {
        assert_eq!(srgb_to_linear(0.0), 0.0);
        assert!((srgb_to_linear(1.0) - 1.0).abs() < 1e-6);
        assert!((srgb_to_linear(0.5) - 0.214_041).abs() < 1e-5);
    }
}
