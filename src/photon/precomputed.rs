//! Irradiance precomputed at photons (Christensen, "Faster Photon Map Global Illumination",
//! 1999): the `precomputed` method's estimate at gather hits, the paper's Figure 7
//! comparison. kiddo's immutable kd-tree finds the nearest precomputed point.

use std::num::NonZero;

use glam::Vec3;
use kiddo::SquaredEuclidean;
use kiddo::immutable::float::kdtree::ImmutableKdTree;
use rayon::prelude::*;

use super::PhotonMap;

/// Irradiance precomputed at every fourth photon (Christensen 1999).
pub struct PrecomputedIrradiance {
    points: Vec<(Vec3, Vec3, Vec3)>, // position, normal, irradiance
    tree: Option<ImmutableKdTree<f32, u32, 3, 32>>,
}

impl PrecomputedIrradiance {
    pub fn new(pm: &PhotonMap, k: usize) -> Self {
        let points: Vec<(Vec3, Vec3, Vec3)> = pm
            .photons
            .par_iter()
            .step_by(4)
            .map(|p| (p.position, p.normal, pm.irradiance(p.position, p.normal, k)))
            .collect();
        let tree = (!points.is_empty()).then(|| {
            let pts: Vec<[f32; 3]> = points.iter().map(|p| p.0.to_array()).collect();
            ImmutableKdTree::new_from_slice(&pts)
        });
        PrecomputedIrradiance { points, tree }
    }

    /// Irradiance of the nearest precomputed point whose normal agrees with `n`.
    pub fn lookup(&self, x: Vec3, n: Vec3) -> Vec3 {
        let Some(t) = &self.tree else {
            return Vec3::ZERO;
        };
        for nb in t.nearest_n::<SquaredEuclidean>(&x.to_array(), NonZero::new(8).expect("8 > 0")) {
            let p = &self.points[nb.item as usize];
            if p.1.dot(n) > 0.5 {
                return p.2;
            }
        }
        Vec3::ZERO
    }
}
