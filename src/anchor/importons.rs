//! Global importons (Suykens & Willems 2002): camera paths stored at their second diffuse
//! hit. Their density drives the importance-driven D_max of §3.3.1: anchors are denser
//! where gathers from what the camera sees land more often.

use glam::Vec3;
use rayon::prelude::*;

use crate::geom::cosine_direction;
use crate::interaction::trace_camera;
use crate::sampling::{Sampler, Stream};
use crate::scene::FrameScene;

/// Global importons (Suykens 2002): camera paths stored at their second diffuse hit; their
/// density sets D_max (§3.3.1).
pub struct Importons {
    tree: Option<kiddo::immutable::float::kdtree::ImmutableKdTree<f32, u32, 3, 32>>,
    mean_density: f32,
    k: usize,
}

impl Importons {
    pub fn trace(
        frame: &FrameScene,
        width: u32,
        height: u32,
        per_pixel: f32,
        seed: u32,
    ) -> Importons {
        let count = ((width * height) as f32 * per_pixel).max(16.0) as u32;
        let pts: Vec<[f32; 3]> = (0..count)
            .into_par_iter()
            .filter_map(|i| {
                let s = Sampler::new(seed, 0, Stream::Importons, i);
                let sp = trace_camera(frame, s.get(0, 0), s.get(0, 1)).1?;
                let d2 = cosine_direction(sp.ns, s.get(0, 2).min(0.999_999_9), s.get(0, 3));
                let h2 = frame.accel.closest(
                    &frame.static_geometry,
                    &frame.dynamic_geometry,
                    sp.spawn(),
                    d2,
                    f32::INFINITY,
                )?;
                Some((sp.spawn() + d2 * h2.t).to_array())
            })
            .collect();
        let k = 16;
        let tree = (pts.len() > k)
            .then(|| kiddo::immutable::float::kdtree::ImmutableKdTree::new_from_slice(&pts));
        let mut imp = Importons {
            tree,
            mean_density: 1.0,
            k,
        };
        // Mean density over the importons themselves (a sample of where gathers land).
        let sample: Vec<f32> = pts
            .iter()
            .step_by((pts.len() / 256).max(1))
            .map(|p| imp.density(Vec3::from(*p)))
            .collect();
        if !sample.is_empty() {
            imp.mean_density = sample.iter().sum::<f32>() / sample.len() as f32;
        }
        imp
    }

    fn density(&self, x: Vec3) -> f32 {
        let Some(t) = &self.tree else { return 1.0 };
        let nn = t.nearest_n::<kiddo::SquaredEuclidean>(
            &x.to_array(),
            std::num::NonZero::new(self.k).expect("k > 0"),
        );
        let r2 = nn.iter().map(|n| n.distance).fold(0.0f32, f32::max);
        self.k as f32 / (std::f32::consts::PI * r2.max(f32::MIN_POSITIVE))
    }

    /// D_max factor at `x`: inversely proportional to the local importon density, relative
    /// to the mean, clamped to [1/8, 8].
    pub fn factor(&self, x: Vec3) -> f32 {
        (self.mean_density / self.density(x).max(f32::MIN_POSITIVE)).clamp(0.125, 8.0)
    }
}
