//! `compare.png` and `compare.svg`: two panels, RMS error of the beauty and of the
//! `indirect` AOV (where the methods differ) against seconds per frame, both axes
//! logarithmic, then a legend that grows with the number of variants.
//!
//! Each variant is a numbered point. Its colour is its method/preset; its marker tells
//! apart the values of a `--vary` sweep, whose points a line joins in sweep order.

use std::path::{Path, PathBuf};

use plotters::coord::Shift;
use plotters::coord::combinators::{LogCoord, WithKeyPoints};
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};

use super::{Report, Score};
use crate::error::{Error, Result};
use crate::output;

/// Noto Sans Regular cut down to Latin (SIL Open Font License 1.1), embedded so that no
/// system font is needed: `assets/fonts/README.md` says where it comes from.
const FONT: &[u8] = include_bytes!("../../assets/fonts/NotoSans-Regular-subset.ttf");
const FAMILY: &str = "sans-serif";

const WIDTH: u32 = 1200;
const TITLE_H: u32 = 36;
const PANEL_H: u32 = 460;
const LEGEND_COLUMNS: usize = 2;
const LEGEND_ROW_H: u32 = 18;
/// Legend entries drawn; the rest are counted in one line (compare.json lists all).
const LEGEND_MAX: usize = 200;

/// Tableau 10: one colour per method/preset, repeating past ten.
const PALETTE: [RGBColor; 10] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(127, 127, 127),
    RGBColor(188, 189, 34),
    RGBColor(23, 190, 207),
];
const MARKERS: usize = 6;

/// Writes `compare.png` and `compare.svg` into `dir`; returns their paths.
pub(super) fn write(dir: &Path, r: &Report) -> Result<[PathBuf; 2]> {
    plotters::style::register_font(FAMILY, FontStyle::Normal, FONT)
        .map_err(|_| Error::Render("the embedded plot font does not parse".into()))?;
    let (png, svg) = (dir.join("compare.png"), dir.join("compare.svg"));
    let img = raster(r)?;
    output::write_atomic(&png, |w| {
        img.write_to(w, image::ImageFormat::Png)
            .map_err(|e| e.to_string())
    })?;
    let text = vector(r)?;
    output::write_atomic(&svg, |w| {
        std::io::Write::write_all(w, text.as_bytes()).map_err(|e| e.to_string())
    })?;
    Ok([png, svg])
}

/// The plot as 8-bit sRGB pixels.
fn raster(r: &Report) -> Result<image::RgbImage> {
    let (w, h) = size(r);
    let mut rgb = vec![0u8; (w * h * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut rgb, (w, h)).into_drawing_area();
        draw(&root, r).map_err(plot_error)?;
        root.present().map_err(plot_error)?;
    }
    image::RgbImage::from_raw(w, h, rgb)
        .ok_or_else(|| Error::Render("plot buffer has the wrong size".into()))
}

/// The plot as SVG text (its labels in the viewer's sans-serif font).
fn vector(r: &Report) -> Result<String> {
    let mut text = String::new();
    {
        let root = SVGBackend::with_string(&mut text, size(r)).into_drawing_area();
        draw(&root, r).map_err(plot_error)?;
        root.present().map_err(plot_error)?;
    }
    Ok(text)
}

fn plot_error(e: impl std::fmt::Display) -> Error {
    Error::Render(format!("cannot draw the compare plot: {e}"))
}

fn legend_rows(r: &Report) -> usize {
    let shown = r.results.len().min(LEGEND_MAX);
    shown.div_ceil(LEGEND_COLUMNS) + usize::from(r.results.len() > LEGEND_MAX)
}

/// The image grows downwards with the legend, so any number of variants fits.
fn size(r: &Report) -> (u32, u32) {
    let legend = 2 * LEGEND_ROW_H + legend_rows(r) as u32 * LEGEND_ROW_H;
    (WIDTH, TITLE_H + PANEL_H + legend)
}

type DrawResult<DB> =
    std::result::Result<(), DrawingAreaErrorKind<<DB as DrawingBackend>::ErrorType>>;

fn draw<DB: DrawingBackend>(root: &DrawingArea<DB, Shift>, r: &Report) -> DrawResult<DB> {
    root.fill(&WHITE)?;
    let title = format!(
        "{}: frames {}..{}, {}x{}, error against {}",
        r.job, r.frames[0], r.frames[1], r.resolution[0], r.resolution[1], r.reference
    );
    let title_style = TextStyle::from((FAMILY, 18)).pos(Pos::new(HPos::Center, VPos::Center));
    let title = fit(root, &title, &title_style, WIDTH - 20)?;
    let (title_area, rest) = root.split_vertically(TITLE_H);
    title_area.draw(&Text::new(
        title,
        ((WIDTH / 2) as i32, (TITLE_H / 2) as i32),
        title_style,
    ))?;
    let (panels, legend_area) = rest.split_vertically(PANEL_H);
    let (beauty, indirect) = panels.split_horizontally(WIDTH / 2);
    let styles = Styles::of(r);
    panel(
        &beauty,
        r,
        &styles,
        "beauty",
        "RMS error of the beauty, %",
        |s| s.rms_error_pct,
    )?;
    panel(
        &indirect,
        r,
        &styles,
        "indirect",
        "RMS error of the indirect AOV, %",
        |s| s.indirect_rms_error_pct,
    )?;
    legend(&legend_area, r, &styles)
}

/// How each variant is drawn: colour by method/preset, marker by place in its sweep, and
/// the sweep (method/preset and swept key) whose points a line joins.
struct Styles {
    colour: Vec<RGBColor>,
    marker: Vec<usize>,
    sweeps: Vec<Vec<usize>>,
}

impl Styles {
    fn of(r: &Report) -> Styles {
        let (mut groups, mut sweep_keys) = (Vec::new(), Vec::new());
        let mut sweeps: Vec<Vec<usize>> = Vec::new();
        let (mut colour, mut marker) = (Vec::new(), Vec::new());
        for (i, s) in r.results.iter().enumerate() {
            let g = index_of(&mut groups, (&s.method, &s.preset));
            colour.push(PALETTE[g % PALETTE.len()]);
            let k = index_of(&mut sweep_keys, (&s.method, &s.preset, swept_key(s)));
            if k == sweeps.len() {
                sweeps.push(Vec::new());
            }
            marker.push(sweeps[k].len() % MARKERS);
            sweeps[k].push(i);
        }
        Styles {
            colour,
            marker,
            sweeps,
        }
    }

    /// Variant `i`'s marker, centred on the element's origin.
    fn marker<DB: DrawingBackend>(&self, i: usize) -> DynElement<'static, DB, (i32, i32)> {
        let c = self.colour[i];
        match self.marker[i] {
            0 => Circle::new((0, 0), 4, c.filled()).into_dyn(),
            1 => Rectangle::new([(-4, -4), (4, 4)], c.filled()).into_dyn(),
            2 => TriangleMarker::new((0, 0), 5, c.filled()).into_dyn(),
            3 => Cross::new((0, 0), 4, c.stroke_width(2)).into_dyn(),
            4 => Circle::new((0, 0), 4, c.stroke_width(2)).into_dyn(),
            _ => Rectangle::new([(-4, -4), (4, 4)], c.stroke_width(2)).into_dyn(),
        }
    }
}

/// Where `x` is in `list`, appending it if it is not there yet.
fn index_of<T: PartialEq>(list: &mut Vec<T>, x: T) -> usize {
    list.iter().position(|y| *y == x).unwrap_or_else(|| {
        list.push(x);
        list.len() - 1
    })
}

/// The swept key of a variant's label (`anchors/draft photons=50000` → `photons`), or "".
fn swept_key(s: &Score) -> &str {
    s.label
        .split_once(' ')
        .and_then(|(_, setting)| setting.split_once('='))
        .map_or("", |(key, _)| key)
}

/// One panel: `error` (%) against seconds per frame, both on log axes.
fn panel<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    r: &Report,
    styles: &Styles,
    caption: &str,
    y_desc: &str,
    error: impl Fn(&Score) -> f64,
) -> DrawResult<DB> {
    let xs: Vec<f64> = r
        .results
        .iter()
        .map(|s| s.seconds_per_frame_median)
        .collect();
    let ys: Vec<f64> = r.results.iter().map(error).collect();
    let (x_axis, xs) = LogAxis::new(&xs);
    let (y_axis, ys) = LogAxis::new(&ys);
    let mut chart = ChartBuilder::on(area)
        .caption(caption, (FAMILY, 16))
        .margin(12)
        .x_label_area_size(44)
        .y_label_area_size(64)
        .build_cartesian_2d(x_axis.coord(), y_axis.coord())?;
    chart
        .configure_mesh()
        .x_desc("seconds per frame (median)")
        .y_desc(y_desc)
        .x_label_formatter(&|v| short(*v))
        .y_label_formatter(&|v| short(*v))
        .label_style((FAMILY, 12))
        .axis_desc_style((FAMILY, 14))
        .light_line_style(WHITE)
        .draw()?;
    for sweep in styles.sweeps.iter().filter(|s| s.len() > 1) {
        let colour = styles.colour[sweep[0]];
        chart.draw_series(LineSeries::new(
            sweep.iter().map(|&i| (xs[i], ys[i])),
            colour.mix(0.6).stroke_width(1),
        ))?;
    }
    let label = TextStyle::from((FAMILY, 11)).pos(Pos::new(HPos::Left, VPos::Bottom));
    chart.draw_series((0..xs.len()).map(|i| {
        EmptyElement::at((xs[i], ys[i]))
            + styles.marker(i)
            + Text::new((i + 1).to_string(), (5, -3), label.color(&styles.colour[i]))
    }))?;
    Ok(())
}

/// Numbered entries in columns under the panels: marker, label, both errors.
fn legend<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    r: &Report,
    styles: &Styles,
) -> DrawResult<DB> {
    let style = TextStyle::from((FAMILY, 13)).pos(Pos::new(HPos::Left, VPos::Center));
    let column_w = (WIDTH - 40) / LEGEND_COLUMNS as u32;
    let row = |k: usize| (LEGEND_ROW_H * (k as u32 + 1)) as i32;
    area.draw(&Text::new(
        "N  method/preset [setting]: error of beauty, indirect (%)",
        (20, row(0)),
        style.color(&BLACK.mix(0.7)),
    ))?;
    let shown = r.results.len().min(LEGEND_MAX);
    let rows = shown.div_ceil(LEGEND_COLUMNS);
    for (i, s) in r.results.iter().take(shown).enumerate() {
        let (column, k) = (i / rows.max(1), i % rows.max(1));
        let x = 20 + (column as u32 * column_w) as i32;
        let text = format!(
            "{:>2}  {}: {:.2}, {:.2}",
            i + 1,
            s.label,
            s.rms_error_pct,
            s.indirect_rms_error_pct
        );
        let text = fit(area, &text, &style, column_w - 30)?;
        area.draw(
            &(EmptyElement::at((x + 6, row(k + 1)))
                + styles.marker(i)
                + Text::new(text, (10, 0), style.clone())),
        )?;
    }
    if r.results.len() > shown {
        let more = format!(
            "... and {} more (compare.json lists every variant)",
            r.results.len() - shown
        );
        area.draw(&Text::new(more, (20, row(rows + 1)), style.clone()))?;
    }
    Ok(())
}

/// `text`, cut short with "..." where it is wider than `max_w` pixels.
fn fit<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    text: &str,
    style: &TextStyle,
    max_w: u32,
) -> std::result::Result<String, DrawingAreaErrorKind<DB::ErrorType>> {
    if area.estimate_text_size(text, style)?.0 <= max_w {
        return Ok(text.to_string());
    }
    let chars: Vec<char> = text.chars().collect();
    for n in (0..chars.len()).rev() {
        let cut = format!("{}...", chars[..n].iter().collect::<String>());
        if area.estimate_text_size(&cut, style)?.0 <= max_w {
            return Ok(cut);
        }
    }
    Ok(String::new())
}

/// A log axis spanning some values, with tick marks where a reader can use them.
struct LogAxis {
    lo: f64,
    hi: f64,
}

impl LogAxis {
    /// The axis for `values`, and the values clamped onto it: zero (an exact match with
    /// the reference) sits on its lower edge, a value that is not finite on its upper.
    fn new(values: &[f64]) -> (LogAxis, Vec<f64>) {
        let positive = values.iter().copied().filter(|v| v.is_finite() && *v > 0.0);
        let (min, max) = positive.fold((f64::INFINITY, 0.0f64), |(a, b), v| (a.min(v), b.max(v)));
        let (lo, hi) = if max == 0.0 {
            (0.1, 10.0)
        } else {
            // Pad by 8 % of the span in log space, at least a factor 1.05 at each end.
            let pad = (max / min).powf(0.08).max(1.05);
            (min / pad, max * pad)
        };
        let clamped = values
            .iter()
            .map(|&v| if v.is_finite() { v.clamp(lo, hi) } else { hi })
            .collect();
        (LogAxis { lo, hi }, clamped)
    }

    fn coord(&self) -> WithKeyPoints<LogCoord<f64>> {
        (self.lo..self.hi).log_scale().with_key_points(self.ticks())
    }

    /// Powers of ten; or 1, 2, 5 per decade; or 1 to 9 per decade; or, on a span under a
    /// factor of about two, evenly spaced round numbers: whichever first gives three ticks.
    fn ticks(&self) -> Vec<f64> {
        let (lo, hi) = (self.lo, self.hi);
        let decades = lo.log10().floor() as i32..=hi.log10().ceil() as i32;
        let per_decade: [&[f64]; 3] = [
            &[1.0],
            &[1.0, 2.0, 5.0],
            &[1., 2., 3., 4., 5., 6., 7., 8., 9.],
        ];
        for mantissas in per_decade {
            let ticks: Vec<f64> = decades
                .clone()
                .flat_map(|e| mantissas.iter().map(move |m| m * 10f64.powi(e)))
                .filter(|t| (lo..=hi).contains(t))
                .collect();
            if ticks.len() >= 3 {
                // At most eight: every n-th of a long list.
                let step = ticks.len().div_ceil(8);
                return ticks.into_iter().step_by(step).collect();
            }
        }
        // The largest round step that leaves three ticks or more (and so at most eight).
        let step = nice_step_below((hi - lo) / 3.0);
        let first = (lo / step).ceil() as i64;
        let last = (hi / step).floor() as i64;
        (first..=last)
            .map(|k| k as f64 * step)
            .filter(|t| (lo..=hi).contains(t))
            .collect()
    }
}

/// The largest round number (1, 2 or 5 times a power of ten) not above `raw`.
fn nice_step_below(raw: f64) -> f64 {
    let decade = 10f64.powf(raw.log10().floor());
    [5.0, 2.0, 1.0]
        .into_iter()
        .map(|m| m * decade)
        .find(|&s| s <= raw)
        .unwrap_or(decade)
}

/// Three significant digits, trailing zeros dropped: 0.0123, 1.5, 20.
fn short(v: f64) -> String {
    if v == 0.0 || !v.is_finite() {
        return format!("{v}");
    }
    let decimals = (2 - v.abs().log10().floor() as i32).max(0) as usize;
    let s = format!("{v:.decimals$}");
    if s.contains('.') {
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::compare::score::sample as report;

    /// A fresh directory under the system's temporary directory, removed on drop.
    struct TempDir(std::path::PathBuf);

    impl TempDir {
        fn new(name: &str) -> TempDir {
            let p =
                std::env::temp_dir().join(format!("anchorage-plot-{name}-{}", std::process::id()));
            let _ = std::fs::remove_dir_all(&p);
            std::fs::create_dir_all(&p).unwrap();
            TempDir(p)
        }

        fn path(&self) -> &std::path::Path {
            &self.0
        }
    }

    impl Drop for TempDir {
        fn drop(&mut self) {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }

    fn check_written(n: usize) -> image::RgbImage {
        let dir = TempDir::new(&format!("n{n}"));
        let [png, svg] = write(dir.path(), &report(n)).unwrap();
        assert_eq!(png, dir.path().join("compare.png"));
        let svg = std::fs::read_to_string(svg).unwrap();
        assert!(svg.starts_with("<svg") && svg.contains("anchors/production"));
        let img = image::open(&png).unwrap().to_rgb8();
        assert_eq!(img.dimensions(), size(&report(n)));
        img
    }

    /// The hand-placed legend this plot replaced drew past the image's bottom edge, and
    /// panicked, from about 38 variants.
    #[test]
    fn sixty_variants_fit_in_png_and_svg() {
        let img = check_written(60);
        // Text was drawn: the embedded font rasterises (dark pixels in the legend).
        let legend_dark = (TITLE_H + PANEL_H..img.height())
            .flat_map(|y| (0..img.width()).map(move |x| (x, y)))
            .filter(|&(x, y)| img.get_pixel(x, y).0.iter().all(|&c| c < 100))
            .count();
        assert!(legend_dark > 1000, "{legend_dark} dark legend pixels");
    }

    #[test]
    fn one_and_very_many_variants_draw() {
        check_written(1);
        let img = check_written(LEGEND_MAX + 7);
        assert!(img.height() < 3000);
    }

    #[test]
    fn zero_error_and_equal_times_stay_on_the_axes() {
        let mut r = report(3);
        for s in &mut r.results {
            s.seconds_per_frame_median = 0.5;
        }
        r.results[0].rms_error_pct = 0.0;
        r.results[1].indirect_rms_error_pct = f64::NAN;
        let dir = TempDir::new("degenerate");
        write(dir.path(), &r).unwrap();
    }

    #[test]
    fn ticks_are_readable_on_narrow_and_wide_spans() {
        let ticks = |lo, hi| LogAxis { lo, hi }.ticks();
        assert_eq!(ticks(0.01, 20.0), [0.01, 0.1, 1.0, 10.0]);
        assert_eq!(ticks(0.3, 2.5), [0.5, 1.0, 2.0]);
        let close = |a: Vec<f64>, b: &[f64]| {
            a.len() == b.len() && a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-9)
        };
        assert!(close(ticks(1.65, 2.2), &[1.7, 1.8, 1.9, 2.0, 2.1, 2.2]));
        for (lo, hi) in [(1.63, 2.23), (4.4, 7.3), (1e-4, 1e4), (0.99, 1.01)] {
            let t = ticks(lo, hi);
            assert!((3..=8).contains(&t.len()), "{lo}..{hi}: {t:?}");
            assert!(t.iter().all(|v| (lo..=hi).contains(v)), "{lo}..{hi}: {t:?}");
        }
        assert_eq!(short(0.0123), "0.0123");
        assert_eq!(short(1.5), "1.5");
        assert_eq!(short(20.0), "20");
    }
}
