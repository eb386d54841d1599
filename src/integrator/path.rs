//! `path-trace`: unbiased path tracing with next-event estimation, the ground truth every
//! other method is measured against. Emission is counted at the camera hit only; every
//! diffuse vertex samples the lights with shadow rays and continues by cosine sampling;
//! Russian roulette after three bounces.

use std::f32::consts::FRAC_1_PI;

use glam::Vec3;

use super::{Accumulator, CameraHit, FrameContext, FrameImage, RenderCounts, Shade, shading_dims};
use crate::geom::cosine_direction;
use crate::interaction::{direct_irradiance, trace};

/// The path tracer's settings.
pub struct PathTracer {
    /// Path vertices at most (the camera hit included).
    pub depth: u32,
    /// Emissive-triangle samples per vertex.
    pub light_samples: u32,
}

impl Shade for PathTracer {
    type Row = RenderCounts;
    type Pixel = ();

    fn begin_pixel(&self, _: &FrameContext, _: u32, _: u32) {}

    fn sample(
        &self,
        ctx: &FrameContext,
        _: &mut (),
        counts: &mut RenderCounts,
        hit: &CameraHit,
        acc: &mut Accumulator,
    ) {
        let (sampler, s) = (hit.sampler, hit.sample);
        let mut dims = shading_dims();
        let mut sp = hit.sp;
        let (mut o, mut d) = (sp.spawn(), hit.dir);
        let mut beta = Vec3::ONE;
        for bounce in 0..self.depth {
            // Per vertex: three dimensions of light samples, one of roulette, two of direction.
            let (dim_light, dim_roulette, dim_dir) = (dims.take(3), dims.take(1), dims.take(2));
            if bounce > 0 {
                let Some(next) = trace(ctx.scene, o, d) else {
                    break;
                };
                sp = next;
            }
            let albedo = sp.albedo(ctx.materials);
            let l = beta
                * albedo
                * FRAC_1_PI
                * direct_irradiance(
                    ctx.scene,
                    &sp,
                    sampler,
                    s,
                    self.light_samples,
                    dim_light,
                    &mut counts.shadow_rays,
                );
            if bounce == 0 {
                acc.hit(hit.depth(ctx), sp.emission(ctx.materials), l, Vec3::ZERO);
            } else {
                acc.add(Vec3::ZERO, l);
            }
            beta *= albedo;
            if bounce >= 3 {
                let p = beta.max_element().clamp(0.05, 1.0);
                if sampler.get(s, dim_roulette) >= p {
                    break;
                }
                beta /= p;
            }
            let nd = cosine_direction(
                sp.ns,
                sampler.get(s, dim_dir).min(0.999_999_9),
                sampler.get(s, dim_dir + 1),
            );
            if nd.dot(sp.ng) <= 0.0 {
                break;
            }
            o = sp.spawn();
            d = nd;
        }
    }
}

/// Renders the path-traced reference with `spp` samples per pixel.
pub fn render(ctx: &FrameContext, spp: u32, tracer: &PathTracer) -> (FrameImage, RenderCounts) {
    let (mut img, rows) = super::render_pixels(ctx, spp, tracer);
    img.drop_cache_aovs();
    (img, RenderCounts::sum(&rows))
}
