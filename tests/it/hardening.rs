//! Hostile and unlucky conditions: signals mid-render, planted symlinks, a full disk, limits
//! on memory, threads, frames, names and file sizes. Whatever happens, no file outside the
//! outputs changes, a frame is its EXR and its stats or nothing, and the exit code says why.

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use super::common::*;

/// Files in `dir` by name.
fn names(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .map(|r| {
            r.map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
                .collect()
        })
        .unwrap_or_default();
    v.sort();
    v
}

/// Every EXR has its stats and nothing else is left: no temporary file, no lone stats.
fn assert_whole_frames(dir: &Path) {
    let all = names(dir);
    for n in &all {
        assert!(!n.starts_with('.'), "temporary file left: {n} in {all:?}");
        if let Some(stem) = n.strip_suffix(".exr") {
            assert!(
                all.contains(&format!("{stem}.json")),
                "{n} without stats: {all:?}"
            );
        }
    }
}

/// A child render killed with SIGTERM (or SIGINT) at different moments removes its temporary
/// files and exits 143 (130); the frames it finished are whole.
#[test]
fn interrupted_renders_leave_whole_frames_and_no_temporary_files() {
    let dir = tempdir();
    let job = example_job();
    let mut finished = 0;
    for (i, delay_ms) in [300u64, 900, 1500, 2500, 4000, 6000]
        .into_iter()
        .enumerate()
    {
        let out = dir.path().join(format!("out{i}"));
        let sig = if i % 2 == 0 { "TERM" } else { "INT" };
        let mut child = Command::new(env!("CARGO_BIN_EXE_anchorage"))
            .args([
                "render",
                job.to_str().unwrap(),
                "--frames",
                "0-3",
                "--preview",
                "--quiet",
            ])
            .arg("--out")
            .arg(&out)
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        std::thread::sleep(Duration::from_millis(delay_ms));
        let _ = Command::new("kill")
            .args([&format!("-{sig}"), &child.id().to_string()])
            .status();
        let t = Instant::now();
        let status = child.wait().unwrap();
        assert!(
            t.elapsed() < Duration::from_secs(10),
            "the render ignored SIG{sig}"
        );
        let code = status.code();
        if code == Some(0) {
            finished += 1;
        } else {
            let want = if sig == "TERM" { 143 } else { 130 };
            assert_eq!(code, Some(want), "SIG{sig} after {delay_ms} ms");
        }
        assert_whole_frames(&out);
    }
    assert!(finished < 6, "every render finished before its signal");
}

/// Symlinks planted in a shared output directory, at the final names and at the temporary
/// names older versions used, redirect nothing: the files they point to are unchanged and
/// the outputs are regular files of this render (reproducer S1).
#[cfg(unix)]
#[test]
fn planted_symlinks_redirect_no_writes() {
    let dir = tempdir();
    let out = dir.path().join("shared");
    std::fs::create_dir(&out).unwrap();
    let victim = dir.path().join("victim.txt");
    std::fs::write(&victim, "precious\n").unwrap();
    let pid_guess = std::process::id();
    let mut planted = vec!["room.0000.exr".to_string(), "room.0000.json".to_string()];
    for pid in pid_guess..pid_guess + 200 {
        planted.push(format!(".anchorage-probe-{pid}"));
        planted.push(format!(".room.0000.exr.tmp-{pid}"));
        planted.push(format!(".room.0000.json.tmp-{pid}"));
    }
    for n in &planted {
        std::os::unix::fs::symlink(&victim, out.join(n)).unwrap();
    }
    let o = run(&[
        "render",
        example_job().to_str().unwrap(),
        "--frames",
        "0",
        "--out",
        out.to_str().unwrap(),
        "--quiet",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(std::fs::read_to_string(&victim).unwrap(), "precious\n");
    for n in ["room.0000.exr", "room.0000.json"] {
        let meta = std::fs::symlink_metadata(out.join(n)).unwrap();
        assert!(
            meta.is_file(),
            "{n} is a regular file, not the planted link"
        );
    }
}

/// A disk that fills up mid-frame: the render fails with exit 1 and leaves no EXR without
/// its stats and no temporary file. Needs a small tmpfs, so root (CI); skipped otherwise.
#[cfg(target_os = "linux")]
#[test]
fn a_full_disk_leaves_no_partial_frame() {
    let dir = tempdir();
    let mnt = dir.path().join("small");
    std::fs::create_dir(&mnt).unwrap();
    // The example's EXR is about 2 MB: 1 MB holds its stats but not its image.
    let mounted = Command::new("mount")
        .args(["-t", "tmpfs", "-o", "size=1m", "tmpfs"])
        .arg(&mnt)
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success());
    if !mounted {
        eprintln!("skipped: cannot mount a tmpfs (needs root)");
        return;
    }
    let o = run(&[
        "render",
        example_job().to_str().unwrap(),
        "--frames",
        "0",
        "--out",
        mnt.to_str().unwrap(),
        "--quiet",
    ]);
    let left = names(&mnt);
    let _ = Command::new("umount").arg(&mnt).status();
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert!(stderr(&o).contains("room.0000"), "{}", stderr(&o));
    assert!(left.is_empty(), "left on the full disk: {left:?}");
}

/// Limits that stop a job before it starts, with exit 2 and the reason: memory over the
/// limit, a frame range beyond reason, an absurd thread count, names that cannot be files,
/// something that is not a job file.
#[test]
fn limits_refuse_jobs_before_they_start() {
    let dir = tempdir();
    let room = root().join("examples/room/room.gltf");
    // `name` is the JSON of `output.name`, or empty.
    let job_named = |name: &str, extra: &str| {
        let p = dir.path().join("job.json");
        std::fs::write(
            &p,
            format!(
                r#"{{"scene":[{{"path":"{}"}}],"output":{{"directory":"out"{name}}}{extra}}}"#,
                room.display()
            ),
        )
        .unwrap();
        p.to_str().unwrap().to_string()
    };
    let job = |extra: &str| job_named("", extra);
    let refused = |args: &[&str], needle: &str| {
        let o = run(args);
        let e = stderr(&o);
        assert_eq!(o.status.code(), Some(2), "{args:?}: {e}");
        assert!(e.contains(needle), "{args:?}: {e}");
        assert!(!dir.path().join("out").exists(), "{args:?} wrote output");
    };
    let j = job("");
    refused(&["render", &j, "--memory-limit", "1M"], "--memory-limit");
    refused(&["render", &j, "--memory-limit", "lots"], "--memory-limit");
    refused(&["render", &j, "--threads", "1000000"], "--threads");
    refused(
        &["validate", &job(r#","resolution":[16384,16384]"#)],
        "the render needs about",
    );
    let full = format!(r#","frames":{{"start":{},"end":{}}}"#, i32::MIN, i32::MAX);
    refused(&["validate", &job(&full)], "frames");
    let long = format!(r#","name":"{}""#, "n".repeat(300));
    refused(&["validate", &job_named(&long, "")], "output.name");
    refused(
        &["validate", &job_named(r#","name":"a\u0000b""#, "")],
        "output.name",
    );
    refused(&["validate", "/dev/zero"], "not a regular file");
    let j = job("");
    refused(&["render", &j, "--warmup", "100001"], "--warmup");
    refused(
        &["farm", &j, "--chunk-size", "4", "--warmup", "4000000000"],
        "--warmup",
    );
    refused(
        &[
            "farm",
            &j,
            "--chunk-size",
            "4",
            "--measure-warmup",
            "1,100001",
        ],
        "--measure-warmup",
    );
    // A farm template written over the job file or a scene file it reads, by any name.
    let link = dir.path().join("link.json");
    std::os::unix::fs::symlink(&j, &link).unwrap();
    let before = std::fs::read(&j).unwrap();
    for over in [j.as_str(), link.to_str().unwrap(), room.to_str().unwrap()] {
        refused(&["farm", &j, "--chunk-size", "4", "-o", over], "--template");
    }
    assert_eq!(std::fs::read(&j).unwrap(), before, "the job file changed");
}

/// A FIFO where a regular file belongs (the job, a scene, a checkpoint to resume from) is
/// refused at once with exit 2: opening one to read would wait for a writer forever.
#[test]
fn fifos_are_refused_without_waiting_for_a_writer() {
    let dir = tempdir();
    let fifo = |name: &str| {
        let p = dir.path().join(name);
        let ok = Command::new("mkfifo").arg(&p).status().unwrap().success();
        assert!(ok, "mkfifo {}", p.display());
        p.to_str().unwrap().to_string()
    };
    let job_with = |name: &str, scene: &str| {
        let p = dir.path().join(name);
        std::fs::write(
            &p,
            format!(r#"{{"scene":[{{"path":"{scene}"}}],"output":{{"directory":"out"}}}}"#),
        )
        .unwrap();
        p.to_str().unwrap().to_string()
    };
    let room = root().join("examples/room/room.gltf");
    let job = job_with("job.json", room.to_str().unwrap());
    let fifo_job = fifo("fifo.json");
    let fifo_scene = fifo("scene.gltf");
    let on_fifo_scene = job_with("fifo_scene.json", &fifo_scene);
    let fifo_state = fifo("room.0000.state");
    // A glTF whose external buffer is a FIFO.
    let with_fifo_buffer = dir.path().join("buffer.gltf");
    std::fs::write(
        &with_fifo_buffer,
        r#"{"asset":{"version":"2.0"},"buffers":[{"byteLength":4,"uri":"b.bin"}]}"#,
    )
    .unwrap();
    fifo("b.bin");
    let with_fifo_buffer = with_fifo_buffer.to_str().unwrap().to_string();
    for args in [
        vec!["validate", fifo_job.as_str()],
        vec!["inspect", fifo_scene.as_str()],
        vec!["validate", on_fifo_scene.as_str()],
        vec!["inspect", with_fifo_buffer.as_str()],
        vec!["render", &job, "--frames", "1", "--resume", &fifo_state],
    ] {
        let mut child = bin()
            .args(&args)
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        let start = Instant::now();
        let status = loop {
            if let Some(s) = child.try_wait().unwrap() {
                break s;
            }
            if start.elapsed() > Duration::from_secs(60) {
                child.kill().unwrap();
                panic!("{args:?} still waits after a minute");
            }
            std::thread::sleep(Duration::from_millis(20));
        };
        let mut err = String::new();
        std::io::Read::read_to_string(&mut child.stderr.take().unwrap(), &mut err).unwrap();
        assert_eq!(status.code(), Some(2), "{args:?}: {err}");
        assert!(err.contains("not a regular file"), "{args:?}: {err}");
        assert!(!dir.path().join("out").exists(), "{args:?} wrote output");
    }
}

/// While a batch of new records is gathered, a render holds the strata and radiance the
/// batch resolves and the hits of one part of it (`cache::gather::PART_HITS`; before, the
/// whole batch's hits, 112 bytes each: 1.65 GB in one batch of Sponza's first frame at the
/// final preset, five times the estimate then): the memory estimate counts both, and the
/// part's share stays the same at any resolution. Brute force keeps every stratum's
/// radiance; `anchors` keeps a batch's strata alone (6 bytes each, their radiance read from
/// their anchors as the records are made) and holds the shares of its search beside a part.
#[test]
fn gathering_counts_in_the_memory_estimate() {
    let estimate = |method: &str, resolution: &str| {
        let job = job_from_json(
            &example_job(),
            &format!(
                r#"{{"scene":[{{"path":"room.gltf"}}],"resolution":{resolution},
                "frames":{{"start":0,"end":4}},"method":{{"name":"{method}","preset":"final"}}}}"#
            ),
        )
        .unwrap();
        let scene = job.load_scene().unwrap();
        anchorage::budget::Estimate::of(&job, &scene, false)
    };
    let hits = anchorage::cache::gather::PART_HITS as u64;
    let hit = size_of::<anchorage::cache::GatherHit>() as u64;
    let search = 2 * anchorage::anchor::attach::SHARE_BYTES as u64;
    // The cache counts 10 bytes a stratum; brute force's batch 18 more for its resolved
    // strata, then one part's hits and what resolving them holds.
    let part = |e: &anchorage::budget::Estimate| e.gather.saturating_sub(e.cache / 10 * 18);
    let [hd, uhd] = ["[1920,1080]", "[3840,2160]"].map(|r| estimate("brute-force", r));
    for e in [&hd, &uhd] {
        assert!(e.gather >= e.cache / 10 * 18, "the resolved strata: {e:?}");
        assert!(
            part(e) >= hits * hit && part(e) <= hits * (hit + 32),
            "one part's hits: {e:?}"
        );
    }
    assert_eq!(part(&hd), part(&uhd), "the part at twice the resolution");
    // `anchors` holds 12 bytes a stratum less (no radiance) and its search's shares more.
    for (resolution, brute) in [("[1920,1080]", &hd), ("[3840,2160]", &uhd)] {
        let anchors = estimate("anchors", resolution);
        assert_eq!(anchors.cache, brute.cache);
        assert_eq!(
            anchors.gather + anchors.cache / 10 * 12,
            brute.gather + search,
            "anchors at {resolution}: {anchors:?} against {brute:?}"
        );
    }
    assert!(hit <= 92, "a gather hit takes {hit} bytes");
}

/// A render that writes or reads checkpoints needs memory for their buffers beside the
/// cache (a batch of chunks: a checkpoint is encoded and decoded as it streams, so the
/// buffers do not grow with the state): under a limit between the estimates without and
/// with them, the render alone starts, and with `--state-out` or `--resume` it is refused
/// before anything is written.
#[test]
fn checkpoints_count_in_the_memory_estimate() {
    let dir = tempdir();
    let src = example_job();
    let job = anchorage::job::Job::load(&src, &Default::default()).unwrap();
    let scene = job.load_scene().unwrap();
    let plain = anchorage::budget::Estimate::of(&job, &scene, false);
    let with = anchorage::budget::Estimate::of(&job, &scene, true);
    assert_eq!(plain.checkpoint, 0);
    assert!(with.checkpoint >= 64 << 20, "{with:?}");
    let larger = job_from_json(
        &src,
        r#"{"scene":[{"path":"room.gltf"}],"resolution":[3840,2160],
        "frames":{"start":0,"end":4},"method":{"name":"anchors","preset":"final"}}"#,
    )
    .unwrap();
    let larger = anchorage::budget::Estimate::of(&larger, &larger.load_scene().unwrap(), true);
    assert!(larger.cache > 100 * with.cache, "{larger:?}");
    assert_eq!(
        larger.checkpoint, with.checkpoint,
        "the buffers of a larger state"
    );
    let limit = ((plain.total() + with.total()) / 2).to_string();
    let out = dir.path().join("out");
    let states = dir.path().join("states");
    let args = |extra: &[&str]| -> Vec<String> {
        let mut a: Vec<String> = ["render", src.to_str().unwrap(), "--frames", "0", "-q"]
            .iter()
            .map(|s| s.to_string())
            .collect();
        a.extend(["--memory-limit".into(), limit.clone()]);
        a.extend(["--out".into(), out.to_str().unwrap().into()]);
        a.extend(extra.iter().map(|s| s.to_string()));
        a
    };
    let run_with = |extra: &[&str]| {
        let a = args(extra);
        run(&a.iter().map(String::as_str).collect::<Vec<_>>())
    };
    let o = run_with(&["--state-out", states.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(stderr(&o).contains("checkpoints"), "{}", stderr(&o));
    assert!(
        !out.exists() && !states.exists(),
        "a refused render wrote output"
    );
    let o = run_with(&[]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(out.join("room.0000.exr").exists());
}

/// The Vulkan probe says nothing on machines without a desktop session beyond anchorage's
/// own line (render farms scrape logs for `error:`).
#[test]
fn the_gpu_probe_prints_no_error_lines() {
    let dir = tempdir();
    let o = Command::new(env!("CARGO_BIN_EXE_anchorage"))
        .args([
            "render",
            example_job().to_str().unwrap(),
            "--frames",
            "0",
            "--quiet",
        ])
        .arg("--out")
        .arg(dir.path())
        .env_remove("XDG_RUNTIME_DIR")
        .env_remove("WAYLAND_DISPLAY")
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let e = stderr(&o);
    assert!(!e.contains("error"), "{e}");
}

/// A job's camera that is wrong says which key is at fault: a look-at camera's missing or
/// unknown key, a node camera's stray key, a position too far away to subtract.
#[test]
fn a_job_camera_error_names_the_key() {
    let dir = tempdir();
    let room = root().join("examples/room/room.gltf");
    let job = |camera: &str| {
        let p = dir.path().join("job.json");
        std::fs::write(
            &p,
            format!(
                r#"{{"scene":[{{"path":"{}"}}],"camera":{camera},"output":{{"directory":"out"}}}}"#,
                room.display()
            ),
        )
        .unwrap();
        p.to_str().unwrap().to_string()
    };
    for (camera, needle) in [
        (
            r#"{"position":[0,1,5],"look_at":[0,1,0]}"#,
            "missing field `yfov_deg`",
        ),
        (
            r#"{"position":[0,1,5],"look_at":[0,1,0],"yfov_deg":40,"fov":40}"#,
            "unknown field `fov`",
        ),
        (
            r#"{"node":"Camera","yfov_deg":40}"#,
            "unknown field `yfov_deg`",
        ),
        (
            r#"{"position":[1e300,1,5],"look_at":[0,1,0],"yfov_deg":40}"#,
            "camera.position",
        ),
    ] {
        let o = run(&["validate", &job(camera)]);
        let e = stderr(&o);
        assert_eq!(o.status.code(), Some(2), "{camera}: {e}");
        assert!(e.contains(needle), "{camera}: {e}");
    }
}

/// A job-file error says where once (serde's own "at line L column C" dropped), and of a job
/// written on one line shows the text around the column, not the whole line.
#[test]
fn a_job_file_error_shows_where_once_and_the_text_around_it() {
    let dir = tempdir();
    let p = dir.path().join("job.json");
    let pad = "x".repeat(500);
    std::fs::write(
        &p,
        format!(r#"{{"scene":[{{"path":"room.gltf"}}],"pad":"{pad}","resolution":[64,"x"]}}"#),
    )
    .unwrap();
    let o = run(&["validate", p.to_str().unwrap()]);
    let e = stderr(&o);
    assert_eq!(o.status.code(), Some(2), "{e}");
    assert!(
        e.contains("line 1, column ") && !e.contains(" at line "),
        "{e}"
    );
    assert!(e.contains("unknown field `pad`") && e.len() < 400, "{e}");
}

/// A frame rate so low that half a frame's seconds overflow f32 is refused: the check that
/// frames lie within the animation compared against an infinite slack and let any through.
#[test]
fn an_fps_too_low_for_f32_frame_times_is_refused() {
    let dir = tempdir();
    let p = dir.path().join("job.json");
    let room = root().join("examples/room/room.gltf");
    std::fs::write(
        &p,
        format!(
            r#"{{"scene":[{{"path":{:?}}}],"fps":1e-39}}"#,
            room.display().to_string()
        ),
    )
    .unwrap();
    let o = run(&["validate", p.to_str().unwrap()]);
    let e = stderr(&o);
    assert_eq!(o.status.code(), Some(2), "{e}");
    assert!(e.contains("fps") && e.contains("f32"), "{e}");
}

/// No output replaces an input: a job whose name is one of its own frames' stats, or a
/// `compare` job written where its table goes, is refused before anything renders. A
/// directory that cannot be made is found before any other is made, and `validate` makes
/// none.
#[test]
fn outputs_never_replace_inputs_and_refusals_make_no_directories() {
    let dir = tempdir();
    let d = dir.path();
    std::fs::copy(root().join("examples/room/room.gltf"), d.join("room.gltf")).unwrap();
    let write = |name: &str, extra: &str| {
        let p = d.join(name);
        std::fs::write(
            &p,
            format!(
                r#"{{"scene":[{{"path":"room.gltf"}}],"resolution":[16,12],"frames":{{"start":20,"end":20}},
                "method":{{"name":"direct"}}{extra}}}"#
            ),
        )
        .unwrap();
        (p.to_str().unwrap().to_string(), std::fs::read(&p).unwrap())
    };
    let (framed, before) = write(
        "room.0020.json",
        r#","output":{"directory":".","name":"room"}"#,
    );
    let o = run(&["render", &framed, "-q"]);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(
        stderr(&o).contains("a file this run reads"),
        "{}",
        stderr(&o)
    );
    assert_eq!(
        std::fs::read(&framed).unwrap(),
        before,
        "the job was replaced"
    );
    assert!(!d.join("room.0020.exr").exists());
    let (compare, before) = write("compare.json", "");
    let out = d.to_str().unwrap();
    let o = run(&[
        "compare",
        &compare,
        "--methods",
        "direct",
        "--reference",
        "direct",
        "--out",
        out,
    ]);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert_eq!(
        std::fs::read(&compare).unwrap(),
        before,
        "the job was replaced"
    );
    // A state directory that is a file: refused before the output directory is made.
    let (job, _) = write("job.json", r#","output":{"directory":"out/a"}"#);
    std::fs::write(d.join("afile"), "x").unwrap();
    let afile = d.join("afile");
    let o = run(&["render", &job, "-q", "--state-out", afile.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(
        !d.join("out").exists(),
        "a refused render made its output directory"
    );
    let o = run(&["validate", &job]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    assert!(
        !d.join("out").exists(),
        "validate made the output directory"
    );
}
