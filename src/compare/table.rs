//! The text tables `compare` prints: one row per variant with time, error and flicker, then
//! the paper's Table 1 breakdown of seconds per stage.

use super::Report;

/// The table printed on stdout.
pub fn table(r: &Report) -> String {
    let mut s = format!(
        "reference {} ({:.2} s/frame, own flicker {} beauty, {} indirect), frames {}..{}, {}x{}\n",
        r.reference,
        r.reference_seconds_per_frame_median,
        fmt_opt(r.reference_flicker_pct),
        fmt_opt(r.reference_indirect_flicker_pct),
        r.frames[0],
        r.frames[1],
        r.resolution[0],
        r.resolution[1]
    );
    s += &format!(
        "{:<40} {:>9} {:>9} {:>9} {:>9} {:>9} {:>12} {:>8} {:>9} {:>9} {:>9}\n",
        "method/preset",
        "s/frame",
        "RMS err%",
        "flicker%",
        "ind.err%",
        "ind.flk%",
        "gather rays",
        "caches",
        "photons",
        "RMS*%",
        "ind.err*%"
    );
    for x in &r.results {
        s += &format!(
            "{:<40} {:>9.3} {:>9.2} {:>9} {:>9.2} {:>9} {:>12.0} {:>8.0} {:>9.0} {:>9} {:>9}\n",
            x.label,
            x.seconds_per_frame_median,
            x.rms_error_pct,
            fmt_opt(x.flicker_pct),
            x.indirect_rms_error_pct,
            fmt_opt(x.indirect_flicker_pct),
            x.rays_shot_per_frame,
            x.caches_per_frame,
            x.photons_per_frame,
            fmt_pct(x.rms_error_pct_denoised),
            fmt_pct(x.indirect_rms_error_pct_denoised)
        );
    }
    s += "RMS*% and ind.err*%: the same errors less the reference's own noise (its per-pixel variance)\n";
    s += &format!(
        "\nmedian seconds per stage (paper Table 1), {} worker threads\n{:<40} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8} {:>14} {:>8} {:>8} {:>8}\n",
        rayon::current_num_threads(),
        "method/preset",
        "photons",
        "irr.est",
        "attach",
        "integr",
        "gather",
        "interp",
        "direct",
        "visib.",
        "place",
        "upkeep",
        "other",
        "total",
        "gather rays/s/core",
        "reshot%",
        "flag%",
        "vis/10k"
    );
    for x in &r.results {
        let t = &x.table1_s;
        s += &format!(
            "{:<40} {:>8.3} {:>8.3} {:>8.3} {:>8.3} {:>8.3} {:>8.3} {:>8.3} {:>8.3} {:>8.3} {:>8.3} {:>8.3} {:>8.3} {:>14} {:>8} {:>8} {:>8}\n",
            x.label,
            t.photon_tracing,
            t.irradiance_estimation,
            t.attachment,
            t.integration,
            t.final_gathering,
            t.cache_interpolation,
            t.direct_lighting,
            t.visibility,
            t.placement,
            t.upkeep,
            t.other,
            t.total,
            x.gather_rays_per_s_per_core
                .map_or("n/a".into(), |v| format!("{:.2} M", v / 1e6)),
            x.reshot_pct.map_or("n/a".into(), |v| format!("{v:.2}")),
            x.flagged_pct.map_or("n/a".into(), |v| format!("{v:.2}")),
            x.visibility_s_per_10k_caches
                .map_or("n/a".into(), |v| format!("{v:.3}"))
        );
    }
    s
}

fn fmt_pct(v: Option<f64>) -> String {
    v.map_or("n/a".into(), |v| format!("{v:.2}"))
}

fn fmt_opt(v: Option<f64>) -> String {
    v.map_or("n/a".into(), |v| format!("{v:.3}"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::compare::score::sample;

    /// The columns that README.md's measurements and scripts read.
    #[test]
    fn rows_keep_their_columns() {
        let t = table(&sample(2));
        let lines: Vec<&str> = t.lines().collect();
        assert_eq!(
            lines[..3],
            [
                "reference path-trace/final (12.00 s/frame, own flicker 0.100 beauty, n/a indirect), frames 0..2, 128x96",
                "method/preset                              s/frame  RMS err%  flicker%  ind.err%  ind.flk%  gather rays   caches   photons     RMS*% ind.err*%",
                "anchors/production photons=10000             0.200      1.90     0.500      5.10       n/a      1000000      800     50000      1.50       n/a",
            ]
        );
        assert_eq!(
            lines[7..9],
            [
                "method/preset                             photons  irr.est   attach   integr   gather   interp   direct   visib.    place   upkeep    other    total gather rays/s/core  reshot%    flag%  vis/10k",
                "anchors/production photons=10000            0.010    0.020    0.030    0.005    0.100    0.010    0.020    0.000    0.015    0.005    0.020    0.200         2.00 M      n/a      n/a      n/a",
            ]
        );
    }
}
