//! Shared helpers: paths, the third-party scenes, temporary directories, jobs built in code,
//! and an independent glTF accessor reader.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::atomic::{AtomicU64, Ordering};

use anchorage::integrator::FrameImage;
use anchorage::job::{Job, JobFile, Overrides};
use anchorage::pipeline;
use anchorage::session::FrameState;
use anchorage::stats::FrameStats;

pub fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// Where the third-party scenes live: `$ANCHORAGE_SCENES` if set (a relative path is taken
/// from the repository root), else `../shared/scenes` beside the repository.
pub fn scenes_dir() -> PathBuf {
    match std::env::var_os("ANCHORAGE_SCENES") {
        Some(dir) => root().join(dir),
        None => root().join("../shared/scenes"),
    }
}

/// The command that fetches the third-party scenes, for messages.
pub const FETCH_SCENES: &str = "scripts/fetch-scenes.sh";

/// A third-party scene file or folder, `FOLDER/FILE` or `FOLDER` (e.g.
/// `BoxAnimated/BoxAnimated.gltf`): the one way the tests locate these scenes.
/// Panics with one message saying how to fetch them when any file that
/// `tests/scenes/manifest.tsv` lists for the folder is missing, or the folder is not listed.
pub fn shared_scene(rel: &str) -> PathBuf {
    let dir = scenes_dir();
    let folder = rel.split('/').next().unwrap_or(rel);
    let files: Vec<ManifestEntry> = scene_manifest()
        .into_iter()
        .filter(|e| e.scene == folder)
        .collect();
    assert!(
        !files.is_empty(),
        "scene folder {folder} is not listed in tests/scenes/manifest.tsv: add its files, \
         source and licence there"
    );
    let missing: Vec<String> = files
        .iter()
        .map(|e| dir.join(&e.scene).join(&e.file))
        .filter(|p| !p.is_file())
        .map(|p| p.display().to_string())
        .collect();
    assert!(
        missing.is_empty(),
        "third-party scene {rel} is missing ({}): run `{FETCH_SCENES}` to fetch the scenes \
         into {}, where the tests read them ($ANCHORAGE_SCENES, else ../shared/scenes beside \
         the repository)",
        missing.join(", "),
        dir.display(),
    );
    dir.join(rel)
}

/// One row of `tests/scenes/manifest.tsv`: a file of a third-party scene and where it is from.
#[derive(Clone, Debug)]
pub struct ManifestEntry {
    pub scene: String,
    pub file: String,
    pub sha256: String,
    pub bytes: u64,
    pub repository: String,
    pub commit: String,
    pub path: String,
    pub licence: String,
}

/// The rows of `tests/scenes/manifest.tsv` (tab-separated; `#` starts a comment line).
pub fn scene_manifest() -> Vec<ManifestEntry> {
    let path = root().join("tests/scenes/manifest.tsv");
    let text = std::fs::read_to_string(&path).expect("tests/scenes/manifest.tsv is readable");
    text.lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty() && !l.starts_with('#'))
        .map(|(i, l)| {
            let f: Vec<&str> = l.split('\t').collect();
            assert_eq!(
                f.len(),
                8,
                "manifest.tsv line {}: 8 tab-separated fields",
                i + 1
            );
            ManifestEntry {
                scene: f[0].into(),
                file: f[1].into(),
                sha256: f[2].into(),
                bytes: f[3]
                    .parse()
                    .unwrap_or_else(|_| panic!("manifest.tsv line {}: bytes", i + 1)),
                repository: f[4].into(),
                commit: f[5].into(),
                path: f[6].into(),
                licence: f[7].into(),
            }
        })
        .collect()
}

/// SHA-256 (FIPS 180-4) of `data`, as lowercase hex. Here so that the manifest check needs
/// no extra crate (see `TempDir`).
pub fn sha256_hex(data: &[u8]) -> String {
    const K: [u32; 64] = [
        0x428a2f98, 0x71374491, 0xb5c0fbcf, 0xe9b5dba5, 0x3956c25b, 0x59f111f1, 0x923f82a4,
        0xab1c5ed5, 0xd807aa98, 0x12835b01, 0x243185be, 0x550c7dc3, 0x72be5d74, 0x80deb1fe,
        0x9bdc06a7, 0xc19bf174, 0xe49b69c1, 0xefbe4786, 0x0fc19dc6, 0x240ca1cc, 0x2de92c6f,
        0x4a7484aa, 0x5cb0a9dc, 0x76f988da, 0x983e5152, 0xa831c66d, 0xb00327c8, 0xbf597fc7,
        0xc6e00bf3, 0xd5a79147, 0x06ca6351, 0x14292967, 0x27b70a85, 0x2e1b2138, 0x4d2c6dfc,
        0x53380d13, 0x650a7354, 0x766a0abb, 0x81c2c92e, 0x92722c85, 0xa2bfe8a1, 0xa81a664b,
        0xc24b8b70, 0xc76c51a3, 0xd192e819, 0xd6990624, 0xf40e3585, 0x106aa070, 0x19a4c116,
        0x1e376c08, 0x2748774c, 0x34b0bcb5, 0x391c0cb3, 0x4ed8aa4a, 0x5b9cca4f, 0x682e6ff3,
        0x748f82ee, 0x78a5636f, 0x84c87814, 0x8cc70208, 0x90befffa, 0xa4506ceb, 0xbef9a3f7,
        0xc67178f2,
    ];
    let mut h: [u32; 8] = [
        0x6a09e667, 0xbb67ae85, 0x3c6ef372, 0xa54ff53a, 0x510e527f, 0x9b05688c, 0x1f83d9ab,
        0x5be0cd19,
    ];
    // Padding (§5.1.1): a 1 bit, zeros, then the message length in bits, to a 64-byte multiple.
    let mut msg = data.to_vec();
    msg.push(0x80);
    while msg.len() % 64 != 56 {
        msg.push(0);
    }
    msg.extend_from_slice(&((data.len() as u64) * 8).to_be_bytes());
    for block in msg.chunks_exact(64) {
        let mut w = [0u32; 64];
        for (t, word) in block.chunks_exact(4).enumerate() {
            w[t] = u32::from_be_bytes(word.try_into().unwrap());
        }
        for t in 16..64 {
            let s0 = w[t - 15].rotate_right(7) ^ w[t - 15].rotate_right(18) ^ (w[t - 15] >> 3);
            let s1 = w[t - 2].rotate_right(17) ^ w[t - 2].rotate_right(19) ^ (w[t - 2] >> 10);
            w[t] = w[t - 16]
                .wrapping_add(s0)
                .wrapping_add(w[t - 7])
                .wrapping_add(s1);
        }
        let [mut a, mut b, mut c, mut d, mut e, mut f, mut g, mut hh] = h;
        for t in 0..64 {
            let s1 = e.rotate_right(6) ^ e.rotate_right(11) ^ e.rotate_right(25);
            let ch = (e & f) ^ (!e & g);
            let t1 = hh
                .wrapping_add(s1)
                .wrapping_add(ch)
                .wrapping_add(K[t])
                .wrapping_add(w[t]);
            let s0 = a.rotate_right(2) ^ a.rotate_right(13) ^ a.rotate_right(22);
            let maj = (a & b) ^ (a & c) ^ (b & c);
            let t2 = s0.wrapping_add(maj);
            hh = g;
            g = f;
            f = e;
            e = d.wrapping_add(t1);
            d = c;
            c = b;
            b = a;
            a = t1.wrapping_add(t2);
        }
        for (x, y) in h.iter_mut().zip([a, b, c, d, e, f, g, hh]) {
            *x = x.wrapping_add(y);
        }
    }
    h.iter().map(|x| format!("{x:08x}")).collect()
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
    let scene = job.load_scene().expect("scene loads");
    let resources = pipeline::new_resources(job, &scene).expect("resources");
    let mut stats = blank_stats();
    pipeline::render_frame(
        job,
        &scene,
        &resources,
        &mut FrameState::default(),
        frame,
        &mut stats,
    )
    .expect("frame renders")
}

/// Renders `frames` in order in memory, carrying the cache and anchors from frame to frame
/// as a render does.
pub fn render_frames(job: &Job, frames: &[i32]) -> Vec<FrameImage> {
    let scene = job.load_scene().expect("scene loads");
    let resources = pipeline::new_resources(job, &scene).expect("resources");
    let mut state = FrameState::default();
    frames
        .iter()
        .map(|&f| {
            pipeline::render_frame(job, &scene, &resources, &mut state, f, &mut blank_stats())
                .expect("frame renders")
        })
        .collect()
}

fn blank_stats() -> FrameStats {
    FrameStats {
        frame: 0,
        time: 0.0,
        method: "direct".into(),
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

/// Blender (`$ANCHORAGE_BLENDER` or `blender` on the PATH; `.ci/run` installs Debian's), or
/// `None` with the reason printed. In CI (`CI` set) a missing Blender fails the test instead.
pub fn blender() -> Option<PathBuf> {
    let p = std::env::var_os("ANCHORAGE_BLENDER")
        .map(PathBuf::from)
        .or_else(|| {
            std::env::var_os("PATH").and_then(|path| {
                std::env::split_paths(&path)
                    .map(|d| d.join("blender"))
                    .find(|p| p.is_file())
            })
        });
    if let Some(p) = p.filter(|p| p.is_file()) {
        return Some(p);
    }
    if std::env::var_os("CI").is_some() {
        panic!("blender is missing: .ci/run must install it");
    }
    eprintln!("skipped: blender not found (.ci/run installs Debian's)");
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

/// `benches/sponza/job.json` (its moving box, its lights) with `method` and the keys of
/// `settings` added to its `method` object, at 80 × 45, seen from a fixed camera where the
/// shot starts.
pub fn sponza_from_a_fixed_camera(method: &str, settings: serde_json::Value) -> Job {
    let path = root().join("benches/sponza/job.json");
    let mut j: serde_json::Value = serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
    j["camera"] = serde_json::json!({"position": [-11, 2.5, -0.5], "look_at": [-1, 2.5, -0.5], "yfov_deg": 55});
    j["resolution"] = serde_json::json!([80, 45]);
    j["method"]["name"] = method.into();
    for (key, value) in settings.as_object().unwrap() {
        j["method"][key] = value.clone();
    }
    job_from_json(&path, &j.to_string()).unwrap()
}
