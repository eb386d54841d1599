//! A mutation fuzzer for everything anchorage reads, on stable Rust: real glTF, GLB and job
//! files are mutated (bit flips, truncations, byte runs, JSON value and structure swaps) and
//! handed to the loader and the validator in-process; a panic is a failure.
//!
//! ```text
//! cargo run --release --example fuzz -- [INPUTS] [SEED]
//! ```
//!
//! Inputs run in child processes of this same program in batches, so that an abort (an
//! allocation failure, a stack overflow) or a hang is caught too: the parent restarts after
//! the input that killed the child and keeps it. Every failing input is written to
//! `target/fuzz-crashers/` for `tests/fuzz-crashers/`, where a test keeps it fixed.

use std::io::Write;
use std::panic::AssertUnwindSafe;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// SplitMix64: small, fast and the same everywhere.
pub struct Rng(u64);

impl Rng {
    pub fn new(seed: u64) -> Rng {
        Rng(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ 0xD1B5_4A32_D192_ED03)
    }
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    pub fn below(&mut self, n: usize) -> usize {
        (self.next_u64() % n.max(1) as u64) as usize
    }
}

/// One seed file: its kind decides how it is loaded.
#[derive(Clone)]
pub struct Seed {
    pub name: String,
    pub kind: Kind,
    pub bytes: Vec<u8>,
}

#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum Kind {
    Gltf,
    Glb,
    Job,
}

/// The seed corpus: the example, the shared real scenes that are small enough, and a job.
pub fn seeds(root: &Path, scenes: &Path) -> Vec<Seed> {
    let mut out = Vec::new();
    let mut add = |name: &str, kind: Kind, path: PathBuf| {
        if let Ok(bytes) = std::fs::read(&path)
            && bytes.len() < 64 << 10
        {
            out.push(Seed {
                name: name.into(),
                kind,
                bytes,
            });
        }
    };
    add(
        "room.gltf",
        Kind::Gltf,
        root.join("examples/room/room.gltf"),
    );
    add(
        "room-job.json",
        Kind::Job,
        root.join("examples/room/job.json"),
    );
    for (name, kind, rel) in [
        ("cubes.glb", Kind::Glb, "bevy_Cubes/Cubes.glb"),
        ("extras.glb", Kind::Glb, "bevy_gltf_extras/gltf_extras.glb"),
        ("cornell.glb", Kind::Glb, "cornellbox_bevy/CornellBox.glb"),
        (
            "triangle.gltf",
            Kind::Gltf,
            "AnimatedTriangle/AnimatedTriangle.gltf",
        ),
        ("box.gltf", Kind::Gltf, "BoxAnimated/BoxAnimated.gltf"),
        ("rigged.gltf", Kind::Gltf, "RiggedSimple/RiggedSimple.gltf"),
        (
            "anims.gltf",
            Kind::Gltf,
            "blenderio_03_all_animations/03_all_animations.gltf",
        ),
        (
            "nla.gltf",
            Kind::Gltf,
            "blenderio_07_nla-anim/07_nla-anim.gltf",
        ),
    ] {
        add(name, kind, scenes.join(rel));
    }
    out
}

const INTERESTING: &[&str] = &[
    "0",
    "-1",
    "1",
    "2",
    "3",
    "255",
    "65535",
    "4294967295",
    "2147483648",
    "4611686018427387904",
    "-2147483649",
    "1e30",
    "-1e30",
    "1e-45",
    "0.5",
    "\"\"",
    "\"x\"",
    "null",
    "true",
    "[]",
    "{}",
    "[0,0,0]",
    "[1e38,1e38,1e38]",
    "[[[[[[[[[[[[[[[[1]]]]]]]]]]]]]]]]",
    "\"nodes[0]\"",
    "\"../../etc/passwd\"",
    "\"/dev/zero\"",
    "5126",
    "5125",
    "5123",
    "5121",
    "5120",
    "34962",
];

/// Mutates `seed` once or a few times.
pub fn mutate(seed: &Seed, rng: &mut Rng) -> Vec<u8> {
    let mut b = seed.bytes.clone();
    let rounds = 1 + rng.below(3);
    for _ in 0..rounds {
        let json = seed.kind != Kind::Glb || rng.below(2) == 0;
        match rng.below(if json { 8 } else { 5 }) {
            0 if !b.is_empty() => {
                let i = rng.below(b.len());
                b[i] ^= 1 << rng.below(8);
            }
            1 if !b.is_empty() => {
                let n = rng.below(b.len());
                b.truncate(n);
            }
            2 if !b.is_empty() => {
                let i = rng.below(b.len());
                let v = [0u8, 0xff, 0x7f, 0x80][rng.below(4)];
                let n = (1 + rng.below(8)).min(b.len() - i);
                b[i..i + n].fill(v);
            }
            3 if b.len() > 1 => {
                let (i, j) = (rng.below(b.len()), rng.below(b.len()));
                let (lo, hi) = (i.min(j), i.max(j));
                let chunk = b[lo..hi.min(lo + 64)].to_vec();
                let at = rng.below(b.len());
                b.splice(at..at, chunk);
            }
            4 if b.len() >= 4 => {
                // A little-endian u32 somewhere set to an interesting value (GLB headers,
                // chunk lengths, binary data).
                let i = rng.below(b.len() - 3) & !3;
                let v: u32 = [0, 1, 0x7fff_ffff, 0xffff_ffff, 0x8000_0000, 12, 20][rng.below(7)];
                b[i..i + 4].copy_from_slice(&v.to_le_bytes());
            }
            _ => b = mutate_json(&b, rng),
        }
    }
    b
}

/// Replaces a JSON value with an interesting one, swaps two values, or deletes a key. In a
/// GLB, works on its JSON chunk and keeps the container consistent.
fn mutate_json(b: &[u8], rng: &mut Rng) -> Vec<u8> {
    if b.len() >= 20 && &b[0..4] == b"glTF" {
        let len = u32::from_le_bytes([b[12], b[13], b[14], b[15]]) as usize;
        if 20 + len <= b.len() {
            let json = mutate_json(&b[20..20 + len], rng);
            let mut pad = json;
            while !pad.len().is_multiple_of(4) {
                pad.push(b' ');
            }
            let mut out = b[..12].to_vec();
            out.extend((pad.len() as u32).to_le_bytes());
            out.extend(&b[16..20]);
            out.extend(&pad);
            out.extend(&b[20 + len..]);
            let total = out.len() as u32;
            out[8..12].copy_from_slice(&total.to_le_bytes());
            return out;
        }
        return b.to_vec();
    }
    let Ok(mut v) = serde_json::from_slice::<serde_json::Value>(b) else {
        return b.to_vec();
    };
    let mut paths = Vec::new();
    collect_paths(&v, &mut Vec::new(), &mut paths);
    if paths.is_empty() {
        return b.to_vec();
    }
    let p = paths[rng.below(paths.len())].clone();
    match rng.below(4) {
        0 | 1 => {
            let new: serde_json::Value =
                serde_json::from_str(INTERESTING[rng.below(INTERESTING.len())]).unwrap();
            if let Some(slot) = at_mut(&mut v, &p) {
                *slot = new;
            }
        }
        2 => {
            let q = paths[rng.below(paths.len())].clone();
            let other = at_mut(&mut v, &q).map(|s| s.clone());
            if let (Some(o), Some(slot)) = (other, at_mut(&mut v, &p)) {
                *slot = o;
            }
        }
        _ => {
            if let Some((last, parent)) = p.split_last()
                && let Some(serde_json::Value::Object(m)) = at_mut(&mut v, parent)
                && let Step::Key(k) = last
            {
                m.remove(k);
            }
        }
    }
    serde_json::to_vec(&v).unwrap_or_else(|_| b.to_vec())
}

#[derive(Clone)]
enum Step {
    Key(String),
    Index(usize),
}

fn collect_paths(v: &serde_json::Value, here: &mut Vec<Step>, out: &mut Vec<Vec<Step>>) {
    if out.len() > 20_000 {
        return;
    }
    match v {
        serde_json::Value::Object(m) => {
            for (k, c) in m {
                here.push(Step::Key(k.clone()));
                out.push(here.clone());
                collect_paths(c, here, out);
                here.pop();
            }
        }
        serde_json::Value::Array(a) => {
            for (i, c) in a.iter().enumerate().take(64) {
                here.push(Step::Index(i));
                out.push(here.clone());
                collect_paths(c, here, out);
                here.pop();
            }
        }
        _ => {}
    }
}

fn at_mut<'a>(v: &'a mut serde_json::Value, p: &[Step]) -> Option<&'a mut serde_json::Value> {
    let mut cur = v;
    for s in p {
        cur = match s {
            Step::Key(k) => cur.get_mut(k)?,
            Step::Index(i) => cur.get_mut(*i)?,
        };
    }
    Some(cur)
}

/// Loads and validates one input the way `anchorage validate` and `inspect` do. Errors are
/// fine; only panics (and aborts and hangs, seen by the parent) are failures.
pub fn check(dir: &Path, kind: Kind, bytes: &[u8]) -> Result<(), String> {
    let (file, job) = match kind {
        Kind::Gltf => ("in.gltf", None),
        Kind::Glb => ("in.glb", None),
        Kind::Job => ("in.json", Some(())),
    };
    let path = dir.join(file);
    std::fs::write(&path, bytes).map_err(|e| e.to_string())?;
    let result = std::panic::catch_unwind(AssertUnwindSafe(|| {
        use anchorage::job::{Job, JobFile, Overrides};
        let loaded = if job.is_some() {
            Job::load(&path, &Overrides::default())
        } else {
            let file = JobFile {
                resolution: [16, 16],
                ..JobFile::for_scene(PathBuf::from(file))
            };
            Job::from_file(&dir.join("job.json"), file, &Overrides::default())
        };
        if let Ok(job) = loaded
            && let Ok(scene) = job.load_scene_layers()
        {
            let _ = scene.warnings();
            if scene.camera.is_some() {
                let _ = anchorage::budget::check(&job, &scene, None);
                // Evaluating the first frame builds every prim, as a render would.
                let statics = scene.statics();
                let _ = scene.evaluate(0.0, 1.0, &statics);
            }
        }
    }));
    result.map_err(|p| {
        p.downcast_ref::<&str>()
            .map(|s| s.to_string())
            .or_else(|| p.downcast_ref::<String>().cloned())
            .unwrap_or_else(|| "panic".into())
    })
}

/// Runs inputs `from..to` of the sequence (`seed`), printing `done N` after each, and
/// `panic N` with the message for panics.
fn worker(seeds: &[Seed], seed: u64, from: u64, to: u64, dir: &Path) {
    std::panic::set_hook(Box::new(|_| {}));
    let mut out = std::io::stdout().lock();
    for i in from..to {
        let (s, bytes) = input(seeds, seed, i);
        if let Err(msg) = check(dir, s.kind, &bytes) {
            let _ = writeln!(out, "panic {i} {}", msg.replace('\n', " "));
        }
        let _ = writeln!(out, "done {i}");
        let _ = out.flush();
    }
}

/// Input `i` of the sequence: which seed and its mutation.
pub fn input(seeds: &[Seed], seed: u64, i: u64) -> (&Seed, Vec<u8>) {
    let mut rng = Rng::new(seed ^ i.wrapping_mul(0xA076_1D64_78BD_642F));
    let s = &seeds[rng.below(seeds.len())];
    let bytes = mutate(s, &mut rng);
    (s, bytes)
}

fn keep(crashers: &Path, s: &Seed, i: u64, bytes: &[u8], what: &str) {
    let _ = std::fs::create_dir_all(crashers);
    let ext = match s.kind {
        Kind::Gltf => "gltf",
        Kind::Glb => "glb",
        Kind::Job => "json",
    };
    let name = format!("{what}-{}-{i}.{ext}", s.name.replace('.', "_"));
    let _ = std::fs::write(crashers.join(name), bytes);
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let scenes = std::env::var_os("ANCHORAGE_SCENES")
        .map(PathBuf::from)
        .unwrap_or_else(|| root.join("../shared/scenes"));
    let seeds = seeds(&root, &scenes);
    let work = std::env::temp_dir().join(format!("anchorage-fuzz-{}", std::process::id()));
    let _ = std::fs::create_dir_all(&work);
    // Jobs name the example's scene beside them.
    let _ = std::fs::copy(root.join("examples/room/room.gltf"), work.join("room.gltf"));
    if args.get(1).map(String::as_str) == Some("--worker") {
        let n = |k: usize| args[k].parse::<u64>().unwrap();
        worker(&seeds, n(2), n(3), n(4), &work);
        let _ = std::fs::remove_dir_all(&work);
        return;
    }
    let total: u64 = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(10_000);
    let seed: u64 = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(1);
    let crashers = root.join("target/fuzz-crashers");
    let (mut panics, mut aborts, mut hangs) = (0u64, 0u64, 0u64);
    let mut by_kind = [0u64; 3];
    let start = Instant::now();
    let batch = 5_000u64;
    let mut next = 0u64;
    while next < total {
        let to = (next + batch).min(total);
        let mut child = Command::new(&args[0])
            .args([
                "--worker",
                &seed.to_string(),
                &next.to_string(),
                &to.to_string(),
            ])
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .expect("worker starts");
        let stdout = child.stdout.take().unwrap();
        let (tx, rx) = std::sync::mpsc::channel::<String>();
        std::thread::spawn(move || {
            use std::io::BufRead;
            for line in std::io::BufReader::new(stdout)
                .lines()
                .map_while(Result::ok)
            {
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        let mut last_done: Option<u64> = None;
        loop {
            match rx.recv_timeout(Duration::from_secs(20)) {
                Ok(line) => {
                    if let Some(rest) = line.strip_prefix("panic ") {
                        let (i, msg) = rest.split_once(' ').unwrap_or((rest, ""));
                        let i: u64 = i.parse().unwrap();
                        let (s, bytes) = input(&seeds, seed, i);
                        panics += 1;
                        eprintln!("panic at input {i} ({}): {msg}", s.name);
                        keep(&crashers, s, i, &bytes, "panic");
                    } else if let Some(i) = line.strip_prefix("done ") {
                        let i: u64 = i.parse().unwrap();
                        by_kind[input(&seeds, seed, i).0.kind as usize] += 1;
                        last_done = Some(i);
                    }
                }
                Err(std::sync::mpsc::RecvTimeoutError::Timeout) => {
                    let _ = child.kill();
                    let i = last_done.map_or(next, |d| d + 1);
                    let (s, bytes) = input(&seeds, seed, i);
                    hangs += 1;
                    eprintln!("hang at input {i} ({})", s.name);
                    keep(&crashers, s, i, &bytes, "hang");
                    last_done = Some(i);
                    break;
                }
                Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => break,
            }
        }
        let status = child.wait().expect("worker exits");
        let resume = last_done.map_or(next, |d| d + 1);
        if !status.success() && resume < to {
            let (s, bytes) = input(&seeds, seed, resume);
            aborts += 1;
            eprintln!("abort at input {resume} ({}): {status}", s.name);
            keep(&crashers, s, resume, &bytes, "abort");
            next = resume + 1;
        } else {
            next = resume.max(to);
        }
    }
    let _ = std::fs::remove_dir_all(&work);
    println!(
        "{total} inputs (glTF {}, GLB {}, job {}) from {} seeds in {:.0} s: {panics} panics, {aborts} aborts, {hangs} hangs",
        by_kind[Kind::Gltf as usize],
        by_kind[Kind::Glb as usize],
        by_kind[Kind::Job as usize],
        seeds.len(),
        start.elapsed().as_secs_f64()
    );
    if panics + aborts + hangs > 0 {
        println!("failing inputs kept in {}", crashers.display());
        std::process::exit(1);
    }
}
