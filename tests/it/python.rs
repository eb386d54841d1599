//! Checks by independent tools, in Python: the EXR read back with the OpenEXR bindings, and
//! the USD path (usd-core authors a stage, usd2gltf converts it, anchorage renders it and
//! matches USD's own world transforms).

use std::process::Command;

use glam::Mat4;

use super::common::*;
use anchorage::geom::Motion;

#[test]
fn exr_channels_and_values_read_back_with_openexr() {
    let Some(py) = python() else { return };
    let dir = tempdir();
    let job = example_job();
    let out = run(&[
        "render",
        job.to_str().unwrap(),
        "--frames",
        "7",
        "--out",
        dir.path().to_str().unwrap(),
        "--quiet",
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let exr = dir.path().join("room.0007.exr");
    let o = Command::new(py)
        .arg(root().join("tests/python/read_exr.py"))
        .arg(&exr)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(v["parts"], 1, "single-part file");
    let mut names: Vec<&str> = v["channels"]
        .as_object()
        .unwrap()
        .keys()
        .map(String::as_str)
        .collect();
    names.sort();
    assert_eq!(
        names,
        [
            "A",
            "B",
            "G",
            "R",
            "Z",
            "anchor_id.V",
            "diffuse_direct.B",
            "diffuse_direct.G",
            "diffuse_direct.R",
            "diffuse_indirect.B",
            "diffuse_indirect.G",
            "diffuse_indirect.R",
            "direct.B",
            "direct.G",
            "direct.R",
            "glossy_direct.B",
            "glossy_direct.G",
            "glossy_direct.R",
            "glossy_indirect.B",
            "glossy_indirect.G",
            "glossy_indirect.R",
            "indirect.B",
            "indirect.G",
            "indirect.R",
            "reshoot.V"
        ]
    );
    // Values equal an in-memory render of the same frame, bit for bit.
    let j = anchorage::job::Job::load(&job, &Default::default()).unwrap();
    let img = render(&j, 7);
    let ch = |n: &str| {
        v["channels"][n]["pixels"]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap() as f32)
            .collect::<Vec<f32>>()
    };
    assert_eq!(
        v["channels"]["R"]["shape"],
        serde_json::json!([j.height, j.width])
    );
    assert_eq!(v["channels"]["R"]["type"], "float32");
    let (r, a, dg, z) = (ch("R"), ch("A"), ch("direct.G"), ch("Z"));
    for i in 0..img.beauty.len() {
        assert_eq!(r[i], img.beauty[i][0], "R at {i}");
        assert_eq!(a[i], img.beauty[i][3], "A at {i}");
        assert_eq!(dg[i], img.direct[i][1], "direct.G at {i}");
        assert_eq!(z[i], img.depth[i], "Z at {i}");
    }
    // The lobes' layers hold the in-memory AOVs and sum to direct and indirect.
    for (name, aov) in [
        ("diffuse_direct", &img.diffuse_direct),
        ("glossy_direct", &img.glossy_direct),
        ("diffuse_indirect", &img.diffuse_indirect),
        ("glossy_indirect", &img.glossy_indirect),
    ] {
        for (c, suffix) in ["R", "G", "B"].iter().enumerate() {
            let plane = ch(&format!("{name}.{suffix}"));
            for i in 0..plane.len() {
                assert_eq!(plane[i], aov[i][c], "{name}.{suffix} at {i}");
            }
        }
    }
    for i in 0..img.beauty.len() {
        for c in 0..3 {
            let d = img.diffuse_direct[i][c] + img.glossy_direct[i][c];
            let n = img.diffuse_indirect[i][c] + img.glossy_indirect[i][c];
            assert!((d - img.direct[i][c]).abs() <= 1e-6 * img.direct[i][c].abs().max(1e-6));
            assert!((n - img.indirect[i][c]).abs() <= 1e-6 * img.indirect[i][c].abs().max(1e-6));
        }
    }
    assert!(r.iter().any(|&x| x > 0.0));
    // anchor_id is a 32-bit unsigned channel: exact integers, as many anchors as there are.
    assert_eq!(v["channels"]["anchor_id.V"]["type"], "uint32");
    let ids = ch("anchor_id.V");
    let mine = img.anchor_id.as_ref().unwrap();
    for i in 0..ids.len() {
        assert_eq!(ids[i] as u32, mine[i], "anchor_id at {i}");
    }
    assert!(mine.iter().any(|&id| id > 0));
    assert_eq!(ch("reshoot.V"), *img.reshoot.as_ref().unwrap());
}

/// Blender's compositor lists every AOV as a layer (a bare channel name such as
/// `anchor_id` is dropped there; `anchor_id.V` shows).
#[test]
fn blender_compositor_lists_every_aov() {
    let Some(blender) = blender() else { return };
    let dir = tempdir();
    let out = run(&[
        "render",
        example_job().to_str().unwrap(),
        "--frames",
        "3",
        "--out",
        dir.path().to_str().unwrap(),
        "--quiet",
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let o = Command::new(blender)
        .args(["-b", "--factory-startup", "--python"])
        .arg(root().join("tests/blender/list_layers.py"))
        .arg("--")
        .arg(dir.path().join("room.0003.exr"))
        .current_dir(dir.path())
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&o.stdout);
    let line = text
        .lines()
        .find_map(|l| l.strip_prefix("ANCHORAGE:"))
        .unwrap_or_else(|| panic!("no result from Blender: {text}{}", stderr(&o)));
    let v: serde_json::Value = serde_json::from_str(line).unwrap();
    assert_eq!(v["type"], "MULTILAYER");
    let mut outputs: Vec<&str> = v["outputs"]
        .as_array()
        .unwrap()
        .iter()
        .map(|o| o.as_str().unwrap())
        .collect();
    outputs.sort();
    assert_eq!(
        outputs,
        [
            "Alpha",
            "Combined",
            "Depth",
            "anchor_id",
            "diffuse_direct",
            "diffuse_indirect",
            "direct",
            "glossy_direct",
            "glossy_indirect",
            "indirect",
            "reshoot"
        ]
    );
}

#[test]
fn usd_stage_through_usd2gltf_matches_usd_transforms_and_renders() {
    let Some(py) = python() else { return };
    let dir = tempdir();
    let o = Command::new(&py)
        .arg(root().join("tests/python/usd_stage.py"))
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let job_path = dir.path().join("job.json");
    std::fs::write(
        &job_path,
        r#"{"scene":[{"path":"stage.gltf"}],"camera":{"position":[0,3,9],"look_at":[0,0.5,0],"yfov_deg":45},
        "resolution":[64,48],"frames":{"start":1,"end":24},"fps":24,"render":{"samples_per_pixel":2},
        "output":{"directory":"out","name":"stage"}}"#,
    )
    .unwrap();
    let job = anchorage::job::Job::load(&job_path, &Default::default()).unwrap();
    let scene = job.load_scene().unwrap();
    let layer = &scene.layers[0];
    let node = |n: &str| {
        layer
            .nodes
            .iter()
            .position(|x| x.name == n)
            .unwrap_or_else(|| panic!("node {n}"))
    };
    // Tags authored as USD attributes gltf:motion arrive as node extras and inherit.
    assert_eq!(layer.nodes[node("Ground")].motion, Motion::Static);
    assert_eq!(layer.nodes[node("Mover")].motion, Motion::Dynamic);
    assert_eq!(layer.nodes[node("Box")].motion, Motion::Dynamic);
    assert_eq!(layer.nodes[node("Tip")].motion, Motion::Dynamic);
    // World transforms equal USD's XformCache at every sampled frame (USD matrices are
    // row-major for row vectors: read as columns they are the column-vector matrix).
    let x: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("xforms.json")).unwrap()).unwrap();
    let frames: Vec<i32> = x["frames"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| f.as_i64().unwrap() as i32)
        .collect();
    let mut compared = 0;
    for (fi, &f) in frames.iter().enumerate() {
        let world = layer.world_matrices(job.time_of(f));
        for (name, mats) in x["prims"].as_object().unwrap() {
            let usd: Vec<f32> = mats[fi]
                .as_array()
                .unwrap()
                .iter()
                .map(|v| v.as_f64().unwrap() as f32)
                .collect();
            let want = Mat4::from_cols_slice(&usd);
            let got = world[node(name)];
            let scale = want
                .to_cols_array()
                .iter()
                .fold(0.0f32, |m, v| m.max(v.abs()));
            for (g, w) in got.to_cols_array().iter().zip(want.to_cols_array()) {
                assert!(
                    (g - w).abs() <= 1e-5 * scale,
                    "{name} at frame {f}: {got} vs USD {want}"
                );
            }
            compared += 1;
        }
    }
    assert_eq!(compared, 30);
    // And it renders.
    let out = run(&[
        "render",
        job_path.to_str().unwrap(),
        "--frames",
        "1-2",
        "--quiet",
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert!(dir.path().join("out/stage.0002.exr").is_file());
}
