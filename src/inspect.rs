//! `anchorage inspect`: what a scene or job contains, in plain text — every prim with its
//! motion tag and why, lights, cameras, the animation's time range and warnings.

use std::fmt::Write;

use crate::job::Job;
use crate::scene::{LightKind, Projection, Scene};

/// A text report of `scene` as `job` composes it.
pub fn report(job: &Job, scene: &Scene) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "job: {}", job.path.display());
    for (li, layer) in scene.layers.iter().enumerate() {
        let _ = writeln!(s, "layer {li}: {}", layer.path.display());
        let _ = writeln!(s, "  prims:");
        for (i, n) in layer.nodes.iter().enumerate() {
            let Some(m) = n.mesh else { continue };
            let tris: usize = layer.meshes[m]
                .primitives
                .iter()
                .map(|p| p.indices.len() / 3)
                .sum();
            let motion = match n.motion {
                crate::geom::Motion::Static => "static",
                crate::geom::Motion::Dynamic => "dynamic",
            };
            let extra = match (
                n.skin.is_some(),
                layer.meshes[m]
                    .primitives
                    .iter()
                    .any(|p| !p.targets.is_empty()),
            ) {
                (true, true) => ", skinned, morph targets",
                (true, false) => ", skinned",
                (false, true) => ", morph targets",
                _ => "",
            };
            let _ = writeln!(
                s,
                "    nodes[{i}] {:<24} {motion:<8} {tris} triangles{extra}  ({})",
                layer.node_label(i),
                n.why
            );
        }
        let _ = writeln!(s, "  lights:");
        for (i, n) in layer.nodes.iter().enumerate() {
            let Some(l) = n.light else { continue };
            let light = &layer.lights[l];
            let (kind, unit) = match light.kind {
                LightKind::Point => ("point".to_string(), "cd"),
                LightKind::Spot { inner, outer } => (
                    format!(
                        "spot {:.1}°..{:.1}°",
                        inner.to_degrees(),
                        outer.to_degrees()
                    ),
                    "cd",
                ),
                LightKind::Directional => ("directional".to_string(), "lx"),
            };
            let _ = writeln!(
                s,
                "    nodes[{i}] {} {kind}, {} {unit}, colour {:?}",
                layer.node_label(i),
                light.intensity,
                light.color.to_array()
            );
        }
        let emissive: usize = layer
            .nodes
            .iter()
            .filter_map(|n| n.mesh)
            .flat_map(|m| &layer.meshes[m].primitives)
            .filter(|p| scene.materials[p.material].is_emissive())
            .map(|p| p.indices.len() / 3)
            .sum();
        if emissive > 0 {
            let _ = writeln!(s, "    {emissive} emissive triangles");
        }
        let _ = writeln!(s, "  cameras:");
        for (i, n) in layer.nodes.iter().enumerate() {
            let Some(c) = n.camera else { continue };
            let p = match layer.cameras[c].projection {
                Projection::Perspective { yfov } => {
                    format!("perspective, yfov {:.2}°", yfov.to_degrees())
                }
                Projection::Orthographic { ymag } => format!("orthographic, ymag {ymag}"),
            };
            let _ = writeln!(s, "    nodes[{i}] {} {p}", layer.node_label(i));
        }
        for a in &layer.animations {
            let (t0, t1) = a
                .channels
                .iter()
                .map(|c| c.sampler.range())
                .reduce(|a, b| (a.0.min(b.0), a.1.max(b.1)))
                .unwrap_or((0.0, 0.0));
            let _ = writeln!(
                s,
                "  animation \"{}\": {} channels, t = {t0:.4}..{t1:.4} s",
                a.name,
                a.channels.len()
            );
        }
    }
    match scene.time_range() {
        Some((t0, t1)) => {
            let _ = writeln!(
                s,
                "time range: {t0:.4}..{t1:.4} s = frames {:.0}..{:.0} at {} fps (frame_offset {})",
                job.frames_in(t0, t1).0,
                job.frames_in(t0, t1).1,
                job.fps,
                job.frame_offset
            );
        }
        None => {
            let _ = writeln!(s, "time range: not animated");
        }
    }
    let _ = writeln!(
        s,
        "camera: {}",
        match &scene.camera {
            Some(crate::scene::CameraChoice::Node { layer, node }) =>
                format!("layer {layer} {}", scene.layers[*layer].node_label(*node)),
            Some(crate::scene::CameraChoice::LookAt(_)) => "from the job file".into(),
            None => "none (a render needs one)".into(),
        }
    );
    let warnings = scene.warnings();
    let _ = writeln!(
        s,
        "warnings: {}",
        if warnings.is_empty() { "none" } else { "" }
    );
    for w in warnings {
        let _ = writeln!(s, "  {w}");
    }
    s
}
