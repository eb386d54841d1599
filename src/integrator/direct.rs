//! `direct`: emission and direct light only, no indirect light.

use crate::bsdf::Lobes;
use crate::interaction::ShadowRays;

use super::{Accumulator, CameraHit, FrameContext, FrameImage, RenderCounts, Shade};

/// Emission plus direct light by shadow rays at camera hits.
pub struct Direct {
    /// Emissive-triangle samples per camera sample.
    pub light_samples: u32,
}

impl Shade for Direct {
    type Row = RenderCounts;
    type Pixel = ();

    fn begin_pixel(&self, _: &FrameContext, _: &mut RenderCounts, _: u32, _: u32) {}

    fn sample(
        &self,
        ctx: &FrameContext,
        _: &mut (),
        counts: &mut RenderCounts,
        hit: &CameraHit,
        acc: &mut Accumulator,
    ) {
        let direct = hit.direct_light(
            ctx,
            &hit.bsdf(ctx),
            self.light_samples,
            &mut ShadowRays::traced(&mut counts.shadow_rays),
        );
        let emission = hit.sp.emission(ctx.materials);
        acc.hit(hit.depth(ctx), emission, direct, Lobes::ZERO);
    }
}

/// Renders emission and direct lighting (`method: direct`) with `spp` samples per pixel.
pub fn render(ctx: &FrameContext, spp: u32, light_samples: u32) -> (FrameImage, RenderCounts) {
    let (mut img, rows) = super::render_pixels(ctx, spp, &Direct { light_samples });
    img.drop_cache_aovs();
    (img, RenderCounts::sum(&rows))
}
