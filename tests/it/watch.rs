//! `anchorage watch` on a temporary copy of the example room: each edit is seen, classified
//! under the right rule, and re-rendered as a cold render of the edited files would look; a
//! truncated file is reported once and leaves the frames alone; SIGTERM ends it cleanly.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use serde_json::Value;

use super::common::{TempDir, root, tempdir};

/// A running `anchorage watch` and the lines it has logged.
struct Watch {
    child: Child,
    lines: mpsc::Receiver<String>,
    log: Vec<String>,
}

impl Watch {
    fn start(job: &Path) -> Watch {
        Watch::spawn(job, &["-q"])
    }

    /// `anchorage watch` with `args` besides the job and two threads.
    fn spawn(job: &Path, args: &[&str]) -> Watch {
        let mut child = Command::new(env!("CARGO_BIN_EXE_anchorage"))
            .args(["watch", "--threads", "2"])
            .args(args)
            .arg(job)
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .expect("start anchorage watch");
        let stderr = child.stderr.take().unwrap();
        let (tx, rx) = mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        Watch {
            child,
            lines: rx,
            log: Vec::new(),
        }
    }

    /// The next line that `want` accepts, waiting at most `secs`.
    fn wait_for(&mut self, secs: u64, want: impl Fn(&str) -> bool) -> String {
        let end = Instant::now() + Duration::from_secs(secs);
        loop {
            let left = end.saturating_duration_since(Instant::now());
            match self.lines.recv_timeout(left) {
                Ok(l) => {
                    self.log.push(l.clone());
                    if want(&l) {
                        return l;
                    }
                }
                Err(_) => panic!(
                    "no such line within {secs} s; the log:\n{}",
                    self.log.join("\n")
                ),
            }
        }
    }

    /// The next re-render's line.
    fn render_line(&mut self) -> String {
        self.wait_for(120, |l| l.contains(" -> rule "))
    }

    /// Lines logged within `secs`, without waiting for any in particular.
    fn drain(&mut self, secs: f64) -> Vec<String> {
        let end = Instant::now() + Duration::from_secs_f64(secs);
        let mut got = Vec::new();
        while let Ok(l) = self
            .lines
            .recv_timeout(end.saturating_duration_since(Instant::now()))
        {
            self.log.push(l.clone());
            got.push(l);
        }
        got
    }
}

impl Drop for Watch {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The gather rays a re-render line reports.
fn gather_rays(line: &str) -> u64 {
    let before = line.split(" gather rays").next().unwrap();
    before.rsplit(' ').next().unwrap().parse().unwrap()
}

/// The gather rays of a re-render line that brought the cache up to date: all of them less
/// those of pixel samples no record covered (gathered on the spot in any render, M·N = 192
/// each at the draft preset), read from the stats of the line's frames in `out`.
fn cache_rays(line: &str, out: &Path) -> u64 {
    let frames = line.split("frames ").nth(1).unwrap();
    let frames = frames.split(',').next().unwrap();
    let (a, b) = frames.split_once('-').unwrap();
    let (a, b): (i32, i32) = (a.parse().unwrap(), b.parse().unwrap());
    let uncached: u64 = (a..=b)
        .map(|f| {
            let st: Value = serde_json::from_slice(
                &std::fs::read(out.join(format!("room.{f:04}.json"))).unwrap(),
            )
            .unwrap();
            st["counts"]["uncached_samples"].as_u64().unwrap()
        })
        .sum();
    gather_rays(line) - uncached * 192
}

/// One channel of an EXR, as f32.
fn channel(path: &Path, name: &str) -> Vec<f32> {
    use exr::prelude::FlatSamples;
    let img = exr::prelude::read_all_flat_layers_from_file(path).unwrap();
    let ch = img.layer_data[0]
        .channel_data
        .list
        .iter()
        .find(|c| c.name.to_string() == name)
        .unwrap_or_else(|| panic!("{}: no channel {name}", path.display()));
    match &ch.sample_data {
        FlatSamples::F32(v) => v.clone(),
        FlatSamples::F16(v) => v.iter().map(|x| x.to_f32()).collect(),
        FlatSamples::U32(v) => v.iter().map(|&x| x as f32).collect(),
    }
}

fn mean(v: &[f32]) -> f64 {
    v.iter().map(|&x| x as f64).sum::<f64>() / v.len() as f64
}

/// Writes the glTF as an editor's atomic save: a temporary file renamed over it.
fn save_atomic(path: &Path, g: &Value) {
    let tmp = path.with_extension("gltf.part");
    std::fs::write(&tmp, serde_json::to_vec(g).unwrap()).unwrap();
    std::fs::rename(&tmp, path).unwrap();
}

/// Writes the glTF in place (truncate, then write), as simpler editors do.
fn save_in_place(path: &Path, g: &Value) {
    std::fs::write(path, serde_json::to_vec(g).unwrap()).unwrap();
}

/// Renders frame 0 of `job` cold (a plain `render`) into `out`; returns the EXR.
fn cold_render(job: &Path, out: &Path) -> PathBuf {
    cold_frames(job, out, &["--frames", "0"]);
    out.join("room.0000.exr")
}

/// Renders `job` cold (a plain `render`, with `args`) into `out`.
fn cold_frames(job: &Path, out: &Path, args: &[&str]) {
    let o = Command::new(env!("CARGO_BIN_EXE_anchorage"))
        .args(["render", "-q", "--threads", "2"])
        .args(args)
        .arg(job)
        .arg("--out")
        .arg(out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}

/// A temporary copy of the example room's glTF and a draft `anchors` job over it (output
/// `out/room.####`): the directory, the glTF and the job.
fn room_copy(resolution: [u32; 2], last_frame: i32) -> (TempDir, PathBuf, PathBuf) {
    let dir = tempdir();
    let gltf = dir.path().join("room.gltf");
    std::fs::copy(root().join("examples/room/room.gltf"), &gltf).unwrap();
    let job = dir.path().join("job.json");
    let text = serde_json::json!({
        "scene": [{"path": "room.gltf"}],
        "resolution": resolution,
        "frames": {"start": 0, "end": last_frame},
        "output": {"directory": "out", "name": "room"},
        "seed": 1,
        "render": {"samples_per_pixel": 2},
        "method": {"name": "anchors", "preset": "draft"}
    });
    std::fs::write(&job, serde_json::to_vec(&text).unwrap()).unwrap();
    (dir, gltf, job)
}

/// Relative difference of two means.
fn rel(a: f64, b: f64) -> f64 {
    (a - b).abs() / b.abs().max(1e-12)
}

#[test]
fn watch_re_renders_each_edit_under_its_rule_and_survives_a_truncated_file() {
    let (dir, gltf, job) = room_copy([64, 48], 1);
    let out = dir.path().join("out");
    let exr0 = out.join("room.0000.exr");
    let mut g: Value = serde_json::from_slice(&std::fs::read(&gltf).unwrap()).unwrap();
    let mut w = Watch::start(&job);

    // The first render.
    let first = w.render_line();
    assert!(first.contains("first render -> rule rebuild"), "{first}");
    let cold_rays = cache_rays(&first, &out);
    assert!(cold_rays > 0, "{first}");
    let beauty0 = mean(&channel(&exr0, "G"));
    let ids0 = channel(&exr0, "anchor_id.V");

    // A light: the lamp's emission doubled. Relight keeps every anchor link, traces no ray
    // for the cache, and matches a cold render of the edited room.
    g["materials"][4]["extensions"]["KHR_materials_emissive_strength"]["emissiveStrength"] =
        34.0.into();
    save_atomic(&gltf, &g);
    let line = w.render_line();
    assert!(
        line.contains(r#"light "lamp" (emissive material) emission -> rule relight"#),
        "{line}"
    );
    // No gather ray for the cache: the strata that hit the cube read the hits the frame's
    // render kept.
    let rays = cache_rays(&line, &out);
    assert_eq!(rays, 0, "relight traced {rays} rays: {line}");
    let beauty1 = mean(&channel(&exr0, "G"));
    assert!(
        beauty1 > 1.8 * beauty0,
        "the lamp doubled: {beauty0} -> {beauty1}"
    );
    assert_eq!(
        channel(&exr0, "anchor_id.V"),
        ids0,
        "relight changed the anchor links"
    );
    let cold = cold_render(&job, &dir.path().join("cold1"));
    let (ind, ind_cold) = (
        mean(&channel(&exr0, "indirect.G")),
        mean(&channel(&cold, "indirect.G")),
    );
    assert!(
        rel(ind, ind_cold) < 0.05,
        "relit indirect {ind} against a cold render's {ind_cold}"
    );

    // A material: the white walls lose most of their red. Anchors read their albedo again.
    g["materials"][0]["pbrMetallicRoughness"]["baseColorFactor"] =
        serde_json::json!([0.2, 0.73, 0.73, 1.0]);
    save_in_place(&gltf, &g);
    let line = w.render_line();
    assert!(
        line.contains(r#"material "white" -> rule relight"#),
        "{line}"
    );
    let rays = cache_rays(&line, &out);
    assert_eq!(rays, 0, "relight traced {rays} rays: {line}");
    let cold = cold_render(&job, &dir.path().join("cold2"));
    for c in ["indirect.R", "indirect.G"] {
        let (ind, ind_cold) = (mean(&channel(&exr0, c)), mean(&channel(&cold, c)));
        assert!(
            rel(ind, ind_cold) < 0.05,
            "{c}: relit {ind} against a cold render's {ind_cold}"
        );
    }

    // The dynamic cube moved (its translation no longer animated): the visibility machinery
    // re-shoots the strata that see it, fewer than half a cold render's rays (a fresh state
    // would shoot about as many as the first render), more than a relight's.
    let before = channel(&exr0, "G");
    let anim = &mut g["animations"][0];
    let channels = anim["channels"].as_array_mut().unwrap();
    channels.remove(0);
    for c in channels.iter_mut() {
        c["sampler"] = (c["sampler"].as_u64().unwrap() - 1).into();
    }
    anim["samplers"].as_array_mut().unwrap().remove(0);
    g["nodes"][6]["translation"] = serde_json::json!([-1.0, 0.35, 1.2]);
    save_atomic(&gltf, &g);
    let line = w.render_line();
    assert!(line.contains(r#"dynamic prim "cube""#), "{line}");
    assert!(line.contains("-> rule dynamic"), "{line}");
    let moved_rays = cache_rays(&line, &out);
    assert!(
        moved_rays > rays && moved_rays * 2 < cold_rays,
        "moving the cube traced {moved_rays} rays (relight {rays}, cold {cold_rays})"
    );
    let after = channel(&exr0, "G");
    let changed = before
        .iter()
        .zip(&after)
        .filter(|(a, b)| (*a - *b).abs() > 0.05 * a.abs().max(0.01))
        .count();
    assert!(
        changed > before.len() / 50,
        "only {changed} pixels changed after the cube moved"
    );

    // The camera's field of view narrowed: static records kept, new ones placed.
    let before = channel(&exr0, "G");
    let yfov = g["cameras"][0]["perspective"]["yfov"].as_f64().unwrap();
    g["cameras"][0]["perspective"]["yfov"] = (0.8 * yfov).into();
    save_atomic(&gltf, &g);
    let line = w.render_line();
    assert!(line.contains("camera -> rule camera"), "{line}");
    let camera_rays = cache_rays(&line, &out);
    assert!(
        camera_rays * 2 < cold_rays,
        "the camera edit traced {camera_rays} rays (cold {cold_rays})"
    );
    assert_ne!(channel(&exr0, "G"), before, "the frame did not change");
    let before = channel(&exr0, "G");

    // A save interrupted half-way (twice, at different bytes), then completed: one error,
    // the frames untouched, then a re-render of the completed file.
    let frames_before = std::fs::read(&exr0).unwrap();
    g["materials"][4]["extensions"]["KHR_materials_emissive_strength"]["emissiveStrength"] =
        17.0.into();
    let whole = serde_json::to_vec(&g).unwrap();
    std::fs::write(&gltf, &whole[..whole.len() / 3]).unwrap();
    w.wait_for(60, |l| l.contains("error:"));
    std::fs::write(&gltf, &whole[..whole.len() / 2]).unwrap();
    std::fs::remove_file(&gltf).unwrap();
    std::thread::sleep(Duration::from_millis(600));
    let quiet = w.drain(2.0);
    let errors = w.log.iter().filter(|l| l.contains("error:")).count();
    assert_eq!(errors, 1, "the error is reported once: {:#?}", w.log);
    let error = w.log.iter().find(|l| l.contains("error:")).unwrap();
    assert!(
        error.contains("room.gltf"),
        "the error names the file: {error}"
    );
    assert!(quiet.iter().all(|l| !l.contains("-> rule")), "{quiet:?}");
    assert_eq!(
        std::fs::read(&exr0).unwrap(),
        frames_before,
        "a bad file changed the frames"
    );
    std::fs::write(&gltf, &whole).unwrap();
    let line = w.render_line();
    assert!(
        line.contains(r#"light "lamp" (emissive material) emission -> rule relight"#),
        "{line}"
    );
    assert!(mean(&channel(&exr0, "G")) < 0.7 * mean(&before));

    // SIGTERM: exit 143, nothing but the frames left in the output directory.
    let status = Command::new("kill")
        .args(["-TERM", &w.child.id().to_string()])
        .status()
        .unwrap();
    assert!(status.success());
    let t = Instant::now();
    let code = loop {
        if let Some(s) = w.child.try_wait().unwrap() {
            break s.code();
        }
        assert!(t.elapsed() < Duration::from_secs(10), "SIGTERM ignored");
        std::thread::sleep(Duration::from_millis(50));
    };
    assert_eq!(code, Some(143));
    let mut left: Vec<String> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    left.sort();
    assert_eq!(
        left,
        [
            "room.0000.exr",
            "room.0000.json",
            "room.0001.exr",
            "room.0001.json"
        ]
    );
}

/// Frames 0..=`last` of `out` have the mean green of a cold render of `job` (into `cold`)
/// within 5 %.
fn assert_frames_match_a_cold_render(job: &Path, out: &Path, cold: &Path, last: i32) {
    cold_frames(job, cold, &[]);
    for f in 0..=last {
        let (watched, cold) = (
            mean(&channel(&frame(out, f), "G")),
            mean(&channel(&frame(cold, f), "G")),
        );
        assert!(
            rel(watched, cold) < 0.05,
            "frame {f}: watched {watched} against a cold render's {cold}"
        );
    }
}

/// The frame after which a re-render line says its pass was stopped.
fn stopped_after(line: &str) -> i32 {
    line.split("interrupted after frame ")
        .nth(1)
        .unwrap_or_else(|| panic!("the pass in progress ran to its end: {line}"))
        .split(' ')
        .next()
        .unwrap()
        .parse()
        .unwrap()
}

/// Frame `f`'s EXR of `out`.
fn frame(out: &Path, f: i32) -> PathBuf {
    out.join(format!("room.{f:04}.exr"))
}

#[test]
fn a_newer_edit_stops_the_pass_in_progress_and_every_frame_shows_the_last_edit() {
    let (dir, gltf, job) = room_copy([96, 72], 11);
    let out = dir.path().join("out");
    let mut g: Value = serde_json::from_slice(&std::fs::read(&gltf).unwrap()).unwrap();
    // Without -q: the log has a line per frame.
    let mut w = Watch::spawn(&job, &[]);
    let first = w.render_line();
    assert!(first.contains("first render"), "{first}");

    // The lamp doubled; as soon as the pass for it has written its first frame, the lamp
    // is turned down to a quarter: that pass stops, and the next renders the whole range.
    let lamp = |g: &mut Value, strength: f64| {
        g["materials"][4]["extensions"]["KHR_materials_emissive_strength"]["emissiveStrength"] =
            strength.into();
    };
    lamp(&mut g, 34.0);
    save_atomic(&gltf, &g);
    w.wait_for(60, |l| l.contains("watch: frame 0:"));
    lamp(&mut g, 4.25);
    save_atomic(&gltf, &g);
    let stopped = w.render_line();
    assert!(
        stopped.contains("interrupted after frame"),
        "the pass in progress ran to its end: {stopped}"
    );
    let last = w.render_line();
    assert!(
        last.contains("-> rule relight") && !last.contains("interrupted"),
        "{last}"
    );

    // Every frame as a cold render of the final scene shows it.
    assert_frames_match_a_cold_render(&job, &out, &dir.path().join("cold"), 11);
}

#[test]
fn frame_states_beyond_the_state_memory_are_not_kept_and_their_frames_are_made_afresh() {
    let (dir, gltf, job) = room_copy([64, 48], 2);
    let out = dir.path().join("out");
    let mut g: Value = serde_json::from_slice(&std::fs::read(&gltf).unwrap()).unwrap();
    // 1 KiB holds no frame's state: every pass renders as `render` would.
    let mut w = Watch::spawn(&job, &["-q", "--state-memory", "1K"]);
    let first = w.render_line();
    assert!(
        first.contains("the states of 3 frame(s) not kept (over --state-memory)"),
        "{first}"
    );
    let cold_rays = cache_rays(&first, &out);

    g["materials"][4]["extensions"]["KHR_materials_emissive_strength"]["emissiveStrength"] =
        34.0.into();
    save_atomic(&gltf, &g);
    let line = w.render_line();
    assert!(line.contains("-> rule relight"), "{line}");
    assert!(line.contains("3 frame(s) not kept"), "{line}");
    // No state to relight: frame 0 gathers every record again.
    let rays = cache_rays(&line, &out);
    assert!(
        rays * 2 > cold_rays,
        "a relight without states traced {rays} rays (cold {cold_rays}): {line}"
    );
    let cold_out = dir.path().join("cold");
    cold_frames(&job, &cold_out, &[]);
    for f in 0..=2 {
        assert_eq!(
            std::fs::read(frame(&out, f)).unwrap(),
            std::fs::read(frame(&cold_out, f)).unwrap(),
            "frame {f}: a watch with no states kept renders as `render` does"
        );
    }
}

#[test]
fn a_save_without_a_change_that_stops_a_pass_renders_the_frames_it_did_not_reach() {
    let (dir, gltf, job) = room_copy([96, 72], 11);
    let out = dir.path().join("out");
    let mut g: Value = serde_json::from_slice(&std::fs::read(&gltf).unwrap()).unwrap();
    let mut w = Watch::spawn(&job, &[]);
    w.render_line();

    // The lamp doubled, then the same file saved again while that pass renders: the second
    // save stops the pass and changes nothing, and the frames the pass did not reach must
    // still be rendered with the doubled lamp.
    g["materials"][4]["extensions"]["KHR_materials_emissive_strength"]["emissiveStrength"] =
        34.0.into();
    save_atomic(&gltf, &g);
    w.wait_for(60, |l| l.contains("watch: frame 0:"));
    save_atomic(&gltf, &g);
    let stopped = w.render_line();
    let after = stopped_after(&stopped);
    let rest = w.render_line();
    assert!(
        rest.contains(&format!("frames {}-11", after + 1)) && rest.contains("-> rule relight"),
        "after a pass stopped at frame {after}: {rest}"
    );

    assert_frames_match_a_cold_render(&job, &out, &dir.path().join("cold"), 11);
}

#[test]
fn a_first_render_stopped_by_a_save_without_a_change_goes_on_as_render_would() {
    let (dir, gltf, job) = room_copy([96, 72], 11);
    let out = dir.path().join("out");
    let g: Value = serde_json::from_slice(&std::fs::read(&gltf).unwrap()).unwrap();
    let mut w = Watch::spawn(&job, &[]);
    w.wait_for(60, |l| l.contains("watch: frame 0:"));
    save_atomic(&gltf, &g);
    let stopped = w.render_line();
    assert!(
        stopped.contains("first render") && stopped.contains("interrupted after frame"),
        "{stopped}"
    );
    let rest = w.render_line();
    assert!(rest.contains("first render"), "{rest}");
    // The rest starts from the state the stopped pass's last frame left: every frame is the
    // bytes a plain render writes.
    let cold_out = dir.path().join("cold");
    cold_frames(&job, &cold_out, &[]);
    for f in 0..=11 {
        assert_eq!(
            std::fs::read(frame(&out, f)).unwrap(),
            std::fs::read(frame(&cold_out, f)).unwrap(),
            "frame {f} differs from a plain render ({stopped} / {rest})"
        );
    }
}

#[test]
fn a_bad_state_memory_is_refused_naming_the_option() {
    let (dir, _gltf, job) = room_copy([16, 12], 0);
    let o = Command::new(env!("CARGO_BIN_EXE_anchorage"))
        .args(["watch", "--state-memory", "lots"])
        .arg(&job)
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("--state-memory: lots:"), "{err}");
    assert!(!dir.path().join("out").exists(), "output written");
}

/// Sets the lamp's emissive strength in the room's glTF.
fn set_lamp(g: &mut Value, strength: f64) {
    g["materials"][4]["extensions"]["KHR_materials_emissive_strength"]["emissiveStrength"] =
        strength.into();
}

#[test]
fn a_save_that_stops_a_pass_and_does_not_load_leaves_the_frames_showing_the_last_good_scene() {
    let (dir, gltf, job) = room_copy([96, 72], 11);
    let out = dir.path().join("out");
    let mut g: Value = serde_json::from_slice(&std::fs::read(&gltf).unwrap()).unwrap();
    let mut w = Watch::spawn(&job, &[]);
    w.render_line();

    // The lamp doubled; while that pass renders, a save breaks off half-way. The pass stops,
    // the file does not load, and the last good scene — the doubled lamp — is rendered on
    // the frames the pass did not reach.
    set_lamp(&mut g, 34.0);
    save_atomic(&gltf, &g);
    w.wait_for(60, |l| l.contains("watch: frame 0:"));
    let whole = serde_json::to_vec(&g).unwrap();
    std::fs::write(&gltf, &whole[..whole.len() / 2]).unwrap();
    let stopped = w.render_line();
    let after = stopped_after(&stopped);
    w.wait_for(60, |l| l.contains("error:") && l.contains("room.gltf"));
    let rest = w.render_line();
    assert!(
        rest.contains(&format!("frames {}-11", after + 1)) && rest.contains("-> rule relight"),
        "after a pass stopped at frame {after} by a file that does not load: {rest}"
    );

    // The file completed with the same content: nothing left to render.
    std::fs::write(&gltf, &whole).unwrap();
    w.wait_for(60, |l| l.contains("saved without a change"));
    assert_frames_match_a_cold_render(&job, &out, &dir.path().join("cold"), 11);
}

#[test]
fn a_pass_that_failed_is_rendered_again_at_the_next_save_even_without_a_change() {
    let (dir, gltf, job) = room_copy([64, 48], 1);
    let out = dir.path().join("out");
    let mut g: Value = serde_json::from_slice(&std::fs::read(&gltf).unwrap()).unwrap();
    let mut w = Watch::start(&job);
    w.render_line();

    // The output directory replaced by a file: the pass for the doubled lamp fails.
    std::fs::remove_dir_all(&out).unwrap();
    std::fs::write(&out, b"not a directory").unwrap();
    set_lamp(&mut g, 34.0);
    save_atomic(&gltf, &g);
    let error = w.wait_for(60, |l| l.contains("error:"));
    assert!(error.contains("rendered again at the next save"), "{error}");

    // The directory back, and the same glTF saved again: every frame is rendered again.
    std::fs::remove_file(&out).unwrap();
    save_atomic(&gltf, &g);
    let line = w.render_line();
    assert!(
        line.contains("again after a failed pass") && line.contains("-> rule rebuild"),
        "{line}"
    );
    assert!(line.contains("frames 0-1"), "{line}");
    assert_frames_match_a_cold_render(&job, &out, &dir.path().join("cold"), 1);
}

#[test]
fn frames_back_in_the_range_after_a_material_edit_reflect_the_new_colour() {
    let (dir, gltf, job) = room_copy([64, 48], 2);
    let out = dir.path().join("out");
    let mut g: Value = serde_json::from_slice(&std::fs::read(&gltf).unwrap()).unwrap();
    let mut j: Value = serde_json::from_slice(&std::fs::read(&job).unwrap()).unwrap();
    let mut w = Watch::start(&job);
    w.render_line();

    // The range cut to frame 0; the white walls turned cyan; the range back to 0-2. Frames
    // 1 and 2 start again from the states they kept from before the edit, whose anchors
    // hold the old albedo.
    j["frames"]["end"] = 0.into();
    std::fs::write(&job, serde_json::to_vec(&j).unwrap()).unwrap();
    let line = w.render_line();
    assert!(line.contains("frames 0-0"), "{line}");
    g["materials"][0]["pbrMetallicRoughness"]["baseColorFactor"] =
        serde_json::json!([0.05, 0.73, 0.73, 1.0]);
    save_atomic(&gltf, &g);
    let line = w.render_line();
    assert!(line.contains(r#"material "white""#), "{line}");
    j["frames"]["end"] = 2.into();
    std::fs::write(&job, serde_json::to_vec(&j).unwrap()).unwrap();
    let line = w.render_line();
    assert!(
        line.contains("frames 0-2") && line.contains("-> rule dynamic"),
        "{line}"
    );

    let cold = dir.path().join("cold");
    cold_frames(&job, &cold, &[]);
    for f in 1..=2 {
        let (watched, cold) = (
            mean(&channel(&frame(&out, f), "indirect.R")),
            mean(&channel(&frame(&cold, f), "indirect.R")),
        );
        assert!(
            rel(watched, cold) < 0.05,
            "frame {f}: indirect red {watched} against a cold render's {cold}"
        );
    }
}

/// Every AOV of an image as text (`{:?}` writes each float's shortest exact form): equal
/// texts, equal bits.
fn image_text(img: &anchorage::integrator::FrameImage) -> String {
    format!("{img:?}")
}

/// `g` (the room's glTF) with the material "white" recoloured.
fn with_white_recoloured(g: &Value) -> Value {
    let mut g = g.clone();
    let white = g["materials"]
        .as_array_mut()
        .unwrap()
        .iter_mut()
        .find(|m| m["name"] == "white")
        .expect("the room has a white material");
    white["pbrMetallicRoughness"]["baseColorFactor"] = serde_json::json!([0.4, 0.8, 0.8, 1.0]);
    g
}

/// Frame 0 of `loaded`'s scene (with `job`'s settings) rendered afresh with its shading
/// logged, as watch mode renders: the state it leaves and the log.
fn logged_render(
    job: &anchorage::job::Job,
    loaded: &anchorage::watch::Loaded,
    resources: &anchorage::session::Resources,
) -> (
    anchorage::session::FrameState,
    anchorage::integrator::replay::ShadingLog,
) {
    use anchorage::integrator::cached::Refresh;
    let mut state = anchorage::session::FrameState::default();
    let mut log = anchorage::integrator::replay::ShadingLog::default();
    anchorage::pipeline::render_frame_with(
        job,
        &loaded.scene,
        resources,
        &mut state,
        0,
        &mut anchorage::pipeline::new_stats(job, 0),
        Refresh::default(),
        Some((&mut log, &anchorage::watch::direct_keys(loaded, 0))),
    )
    .unwrap();
    (state, log)
}

/// Frame 0 relit from `state` after an edit (`edited`, the scene as it is now), replaying
/// `log` where one is given: every AOV of the image as text, and the pixel samples gathered
/// on the spot.
fn relit_frame(
    job: &anchorage::job::Job,
    edited: &anchorage::watch::Loaded,
    resources: &anchorage::session::Resources,
    state: &anchorage::session::FrameState,
    log: Option<&mut anchorage::integrator::replay::ShadingLog>,
) -> (String, u64) {
    use anchorage::integrator::cached::Refresh;
    let mut s = state.clone();
    let mut stats = anchorage::pipeline::new_stats(job, 0);
    let refresh = Refresh {
        relight_only: true,
        albedo: true,
    };
    let keys = anchorage::watch::direct_keys(edited, 0);
    let img = anchorage::pipeline::render_frame_with(
        job,
        &edited.scene,
        resources,
        &mut s,
        0,
        &mut stats,
        refresh,
        log.map(|l| (l, &keys)),
    )
    .unwrap();
    (image_text(&img), stats.counts.uncached_samples)
}

/// A relight reads the spot records (`Record::spot`: made where no other record covers a
/// camera sample; records valid out to a hundredth of a pixel make them common here) through
/// the log as it reads the other records: after a material edit, the replayed relight is
/// the image that tracing gives (seen failing with spot reads left out of the log: their
/// samples then gather on the spot).
#[test]
fn a_relight_reads_spot_records_through_the_log_as_tracing_does() {
    use anchorage::job::Overrides;
    use anchorage::watch::Loaded;

    let (_dir, gltf, job_path) = room_copy([64, 48], 0);
    let mut j: Value = serde_json::from_slice(&std::fs::read(&job_path).unwrap()).unwrap();
    j["render"]["samples_per_pixel"] = 4.into();
    j["method"]["min_spacing_px"] = 0.01.into();
    j["method"]["max_spacing_px"] = 0.01.into();
    std::fs::write(&job_path, serde_json::to_vec(&j).unwrap()).unwrap();
    let load = || Loaded::load(&job_path, &Overrides::default()).unwrap();
    let first = load();
    let job = &first.job;
    let resources = anchorage::pipeline::new_resources(job, &first.scene).unwrap();
    let (state, log) = logged_render(job, &first, &resources);
    let spots = state.cache.records.iter().filter(|r| r.spot).count();
    eprintln!("{spots} spot records");
    assert!(spots > 0, "the test needs spot records");

    let g: Value = serde_json::from_slice(&std::fs::read(&gltf).unwrap()).unwrap();
    save_atomic(&gltf, &with_white_recoloured(&g));
    let edited = load();
    let (traced, on_the_spot) = relit_frame(job, &edited, &resources, &state, None);
    let (replayed, replayed_on_the_spot) =
        relit_frame(job, &edited, &resources, &state, Some(&mut log.clone()));
    assert_eq!(on_the_spot, replayed_on_the_spot);
    assert!(
        replayed == traced,
        "the replayed relight differs from the traced one"
    );
}

#[test]
fn a_relight_that_replays_the_logged_rays_gives_the_image_that_tracing_them_gives() {
    use anchorage::integrator::replay::ShadingLog;
    use anchorage::job::Overrides;
    use anchorage::pipeline;
    use anchorage::watch::Loaded;

    let (_dir, gltf, job_path) = room_copy([48, 36], 0);
    let load = || Loaded::load(&job_path, &Overrides::default()).unwrap();
    let first = load();
    let job = &first.job;
    let resources = pipeline::new_resources(job, &first.scene).unwrap();
    let (state, log) = logged_render(job, &first, &resources);
    assert!(log.heap_bytes() > 0, "the render logged its rays");

    let original: Value = serde_json::from_slice(&std::fs::read(&gltf).unwrap()).unwrap();
    // Edits a relight serves: a material's colour (the other materials' direct light is
    // reused from the log, the edited one's computed again), the lamp brighter (no direct
    // light reused: the lights changed; the same rays, all answered from the log), and a
    // point light added besides (its shadow rays come first at every point, so the logged
    // answers no longer line up with the rays cast: they must not be used).
    let redder = with_white_recoloured(&original);
    let mut brighter = original.clone();
    set_lamp(&mut brighter, 40.0);
    let mut bulb = brighter.clone();
    bulb["extensionsUsed"]
        .as_array_mut()
        .unwrap()
        .push("KHR_lights_punctual".into());
    bulb["extensions"] = serde_json::json!({"KHR_lights_punctual": {"lights": [
        {"type": "point", "intensity": 30.0}
    ]}});
    let nodes = bulb["nodes"].as_array_mut().unwrap();
    nodes.push(serde_json::json!({
        "name": "bulb", "translation": [-1.0, 2.5, 0.5],
        "extensions": {"KHR_lights_punctual": {"light": 0}}
    }));
    let bulb_node = nodes.len() - 1;
    bulb["scenes"][0]["nodes"]
        .as_array_mut()
        .unwrap()
        .push(bulb_node.into());

    let relit = |edited: &Loaded, log: Option<&mut ShadingLog>| {
        relit_frame(job, edited, &resources, &state, log).0
    };
    for (name, g) in [
        ("white redder", &redder),
        ("lamp brighter", &brighter),
        ("point light added", &bulb),
    ] {
        save_atomic(&gltf, g);
        let edited = load();
        let mut replayed_log = log.clone();
        let replayed = relit(&edited, Some(&mut replayed_log));
        assert!(
            replayed == relit(&edited, None),
            "{name}: the replayed relight differs from the traced one"
        );
        // The replay logged this render's rays in turn: a second relight replays them.
        assert!(
            replayed == relit(&edited, Some(&mut replayed_log)),
            "{name}"
        );
    }
    // The log is what the replay reads: with its shadow answers inverted, the lamp's
    // relight (whose rays all match, and which reuses no direct light) comes out otherwise;
    // with its direct light cleared, the lamp's relight is as before (none reused) and the
    // material edit's is not (the other materials' reused).
    save_atomic(&gltf, &brighter);
    let edited = load();
    let mut inverted = log.clone();
    inverted.invert_shadow_answers();
    assert!(relit(&edited, Some(&mut inverted)) != relit(&edited, None));
    let mut cleared = log.clone();
    cleared.clear_direct_light();
    assert!(relit(&edited, Some(&mut cleared.clone())) == relit(&edited, None));
    save_atomic(&gltf, &redder);
    let edited = load();
    assert!(relit(&edited, Some(&mut cleared)) != relit(&edited, None));
    // And its cache reads: with their weights made equal, the relight comes out otherwise;
    // the same log marked as made where the cache's records were valid elsewhere (another
    // interpolation key) has its reads made again.
    let mut flat = log.clone();
    flat.flatten_interpolation_weights();
    assert!(relit(&edited, Some(&mut flat.clone())) != relit(&edited, None));
    let mut elsewhere = flat.with_interpolation_key(Some(1));
    assert!(relit(&edited, Some(&mut elsewhere)) == relit(&edited, None));
    // And its emitter samples: with their BRDF values cleared, the lamp's relight (the
    // other materials' BRDF values reused, the emission read again) comes out otherwise,
    // and the material edit's is as before (the edited material's BRDF evaluated again, the
    // others' direct light reused whole); marked as made with other emitters, they are not
    // read.
    let mut dark = log.clone();
    dark.clear_emitter_brdfs();
    assert!(relit(&edited, Some(&mut dark.clone())) == relit(&edited, None));
    save_atomic(&gltf, &brighter);
    let edited = load();
    assert!(relit(&edited, Some(&mut dark.clone())) != relit(&edited, None));
    let mut others = dark.with_emitters_key(Some(1));
    assert!(relit(&edited, Some(&mut others)) == relit(&edited, None));

    // A log made with two emitting materials, relit after one of them grew brighter: the
    // emitters are picked by their powers, so some samples pick another emitter, or the same
    // one with another probability, than they were logged with — those light samples are
    // computed again, the others read back.
    let mut two = original.clone();
    two["materials"][1]["emissiveFactor"] = serde_json::json!([0.6, 0.2, 0.2]);
    save_atomic(&gltf, &two);
    let before = load();
    let (state2, log2) = logged_render(job, &before, &resources);
    let mut two_brighter = two.clone();
    set_lamp(&mut two_brighter, 40.0);
    save_atomic(&gltf, &two_brighter);
    let edited = load();
    let relit2 =
        |log: Option<&mut ShadingLog>| relit_frame(job, &edited, &resources, &state2, log).0;
    assert!(relit2(Some(&mut log2.clone())) == relit2(None));
}
