//! Frame output: one single-part OpenEXR per frame with `layer.channel` names (the layout
//! Nuke and Blender both read as layers), a stats JSON beside it (`schemas/stats.schema.json`)
//! and an optional PNG preview.
//!
//! Every file is first written to a temporary file created exclusively (never following a
//! symlink) under an unpredictable name in the output directory ([`tempfile`]), then renamed
//! into place. A frame's files are renamed together ([`commit`]), the EXR last, and removed
//! again if any rename fails: a frame is its EXR and its stats, or nothing. Temporary files
//! not yet renamed are listed so that SIGINT/SIGTERM can remove them before exiting
//! ([`install_signal_cleanup`]), which waits for a set being renamed to be whole. No output
//! replaces a file the run reads ([`protect_inputs`]).

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use exr::prelude::*;
use serde::Serialize;

use crate::error::{Error, Result};
use crate::integrator::FrameImage;

/// Temporary files of this process that are not renamed into place yet.
static PENDING: Mutex<Vec<PathBuf>> = Mutex::new(Vec::new());

fn pending() -> std::sync::MutexGuard<'static, Vec<PathBuf>> {
    PENDING.lock().unwrap_or_else(|e| e.into_inner())
}

/// Held while [`commit`] renames a set of files into place, and by the signal thread before
/// it removes the temporary files and exits: a signal that arrives mid-commit waits for the
/// set to be whole (a rename takes microseconds), rather than leaving a frame's stats
/// renamed without its EXR.
static COMMITTING: Mutex<()> = Mutex::new(());

/// The files this process reads as input (the job, its scenes' glTF, buffers and images):
/// [`commit`] renames nothing over one of them, by any name.
static INPUTS: Mutex<Vec<PathBuf>> = Mutex::new(Vec::new());

/// Makes `files` the inputs no output may replace ([`commit`]), in place of those of an
/// earlier load (watch mode loads the job again after each edit).
pub fn protect_inputs<'a>(files: impl IntoIterator<Item = &'a Path>) {
    let mut inputs = INPUTS.lock().unwrap_or_else(|e| e.into_inner());
    *inputs = files.into_iter().map(Path::to_path_buf).collect();
}

/// Refuses `paths` as outputs, before anything is written, if one names an input
/// ([`protect_inputs`]); the error names `at`, the key or flag that chose them.
pub fn refuse_inputs<P: AsRef<Path>>(at: &str, paths: impl IntoIterator<Item = P>) -> Result<()> {
    paths
        .into_iter()
        .try_for_each(|p| refuse_input(at, p.as_ref()))
}

/// Refuses `path` as an output if it is one of the inputs ([`protect_inputs`]): the same
/// file (device and inode) as an input's path is now, so that an input replaced since its
/// load, whose inode a new file may take, is not mistaken for its old self.
fn refuse_input(at: &str, path: &Path) -> Result<()> {
    use std::os::unix::fs::MetadataExt;
    let Ok(m) = std::fs::metadata(path) else {
        return Ok(());
    };
    let inputs = INPUTS.lock().unwrap_or_else(|e| e.into_inner());
    let same =
        |p: &PathBuf| std::fs::metadata(p).is_ok_and(|i| (i.dev(), i.ino()) == (m.dev(), m.ino()));
    if inputs.iter().any(same) {
        return Err(Error::input(
            path,
            at,
            "is a file this run reads (the job, or a file of its scene): writing the output \
             would replace it; choose another output directory or name",
        ));
    }
    Ok(())
}

/// A file written under a temporary name beside `path`, waiting to be renamed to it.
/// Dropped without [`commit`], the temporary file is removed.
pub struct Staged {
    tmp: Option<tempfile::TempPath>,
    path: PathBuf,
}

impl Drop for Staged {
    fn drop(&mut self) {
        if let Some(tmp) = self.tmp.take() {
            let p = tmp.to_path_buf();
            drop(tmp);
            pending().retain(|q| *q != p);
        }
    }
}

fn write_error(path: &Path, e: impl std::fmt::Display) -> Error {
    Error::Render(format!("cannot write {}: {e}", path.display()))
}

/// A new temporary file in `dir`, created exclusively, listed for removal on signals.
fn create_temp(dir: &Path, prefix: &str) -> std::io::Result<tempfile::NamedTempFile> {
    // Held while creating, so that a signal cannot fall between creation and listing.
    let mut list = pending();
    let mut b = tempfile::Builder::new();
    b.prefix(prefix).suffix(".tmp");
    // Outputs are read by others (compositors, farm users): the usual 0666 less the umask,
    // not the private 0600 of a temporary file.
    #[cfg(unix)]
    b.permissions(std::os::unix::fs::PermissionsExt::from_mode(0o666));
    let f = b.tempfile_in(dir)?;
    list.push(f.path().to_path_buf());
    Ok(f)
}

/// Writes a file through `write` to a new temporary file beside `path`.
pub fn stage(
    path: &Path,
    write: impl FnOnce(&mut BufWriter<&mut File>) -> std::result::Result<(), String>,
) -> Result<Staged> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let file = create_temp(dir, &format!(".{name}.")).map_err(|e| write_error(path, e))?;
    let (mut f, tmp) = file.into_parts();
    let staged = Staged {
        tmp: Some(tmp),
        path: path.to_path_buf(),
    };
    let mut w = BufWriter::new(&mut f);
    write(&mut w)
        .and_then(|()| w.flush().map_err(|e| e.to_string()))
        .map_err(|e| write_error(path, e))?;
    drop(w);
    f.sync_all().map_err(|e| write_error(path, e))?;
    Ok(staged)
}

/// Renames staged files into place in order; if one fails, those already renamed are
/// removed again, so the set appears whole or not at all.
pub fn commit(files: Vec<Staged>) -> Result<()> {
    for f in &files {
        refuse_input("output", &f.path)?;
    }
    let _committing = COMMITTING.lock().unwrap_or_else(|e| e.into_inner());
    let mut done: Vec<PathBuf> = Vec::new();
    for mut f in files {
        let Some(tmp) = f.tmp.take() else { continue };
        let tmp_path = tmp.to_path_buf();
        match tmp.persist(&f.path) {
            Ok(()) => {
                pending().retain(|q| *q != tmp_path);
                done.push(f.path.clone());
            }
            Err(e) => {
                drop(e.path);
                pending().retain(|q| *q != tmp_path);
                for d in &done {
                    let _ = std::fs::remove_file(d);
                }
                return Err(write_error(&f.path, e.error));
            }
        }
    }
    Ok(())
}

/// Writes one file: staged, then renamed into place.
pub fn write_atomic(
    path: &Path,
    write: impl FnOnce(&mut BufWriter<&mut File>) -> std::result::Result<(), String>,
) -> Result<()> {
    commit(vec![stage(path, write)?])
}

/// On SIGINT or SIGTERM, removes this process's temporary files and exits with 130 or 143
/// (128 + the signal), as shells report a process the signal ended.
pub fn install_signal_cleanup() -> Result<()> {
    use signal_hook::consts::{SIGINT, SIGTERM};
    let mut signals = signal_hook::iterator::Signals::new([SIGINT, SIGTERM])
        .map_err(|e| Error::Render(format!("cannot install signal handlers: {e}")))?;
    std::thread::Builder::new()
        .name("signals".into())
        .spawn(move || {
            if let Some(sig) = signals.forever().next() {
                // Never released: the process exits below.
                let _committing = COMMITTING.lock().unwrap_or_else(|e| e.into_inner());
                for p in pending().drain(..) {
                    let _ = std::fs::remove_file(p);
                }
                eprintln!("anchorage: interrupted (signal {sig}); temporary files removed");
                std::process::exit(128 + sig);
            }
        })
        .map_err(|e| Error::Render(format!("cannot start the signal thread: {e}")))?;
    Ok(())
}

/// Checks, creating nothing, that `dir` is a directory or can become one: each part of its
/// path that exists is a directory (`validate`, and a render's directories all checked
/// before any is made). Whether it accepts files is known only once it exists
/// ([`check_output_dir`]).
pub fn check_output_dir_unmade(dir: &Path) -> Result<()> {
    let fail = |at: &Path, m: &str| Error::Output {
        path: dir.to_path_buf(),
        message: if at == dir {
            m.to_string()
        } else {
            format!("{}: {m}", at.display())
        },
    };
    let mut at = Some(dir);
    while let Some(p) = at.filter(|p| !p.as_os_str().is_empty()) {
        match std::fs::metadata(p) {
            Ok(m) if m.is_dir() => return Ok(()),
            Ok(_) => return Err(fail(p, "is not a directory")),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => at = p.parent(),
            Err(e) => return Err(fail(p, &format!("cannot be read: {e}"))),
        }
    }
    Ok(())
}

/// Checks that `dir` exists (creating it) and accepts files, before any frame renders.
pub fn check_output_dir(dir: &Path) -> Result<()> {
    let fail = |m: String| Error::Output {
        path: dir.to_path_buf(),
        message: m,
    };
    std::fs::create_dir_all(dir)
        .map_err(|e| fail(format!("cannot create output directory: {e}")))?;
    let probe = create_temp(dir, ".anchorage-probe.")
        .map_err(|e| fail(format!("output directory is not writable: {e}")))?;
    let p = probe.path().to_path_buf();
    drop(probe);
    pending().retain(|q| *q != p);
    Ok(())
}

/// Stages the frame's AOVs as a ZIP-compressed, single-part, scanline EXR of 32-bit floats.
pub fn stage_exr(path: &Path, img: &FrameImage) -> Result<Staged> {
    let n = (img.width * img.height) as usize;
    let plane = |f: &dyn Fn(usize) -> f32| -> Vec<f32> { (0..n).map(f).collect() };
    let ch = |name: &str, v: Vec<f32>| AnyChannel::new(name, FlatSamples::F32(v));
    let channels = vec![
        ch("R", plane(&|i| img.beauty[i][0])),
        ch("G", plane(&|i| img.beauty[i][1])),
        ch("B", plane(&|i| img.beauty[i][2])),
        ch("A", plane(&|i| img.beauty[i][3])),
        ch("direct.R", plane(&|i| img.direct[i][0])),
        ch("direct.G", plane(&|i| img.direct[i][1])),
        ch("direct.B", plane(&|i| img.direct[i][2])),
        ch("indirect.R", plane(&|i| img.indirect[i][0])),
        ch("indirect.G", plane(&|i| img.indirect[i][1])),
        ch("indirect.B", plane(&|i| img.indirect[i][2])),
        ch("Z", img.depth.clone()),
    ];
    let mut channels = channels;
    for (layer, v) in [
        ("diffuse_direct", &img.diffuse_direct),
        ("glossy_direct", &img.glossy_direct),
        ("diffuse_indirect", &img.diffuse_indirect),
        ("glossy_indirect", &img.glossy_indirect),
    ] {
        if v.len() == n {
            for (c, name) in ["R", "G", "B"].iter().enumerate() {
                channels.push(ch(&format!("{layer}.{name}"), plane(&|i| v[i][c])));
            }
        }
    }
    if let Some(ids) = &img.anchor_id {
        channels.push(AnyChannel::new(
            "anchor_id.V",
            FlatSamples::U32(ids.clone()),
        ));
    }
    if let Some(r) = &img.reshoot {
        channels.push(ch("reshoot.V", r.clone()));
    }
    let layer = Layer::new(
        (img.width as usize, img.height as usize),
        LayerAttributes::default(),
        Encoding {
            compression: Compression::ZIP16,
            blocks: Blocks::ScanLines,
            line_order: LineOrder::Increasing,
        },
        AnyChannels::sort(smallvec::SmallVec::from_vec(channels)),
    );
    let image = Image::from_layer(layer);
    if cfg!(target_endian = "big") {
        return stage(path, |w| {
            image.write().to_buffered(w).map_err(|e| e.to_string())
        });
    }
    stage(path, |w| write_zip(&image, w).map_err(|e| e.to_string()))
}

/// Writes `image` (scan lines, ZIP compression) as the `exr` crate writes it — its header,
/// its blocks' pixel layout, its offset table — with each block deflated by libdeflate
/// instead of the crate's `miniz_oxide` at a fixed level: the same zlib stream format, made
/// about three times as fast (the crate's compression was an eighth of a watch-mode relight
/// of the example). Blocks are compressed in parallel on the render's pool and written in
/// increasing line order, so the bytes do not depend on scheduling. Little-endian hosts only
/// (the block bytes are taken as the file's little-endian samples).
fn write_zip(
    image: &Image<Layer<AnyChannels<FlatSamples>>>,
    w: impl std::io::Write + std::io::Seek,
) -> exr::error::UnitResult {
    use exr::block::chunk::{Chunk, CompressedBlock, CompressedScanLineBlock};
    use exr::block::writer::ChunksWriter;
    use exr::image::write::layers::{LayersWriter, WritableLayers};
    use rayon::prelude::*;
    let headers = image.layer_data.infer_headers(&image.attributes);
    let layers = image.layer_data.create_writer(&headers);
    let blocks: Vec<_> = exr::block::enumerate_ordered_header_block_indices(&headers).collect();
    let chunks: Vec<Chunk> = blocks
        .par_iter()
        .map(|&(_, index)| {
            let raw = layers.extract_uncompressed_block(&headers, index);
            let zipped = zip_block(&raw).filter(|z| z.len() < raw.len());
            let header = &headers[index.layer];
            Chunk {
                layer_index: index.layer,
                compressed_block: CompressedBlock::ScanLine(CompressedScanLineBlock {
                    // Stored compressed only where that is smaller (OpenEXR's rule).
                    compressed_pixels_le: zipped.unwrap_or(raw),
                    y_coordinate: index.pixel_position.y() as i32
                        + header.own_attributes.layer_position.y(),
                }),
            }
        })
        .collect();
    exr::block::write(w, headers, true, |_, writer| {
        for ((i, _), chunk) in blocks.iter().zip(chunks) {
            writer.write_chunk(*i, chunk)?;
        }
        Ok(())
    })
}

/// OpenEXR's ZIP compression of a block's little-endian bytes: the bytes split into their
/// even and odd halves, each byte replaced by its difference to the one before (plus 128),
/// and the result deflated into a zlib stream (`None` if libdeflate fails).
fn zip_block(raw: &[u8]) -> Option<Vec<u8>> {
    let half = raw.len().div_ceil(2);
    let mut bytes = vec![0u8; raw.len()];
    for (i, &b) in raw.iter().enumerate() {
        bytes[if i % 2 == 0 { i / 2 } else { half + i / 2 }] = b;
    }
    let mut previous = bytes.first().copied().unwrap_or(0);
    for b in bytes.iter_mut().skip(1) {
        let sample = *b;
        *b = sample.wrapping_sub(previous).wrapping_add(128);
        previous = sample;
    }
    let mut deflate = libdeflater::Compressor::new(libdeflater::CompressionLvl::default());
    let mut out = vec![0u8; deflate.zlib_compress_bound(bytes.len())];
    let n = deflate.zlib_compress(&bytes, &mut out).ok()?;
    out.truncate(n);
    Some(out)
}

/// Display transform for previews: clamp, then the sRGB curve.
fn to_srgb8(v: f32) -> u8 {
    let v = if v.is_finite() {
        v.clamp(0.0, 1.0)
    } else {
        0.0
    };
    let s = if v <= 0.003_130_8 {
        12.92 * v
    } else {
        1.055 * v.powf(1.0 / 2.4) - 0.055
    };
    (s * 255.0).round() as u8
}

/// How a preview's exposure fits the image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PreviewExposure {
    /// Fraction of pixels with a channel clipped at white.
    pub clipped: f32,
    /// The exposure (stops) that would put the 99th-percentile luminance at white.
    pub suggested: f32,
}

/// Stages an 8-bit sRGB preview of the beauty pass scaled by 2^`exposure`, composited over
/// black, and says how much of it clips.
pub fn stage_png(
    path: &Path,
    img: &FrameImage,
    exposure: f32,
) -> Result<(Staged, PreviewExposure)> {
    let gain = exposure.exp2();
    let mut buf = image::RgbImage::new(img.width, img.height);
    let mut clipped = 0usize;
    for (i, p) in buf.pixels_mut().enumerate() {
        let b = img.beauty[i].map(|v| v * gain);
        clipped += usize::from(b[..3].iter().any(|&v| v > 1.0));
        *p = image::Rgb([to_srgb8(b[0]), to_srgb8(b[1]), to_srgb8(b[2])]);
    }
    let mut lum: Vec<f32> = img
        .beauty
        .iter()
        .map(|b| crate::color::luminance(glam::Vec3::new(b[0], b[1], b[2])))
        .filter(|l| l.is_finite() && *l > 0.0)
        .collect();
    let p99 = if lum.is_empty() {
        1.0
    } else {
        let k = (lum.len() * 99 / 100).min(lum.len() - 1);
        *lum.select_nth_unstable_by(k, f32::total_cmp).1
    };
    let staged = stage(path, |w| {
        buf.write_to(w, image::ImageFormat::Png)
            .map_err(|e| e.to_string())
    })?;
    Ok((
        staged,
        PreviewExposure {
            clipped: clipped as f32 / img.beauty.len().max(1) as f32,
            suggested: -(p99.log2() * 2.0).round() / 2.0,
        },
    ))
}

/// Stages any serialisable value as pretty JSON.
pub fn stage_json<T: Serialize>(path: &Path, value: &T) -> Result<Staged> {
    let text = serde_json::to_string_pretty(value).map_err(|e| Error::Render(e.to_string()))?;
    stage(path, |w| {
        w.write_all(text.as_bytes())
            .and_then(|()| w.write_all(b"\n"))
            .map_err(|e| e.to_string())
    })
}

/// Writes one frame's AOVs as an EXR on its own (outside a frame's set of files).
pub fn write_exr(path: &Path, img: &FrameImage) -> Result<()> {
    commit(vec![stage_exr(path, img)?])
}

/// Writes one preview PNG at exposure 0 on its own.
pub fn write_png(path: &Path, img: &FrameImage) -> Result<()> {
    commit(vec![stage_png(path, img, 0.0)?.0])
}

/// Writes any serialisable value as pretty JSON.
pub fn write_json<T: Serialize>(path: &Path, value: &T) -> Result<()> {
    commit(vec![stage_json(path, value)?])
}
