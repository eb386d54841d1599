//! What `compare` renders: the variants (method × preset × swept setting) and the
//! reference, planned from the command line's flags and checked before anything renders.
//! Errors name the flag at fault (exit code 2).

use clap::ValueEnum;

use crate::error::{Error, Result};
use crate::integrator::Preset;
use crate::integrator::cached::GlossyMode;
use crate::job::{Job, Method, VisibilityChoice};

/// The `compare` flags that choose variants, as typed on the command line.
#[derive(Debug, Clone)]
pub struct Flags {
    /// `--methods`: comma-separated methods to measure.
    pub methods: String,
    /// `--presets`: comma-separated presets each method runs at. `None`: the job's preset.
    pub presets: Option<String>,
    /// `--vary KEY=V1,V2,..`, repeatable: each value runs as its own variant of every
    /// method. Empty: the job's settings only.
    pub vary: Vec<String>,
    /// `--reference`: the reference method.
    pub reference: String,
    /// `--reference-preset`: the reference's preset. `None`: the job's preset.
    pub reference_preset: Option<String>,
}

/// The variants to measure, in the order the tables list them, and the reference.
#[derive(Debug, Clone, PartialEq)]
pub struct Plan {
    pub variants: Vec<Variant>,
    pub reference: Variant,
}

/// One method at one preset, optionally with one setting changed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Variant {
    pub method: Method,
    pub preset: Preset,
    pub setting: Option<Setting>,
}

/// A method setting swept by `compare --vary`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Setting {
    Photons(u32),
    K(u32),
    Strata([u32; 2]),
    Error(f32),
    /// Where visibility detection runs (a render setting, not a method's).
    Visibility(VisibilityChoice),
    /// Photons per anchor estimate as a multiple of `k`.
    AnchorK(f32),
    /// How moderately glossy lobes gather (`glossy_mode`).
    Glossy(GlossyMode),
    /// Importance-sampled glossy rays per camera sample (`glossy_rays`).
    GlossyRays(u32),
    /// Anchor bucketing's θ × φ cells (`glossy_bucket_strata`), with `glossy_mode` bucketing
    /// (the cells mean nothing otherwise).
    BucketStrata([u32; 2]),
    /// The Weber rule's threshold (`weber_threshold`; 0 keeps every record).
    Weber(f32),
    /// Neighbour clamping's slope (`neighbour_clamp`; 0 turns it off).
    Neighbour(f32),
    /// How far records of earlier frames count as covering placement's pixel centres
    /// (`coverage_slack`; 1: as densely as the first frame).
    Slack(f32),
}

const SETTINGS: &str = "expected photons=, k=, strata=MxN, error=, anchor_k=, visibility=, \
                        glossy=bucketing|importance, glossy_rays=, bucket_strata=MxN, weber=, neighbour= or slack= with comma-separated values";

impl Plan {
    /// Parses and checks `flags` against `job`: every swept value is checked like a
    /// job-file value at every preset it runs at.
    pub fn new(flags: &Flags, job: &Job) -> Result<Plan> {
        let presets = match &flags.presets {
            Some(list) => list
                .split(',')
                .map(|s| parse_preset("--presets", s.trim()))
                .collect::<Result<Vec<_>>>()?,
            None => vec![job.method.preset],
        };
        // Each swept value with the flag it came from; no `--vary`: the job's settings.
        let mut settings = Vec::new();
        for arg in &flags.vary {
            let list =
                Setting::parse_list(arg).map_err(|message| Error::input("--vary", arg, message))?;
            settings.extend(list.into_iter().map(|s| Some((s, arg))));
        }
        if settings.is_empty() {
            settings.push(None);
        }
        let mut variants = Vec::new();
        for m in flags.methods.split(',') {
            let method = parse_method("--methods", m.trim())?;
            for &preset in &presets {
                for setting in &settings {
                    if let Some((s, arg)) = setting {
                        check_setting(job, preset, *s, arg)?;
                    }
                    variants.push(Variant {
                        method,
                        preset,
                        setting: setting.map(|(s, _)| s),
                    });
                }
            }
        }
        let reference = Variant {
            method: parse_method("--reference", &flags.reference)?,
            preset: match &flags.reference_preset {
                Some(p) => parse_preset("--reference-preset", p)?,
                None => job.method.preset,
            },
            setting: None,
        };
        Ok(Plan {
            variants,
            reference,
        })
    }
}

/// One of a [`ValueEnum`]'s names, or an error listing them.
fn parse_value<T: ValueEnum>(flag: &str, s: &str) -> Result<T> {
    T::from_str(s, false).map_err(|_| {
        let names: Vec<String> = T::value_variants()
            .iter()
            .filter_map(|v| v.to_possible_value())
            .map(|v| v.get_name().to_string())
            .collect();
        Error::input(flag, s, format!("expected one of {}", names.join(", ")))
    })
}

fn parse_method(flag: &str, s: &str) -> Result<Method> {
    parse_value(flag, s)
}

fn parse_preset(flag: &str, s: &str) -> Result<Preset> {
    parse_value(flag, s)
}

/// A swept value is checked like a job-file value; the error names `--vary` and the key.
fn check_setting(job: &Job, preset: Preset, s: Setting, arg: &str) -> Result<()> {
    let mut j = job.clone();
    j.method.preset = preset;
    s.apply(&mut j);
    j.method.validate(&job.path).map_err(|e| match e {
        Error::Input { at, message, .. } => Error::input(
            "--vary",
            arg,
            format!("{at} {message} (at preset {})", preset.name()),
        ),
        e => e,
    })
}

impl Setting {
    /// Parses `KEY=V1,V2,...` into one setting per value; the error says what is wrong.
    pub fn parse_list(s: &str) -> Result<Vec<Setting>, String> {
        let (key, values) = s.split_once('=').ok_or(SETTINGS)?;
        let key = key.trim();
        values
            .split(',')
            .map(|v| {
                let v = v.trim();
                Setting::parse(key, v).ok_or_else(|| match key {
                    "photons" | "k" | "strata" | "error" | "anchor_k" | "visibility" | "glossy"
                    | "glossy_rays" | "bucket_strata" | "weber" | "neighbour" | "slack" => {
                        format!("{v:?} is not a value of {key} ({SETTINGS})")
                    }
                    _ => format!("unknown setting {key:?}: {SETTINGS}"),
                })
            })
            .collect()
    }

    fn parse(key: &str, v: &str) -> Option<Setting> {
        Some(match key {
            "photons" => Setting::Photons(v.parse().ok()?),
            "k" => Setting::K(v.parse().ok()?),
            "strata" => {
                let (m, n) = v.split_once('x')?;
                Setting::Strata([m.parse().ok()?, n.parse().ok()?])
            }
            "error" => Setting::Error(v.parse().ok()?),
            "anchor_k" => Setting::AnchorK(v.parse().ok()?),
            "visibility" => Setting::Visibility(match v {
                "auto" => VisibilityChoice::Auto,
                "gpu" => VisibilityChoice::Gpu,
                "cpu" => VisibilityChoice::Cpu,
                _ => return None,
            }),
            "glossy" => Setting::Glossy(match v {
                "bucketing" => GlossyMode::Bucketing,
                "importance" => GlossyMode::Importance,
                _ => return None,
            }),
            "glossy_rays" => Setting::GlossyRays(v.parse().ok()?),
            "bucket_strata" => {
                let (m, n) = v.split_once('x')?;
                Setting::BucketStrata([m.parse().ok()?, n.parse().ok()?])
            }
            "weber" => Setting::Weber(v.parse().ok()?),
            "neighbour" => Setting::Neighbour(v.parse().ok()?),
            "slack" => Setting::Slack(v.parse().ok()?),
            _ => return None,
        })
    }

    pub fn apply(&self, job: &mut Job) {
        let m = &mut job.method;
        match *self {
            Setting::Photons(v) => m.photons = Some(v),
            Setting::K(v) => m.k = Some(v),
            Setting::Strata(v) => m.strata = Some(v),
            Setting::Error(v) => m.error = Some(v),
            Setting::Visibility(v) => job.render.visibility = v,
            Setting::AnchorK(v) => m.anchors.get_or_insert_default().k_scale = Some(v),
            Setting::Glossy(v) => m.glossy_mode = Some(v),
            Setting::GlossyRays(v) => m.glossy_rays = Some(v),
            Setting::BucketStrata(v) => {
                m.glossy_bucket_strata = Some(v);
                m.glossy_mode = Some(GlossyMode::Bucketing);
            }
            Setting::Weber(v) => m.weber_threshold = Some(v),
            Setting::Neighbour(v) => m.neighbour_clamp = Some(v),
            Setting::Slack(v) => m.coverage_slack = Some(v),
        }
    }

    fn label(&self) -> String {
        match self {
            Setting::Photons(v) => format!("photons={v}"),
            Setting::K(v) => format!("k={v}"),
            Setting::Strata([m, n]) => format!("strata={m}x{n}"),
            Setting::Error(v) => format!("error={v}"),
            Setting::Visibility(v) => format!("visibility={}", format!("{v:?}").to_lowercase()),
            Setting::AnchorK(v) => format!("anchor_k={v}"),
            Setting::Glossy(GlossyMode::Bucketing) => "glossy=bucketing".into(),
            Setting::Glossy(GlossyMode::Importance) => "glossy=importance".into(),
            Setting::GlossyRays(v) => format!("glossy_rays={v}"),
            Setting::BucketStrata([m, n]) => format!("bucket_strata={m}x{n}"),
            Setting::Weber(v) => format!("weber={v}"),
            Setting::Neighbour(v) => format!("neighbour={v}"),
            Setting::Slack(v) => format!("slack={v}"),
        }
    }
}

impl Variant {
    /// `method/preset`, then the swept setting if any: `anchors/draft photons=50000`.
    pub fn label(&self) -> String {
        let base = format!("{}/{}", self.method.name(), self.preset.name());
        match &self.setting {
            Some(s) => format!("{base} {}", s.label()),
            None => base,
        }
    }
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use super::*;
    use crate::job::{JobFile, Overrides};

    fn job() -> Job {
        let file: JobFile =
            serde_json::from_str(r#"{"scene":[{"path":"s.gltf"}],"method":{"preset":"draft"}}"#)
                .unwrap();
        Job::from_file(Path::new("job.json"), file, &Overrides::default()).unwrap()
    }

    fn flags(methods: &str) -> Flags {
        Flags {
            methods: methods.into(),
            presets: None,
            vary: Vec::new(),
            reference: "path-trace".into(),
            reference_preset: None,
        }
    }

    fn labels(p: &Plan) -> Vec<String> {
        p.variants.iter().map(Variant::label).collect()
    }

    /// The error's exit code, flag and offending value.
    fn culprit(e: Error) -> (i32, String, String) {
        let code = e.exit_code();
        match e {
            Error::Input { file, at, .. } => (code, file.display().to_string(), at),
            e => panic!("not an input error: {e}"),
        }
    }

    #[test]
    fn defaults_to_the_jobs_preset() {
        let p = Plan::new(&flags("anchors, brute-force"), &job()).unwrap();
        assert_eq!(labels(&p), ["anchors/draft", "brute-force/draft"]);
        assert_eq!(p.reference.label(), "path-trace/draft");
    }

    #[test]
    fn every_method_runs_at_every_preset_and_swept_value() {
        let f = Flags {
            presets: Some("draft,final".into()),
            vary: vec!["photons=1000,2000".into(), "strata=4x8".into()],
            reference: "brute-force".into(),
            reference_preset: Some("production".into()),
            ..flags("anchors,precomputed")
        };
        let p = Plan::new(&f, &job()).unwrap();
        assert_eq!(p.variants.len(), 2 * 2 * 3);
        assert_eq!(
            labels(&p)[..4],
            [
                "anchors/draft photons=1000",
                "anchors/draft photons=2000",
                "anchors/draft strata=4x8",
                "anchors/final photons=1000",
            ]
        );
        assert_eq!(p.reference.label(), "brute-force/production");
    }

    #[test]
    fn every_setting_parses() {
        let list = |s: &str| Setting::parse_list(s).unwrap();
        assert_eq!(list("k=10, 20"), [Setting::K(10), Setting::K(20)]);
        assert_eq!(list("error=0.5"), [Setting::Error(0.5)]);
        assert_eq!(list("anchor_k=2"), [Setting::AnchorK(2.0)]);
        assert_eq!(
            list("bucket_strata=6x24,12x48"),
            [
                Setting::BucketStrata([6, 24]),
                Setting::BucketStrata([12, 48])
            ]
        );
        let mut job = job();
        Setting::BucketStrata([6, 24]).apply(&mut job);
        assert_eq!(job.method.glossy_bucket_strata, Some([6, 24]));
        assert_eq!(job.method.glossy_mode, Some(GlossyMode::Bucketing));
        assert_eq!(
            list("visibility=cpu,gpu,auto"),
            [
                VisibilityChoice::Cpu,
                VisibilityChoice::Gpu,
                VisibilityChoice::Auto
            ]
            .map(Setting::Visibility)
        );
        assert_eq!(
            Variant {
                method: Method::Anchors,
                preset: Preset::Final,
                setting: Some(Setting::Visibility(VisibilityChoice::Gpu)),
            }
            .label(),
            "anchors/final visibility=gpu"
        );
    }

    #[test]
    fn bad_flags_are_input_errors_naming_the_flag() {
        let job = job();
        let cases = [
            (flags("anchors,raytrace"), "--methods", "raytrace"),
            (flags("anchors,"), "--methods", ""),
            (
                Flags {
                    presets: Some("draft,fast".into()),
                    ..flags("anchors")
                },
                "--presets",
                "fast",
            ),
            (
                Flags {
                    reference: "exact".into(),
                    ..flags("anchors")
                },
                "--reference",
                "exact",
            ),
            (
                Flags {
                    reference_preset: Some("best".into()),
                    ..flags("anchors")
                },
                "--reference-preset",
                "best",
            ),
        ];
        for (f, flag, value) in cases {
            let got = culprit(Plan::new(&f, &job).unwrap_err());
            assert_eq!(got, (2, flag.to_string(), value.to_string()));
        }
        for vary in [
            "photons",
            "photon=1000",
            "photons=many",
            "strata=4",
            "visibility=fpga",
            "k=",
        ] {
            let f = Flags {
                vary: vec!["k=10".into(), vary.into()],
                ..flags("anchors")
            };
            let got = culprit(Plan::new(&f, &job).unwrap_err());
            assert_eq!(got, (2, "--vary".to_string(), vary.to_string()));
        }
    }

    #[test]
    fn swept_values_out_of_range_name_vary_and_the_key() {
        let f = Flags {
            vary: vec!["photons=1000,0".into()],
            ..flags("brute-force")
        };
        let e = Plan::new(&f, &job()).unwrap_err();
        let message = e.to_string();
        assert!(message.contains("method.photons"), "{message}");
        assert_eq!(culprit(e), (2, "--vary".into(), "photons=1000,0".into()));
    }
}
