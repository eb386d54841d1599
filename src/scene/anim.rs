//! Keyframe animation: the one place where animated values are interpolated
//! (glTF 2.0 §3.11 "Animations", Appendix C "Interpolation").
//!
//! Every animated quantity (translation, rotation, scale, morph weights) is a [`Sampler`]:
//! key times plus a flat slice of outputs, read through [`Sampler::sample`].

use glam::{Quat, Vec3, Vec4};

/// Interpolation modes of glTF samplers.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Interpolation {
    Step,
    Linear,
    /// Cubic Hermite spline with in- and out-tangents stored beside each value.
    CubicSpline,
}

/// Which property of a node a channel drives.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Property {
    Translation,
    Rotation,
    Scale,
    /// Morph target weights; the sampler's width is the number of targets.
    Weights,
}

/// Key times and values. For `CubicSpline`, `values` holds `[in-tangent, value, out-tangent]`
/// per key, each `width` floats wide.
#[derive(Debug, Clone)]
pub struct Sampler {
    pub interpolation: Interpolation,
    pub times: Vec<f32>,
    pub values: Vec<f32>,
    /// Floats per element: 3 (translation, scale), 4 (rotation quaternion xyzw), or the
    /// number of morph targets.
    pub width: usize,
}

/// One animated property of one node.
#[derive(Debug, Clone)]
pub struct Channel {
    pub node: usize,
    pub property: Property,
    pub sampler: Sampler,
}

/// A named glTF animation. All animations of a scene play together on one timeline.
#[derive(Debug, Clone)]
pub struct Animation {
    pub name: String,
    pub channels: Vec<Channel>,
}

impl Sampler {
    /// Time range covered by the keys.
    pub fn range(&self) -> (f32, f32) {
        (
            self.times.first().copied().unwrap_or(0.0),
            self.times.last().copied().unwrap_or(0.0),
        )
    }

    fn element(&self, key: usize, part: usize) -> &[f32] {
        let stride = if self.interpolation == Interpolation::CubicSpline {
            3
        } else {
            1
        };
        let start = (key * stride + part) * self.width;
        &self.values[start..start + self.width]
    }

    fn value(&self, key: usize) -> &[f32] {
        let part = usize::from(self.interpolation == Interpolation::CubicSpline);
        self.element(key, part)
    }

    /// Value at time `t` written to `out` (`width` floats). Times before the first key
    /// clamp to it, after the last key to the last. Rotations are normalised by the caller.
    /// `slerp` selects spherical interpolation (rotations) for `Linear`.
    pub fn sample(&self, t: f32, slerp: bool, out: &mut [f32]) {
        let n = self.times.len();
        debug_assert_eq!(out.len(), self.width);
        if n == 0 {
            return;
        }
        if n == 1 || t <= self.times[0] {
            out.copy_from_slice(self.value(0));
            return;
        }
        if t >= self.times[n - 1] {
            out.copy_from_slice(self.value(n - 1));
            return;
        }
        // Last key k with times[k] <= t; k + 1 exists because t < times[n - 1].
        let k = self.times.partition_point(|&x| x <= t) - 1;
        let (t0, t1) = (self.times[k], self.times[k + 1]);
        let td = t1 - t0;
        let s = if td > 0.0 { (t - t0) / td } else { 0.0 };
        match self.interpolation {
            Interpolation::Step => out.copy_from_slice(self.value(k)),
            Interpolation::Linear if slerp && self.width == 4 => {
                let a = Quat::from_slice(self.value(k)).normalize();
                let b = Quat::from_slice(self.value(k + 1)).normalize();
                out.copy_from_slice(&a.slerp(b, s).to_array());
            }
            Interpolation::Linear => {
                let (a, b) = (self.value(k), self.value(k + 1));
                for i in 0..self.width {
                    out[i] = a[i] + (b[i] - a[i]) * s;
                }
            }
            Interpolation::CubicSpline => {
                // glTF 2.0 Appendix C: p(s) = (2s³−3s²+1)v_k + td(s³−2s²+s)b_k
                //                        + (−2s³+3s²)v_{k+1} + td(s³−s²)a_{k+1}
                let (s2, s3) = (s * s, s * s * s);
                let h00 = 2.0 * s3 - 3.0 * s2 + 1.0;
                let h10 = td * (s3 - 2.0 * s2 + s);
                let h01 = -2.0 * s3 + 3.0 * s2;
                let h11 = td * (s3 - s2);
                let v0 = self.element(k, 1);
                let b0 = self.element(k, 2);
                let v1 = self.element(k + 1, 1);
                let a1 = self.element(k + 1, 0);
                for i in 0..self.width {
                    out[i] = h00 * v0[i] + h10 * b0[i] + h01 * v1[i] + h11 * a1[i];
                }
            }
        }
    }

    pub fn sample_vec3(&self, t: f32) -> Vec3 {
        let mut v = [0.0; 3];
        self.sample(t, false, &mut v);
        Vec3::from(v)
    }

    pub fn sample_quat(&self, t: f32) -> Quat {
        let mut v = [0.0; 4];
        self.sample(t, true, &mut v);
        // Scaled by its largest component first, so that a cubic spline's large tangents do
        // not overflow its squared length.
        let q = Vec4::from(v);
        let largest = q.abs().max_element();
        if largest > 0.0 && largest.is_finite() {
            Quat::from_vec4((q / largest).normalize())
        } else {
            Quat::IDENTITY
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sampler(
        interpolation: Interpolation,
        times: &[f32],
        values: &[f32],
        width: usize,
    ) -> Sampler {
        Sampler {
            interpolation,
            times: times.to_vec(),
            values: values.to_vec(),
            width,
        }
    }

    /// A cubic spline's rotation with tangents of 1e30 is normalised without its squared
    /// length overflowing f32 (it came out as no rotation): halfway, the out-tangent along
    /// x dominates, a half turn about x.
    #[test]
    fn a_cubic_rotation_with_huge_tangents_normalises() {
        let identity = [0.0, 0.0, 0.0, 1.0];
        let tangent = [1e30, 0.0, 0.0, 0.0];
        let zero = [0.0; 4];
        let values: Vec<f32> = [zero, identity, tangent, zero, identity, zero].concat();
        let s = sampler(Interpolation::CubicSpline, &[0.0, 1.0], &values, 4);
        let q = s.sample_quat(0.5);
        assert!(q.is_finite() && (q.x.abs() - 1.0).abs() < 1e-6, "{q:?}");
    }

    #[test]
    fn step_holds_the_previous_key() {
        let s = sampler(
            Interpolation::Step,
            &[0.0, 1.0],
            &[1.0, 2.0, 3.0, 4.0, 5.0, 6.0],
            3,
        );
        assert_eq!(s.sample_vec3(0.99), Vec3::new(1.0, 2.0, 3.0));
        assert_eq!(s.sample_vec3(1.0), Vec3::new(4.0, 5.0, 6.0));
    }

    #[test]
    fn linear_clamps_outside_the_keys() {
        let s = sampler(
            Interpolation::Linear,
            &[1.0, 2.0],
            &[0.0, 0.0, 0.0, 2.0, 4.0, 6.0],
            3,
        );
        assert_eq!(s.sample_vec3(0.0), Vec3::ZERO);
        assert_eq!(s.sample_vec3(1.5), Vec3::new(1.0, 2.0, 3.0));
        assert_eq!(s.sample_vec3(9.0), Vec3::new(2.0, 4.0, 6.0));
    }

    #[test]
    fn linear_rotation_is_slerp() {
        let a = Quat::IDENTITY;
        let b = Quat::from_rotation_y(std::f32::consts::FRAC_PI_2);
        let mut v = a.to_array().to_vec();
        v.extend(b.to_array());
        let s = sampler(Interpolation::Linear, &[0.0, 1.0], &v, 4);
        let q = s.sample_quat(0.5);
        let expect = Quat::from_rotation_y(std::f32::consts::FRAC_PI_4);
        assert!(q.dot(expect).abs() > 1.0 - 1e-6, "{q:?}");
    }

    #[test]
    fn cubic_spline_matches_hermite_by_hand() {
        // One scalar: keys (t=0, v=0, out-tangent 1) and (t=2, v=1, in-tangent 0).
        // s = 0.5, td = 2: h00 = .5, h10 = 2*(.125-.5+.5) = .25, h01 = .5, h11 = 2*(.125-.25) = -.25
        // p = .5*0 + .25*1 + .5*1 + (-.25)*0 = 0.75
        let s = sampler(
            Interpolation::CubicSpline,
            &[0.0, 2.0],
            &[9.0, 0.0, 1.0, 0.0, 1.0, 9.0],
            1,
        );
        let mut out = [0.0];
        s.sample(1.0, false, &mut out);
        assert!((out[0] - 0.75).abs() < 1e-6, "{}", out[0]);
        s.sample(2.0, false, &mut out);
        assert_eq!(out[0], 1.0);
    }
}
