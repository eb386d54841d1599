//! Visibility detection on the GPU (the paper's §3.2) with wgpu: the second implementation
//! of [`Visibility`], running the rule of [`crate::visibility`] in a compute shader
//! (`shaders/visibility.wgsl`).
//!
//! The paper renders the dynamic objects into a 32×32 or 64×64 hemisphere map per cache and
//! reads the maps back. Here one invocation per (record, dynamic triangle) rasterises the
//! triangle's cap straight onto the record's stratum grid and sets bits with `atomicOr`:
//! coverage is conservative by construction (no map resolution to choose, no dependence on
//! the adapter offering conservative rasterisation), nothing but one bit per stratum is read
//! back, and there are no render targets, so no texture formats to get wrong on software
//! drivers. Dynamic triangles and prims are uploaded once per call; the stratum layout and
//! the pipeline are made once per session.
//!
//! Adapters: Vulkan, Metal or DX12 (`WGPU_BACKEND` narrows the choice). OpenGL is not built
//! in: llvmpipe's GL cannot be relied on for storage-buffer compute, and a software Vulkan
//! driver (Mesa's lavapipe) serves machines without a GPU.

use std::borrow::Cow;

use glam::Vec3;
use wgpu::util::DeviceExt;

use super::depth_gpu::GpuDepthMaps;
use super::{
    CpuVisibility, DynamicSet, Error, GPU_SLACK, Hemisphere, MIN_CAP_COS, RecordFrame, StrataBits,
    Visibility, VisibilityChoice,
};

/// The shader's uniform block.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct Params {
    records: u32,
    record_offset: u32,
    triangles: u32,
    m: u32,
    n: u32,
    words: u32,
    groups_x: u32,
    slack: f32,
    min_cap_cos: f32,
    dphi: f32,
    _pad: [u32; 2],
}

const WORKGROUP: u64 = 64;

/// Visibility on a wgpu adapter.
pub struct GpuVisibility {
    device: wgpu::Device,
    queue: wgpu::Queue,
    pipeline: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
    info: wgpu::AdapterInfo,
    max_groups: u32,
    max_binding: u64,
    /// Depth maps for anchor bucketing (§5.1) on the same device.
    depth: GpuDepthMaps,
}

/// Whether an adapter is a hardware GPU (not a CPU-emulated one such as lavapipe).
pub fn is_hardware(info: &wgpu::AdapterInfo) -> bool {
    info.device_type != wgpu::DeviceType::Cpu
}

impl GpuVisibility {
    /// Opens the best adapter: discrete, then integrated, then virtual, then software.
    pub fn new() -> Result<Self, Error> {
        let backends = wgpu::Backends::from_env()
            .unwrap_or(wgpu::Backends::VULKAN | wgpu::Backends::METAL | wgpu::Backends::DX12);
        let instance = wgpu::Instance::new(wgpu::InstanceDescriptor {
            backends,
            flags: wgpu::InstanceFlags::empty(),
            ..wgpu::InstanceDescriptor::new_without_display_handle()
        });
        let mut adapters = pollster::block_on(instance.enumerate_adapters(backends));
        let rank = |t: wgpu::DeviceType| match t {
            wgpu::DeviceType::DiscreteGpu => 0,
            wgpu::DeviceType::IntegratedGpu => 1,
            wgpu::DeviceType::VirtualGpu => 2,
            wgpu::DeviceType::Other => 3,
            wgpu::DeviceType::Cpu => 4,
        };
        adapters.sort_by_key(|a| rank(a.get_info().device_type));
        let Some(adapter) = adapters.into_iter().next() else {
            return Err(Error::NoAdapter(format!(
                "no Vulkan, Metal or DX12 adapter found among {backends:?} (OpenGL is not \
                 supported; on Debian, mesa-vulkan-drivers provides a software Vulkan adapter)"
            )));
        };
        let info = adapter.get_info();
        let limits = adapter.limits();
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("anchorage visibility"),
            required_limits: limits.clone(),
            ..Default::default()
        }))
        .map_err(|e| Error::Device {
            adapter: info.name.clone(),
            message: e.to_string(),
        })?;
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("visibility.wgsl"),
            source: wgpu::ShaderSource::Wgsl(Cow::Borrowed(include_str!(
                "../../shaders/visibility.wgsl"
            ))),
        });
        let storage = |binding, read_only| wgpu::BindGroupLayoutEntry {
            binding,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::Buffer {
                ty: wgpu::BufferBindingType::Storage { read_only },
                has_dynamic_offset: false,
                min_binding_size: None,
            },
            count: None,
        };
        let mut entries = vec![wgpu::BindGroupLayoutEntry {
            binding: 0,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::Buffer {
                ty: wgpu::BufferBindingType::Uniform,
                has_dynamic_offset: false,
                min_binding_size: None,
            },
            count: None,
        }];
        entries.extend((1..=5).map(|b| storage(b, true)));
        entries.push(storage(6, false));
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("visibility"),
            entries: &entries,
        });
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("visibility"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some("visibility"),
            layout: Some(&pipeline_layout),
            module: &module,
            entry_point: Some("main"),
            compilation_options: Default::default(),
            cache: None,
        });
        let depth = GpuDepthMaps::new(device.clone(), queue.clone(), info.clone(), &limits);
        Ok(GpuVisibility {
            depth,
            device,
            queue,
            pipeline,
            layout,
            max_groups: limits.max_compute_workgroups_per_dimension,
            max_binding: limits.max_storage_buffer_binding_size,
            info,
        })
    }

    /// A failure while running on this adapter.
    fn failed(&self, e: impl std::fmt::Display) -> Error {
        Error::Gpu {
            adapter: self.info.name.clone(),
            message: e.to_string(),
        }
    }

    pub fn adapter(&self) -> &wgpu::AdapterInfo {
        &self.info
    }

    /// The depth maps on this device.
    pub fn depth(&self) -> &GpuDepthMaps {
        &self.depth
    }

    fn buffer(&self, label: &str, contents: &[u8], usage: wgpu::BufferUsages) -> wgpu::Buffer {
        self.device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents,
                usage,
            })
    }
}

impl Visibility for GpuVisibility {
    fn name(&self) -> String {
        format!(
            "gpu ({}, {:?}, {})",
            self.info.name, self.info.backend, self.info.driver
        )
    }

    fn flag(
        &self,
        records: &[(Vec3, Vec3)],
        strata: [u32; 2],
        set: &DynamicSet,
    ) -> Result<Vec<StrataBits>, Error> {
        let h = Hemisphere::new(strata);
        let cells = h.len();
        if records.is_empty() || set.is_empty() {
            return Ok(vec![StrataBits::new(cells); records.len()]);
        }
        let words = cells.div_ceil(32);
        let rec_data: Vec<[f32; 4]> = records
            .iter()
            .flat_map(|&(x, n)| {
                let f = RecordFrame::new(x, n);
                [f.x, f.t, f.b, f.n].map(|v| v.extend(0.0).to_array())
            })
            .collect();
        let tri_data: Vec<[f32; 4]> = set
            .triangles
            .iter()
            .flat_map(|t| t.map(|v| v.extend(0.0).to_array()))
            .collect();
        let mut tri_prim = vec![0u32; set.triangles.len()];
        for (p, range) in set.ranges.iter().enumerate() {
            tri_prim[range.clone()].fill(p as u32);
        }
        let prim_data: Vec<[f32; 4]> = set
            .prims
            .iter()
            .map(|p| p.centre.extend(p.radius).to_array())
            .collect();
        let grid: Vec<[f32; 4]> = h
            .rows
            .iter()
            .chain(&h.half_rows)
            .map(|r| [r.cos_theta, r.sin_theta, r.cos_beta, r.sin_beta])
            .chain(h.quarters.iter().map(|c| c.extend(0.0).to_array()))
            .collect();
        let out_bytes = (records.len() * words * 4) as u64;
        let largest = [rec_data.len() * 16, tri_data.len() * 16, out_bytes as usize]
            .into_iter()
            .max()
            .unwrap_or(0) as u64;
        if largest > self.max_binding {
            return Err(Error::TooLarge {
                records: records.len(),
                triangles: set.triangles.len(),
                limit: self.max_binding,
            });
        }
        let read = wgpu::BufferUsages::STORAGE;
        let b_records = self.buffer("records", bytemuck::cast_slice(&rec_data), read);
        let b_tris = self.buffer("triangles", bytemuck::cast_slice(&tri_data), read);
        let b_prim = self.buffer("tri_prim", bytemuck::cast_slice(&tri_prim), read);
        let b_prims = self.buffer("prims", bytemuck::cast_slice(&prim_data), read);
        let b_grid = self.buffer("grid", bytemuck::cast_slice(&grid), read);
        // The flags start zeroed (wgpu guarantees it).
        let (b_flags, b_read) =
            super::depth_gpu::output_and_readback(&self.device, "flags", out_bytes);

        // Chunks of records small enough for u32 pair indices and the dispatch limits.
        let tris = set.triangles.len() as u64;
        let max_groups = self.max_groups as u64;
        let pairs_cap = (u32::MAX as u64 / 2).min(max_groups * max_groups * WORKGROUP);
        let per_chunk = (pairs_cap / tris).max(1) as usize;
        let mut encoder = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("visibility"),
            });
        for start in (0..records.len()).step_by(per_chunk) {
            let count = per_chunk.min(records.len() - start);
            let groups = (count as u64 * tris).div_ceil(WORKGROUP);
            let groups_x = groups.min(max_groups);
            let groups_y = groups.div_ceil(groups_x);
            let params = Params {
                records: count as u32,
                record_offset: start as u32,
                triangles: tris as u32,
                m: h.m,
                n: h.n,
                words: words as u32,
                groups_x: groups_x as u32,
                slack: GPU_SLACK,
                min_cap_cos: MIN_CAP_COS,
                dphi: 2.0 * std::f32::consts::PI / h.n as f32,
                _pad: [0; 2],
            };
            let b_params = self.buffer(
                "params",
                bytemuck::bytes_of(&params),
                wgpu::BufferUsages::UNIFORM,
            );
            let entries: Vec<wgpu::BindGroupEntry> = [
                &b_params, &b_records, &b_tris, &b_prim, &b_prims, &b_grid, &b_flags,
            ]
            .iter()
            .enumerate()
            .map(|(i, b)| wgpu::BindGroupEntry {
                binding: i as u32,
                resource: b.as_entire_binding(),
            })
            .collect();
            let bind = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("visibility"),
                layout: &self.layout,
                entries: &entries,
            });
            {
                let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("visibility"),
                    timestamp_writes: None,
                });
                pass.set_pipeline(&self.pipeline);
                pass.set_bind_group(0, &bind, &[]);
                pass.dispatch_workgroups(groups_x as u32, groups_y as u32, 1);
            }
        }
        encoder.copy_buffer_to_buffer(&b_flags, 0, &b_read, 0, out_bytes);
        let words_read: Vec<u32> = super::depth_gpu::submit_and_map(
            &self.device,
            &self.queue,
            encoder,
            &b_read,
            <[u32]>::to_vec,
        )
        .map_err(|e| self.failed(format!("reading flags back: {e}")))?;
        let bits = words_read
            .chunks(words)
            .map(|w| {
                StrataBits(
                    w.chunks(2)
                        .map(|p| p[0] as u64 | (p.get(1).copied().unwrap_or(0) as u64) << 32)
                        .collect(),
                )
            })
            .collect();
        Ok(bits)
    }

    fn depth_maps(&self) -> &dyn super::depth::DepthMaps {
        &self.depth
    }
}

/// The visibility implementation for `choice`. `auto` takes a hardware
/// adapter and otherwise falls back to the CPU with one line on stderr saying why; `gpu`
/// takes any adapter, software ones included, and fails when there is none.
pub fn choose(choice: VisibilityChoice) -> Result<Box<dyn Visibility>, Error> {
    match choice {
        VisibilityChoice::Cpu => Ok(Box::new(CpuVisibility)),
        VisibilityChoice::Gpu => Ok(Box::new(GpuVisibility::new()?)),
        VisibilityChoice::Auto => match GpuVisibility::new() {
            Ok(g) if is_hardware(g.adapter()) => Ok(Box::new(g)),
            Ok(g) => {
                log_once(&format!(
                    "the only adapter, {}, is a software one and slower than the CPU \
                     implementation (--visibility gpu uses it)",
                    g.adapter().name
                ));
                Ok(Box::new(CpuVisibility))
            }
            Err(e) => {
                log_once(&e.to_string());
                Ok(Box::new(CpuVisibility))
            }
        },
    }
}

/// The fallback line, once per process (`compare` opens a session per variant).
fn log_once(why: &str) {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| eprintln!("anchorage: visibility on the CPU: {why}"));
}

/// Opens an adapter for a test (public for the integration tests, not for users). Without one the test is skipped with a line saying why,
/// unless `ANCHORAGE_REQUIRE_GPU` is set (CI sets it: there, no adapter is a failure).
#[doc(hidden)]
pub fn adapter_for_tests() -> Option<GpuVisibility> {
    match GpuVisibility::new() {
        Ok(g) => Some(g),
        Err(e) if std::env::var_os("ANCHORAGE_REQUIRE_GPU").is_some() => {
            panic!("ANCHORAGE_REQUIRE_GPU is set but no adapter opened: {e}")
        }
        Err(e) => {
            eprintln!("skipped: no GPU adapter ({e})");
            None
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::CpuVisibility;
    use super::super::testing::{assert_conservative, random_scene};
    use super::*;

    /// On random dynamic triangles the GPU flags every stratum the CPU flags, is itself
    /// conservative, and flags at most 1 % more (cells whose caps graze within the slack).
    #[test]
    fn gpu_flags_a_bounded_superset_of_the_cpu() {
        let Some(gpu) = adapter_for_tests() else {
            return;
        };
        eprintln!("adapter: {}", gpu.name());
        for (seed, strata) in [
            (1, [8u32, 24u32]),
            (2, [12, 36]),
            (3, [4, 8]),
            (5, [30, 60]),
        ] {
            let (g, records) = random_scene(seed, 4, 6, 24);
            let set = DynamicSet::new(&g);
            let cpu = CpuVisibility.flag(&records, strata, &set).unwrap();
            let gpu_flags = gpu.flag(&records, strata, &set).unwrap();
            for (i, (c, g)) in cpu.iter().zip(&gpu_flags).enumerate() {
                assert!(
                    g.contains(c),
                    "record {i}: the GPU misses strata the CPU flags"
                );
            }
            let (nc, ng): (usize, usize) = (
                cpu.iter().map(StrataBits::count).sum(),
                gpu_flags.iter().map(StrataBits::count).sum(),
            );
            assert!(nc > 0);
            eprintln!("strata {strata:?}: GPU {ng}, CPU {nc}");
            assert!(ng * 100 <= nc * 101, "GPU {ng} vs CPU {nc} strata");
            if strata[0] * strata[1] <= 432 {
                assert!(assert_conservative(&g, &records, strata, &gpu_flags) > 100);
            }
        }
    }
}
