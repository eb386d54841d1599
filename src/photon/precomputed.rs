//! Irradiance precomputed at photons (Christensen, "Faster Photon Map Global Illumination",
//! 1999): the `precomputed` method's estimate at gather hits, the paper's Figure 7
//! comparison. kiddo's immutable kd-tree finds the nearest precomputed point.

use std::num::NonZero;

use glam::Vec3;
use kiddo::SquaredEuclidean;
use kiddo::immutable::float::kdtree::ImmutableKdTree;

use super::{DISC_THICKNESS, PhotonMap};

/// Irradiance precomputed at every fourth photon (Christensen 1999).
pub struct PrecomputedIrradiance {
    points: Vec<(Vec3, Vec3, Vec3)>, // position, normal, irradiance
    tree: Option<ImmutableKdTree<f32, u32, 3, 32>>,
    /// The photon map's [`PhotonMap::max_radius`].
    max_radius: f32,
}

impl PrecomputedIrradiance {
    pub fn new(pm: &PhotonMap, k: usize) -> Self {
        // Estimated in the photon tree's spatial order (super::knn::query_order).
        let at: Vec<&super::Photon> = pm.photons.iter().step_by(4).collect();
        let positions: Vec<Vec3> = at.iter().map(|p| p.position).collect();
        let points: Vec<(Vec3, Vec3, Vec3)> = super::knn::map_in_query_order(&positions, |i| {
            let p = at[i];
            (p.position, p.normal, pm.irradiance(p.position, p.normal, k))
        });
        let tree = (!points.is_empty()).then(|| {
            let pts: Vec<[f32; 3]> = points.iter().map(|p| p.0.to_array()).collect();
            ImmutableKdTree::new_from_slice(&pts)
        });
        PrecomputedIrradiance {
            points,
            tree,
            max_radius: pm.max_radius,
        }
    }

    /// Irradiance of the nearest precomputed point whose normal agrees with `n`, among the
    /// eight nearest within the photon map's maximum radius: none there, none at all (light
    /// does not leak through closed geometry).
    pub fn lookup(&self, x: Vec3, n: Vec3) -> Vec3 {
        let Some(t) = &self.tree else {
            return Vec3::ZERO;
        };
        let found = t.nearest_n_within::<SquaredEuclidean>(
            &x.to_array(),
            self.max_radius * self.max_radius,
            NonZero::new(8).expect("8 > 0"),
            true,
        );
        for nb in found {
            let p = &self.points[nb.item as usize];
            if p.1.dot(n) > 0.5 && (p.0 - x).dot(n).abs() <= DISC_THICKNESS * nb.distance.sqrt() {
                return p.2;
            }
        }
        Vec3::ZERO
    }
}
