//! The build's identity: a BLAKE3 hash of everything that decides what this build renders —
//! the sources under `src/` and `shaders/`, `Cargo.toml` and `Cargo.lock` (the dependencies'
//! versions) — as `ANCHORAGE_BUILD`, 64 hex digits, and
//! `ANCHORAGE_VERSION`, the crate's version with the hash's first 12 digits (`--version`).
//!
//! Checkpoints carry it (`src/checkpoint.rs`): a state written by one build is read back only
//! by a build of the same sources, since any change to the renderer's behaviour (a default,
//! an estimate, the order records are placed in) would resume a shot from state the new
//! build would not have made, a silently wrong image. The crate's version alone does not
//! change between such builds. The hash is of the files' contents and their paths relative
//! to the package, not of the compiled binary, so machines that build the same sources
//! anywhere agree.

use std::path::{Path, PathBuf};

fn main() {
    let root = PathBuf::from(std::env::var_os("CARGO_MANIFEST_DIR").expect("cargo sets it"));
    let mut files = Vec::new();
    for dir in ["src", "shaders"] {
        collect(&root, &root.join(dir), &mut files);
        println!("cargo:rerun-if-changed={dir}");
    }
    // A source package without its lock file (none is written until cargo resolves one)
    // hashes without it.
    for file in ["Cargo.toml", "Cargo.lock"] {
        if root.join(file).exists() {
            files.push(PathBuf::from(file));
        }
        println!("cargo:rerun-if-changed={file}");
    }
    files.sort();
    let mut h = blake3::Hasher::new();
    h.update(b"anchorage build\0");
    for rel in &files {
        let bytes = std::fs::read(root.join(rel))
            .unwrap_or_else(|e| panic!("cannot read {}: {e}", rel.display()));
        // Separators as `/` on every platform, so that the hash is the same everywhere.
        let name = rel
            .components()
            .map(|c| c.as_os_str().to_string_lossy())
            .collect::<Vec<_>>()
            .join("/");
        h.update(&(name.len() as u64).to_le_bytes());
        h.update(name.as_bytes());
        h.update(&(bytes.len() as u64).to_le_bytes());
        h.update(&bytes);
    }
    let hex = h.finalize().to_hex();
    println!("cargo:rustc-env=ANCHORAGE_BUILD={hex}");
    println!(
        "cargo:rustc-env=ANCHORAGE_VERSION={} (build {})",
        std::env::var("CARGO_PKG_VERSION").expect("cargo sets it"),
        &hex[..12]
    );
}

/// Every file under `dir`, as paths relative to `root`, less hidden ones (an editor's swap
/// files are not sources).
fn collect(root: &Path, dir: &Path, out: &mut Vec<PathBuf>) {
    let entries =
        std::fs::read_dir(dir).unwrap_or_else(|e| panic!("cannot list {}: {e}", dir.display()));
    for entry in entries {
        let entry = entry.expect("a directory entry");
        if entry.file_name().to_string_lossy().starts_with('.') {
            continue;
        }
        let path = entry.path();
        if path.is_dir() {
            collect(root, &path, out);
        } else {
            out.push(
                path.strip_prefix(root)
                    .expect("under the root")
                    .to_path_buf(),
            );
        }
    }
}
