//! Depth maps on the GPU (§5.1) with wgpu: the second implementation of [`DepthMaps`],
//! traversing the frame's obvhs BVH2s in a compute shader (`shaders/depth.wgsl`); the module
//! doc of [`super::depth`] states the contract and how far this one may differ from the CPU.
//!
//! It shares the device and queue of [`super::gpu::GpuVisibility`]. Each BVH is flattened to
//! two arrays: two 16-byte words per node (box corners, primitive count, first child or
//! primitive) and three per primitive slot (the vertices in the BVH's order, with the
//! triangle's index and its alpha-test flag in the spare words). The static BVH is uploaded
//! on the first frame that needs it and kept while its [`crate::accel::StaticBvh::id`] stays
//! the same (a whole render); the dynamic one is uploaded per call. Queries go in chunks that
//! respect the adapter's storage-binding size and dispatch limits, each answered with one
//! invocation per query. A triangle the CPU would decide in f64 — above all the surface a
//! query starts on, whose `t` is zero within rounding — does not send its query back whole:
//! the shader names it (two per query at most), and the CPU tests just that triangle with its
//! own test ([`crate::accel::hit_distance`]) and keeps the nearer answer. Queries the shader leaves
//! undecided (more such triangles, an alpha-tested one in front, a stack overflow) are traced
//! on the CPU. Packing the queries and reading the answers run in parallel, in order.

use std::borrow::Cow;
use std::sync::{Mutex, OnceLock};

use obvhs::bvh2::Bvh2;
use rayon::prelude::*;
use wgpu::util::DeviceExt;

use super::Error;
use super::depth::{DepthMaps, DepthQuery, closest_on_cpu};
use crate::accel::{Hit, ShearedRay, canonical, gamma, hit_distance};
use crate::geom::{Geometry, Motion};
use crate::scene::FrameScene;

/// The shader's uniform block.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct Params {
    queries: u32,
    offset: u32,
    groups_x: u32,
    has_static: u32,
    has_dynamic: u32,
    gamma2: f32,
    gamma3: f32,
    gamma5: f32,
}

const WORKGROUP: u64 = 64;
/// Bytes of one query (origin and direction, a 16-byte word each) and of one answer (t, the
/// triangle, two pending triangles).
const QUERY_BYTES: u64 = 32;
const HIT_BYTES: u64 = 16;
/// Queries per chunk at most: keeps one submission short (no driver watchdog) and the
/// staging memory modest.
const MAX_CHUNK: u64 = 1 << 20;
/// The shader's answers that are not a triangle.
const MISS: u32 = u32::MAX;
const UNDECIDED: u32 = u32::MAX - 1;
/// Bit of a triangle code that marks dynamic geometry.
const DYNAMIC_BIT: u32 = 1 << 31;

/// A BVH on the GPU.
struct Uploaded {
    nodes: wgpu::Buffer,
    tris: wgpu::Buffer,
    /// False for the placeholder that stands for no geometry.
    present: bool,
}

/// Depth maps on a wgpu adapter.
pub struct GpuDepthMaps {
    device: wgpu::Device,
    queue: wgpu::Queue,
    info: wgpu::AdapterInfo,
    max_groups: u32,
    max_binding: u64,
    /// Built on first use (a session without glossy surfaces never compiles it).
    pipeline: OnceLock<Result<(wgpu::ComputePipeline, wgpu::BindGroupLayout), String>>,
    /// The static BVH of the current render, by [`crate::accel::StaticBvh::id`].
    statics: Mutex<Option<(u64, std::sync::Arc<Uploaded>)>>,
}

/// Two 16-byte words per node: (min, prim_count), (max, first_index), floats as their bits.
fn flatten_nodes(bvh: &Bvh2) -> Vec<[u32; 4]> {
    bvh.nodes
        .iter()
        .flat_map(|n| {
            let a = n.aabb();
            [
                [
                    a.min.x.to_bits(),
                    a.min.y.to_bits(),
                    a.min.z.to_bits(),
                    n.prim_count,
                ],
                [
                    a.max.x.to_bits(),
                    a.max.y.to_bits(),
                    a.max.z.to_bits(),
                    n.first_index,
                ],
            ]
        })
        .collect()
}

/// Three 16-byte words per primitive slot: the triangle's vertices in the BVH's order, the
/// triangle's index beside v0 and its alpha-test flag beside v1.
fn flatten_triangles(bvh: &Bvh2, g: &Geometry) -> Vec<[u32; 4]> {
    bvh.primitive_indices
        .iter()
        .flat_map(|&i| {
            let t = &g.triangles[i as usize];
            let w = |v: glam::Vec3A, w: u32| [v.x.to_bits(), v.y.to_bits(), v.z.to_bits(), w];
            [
                w(t.v0, i),
                w(t.v1, g.shading[i as usize].masked as u32),
                w(t.v2, 0),
            ]
        })
        .collect()
}

impl GpuDepthMaps {
    /// Depth maps on the device of a visibility implementation.
    pub(super) fn new(
        device: wgpu::Device,
        queue: wgpu::Queue,
        info: wgpu::AdapterInfo,
        limits: &wgpu::Limits,
    ) -> Self {
        GpuDepthMaps {
            device,
            queue,
            info,
            max_groups: limits.max_compute_workgroups_per_dimension,
            max_binding: limits.max_storage_buffer_binding_size,
            pipeline: OnceLock::new(),
            statics: Mutex::new(None),
        }
    }

    fn failed(&self, e: impl std::fmt::Display) -> Error {
        Error::Gpu {
            adapter: self.info.name.clone(),
            message: e.to_string(),
        }
    }

    /// The pipeline, compiled on first use; a compilation error is kept and returned again.
    fn pipeline(&self) -> Result<&(wgpu::ComputePipeline, wgpu::BindGroupLayout), Error> {
        self.pipeline
            .get_or_init(|| {
                let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
                let module = self
                    .device
                    .create_shader_module(wgpu::ShaderModuleDescriptor {
                        label: Some("depth.wgsl"),
                        source: wgpu::ShaderSource::Wgsl(Cow::Borrowed(include_str!(
                            "../../shaders/depth.wgsl"
                        ))),
                    });
                let entry = |binding, ty| wgpu::BindGroupLayoutEntry {
                    binding,
                    visibility: wgpu::ShaderStages::COMPUTE,
                    ty: wgpu::BindingType::Buffer {
                        ty,
                        has_dynamic_offset: false,
                        min_binding_size: None,
                    },
                    count: None,
                };
                let mut entries = vec![entry(0, wgpu::BufferBindingType::Uniform)];
                entries.extend(
                    (1..=5).map(|b| entry(b, wgpu::BufferBindingType::Storage { read_only: true })),
                );
                entries.push(entry(
                    6,
                    wgpu::BufferBindingType::Storage { read_only: false },
                ));
                let layout =
                    self.device
                        .create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
                            label: Some("depth"),
                            entries: &entries,
                        });
                let pipeline_layout =
                    self.device
                        .create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                            label: Some("depth"),
                            bind_group_layouts: &[Some(&layout)],
                            immediate_size: 0,
                        });
                let pipeline =
                    self.device
                        .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                            label: Some("depth"),
                            layout: Some(&pipeline_layout),
                            module: &module,
                            entry_point: Some("main"),
                            compilation_options: Default::default(),
                            cache: None,
                        });
                match pollster::block_on(scope.pop()) {
                    Some(e) => Err(format!("compiling shaders/depth.wgsl: {e}")),
                    None => Ok((pipeline, layout)),
                }
            })
            .as_ref()
            .map_err(|e| self.failed(e))
    }

    /// A storage buffer of `words`, at least one word long (bindings may not be empty);
    /// an error when it exceeds the adapter's binding size.
    fn upload(&self, what: &str, words: &[[u32; 4]]) -> Result<wgpu::Buffer, Error> {
        let bytes = (words.len() * 16) as u64;
        if bytes > self.max_binding {
            return Err(Error::BufferTooLarge {
                what: what.to_string(),
                bytes,
                limit: self.max_binding,
            });
        }
        let placeholder = [[0u32; 4]];
        let contents = if words.is_empty() {
            &placeholder[..]
        } else {
            words
        };
        Ok(self
            .device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(what),
                contents: bytemuck::cast_slice(contents),
                usage: wgpu::BufferUsages::STORAGE,
            }))
    }

    fn upload_bvh(&self, what: &str, bvh: Option<&Bvh2>, g: &Geometry) -> Result<Uploaded, Error> {
        let (nodes, tris) = match bvh {
            Some(b) if !b.nodes.is_empty() => (flatten_nodes(b), flatten_triangles(b, g)),
            _ => (Vec::new(), Vec::new()),
        };
        Ok(Uploaded {
            present: !nodes.is_empty(),
            nodes: self.upload(&format!("{what} BVH nodes"), &nodes)?,
            tris: self.upload(&format!("{what} triangles"), &tris)?,
        })
    }

    /// The static BVH on the GPU: uploaded once per static set.
    fn statics(&self, frame: &FrameScene) -> Result<std::sync::Arc<Uploaded>, Error> {
        let id = frame.accel.statics().id();
        let mut cached = self.statics.lock().map_err(|e| self.failed(e))?;
        if let Some((cid, up)) = cached.as_ref()
            && *cid == id
        {
            return Ok(up.clone());
        }
        let up = std::sync::Arc::new(self.upload_bvh(
            "static",
            frame.accel.statics().bvh2(),
            &frame.static_geometry,
        )?);
        *cached = Some((id, up.clone()));
        Ok(up)
    }

    /// Runs one chunk of queries and hands the shader's raw answers, as mapped, to `read`.
    fn run_chunk<R>(
        &self,
        (pipeline, layout): &(wgpu::ComputePipeline, wgpu::BindGroupLayout),
        (statics, dynamic): (&Uploaded, &Uploaded),
        queries: &[DepthQuery],
        read: impl FnOnce(&[[u32; 4]]) -> R,
    ) -> Result<R, Error> {
        let data: Vec<[[f32; 4]; 2]> = queries
            .par_iter()
            .map(|q| {
                [
                    q.origin.extend(0.0).to_array(),
                    canonical(q.dir).extend(0.0).to_array(),
                ]
            })
            .collect();
        let n = queries.len() as u64;
        let out_bytes = n * HIT_BYTES;
        let groups = n.div_ceil(WORKGROUP);
        let max_groups = self.max_groups as u64;
        let groups_x = groups.min(max_groups);
        let groups_y = groups.div_ceil(groups_x);
        let params = Params {
            queries: n as u32,
            offset: 0,
            groups_x: groups_x as u32,
            has_static: statics.present as u32,
            has_dynamic: dynamic.present as u32,
            gamma2: gamma(2),
            gamma3: gamma(3),
            gamma5: gamma(5),
        };
        let b_params = self
            .device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("depth params"),
                contents: bytemuck::bytes_of(&params),
                usage: wgpu::BufferUsages::UNIFORM,
            });
        let b_queries = self
            .device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("depth queries"),
                contents: bytemuck::cast_slice(&data),
                usage: wgpu::BufferUsages::STORAGE,
            });
        let (b_hits, b_read) = output_and_readback(&self.device, "depth hits", out_bytes);
        let entries: Vec<wgpu::BindGroupEntry> = [
            &b_params,
            &statics.nodes,
            &statics.tris,
            &dynamic.nodes,
            &dynamic.tris,
            &b_queries,
            &b_hits,
        ]
        .iter()
        .enumerate()
        .map(|(i, b)| wgpu::BindGroupEntry {
            binding: i as u32,
            resource: b.as_entire_binding(),
        })
        .collect();
        let bind = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("depth"),
            layout,
            entries: &entries,
        });
        let mut encoder = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("depth"),
            });
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("depth"),
                timestamp_writes: None,
            });
            pass.set_pipeline(pipeline);
            pass.set_bind_group(0, &bind, &[]);
            pass.dispatch_workgroups(groups_x as u32, groups_y as u32, 1);
        }
        encoder.copy_buffer_to_buffer(&b_hits, 0, &b_read, 0, out_bytes);
        submit_and_map(&self.device, &self.queue, encoder, &b_read, read)
            .map_err(|e| self.failed(format!("reading depths back: {e}")))
    }

    /// Queries per chunk: within the binding size, the 2D dispatch and [`MAX_CHUNK`].
    fn chunk(&self) -> usize {
        let groups = self.max_groups as u64;
        (self.max_binding / QUERY_BYTES)
            .min(groups * groups * WORKGROUP)
            .clamp(1, MAX_CHUNK) as usize
    }

    /// Answers `queries`; counts the queries the shader left to the CPU whole, and those it
    /// left a triangle of to the CPU's test.
    pub fn closest_counting(
        &self,
        frame: &FrameScene,
        queries: &[DepthQuery],
    ) -> Result<(Vec<Option<Hit>>, usize, usize), Error> {
        if queries.is_empty() {
            return Ok((Vec::new(), 0, 0));
        }
        let pipeline = self.pipeline()?;
        let statics = self.statics(frame)?;
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let result = (|| {
            let dynamic = self.upload_bvh(
                "dynamic",
                frame.accel.dynamic_bvh2(),
                &frame.dynamic_geometry,
            )?;
            let mut out = Vec::with_capacity(queries.len());
            let (mut undecided, mut pending) = (0, 0);
            for qs in queries.chunks(self.chunk()) {
                let start = out.len();
                out.resize(start + qs.len(), None);
                let answers = &mut out[start..];
                self.run_chunk(pipeline, (&statics, &dynamic), qs, |raw| {
                    undecided += raw.iter().filter(|w| w[1] == UNDECIDED).count();
                    pending += raw.iter().filter(|w| w[2] != MISS).count();
                    answers
                        .par_iter_mut()
                        .zip(qs.par_iter().zip(raw.par_iter()))
                        .try_for_each(|(a, (q, &words))| {
                            *a = answer(frame, q, words)?;
                            Ok(())
                        })
                })?
                .map_err(|e: String| self.failed(e))?;
            }
            Ok((out, undecided, pending))
        })();
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(self.failed(e));
        }
        result
    }
}

/// The triangle a shader code names, or an error when the geometry has no such triangle (a
/// corrupt answer must not become a panic further on).
fn decode(frame: &FrameScene, code: u32) -> Result<(Motion, u32), String> {
    let motion = if code & DYNAMIC_BIT != 0 {
        Motion::Dynamic
    } else {
        Motion::Static
    };
    let triangle = code & !DYNAMIC_BIT;
    let len = frame.geometry(motion).len();
    if triangle as usize >= len {
        return Err(format!(
            "the shader answered triangle {triangle} of {motion:?} geometry, which has {len}"
        ));
    }
    Ok((motion, triangle))
}

/// One query's answer from the shader's words (t, triangle, two pending triangles): the
/// CPU's trace where the shader left it undecided; else the shader's hit, replaced by a
/// pending triangle that the CPU's own test finds nearer — or as near, when it is static
/// and the hit dynamic, as [`crate::accel::Accel::closest`] keeps the static one then.
fn answer(
    frame: &FrameScene,
    q: &DepthQuery,
    [t, code, p0, p1]: [u32; 4],
) -> Result<Option<Hit>, String> {
    let mut best = match code {
        UNDECIDED => return Ok(closest_on_cpu(frame, q)),
        MISS => None,
        c => {
            let (motion, triangle) = decode(frame, c)?;
            Some(Hit {
                t: f32::from_bits(t),
                motion,
                triangle,
            })
        }
    };
    if p0 == MISS {
        return Ok(best);
    }
    let ray = ShearedRay::new(q.origin, canonical(q.dir));
    for p in [p0, p1].into_iter().filter(|&p| p != MISS) {
        let (motion, triangle) = decode(frame, p)?;
        let t = hit_distance(
            &ray,
            frame.geometry(motion),
            triangle as usize,
            f32::INFINITY,
        );
        let nearer = match best {
            None => t.is_finite(),
            Some(h) => {
                t < h.t || (t == h.t && motion == Motion::Static && h.motion == Motion::Dynamic)
            }
        };
        if nearer {
            best = Some(Hit {
                t,
                motion,
                triangle,
            });
        }
    }
    Ok(best)
}

impl DepthMaps for GpuDepthMaps {
    fn name(&self) -> String {
        format!(
            "gpu ({}, {:?}, {})",
            self.info.name, self.info.backend, self.info.driver
        )
    }

    fn closest(
        &self,
        frame: &FrameScene,
        queries: &[DepthQuery],
    ) -> Result<Vec<Option<Hit>>, Error> {
        self.closest_counting(frame, queries).map(|(h, ..)| h)
    }
}

/// A storage buffer of `size` bytes for a pass's results (zeroed: wgpu starts every buffer
/// so) and the `MAP_READ` buffer they are copied into for [`submit_and_map`] (for the depth
/// maps here and for visibility in `gpu.rs`).
pub(super) fn output_and_readback(
    device: &wgpu::Device,
    label: &str,
    size: u64,
) -> (wgpu::Buffer, wgpu::Buffer) {
    let buffer = |label: &str, usage| {
        device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size,
            usage,
            mapped_at_creation: false,
        })
    };
    (
        buffer(
            label,
            wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
        ),
        buffer(
            &format!("{label} readback"),
            wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        ),
    )
}

/// Submits `encoder` (for the depth maps here and for visibility in `gpu.rs`), whose last
/// command copies results into `read` (a `MAP_READ` buffer), waits for the device and hands
/// `read`'s contents, as mapped, to `f`.
pub(super) fn submit_and_map<T: bytemuck::Pod, R>(
    device: &wgpu::Device,
    queue: &wgpu::Queue,
    encoder: wgpu::CommandEncoder,
    read: &wgpu::Buffer,
    f: impl FnOnce(&[T]) -> R,
) -> Result<R, String> {
    queue.submit([encoder.finish()]);
    let (tx, rx) = std::sync::mpsc::channel();
    read.slice(..)
        .map_async(wgpu::MapMode::Read, move |r| drop(tx.send(r)));
    device
        .poll(wgpu::PollType::wait_indefinitely())
        .map_err(|e| e.to_string())?;
    rx.recv()
        .map_err(|e| e.to_string())?
        .map_err(|e| e.to_string())?;
    let view = read.get_mapped_range(..).map_err(|e| e.to_string())?;
    let out = bytemuck::try_cast_slice(&view)
        .map(f)
        .map_err(|e| e.to_string());
    drop(view);
    read.unmap();
    out
}

#[cfg(test)]
mod tests {
    use super::super::depth::testing::*;
    use super::super::depth::{CpuDepthMaps, GRAZING_SHARE, T_TOLERANCE};
    use super::super::gpu::adapter_for_tests;
    use super::*;

    /// Compares the GPU's answers with the CPU's: the same triangle at the same distance
    /// within [`T_TOLERANCE`] of the larger of the distance and the triangle's reach from the
    /// origin, except at most one query in [`GRAZING_SHARE`] (module doc of
    /// [`super::super::depth`]), and (without alpha-tested triangles) at most 2 % of the
    /// queries left to the CPU (the axis-aligned ones, 1 %, meet faces edge-on); returns
    /// (queries that differ, hits, undecided, with a pending triangle).
    fn compare(
        gpu: &GpuDepthMaps,
        frame: &FrameScene,
        qs: &[DepthQuery],
    ) -> (usize, usize, usize, usize) {
        let cpu = CpuDepthMaps.closest(frame, qs).unwrap();
        let (g, undecided, pending) = gpu.closest_counting(frame, qs).unwrap();
        assert_eq!(g.len(), qs.len());
        let mut differ = 0;
        let mut max_rel = 0.0f32;
        for (i, (c, g)) in cpu.iter().zip(&g).enumerate() {
            match (c, g) {
                (Some(c), Some(g)) if c.motion == g.motion && c.triangle == g.triangle => {
                    let tri = &frame.geometry(c.motion).triangles[c.triangle as usize];
                    let o = glam::Vec3A::from(qs[i].origin);
                    let reach = [tri.v0, tri.v1, tri.v2]
                        .map(|v| (v - o).length())
                        .into_iter()
                        .fold(c.t.abs(), f32::max);
                    let rel = (c.t - g.t).abs() / reach.max(f32::MIN_POSITIVE);
                    assert!(
                        rel <= T_TOLERANCE,
                        "query {i}: t {} vs {} ({rel} of {reach})",
                        c.t,
                        g.t
                    );
                    max_rel = max_rel.max(rel);
                }
                (None, None) => {}
                (c, g) => {
                    eprintln!("query {i}: cpu {c:?}, gpu {g:?}");
                    differ += 1;
                }
            }
        }
        let hits = cpu.iter().flatten().count();
        let misses = (cpu.len() - hits, g.iter().filter(|h| h.is_none()).count());
        eprintln!(
            "{} queries: {hits} hits, misses cpu {} gpu {}, {differ} differ, {undecided} \
             undecided, {pending} with a pending triangle, largest difference of t \
             {max_rel:e} of the triangle's reach",
            qs.len(),
            misses.0,
            misses.1
        );
        assert!(
            undecided * 50 <= qs.len() || frame.dynamic_geometry.alpha.is_some(),
            "{undecided} of {} queries left to the CPU",
            qs.len()
        );
        assert!(
            differ * GRAZING_SHARE <= qs.len(),
            "{differ} of {} queries hit something else on the GPU",
            qs.len()
        );
        (differ, hits, undecided, pending)
    }

    /// Random triangle soups inside a closed box (static), a dynamic soup, queries from
    /// inside: the GPU finds what the CPU finds (module doc of [`super::super::depth`]); the
    /// static BVH is uploaded once and reused while the dynamic one changes.
    #[test]
    fn gpu_depth_maps_agree_with_the_cpu() {
        let Some(vis) = adapter_for_tests() else {
            return;
        };
        let gpu = vis.depth();
        eprintln!("adapter: {}", gpu.name());
        for seed in [1u32, 2, 3] {
            let mut statics = closed_box(4.0);
            let extra = soup(seed + 10, 400, 6.0, 0.5);
            statics.triangles.extend(extra.triangles);
            statics.shading.extend(extra.shading);
            let set = crate::scene::StaticSet::new(statics);
            let mut total_hits = 0;
            for frame_no in 0..2u32 {
                let frame = frame_with(&set, soup(seed * 7 + frame_no, 200, 5.0, 0.6));
                let qs = queries(seed * 3 + frame_no, 20_000, 7.0);
                let (_, hits, ..) = compare(gpu, &frame, &qs);
                let dynamic = CpuDepthMaps
                    .closest(&frame, &qs)
                    .unwrap()
                    .iter()
                    .flatten()
                    .filter(|h| h.motion == Motion::Dynamic)
                    .count();
                assert!(
                    dynamic > 500,
                    "the test must hit dynamic triangles ({dynamic})"
                );
                total_hits += hits;
            }
            assert!(total_hits > 30_000);
        }
        // Without static geometry, and with nothing at all: misses everywhere but the soup.
        let frame = frame(crate::geom::Geometry::default(), soup(9, 100, 2.0, 0.5));
        let (_, hits, ..) = compare(gpu, &frame, &queries(9, 5000, 3.0));
        assert!(hits > 100 && hits < 5000);
        let empty = frame_with(
            &crate::scene::StaticSet::new(crate::geom::Geometry::default()),
            crate::geom::Geometry::default(),
        );
        assert_eq!(compare(gpu, &empty, &queries(9, 100, 3.0)).1, 0);
    }

    /// Rays leaving a surface — a glossy floor's depth maps — meet the floor itself at a `t`
    /// within rounding of zero, which only the CPU's f64 test decides: the shader leaves
    /// that one triangle to the CPU, not the whole query, so (nearly) no query is traced on
    /// the CPU, and the answers are the CPU's: the floor is no hit for rays leaving it, and
    /// the nearest hit for rays turned into it.
    #[test]
    fn gpu_depth_maps_decide_rays_leaving_a_surface() {
        let Some(vis) = adapter_for_tests() else {
            return;
        };
        let frame = frame(closed_box(4.0), soup(5, 200, 5.0, 0.6));
        let up = queries_from_floor(5, 20_000, 4.0);
        // The same rays turned down meet the floor just below their origins: where that
        // hit is within rounding of zero, only the pending triangle's test finds it.
        let down: Vec<DepthQuery> = up
            .iter()
            .map(|q| DepthQuery {
                origin: q.origin,
                dir: q.dir * glam::Vec3::new(1.0, -1.0, 1.0),
            })
            .collect();
        for qs in [&up, &down] {
            let (differ, hits, undecided, pending) = compare(vis.depth(), &frame, qs);
            assert_eq!(hits, qs.len(), "the box is closed");
            assert_eq!(differ, 0);
            assert!(
                undecided * 100 <= qs.len(),
                "{undecided} queries traced on the CPU"
            );
            // The floor's own triangles were met within rounding: the case this test is about.
            assert!(
                pending * 4 > qs.len(),
                "{pending} queries met the floor within rounding"
            );
        }
    }

    /// Alpha-tested triangles are left to the CPU: a masked dynamic soup whose alpha test
    /// rejects everything is seen through on both.
    #[test]
    fn gpu_depth_maps_leave_alpha_tested_triangles_to_the_cpu() {
        let Some(vis) = adapter_for_tests() else {
            return;
        };
        let mut dynamic = soup(4, 300, 4.0, 0.8);
        for s in &mut dynamic.shading {
            s.masked = true;
        }
        dynamic.alpha = Some(std::sync::Arc::new(RejectAll));
        let frame = frame(closed_box(4.0), dynamic);
        let qs = queries(4, 5000, 4.0);
        let (_, hits, undecided, _) = compare(vis.depth(), &frame, &qs);
        assert_eq!(hits, qs.len());
        assert!(undecided > 500, "masked triangles in front: {undecided}");
    }

    /// An alpha test that cuts every triangle away.
    #[derive(Debug)]
    struct RejectAll;

    impl crate::geom::AlphaTest for RejectAll {
        fn opaque(&self, _g: &crate::geom::Geometry, _triangle: usize, _b: glam::Vec2) -> bool {
            false
        }
    }
}
