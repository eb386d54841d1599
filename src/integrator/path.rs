//! `path-trace`: unbiased path tracing, the ground truth every other method is measured
//! against. Every vertex samples the lights with shadow rays (next-event estimation) and
//! continues by sampling its BRDF ([`crate::bsdf`]); emission a continuation ray finds is
//! weighted against the emitter samples by multiple importance sampling (the power
//! heuristic, Veach 1997). Russian roulette after three bounces.
//!
//! [`PathSampling`] can switch either strategy off: all three converge to the same image
//! (a test checks it), which is how the weights are known to be right.

use glam::Vec3;

use super::{Accumulator, CameraHit, FrameContext, FrameImage, RenderCounts, Shade, shading_dims};
use crate::bsdf::Lobes;
use crate::interaction::{
    LightSampling, ShadowRays, direct_light, emitter_pdf, power_heuristic, trace,
};

/// Which strategies light emissive triangles in the path tracer. Punctual lights are always
/// sampled (no ray can hit them).
#[derive(
    Debug,
    Clone,
    Copy,
    Default,
    PartialEq,
    Eq,
    serde::Serialize,
    serde::Deserialize,
    schemars::JsonSchema,
)]
#[serde(rename_all = "kebab-case")]
pub enum PathSampling {
    /// Emitter samples and BRDF sampling, combined by the power heuristic (the default).
    #[default]
    Mis,
    /// Emitter samples only: emission found by continuation rays is not counted.
    Lights,
    /// BRDF sampling only: no emitter samples.
    Brdf,
}

/// The path tracer's settings.
pub struct PathTracer {
    /// Path vertices at most (the camera hit included).
    pub depth: u32,
    /// Emissive-triangle samples per vertex.
    pub light_samples: u32,
    pub sampling: PathSampling,
}

impl Shade for PathTracer {
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
        let (sampler, s) = (hit.sampler, hit.sample);
        let m = ctx.materials;
        let mut dims = shading_dims();
        let mut sp = hit.sp;
        let (mut o, mut d) = (sp.spawn(), hit.dir);
        // Throughput by the camera hit's lobe that reflected the path.
        let mut beta = Lobes::ZERO;
        // Density of the BRDF sample that led to the current vertex.
        let mut last_pdf = 0.0f32;
        let (n_light, sampling) = match self.sampling {
            PathSampling::Mis => (self.light_samples, LightSampling::Mis),
            PathSampling::Lights => (self.light_samples, LightSampling::Lights),
            PathSampling::Brdf => (0, LightSampling::Lights),
        };
        for bounce in 0..self.depth {
            // Per vertex: three dimensions of light samples, one of roulette, three of BRDF
            // sampling.
            let (dim_light, dim_roulette, dim_dir) = (dims.take(3), dims.take(1), dims.take(3));
            if bounce > 0 {
                let Some(next) = trace(ctx.scene, o, d) else {
                    break;
                };
                let l_e = next.emission(m);
                if l_e != Vec3::ZERO {
                    let w = match self.sampling {
                        PathSampling::Lights => 0.0,
                        PathSampling::Brdf => 1.0,
                        PathSampling::Mis => {
                            let t = (next.position - o).length();
                            let p_light = n_light as f32 * emitter_pdf(ctx.scene, &next, d, t);
                            power_heuristic(last_pdf, p_light)
                        }
                    };
                    let c = beta.scale(l_e * w);
                    if bounce == 1 {
                        acc.add(c, Lobes::ZERO);
                    } else {
                        acc.add(Lobes::ZERO, c);
                    }
                }
                sp = next;
            }
            let wo = -d;
            let bsdf = sp.bsdf(m);
            let l = direct_light(
                ctx.scene,
                &sp,
                wo,
                &bsdf,
                sampler,
                (s, n_light, dim_light),
                sampling,
                &mut ShadowRays::traced(&mut counts.shadow_rays),
            );
            if bounce == 0 {
                acc.hit(hit.depth(ctx), sp.emission(m), l, Lobes::ZERO);
            } else {
                acc.add(Lobes::ZERO, beta.scale(l.sum()));
            }
            if bounce >= 3 {
                let p = beta.sum().max_element().clamp(0.05, 1.0);
                if sampler.get(s, dim_roulette) >= p {
                    break;
                }
                beta = beta.scale(Vec3::splat(1.0 / p));
            }
            let ns = sp.shading_normal(wo);
            let u = [
                sampler.get(s, dim_dir),
                sampler.get(s, dim_dir + 1),
                sampler.get(s, dim_dir + 2),
            ];
            let Some(x) = bsdf.sample(ns, wo, u) else {
                break;
            };
            if x.wi.dot(sp.ng) <= 0.0 {
                break;
            }
            let w = Vec3::splat(ns.dot(x.wi) / x.pdf);
            beta = if bounce == 0 {
                x.f.scale(w)
            } else {
                beta.scale(x.f.sum() * w)
            };
            if beta.sum().max_element() <= 0.0 || !beta.sum().is_finite() {
                break;
            }
            last_pdf = x.pdf;
            o = sp.spawn();
            d = x.wi;
        }
    }
}

/// Renders the path-traced reference with `spp` samples per pixel.
pub fn render(ctx: &FrameContext, spp: u32, tracer: &PathTracer) -> (FrameImage, RenderCounts) {
    let (mut img, rows) = super::render_pixels(ctx, spp, tracer);
    img.drop_cache_aovs();
    (img, RenderCounts::sum(&rows))
}
