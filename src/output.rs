//! Frame output: one single-part OpenEXR per frame with `layer.channel` names (the layout
//! Nuke and Blender both read as layers), a stats JSON beside it (`schemas/stats.schema.json`)
//! and an optional PNG preview. Every file is written to a temporary name in the same
//! directory and renamed into place, so a failed or interrupted frame leaves no partial file.

use std::path::{Path, PathBuf};

use exr::prelude::*;
use serde::Serialize;

use crate::error::{Error, Result};
use crate::integrator::FrameImage;

/// Writes a file through `write` to a temporary name beside `path`, then renames it.
pub fn write_atomic(
    path: &Path,
    write: impl FnOnce(&Path) -> std::result::Result<(), String>,
) -> Result<()> {
    let dir = path.parent().unwrap_or(Path::new("."));
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let tmp: PathBuf = dir.join(format!(".{name}.tmp-{}", std::process::id()));
    let result = write(&tmp).and_then(|()| std::fs::rename(&tmp, path).map_err(|e| e.to_string()));
    if let Err(e) = result {
        let _ = std::fs::remove_file(&tmp);
        return Err(Error::Render(format!(
            "cannot write {}: {e}",
            path.display()
        )));
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
    let probe = dir.join(format!(".anchorage-probe-{}", std::process::id()));
    std::fs::write(&probe, b"")
        .map_err(|e| fail(format!("output directory is not writable: {e}")))?;
    let _ = std::fs::remove_file(&probe);
    Ok(())
}

/// Writes the frame's AOVs as a ZIP-compressed, single-part, scanline EXR of 32-bit floats.
pub fn write_exr(path: &Path, img: &FrameImage) -> Result<()> {
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
    // Single-threaded compression keeps the byte stream independent of scheduling.
    write_atomic(path, |tmp| {
        image
            .write()
            .non_parallel()
            .to_file(tmp)
            .map_err(|e| e.to_string())
    })
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

/// Writes an 8-bit sRGB preview of the beauty pass scaled by 2^`exposure`, composited over
/// black, and says how much of it clips.
pub fn write_png(path: &Path, img: &FrameImage, exposure: f32) -> Result<PreviewExposure> {
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
    write_atomic(path, |tmp| {
        buf.save_with_format(tmp, image::ImageFormat::Png)
            .map_err(|e| e.to_string())
    })?;
    Ok(PreviewExposure {
        clipped: clipped as f32 / img.beauty.len().max(1) as f32,
        suggested: -(p99.log2() * 2.0).round() / 2.0,
    })
}

/// Writes any serialisable value as pretty JSON.
pub fn write_json<T: Serialize>(path: &Path, value: &T) -> Result<()> {
    let text = serde_json::to_string_pretty(value).map_err(|e| Error::Render(e.to_string()))?;
    write_atomic(path, |tmp| {
        std::fs::write(tmp, text + "\n").map_err(|e| e.to_string())
    })
}
