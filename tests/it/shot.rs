//! Shot state on disk: checkpoints (`render --state-out/--resume`), warm-up chunks
//! (`--warmup`), and what refuses a checkpoint.

use std::path::{Path, PathBuf};

use super::common::{root, run, stderr, tempdir};

/// `dir/job.json` rendering `dir/room.gltf` (a copy of the example room) at 48×36 with the
/// anchor method at the draft preset; `extra` is spliced into the job's JSON object.
fn room_job(dir: &Path, extra: &str) -> PathBuf {
    std::fs::copy(
        root().join("examples/room/room.gltf"),
        dir.join("room.gltf"),
    )
    .unwrap();
    let job = dir.join("job.json");
    std::fs::write(
        &job,
        format!(
            r#"{{"scene":[{{"path":"room.gltf"}}],"resolution":[48,36],"frames":{{"start":0,"end":48}},
            "render":{{"samples_per_pixel":2}},"method":{{"name":"anchors","preset":"draft"}},"output":{{"name":"room"}}{extra}}}"#
        ),
    )
    .unwrap();
    job
}

fn render(job: &Path, frames: &str, out: &Path, extra: &[&str]) -> std::process::Output {
    let mut args = vec![
        "render",
        job.to_str().unwrap(),
        "--frames",
        frames,
        "--out",
        out.to_str().unwrap(),
        "--quiet",
    ];
    args.extend_from_slice(extra);
    run(&args)
}

fn exr(dir: &Path, frame: i32) -> Vec<u8> {
    let p = dir.join(format!("room.{frame:04}.exr"));
    std::fs::read(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

fn files_in(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .map(|d| {
            d.map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
                .collect()
        })
        .unwrap_or_default();
    v.sort();
    v
}

/// Renders frames 0–`last` of `job` into `full`, keeping the state after every second frame
/// in `states`, then frames 2–`last` into `resumed` from the state after frame 1, and asserts
/// that each resumed frame is the full run's, byte for byte.
fn resume_reproduces(job: &Path, last: i32, full: &Path, states: &Path, resumed: &Path) {
    let state_args = [
        "--state-out",
        states.to_str().unwrap(),
        "--state-every",
        "2",
    ];
    let o = render(job, &format!("0-{last}"), full, &state_args);
    assert!(o.status.success(), "{}", stderr(&o));
    let from = states.join("room.0001.state");
    let o = render(
        job,
        &format!("2-{last}"),
        resumed,
        &["--resume", from.to_str().unwrap()],
    );
    assert!(o.status.success(), "{}", stderr(&o));
    for f in 2..=last {
        assert!(
            exr(full, f) == exr(resumed, f),
            "resumed frame {f} differs from the full run's"
        );
    }
}

/// Frames 3–5 resumed from the state after frame 2 are byte for byte frames 3–5 of a run
/// through 0–5 (the cache, the anchors and their photon links all come back), and a chunk
/// whose warm-up reaches back to the animation's start is too.
#[test]
fn resume_and_a_full_warm_up_reproduce_a_full_run() {
    let d = tempdir();
    let job = room_job(d.path(), "");
    let (full, states, resumed, warm) = (
        d.path().join("full"),
        d.path().join("states"),
        d.path().join("resumed"),
        d.path().join("warm"),
    );
    resume_reproduces(&job, 5, &full, &states, &resumed);
    // After every second frame of the range, and after its last.
    assert_eq!(
        files_in(&states),
        ["room.0001.state", "room.0003.state", "room.0005.state"]
    );
    // 100 frames of warm-up stop at the animation's first frame, 0: the same run again.
    let o = render(&job, "4-5", &warm, &["--warmup", "100"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(
        files_in(&warm)
            .iter()
            .filter(|f| f.ends_with(".exr"))
            .count(),
        2,
        "warm-up frames are not written: {:?}",
        files_in(&warm)
    );
    for f in 4..=5 {
        assert!(
            exr(&full, f) == exr(&warm, f),
            "warmed-up frame {f} differs from the full run's"
        );
    }
    // Without the state the chunk's first frame differs (the test can tell).
    let cold = d.path().join("cold");
    let o = render(&job, "2-2", &cold, &[]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(exr(&full, 2) != exr(&cold, 2));
}

/// A checkpoint of another job, of an edited scene, of another build, of the wrong frame, or
/// no checkpoint at all, is refused with exit code 2, a message naming the file and the
/// reason, and no frame written.
#[test]
fn a_foreign_checkpoint_is_refused() {
    let d = tempdir();
    let job = room_job(d.path(), "");
    let states = d.path().join("states");
    let o = render(
        &job,
        "0-1",
        &d.path().join("a"),
        &["--state-out", states.to_str().unwrap()],
    );
    assert!(o.status.success(), "{}", stderr(&o));
    let state = states.join("room.0001.state");
    let refused = |job: &Path, frames: &str, state: &Path, why: &str| {
        let out = d.path().join(format!("refused-{}", why.len()));
        let o = render(job, frames, &out, &["--resume", state.to_str().unwrap()]);
        let err = stderr(&o);
        assert_eq!(o.status.code(), Some(2), "{why}: {err}");
        assert!(
            err.contains(&state.display().to_string()),
            "{why}: names the file: {err}"
        );
        assert!(err.contains(why), "{why}: {err}");
        assert!(
            files_in(&out).iter().all(|f| !f.ends_with(".exr")),
            "{why}: nothing rendered"
        );
    };
    // Another job: another seed.
    let other = tempdir();
    let other_job = room_job(other.path(), r#","seed":7"#);
    refused(&other_job, "2-3", &state, "another job");
    // The same job with its scene edited (the lamp's emission).
    let gltf = d.path().join("room.gltf");
    let text = std::fs::read_to_string(&gltf).unwrap();
    let mut doc: serde_json::Value = serde_json::from_str(&text).unwrap();
    let lamp = &mut doc["materials"][4];
    assert_eq!(lamp["name"], "lamp");
    lamp["emissiveFactor"] = serde_json::json!([0.5, 0.5, 0.5]);
    std::fs::write(&gltf, doc.to_string()).unwrap();
    refused(&job, "2-3", &state, "another job");
    std::fs::write(&gltf, &text).unwrap();
    // The same job and version, written by another build (other sources).
    let bytes = std::fs::read(&state).unwrap();
    let (mut header, rest): (anchorage::checkpoint::Header, _) =
        postcard::take_from_bytes(&bytes[12..]).unwrap();
    assert_eq!(header.build, anchorage::checkpoint::BUILD);
    header.build = "feedc0ffee00".repeat(5) + "1234";
    let mut other = bytes[..12].to_vec();
    other.extend(postcard::to_stdvec(&header).unwrap());
    other.extend(rest);
    let foreign = d.path().join("other-build.state");
    std::fs::write(&foreign, &other).unwrap();
    refused(&job, "2-3", &foreign, "(build feedc0ffee00)");
    // The right job, the wrong frame.
    refused(&job, "3-4", &state, "state after frame 1");
    // Not a checkpoint.
    refused(&job, "2-3", &job, "not an anchorage checkpoint");
    // The output and frames keys do not count: another output directory resumes.
    let o = render(
        &job,
        "2-2",
        &d.path().join("b"),
        &["--resume", state.to_str().unwrap()],
    );
    assert!(o.status.success(), "{}", stderr(&o));
}

/// `openjd` of the Python environment `.ci/run` creates (`openjd-cli`), beside its python.
fn openjd() -> Option<PathBuf> {
    let exe = super::common::python()?.with_file_name("openjd");
    exe.exists().then_some(exe)
}

fn openjd_run(exe: &Path, args: &[&str]) {
    let o = std::process::Command::new(exe)
        .args(args)
        .output()
        .expect("run openjd");
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(
        o.status.success(),
        "openjd {args:?} failed:\n{out}\n{}",
        stderr(&o)
    );
}

/// The farm templates pass `openjd check`, and `openjd run` renders with them what a plain
/// render does: the chained chunks byte for byte, the warm-up chunks every frame, the first
/// chunk as the plain render (nothing to warm up before the animation's first frame).
#[test]
fn farm_templates_run_on_open_job_description() {
    let Some(openjd) = openjd() else {
        eprintln!("skipped: openjd not found in the Python environment");
        return;
    };
    let d = tempdir();
    let job = room_job(d.path(), "");
    let plain = d.path().join("plain");
    let o = render(&job, "0-4", &plain, &[]);
    assert!(o.status.success(), "{}", stderr(&o));
    for (how, extra) in [("chained", "--chained"), ("warm", "--warmup=1")] {
        let template = d.path().join(format!("{how}.json"));
        let o = run(&[
            "farm",
            job.to_str().unwrap(),
            "--frames",
            "0-4",
            "--chunk-size",
            "2",
            extra,
            "--out",
            d.path().join(how).to_str().unwrap(),
            "-o",
            template.to_str().unwrap(),
        ]);
        assert!(o.status.success(), "{}", stderr(&o));
        let t = template.to_str().unwrap();
        openjd_run(&openjd, &["check", t]);
        if how == "chained" {
            openjd_run(
                &openjd,
                &["run", t, "--step", "Frames 4-4", "--run-dependencies"],
            );
        } else {
            openjd_run(&openjd, &["run", t, "--step", "Render"]);
        }
        let out = d.path().join(how);
        for f in 0..=4 {
            let same = exr(&plain, f) == exr(&out, f);
            let expected = how == "chained" || f < 2;
            assert_eq!(
                same, expected,
                "{how}: frame {f} equal to the plain render's: {same}"
            );
        }
        if how == "chained" {
            assert_eq!(
                files_in(&out.join("state")),
                ["room.0001.state", "room.0003.state", "room.0004.state"]
            );
        }
    }
}

/// With `method.gather_direct` `"shadow-rays"` (a point lamp added to the room, so that there
/// is a punctual light for the shadow rays), the anchors' L_i hold the lamp's direct light
/// from their own shadow rays: frames resumed from a checkpoint are byte for byte the full
/// run's, and so are the frames of one and of two threads, and their counts, the shadow rays
/// of the gather hits and anchors among them (none by photons).
#[test]
fn shadow_rays_at_gather_hits_resume_and_thread_alike() {
    let d = tempdir();
    std::fs::write(
        d.path().join("lamp.gltf"),
        r#"{"asset":{"version":"2.0"},"extensionsUsed":["KHR_lights_punctual"],
        "extensions":{"KHR_lights_punctual":{"lights":[{"type":"point","intensity":8,"color":[1,0.9,0.8]}]}},
        "nodes":[{"name":"lamp","translation":[0.8,2.2,0.5],"extensions":{"KHR_lights_punctual":{"light":0}}}],
        "scenes":[{"nodes":[0]}],"scene":0}"#,
    )
    .unwrap();
    let job_with = |direct: &str| {
        let job = room_job(d.path(), "");
        let text = std::fs::read_to_string(&job).unwrap().replace(
            r#""scene":[{"path":"room.gltf"}]"#,
            r#""scene":[{"path":"room.gltf"},{"path":"lamp.gltf"}]"#,
        );
        let text = text.replace(
            r#""preset":"draft"}"#,
            &format!(r#""preset":"draft","gather_direct":"{direct}"}}"#),
        );
        let path = d.path().join(format!("{direct}.json"));
        std::fs::write(&path, text).unwrap();
        path
    };
    let (job, by_photons) = (job_with("shadow-rays"), job_with("photons"));
    let [full, states, resumed, photons] =
        ["full", "states", "resumed", "photons"].map(|n| d.path().join(n));
    resume_reproduces(&job, 3, &full, &states, &resumed);
    // The setting takes effect: by photons the frames differ.
    let o = render(&by_photons, "0-3", &photons, &[]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(exr(&full, 3) != exr(&photons, 3));
    let counts = |dir: &Path, f: i32| {
        let text = std::fs::read(dir.join(format!("room.{f:04}.json"))).unwrap();
        serde_json::from_slice::<serde_json::Value>(&text).unwrap()["counts"].clone()
    };
    let one = d.path().join("one-thread");
    let o = render(&job, "0-3", &one, &["--threads", "1"]);
    assert!(o.status.success(), "{}", stderr(&o));
    for f in 0..=3 {
        let c = counts(&full, f);
        assert_eq!(
            c,
            counts(&one, f),
            "frame {f}: counts of two threads and one"
        );
        assert!(
            c["gather_shadow_rays"].as_u64().unwrap() > 0,
            "frame {f}: {c}"
        );
        assert_eq!(counts(&photons, f)["gather_shadow_rays"], 0, "frame {f}");
    }
    super::common::assert_same_bytes_with_1_and_2_threads(
        &job,
        &["--frames", "0-2"],
        &["room.0002.exr".to_string()],
    );
}
