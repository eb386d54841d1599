//! AttachToAnchor (Pseudocode 1, §3.1, §3.3): the anchor a static gather hit links to —
//! the nearest photon's anchor, else one of the nearest anchors within D_max that passes
//! the reuse tests, else a new anchor at the hit.

use glam::Vec3;

use super::importons::Importons;
use super::{Anchor, AnchorId, AnchorParams, AnchorSet};
use crate::accel::{gamma, offset_ray_origin};
use crate::interaction::{Materials, SurfacePoint};
use crate::photon::PhotonMap;
use crate::scene::FrameScene;

/// Pseudocode 1 with the reuse heuristics of §3.1, for one frame.
pub struct Attacher<'a> {
    pub frame: &'a FrameScene,
    pub m: Materials<'a>,
    pub pm: &'a PhotonMap,
    pub k: usize,
    pub params: AnchorParams,
    /// The scene radius the relative distances refer to.
    pub scale: f32,
    /// Importance-driven D_max factor at a point (1 = the constant D_max).
    pub importance: Option<&'a Importons>,
}

impl Attacher<'_> {
    fn acceptable(&self, set: &AnchorSet, id: AnchorId, sp: &SurfacePoint, albedo: Vec3) -> bool {
        let a = set.anchor(id);
        // Cheapest first (§3.1): normal, albedo, then visibility by a shadow ray.
        if a.normal().dot(sp.ng) < self.params.normal_cos {
            return false;
        }
        if (a.albedo() - albedo).abs().max_element() > self.params.albedo_tolerance {
            return false;
        }
        // The decoded position is off the anchor's surface by at most the quantiser's
        // half step per axis (twice that for margin), plus the rounding of the hit it came
        // from; the shadow ray runs between the two error boxes (pbrt-v4's `SpawnRayTo`),
        // leaving the anchor on the side its normal faces.
        let p = a.position(&set.quantizer);
        let p_error = 2.0 * set.quantizer.error() + p.abs() * gamma(7);
        let target = offset_ray_origin(p, p_error, a.normal(), a.normal());
        let Some(s) = sp.spawn_to(target, Vec3::ZERO, a.normal()) else {
            return true;
        };
        !self.frame.accel.occluded(
            &self.frame.static_geometry,
            &self.frame.dynamic_geometry,
            s.origin,
            s.dir,
            s.tmax,
        )
    }

    /// AttachToAnchor (Pseudocode 1): the anchor a static gather hit links to.
    pub fn attach(&self, set: &mut AnchorSet, sp: &SurfacePoint) -> AnchorId {
        let albedo = sp.albedo(self.m);
        let x = sp.position;
        // §3.3.2: the nearest photon's anchor, if it has one.
        let photon = self.pm.nearest(x).filter(|&i| {
            (self.pm.photons[i].position - x).length() <= self.params.photon_radius * self.scale
        });
        if let Some(ph) = photon
            && let Some(a) = set.photon_links[ph]
            && set.anchor(a).is_live()
            && self.acceptable(set, a, sp, albedo)
        {
            return a;
        }
        // §3.3.1: the nearest anchors within D_max; three rejections create a new one.
        let factor = self.importance.map_or(1.0, |imp| imp.factor(x));
        let d_max = self
            .params
            .d_max_absolute
            .unwrap_or(self.params.d_max * self.scale)
            * factor;
        let anchors = &set.anchors;
        let candidates = set
            .tree
            .nearest(x, d_max, 3, |i| anchors[i as usize].is_live());
        let found = candidates
            .iter()
            .map(|&(_, id)| AnchorId(id))
            .find(|&id| self.acceptable(set, id, sp, albedo));
        let id = match found {
            Some(id) => id,
            None => {
                // Estimated where the anchor is stored (quantised position and normal),
                // exactly as later frames re-estimate it: the normal test against photons
                // can tip on a fraction of a degree.
                let q = set.quantizer;
                let id = set.add(Anchor::new(&q, x, sp.ng, albedo, Vec3::ZERO));
                let a = *set.anchor(id);
                let (e, r2) = self.pm.irradiance_and_radius(
                    a.position(&q),
                    a.normal(),
                    self.params.anchor_k(self.k),
                );
                set.anchor_mut(id).set_irradiance(e);
                set.set_reach(id, r2);
                id
            }
        };
        if let Some(ph) = photon
            && set.photon_links[ph].is_none()
        {
            set.photon_links[ph] = Some(id);
        }
        id
    }
}
