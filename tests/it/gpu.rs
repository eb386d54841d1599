//! Visibility on the GPU against the CPU implementation, on the example animation. Without
//! an adapter these tests say they were skipped, unless `ANCHORAGE_REQUIRE_GPU` is set (as
//! `.ci/run` does, with Mesa's software Vulkan driver): then they fail.

use super::anchors::{example, render_sequence};
use anchorage::geom::Motion;
use anchorage::job::VisibilityChoice;
use anchorage::pipeline;
use anchorage::session::FrameState;
use anchorage::visibility::gpu::adapter_for_tests;
use anchorage::visibility::{CpuVisibility, DynamicSet, StrataBits, Visibility};

/// The records of the example after a few frames, against the sliding cube at several
/// times: the GPU flags every stratum the CPU flags, and at most 1 % more.
#[test]
fn gpu_and_cpu_flag_the_same_strata_on_the_example() {
    let Some(gpu) = adapter_for_tests() else {
        return;
    };
    let job = example("anchors", r#","strata":[12,36]"#);
    let scene = job.load_scene().unwrap();
    let resources = pipeline::new_resources(&job, &scene).unwrap();
    let mut state = FrameState::default();
    for f in 0..3 {
        let mut stats = pipeline::new_stats(&job, f);
        pipeline::render_frame(&job, &scene, &resources, &mut state, f, &mut stats).unwrap();
    }
    let records: Vec<_> = state
        .cache
        .records
        .iter()
        .filter(|r| r.motion == Motion::Static)
        .map(|r| (r.position, r.normal))
        .collect();
    assert!(records.len() > 50, "{} records", records.len());
    let (mut nc, mut ng) = (0, 0);
    for f in [0, 12, 24, 36, 48] {
        let set = DynamicSet::new(&scene.geometry(job.time_of(f), Motion::Dynamic));
        assert!(!set.is_empty());
        let cpu = CpuVisibility.flag(&records, [12, 36], &set).unwrap();
        let g = gpu.flag(&records, [12, 36], &set).unwrap();
        for (i, (c, g)) in cpu.iter().zip(&g).enumerate() {
            assert!(
                g.contains(c),
                "frame {f}, record {i}: the GPU misses CPU strata"
            );
        }
        nc += cpu.iter().map(StrataBits::count).sum::<usize>();
        ng += g.iter().map(StrataBits::count).sum::<usize>();
    }
    eprintln!("strata flagged: CPU {nc}, GPU {ng}");
    assert!(nc > 0);
    assert!(ng * 100 <= nc * 101, "GPU {ng} vs CPU {nc}");
}

/// Frames rendered with `--visibility gpu` and `cpu` are the same, the `reshoot` AOV
/// included: the GPU flags a superset of the CPU's strata, but a flagged stratum is re-shot
/// only where its own ray meets a dynamic prim, and the CPU flags every such stratum.
#[test]
fn gpu_and_cpu_visibility_render_the_same_frames() {
    if adapter_for_tests().is_none() {
        return;
    }
    let on = |v| {
        let mut job = example("anchors", "");
        job.render.visibility = v;
        render_sequence(&job, 0..6)
    };
    let cpu = on(VisibilityChoice::Cpu);
    let gpu = on(VisibilityChoice::Gpu);
    for ((ic, sc), (ig, sg)) in cpu.iter().zip(&gpu) {
        assert_eq!(ic.beauty, ig.beauty, "frame {}", sc.frame);
        assert_eq!(ic.direct, ig.direct);
        assert_eq!(ic.indirect, ig.indirect);
        assert_eq!(ic.anchor_id, ig.anchor_id);
        assert_eq!(sc.counts.anchors, sg.counts.anchors);
        assert_eq!(ic.reshoot, ig.reshoot);
        assert_eq!(sc.counts.rays_reshot, sg.counts.rays_reshot);
        assert!(sg.counts.strata_flagged >= sc.counts.strata_flagged);
    }
}
