//! Shared helpers: paths, temporary directories, jobs built in code, and an independent glTF
//! accessor reader.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::atomic::{AtomicU64, Ordering};

use anchorage::job::{Job, JobFile, Overrides};
use anchorage::pipeline::{self, FrameStats};
use anchorage::render::FrameImage;
use anchorage::scene::Scene;

pub fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

pub fn shared_scene(rel: &str) -> PathBuf {
    root().join("../shared/scenes").join(rel)
}

/// A fresh directory under the system's temporary directory, removed with its contents when
/// dropped. std only on purpose: a test-only crate such as `tempfile` turns on features of
/// crates the renderer shares (`bitflags/std`), and Cargo then builds ~15 of them a second
/// time for `cargo test --release` after `cargo build --release`.
pub struct TempDir(PathBuf);

impl TempDir {
    pub fn path(&self) -> &Path {
        &self.0
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// Creates a `TempDir` named after the process, a counter and the clock.
pub fn tempdir() -> TempDir {
    static NEXT: AtomicU64 = AtomicU64::new(0);
    let base = std::env::temp_dir();
    loop {
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.subsec_nanos());
        let n = NEXT.fetch_add(1, Ordering::Relaxed);
        let dir = base.join(format!(
            "anchorage-test-{}-{n}-{nanos:08x}",
            std::process::id()
        ));
        match std::fs::create_dir(&dir) {
            Ok(()) => return TempDir(dir),
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => continue,
            Err(e) => panic!("cannot create {}: {e}", dir.display()),
        }
    }
}

pub fn example_job() -> PathBuf {
    root().join("examples/room/job.json")
}

pub fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_anchorage"))
}

pub fn run(args: &[&str]) -> Output {
    bin().args(args).output().expect("run anchorage")
}

pub fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// A job from JSON text, as if read from `path` (which locates relative scene paths).
pub fn job_from_json(path: &Path, json: &str) -> anchorage::Result<Job> {
    let file: JobFile = serde_json::from_str(json).expect("test job parses");
    Job::from_file(path, file, &Overrides::default())
}

/// Renders one frame in memory.
pub fn render(job: &Job, frame: i32) -> FrameImage {
    let scene = Scene::load(job).expect("scene loads");
    let statics = scene.statics();
    let mut stats = blank_stats();
    pipeline::render_frame(
        job,
        &scene,
        &statics,
        &mut Default::default(),
        frame,
        &mut stats,
    )
    .expect("frame renders")
}

fn blank_stats() -> FrameStats {
    FrameStats {
        frame: 0,
        time: 0.0,
        method: "direct",
        visibility: None,
        resolution: [0, 0],
        samples_per_pixel: 0,
        timings_s: Default::default(),
        counts: Default::default(),
        memory: Default::default(),
        anchor_reuse: None,
    }
}

/// The Python interpreter of `.venv` (created by `.ci/run`), or `None` with the reason
/// printed. In CI (`CI` set) a missing interpreter fails the test instead.
pub fn python() -> Option<PathBuf> {
    let p = std::env::var_os("ANCHORAGE_PYTHON")
        .map(PathBuf::from)
        .unwrap_or_else(|| root().join(".venv/bin/python"));
    if p.exists() {
        return Some(p);
    }
    if std::env::var_os("CI").is_some() {
        panic!("{} is missing: .ci/run must create it", p.display());
    }
    eprintln!(
        "skipped: {} not found (run .ci/run to create the Python environment)",
        p.display()
    );
    None
}

/// Minimal glTF reader for checks independent of the `gltf` crate: the JSON and the
/// float data of an accessor (tightly packed f32 accessors only).
pub struct RawGltf {
    pub json: serde_json::Value,
    pub bin: Vec<Vec<u8>>,
}

impl RawGltf {
    pub fn open(path: &Path) -> RawGltf {
        let bytes = std::fs::read(path).unwrap();
        let (json, blob): (serde_json::Value, Option<Vec<u8>>) = if &bytes[0..4] == b"glTF" {
            let jlen = u32::from_le_bytes(bytes[12..16].try_into().unwrap()) as usize;
            let json = serde_json::from_slice(&bytes[20..20 + jlen]).unwrap();
            let rest = &bytes[20 + jlen..];
            let blob = (rest.len() >= 8).then(|| {
                let blen = u32::from_le_bytes(rest[0..4].try_into().unwrap()) as usize;
                rest[8..8 + blen].to_vec()
            });
            (json, blob)
        } else {
            (serde_json::from_slice(&bytes).unwrap(), None)
        };
        let base = path.parent().unwrap();
        let bin = json["buffers"]
            .as_array()
            .map(|bs| {
                bs.iter()
                    .map(|b| match b["uri"].as_str() {
                        Some(uri) if uri.starts_with("data:") => Vec::new(),
                        Some(uri) => std::fs::read(base.join(uri)).unwrap(),
                        None => blob.clone().unwrap(),
                    })
                    .collect()
            })
            .unwrap_or_default();
        RawGltf { json, bin }
    }

    pub fn floats(&self, accessor: usize) -> Vec<f32> {
        let a = &self.json["accessors"][accessor];
        assert_eq!(a["componentType"], 5126);
        let width = match a["type"].as_str().unwrap() {
            "SCALAR" => 1,
            "VEC2" => 2,
            "VEC3" => 3,
            "VEC4" => 4,
            t => panic!("{t}"),
        };
        let v = &self.json["bufferViews"][a["bufferView"].as_u64().unwrap() as usize];
        let buf = &self.bin[v["buffer"].as_u64().unwrap() as usize];
        let start = v["byteOffset"].as_u64().unwrap_or(0) as usize
            + a["byteOffset"].as_u64().unwrap_or(0) as usize;
        let stride = v["byteStride"].as_u64().unwrap_or(4 * width as u64) as usize;
        let n = a["count"].as_u64().unwrap() as usize;
        (0..n)
            .flat_map(|i| (0..width).map(move |k| start + i * stride + 4 * k))
            .map(|o| f32::from_le_bytes(buf[o..o + 4].try_into().unwrap()))
            .collect()
    }

    /// Triangles the file's meshes hold, counted per node that instances a mesh.
    pub fn triangle_count(&self) -> usize {
        let meshes = self.json["meshes"].as_array().cloned().unwrap_or_default();
        let per_mesh: Vec<usize> = meshes
            .iter()
            .map(|m| {
                m["primitives"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .map(|p| {
                        let count = |acc: &serde_json::Value| {
                            self.json["accessors"][acc.as_u64().unwrap() as usize]["count"]
                                .as_u64()
                                .unwrap() as usize
                        };
                        let n = if p["indices"].is_null() {
                            count(&p["attributes"]["POSITION"])
                        } else {
                            count(&p["indices"])
                        };
                        match p["mode"].as_u64().unwrap_or(4) {
                            4 => n / 3,
                            5 | 6 => n.saturating_sub(2),
                            _ => 0,
                        }
                    })
                    .sum()
            })
            .collect();
        self.json["nodes"]
            .as_array()
            .map(|ns| {
                ns.iter()
                    .filter_map(|n| n["mesh"].as_u64())
                    .map(|m| per_mesh[m as usize])
                    .sum()
            })
            .unwrap_or(0)
    }
}

/// Writes `dir/job.json`: the example room at 48×36, 2 samples per pixel, `method` at the
/// draft preset, frames 0–48 (for the thread-determinism checks).
pub fn small_room_job(dir: &Path, method: &str) -> PathBuf {
    let job = dir.join("job.json");
    std::fs::write(
        &job,
        format!(
            r#"{{"scene":[{{"path":"{}"}}],"resolution":[48,36],"frames":{{"start":0,"end":48}},"render":{{"samples_per_pixel":2}},
            "method":{{"name":"{method}","preset":"draft"}}}}"#,
            root().join("examples/room/room.gltf").display()
        ),
    )
    .unwrap();
    job
}

/// Renders `job` with `args` on 1 and 2 threads and asserts that every file in `names` (paths
/// under the output directory) has the same bytes both times.
pub fn assert_same_bytes_with_1_and_2_threads(job: &Path, args: &[&str], names: &[String]) {
    let a = tempdir();
    let b = tempdir();
    for (dir, threads) in [(&a, "1"), (&b, "2")] {
        let mut all = vec![
            "render",
            job.to_str().unwrap(),
            "--threads",
            threads,
            "--out",
            dir.path().to_str().unwrap(),
            "--quiet",
        ];
        all.extend_from_slice(args);
        let o = run(&all);
        assert!(o.status.success(), "{}", stderr(&o));
    }
    for name in names {
        let (x, y) = (
            std::fs::read(a.path().join(name)).unwrap(),
            std::fs::read(b.path().join(name)).unwrap(),
        );
        assert!(x == y, "{name} differs between 1 and 2 threads");
    }
    // No temporary files are left behind.
    assert!(
        std::fs::read_dir(a.path()).unwrap().all(|e| !e
            .unwrap()
            .file_name()
            .to_string_lossy()
            .contains(".tmp"))
    );
}

/// RMS of `a - b` over RGB relative to the RMS of `b`.
pub fn relative_rms(a: &FrameImage, b: &FrameImage) -> f64 {
    let (mut d, mut n) = (0.0f64, 0.0f64);
    for (p, q) in a.beauty.iter().zip(&b.beauty) {
        for k in 0..3 {
            d += ((p[k] - q[k]) as f64).powi(2);
            n += (q[k] as f64).powi(2);
        }
    }
    (d / n.max(1e-300)).sqrt()
}
