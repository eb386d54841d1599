//! The `anchorage` command line: parses arguments, calls the library, and turns its typed
//! errors into messages and exit codes (0 success, 2 bad input, 1 render failure).

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anchorage::job::{FrameRange, Job, Overrides, VisibilityChoice};
use anchorage::pipeline::{self, Progress, RenderOptions, StateOptions};
use anchorage::{Error, compare, farm, inspect};
use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "anchorage",
    version = env!("ANCHORAGE_VERSION"),
    about = "Batch renderer for animation: multilayer EXR per frame"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Render every frame of a job to NAME.####.exr (+ stats JSON, optional PNG preview).
    Render {
        job: PathBuf,
        /// Inclusive frame range `A-B` (or one frame `A`), overriding the job's `frames`.
        #[arg(long)]
        frames: Option<String>,
        /// Output directory, overriding the job's `output.directory`.
        #[arg(long)]
        out: Option<PathBuf>,
        /// Method, overriding the job's `method.name`: anchors, brute-force, precomputed,
        /// path-trace, direct.
        #[arg(long)]
        method: Option<String>,
        /// Where visibility detection runs, overriding the job's `render.visibility`.
        #[arg(long, value_enum)]
        visibility: Option<VisibilityChoice>,
        /// Worker threads (default: all cores). The output does not depend on it.
        #[arg(long)]
        threads: Option<usize>,
        /// Also write a tone-mapped sRGB PNG per frame.
        #[arg(long)]
        preview: bool,
        /// Preview exposure in stops, overriding the job's `output.exposure` (EXRs stay in
        /// scene radiance).
        #[arg(long, allow_hyphen_values = true)]
        exposure: Option<f32>,
        /// Most memory the render may use, e.g. 8G or 512M (default: 80 % of the machine's).
        /// A job estimated to need more stops before rendering, with exit code 2.
        #[arg(long)]
        memory_limit: Option<String>,
        /// No progress output.
        #[arg(long, short)]
        quiet: bool,
        /// Start from a checkpoint written by `--state-out`: the state after the frame before
        /// the range's first. The frames then equal those of a run that rendered through.
        #[arg(long, value_name = "FILE", conflicts_with = "warmup")]
        resume: Option<PathBuf>,
        /// Render N frames before the range without writing them, so that it starts from a
        /// warm state (a farm chunk that runs in parallel with the others; never before the
        /// animation's first frame). At most as many as a job's frames may be.
        #[arg(long, value_name = "N", default_value_t = 0, value_parser = warmup_frames())]
        warmup: u32,
        /// Write a checkpoint (NAME.####.state) to DIR after frames of the range.
        #[arg(long, value_name = "DIR")]
        state_out: Option<PathBuf>,
        /// With --state-out: after every N-th frame of the range, and after its last.
        #[arg(long, value_name = "N", default_value_t = 1, requires = "state_out",
              value_parser = clap::value_parser!(u32).range(1..))]
        state_every: u32,
    },
    /// Describe a scene (.gltf/.glb) or a job: prims with tags and why, lights, cameras, time range.
    Inspect { path: PathBuf },
    /// Render frames with several methods and presets and measure time, error against a
    /// reference, and flicker: a table on stdout, compare.json, compare.png and compare.svg.
    Compare {
        job: PathBuf,
        /// Comma-separated methods to measure.
        #[arg(long, default_value = "anchors,brute-force,precomputed")]
        methods: String,
        /// Comma-separated presets each method runs at (default: the job's preset).
        #[arg(long)]
        presets: Option<String>,
        /// Sweep one setting: `photons=A,B,..`, `k=..`, `strata=MxN,..`, `error=..`,
        /// `anchor_k=..` (`anchors.k_scale`), `visibility=cpu,gpu`, `glossy=bucketing,importance`
        /// (`glossy_mode`), `glossy_rays=..`, `bucket_strata=MxN,..` (`glossy_bucket_strata`,
        /// with `glossy_mode` bucketing), `weber=..` (`weber_threshold`), `neighbour=..`
        /// (`neighbour_clamp`) or `slack=..` (`coverage_slack`); each value runs as its own variant of every method. Repeatable.
        #[arg(long)]
        vary: Vec<String>,
        /// The reference method.
        #[arg(long, default_value = "path-trace")]
        reference: String,
        /// The reference's preset (default: the job's preset).
        #[arg(long)]
        reference_preset: Option<String>,
        /// Inclusive frame range `A-B` (or one frame `A`), overriding the job's `frames`.
        #[arg(long)]
        frames: Option<String>,
        /// Where compare.json, compare.png and compare.svg go (default: the job's output directory).
        #[arg(long)]
        out: Option<PathBuf>,
        /// Where visibility detection runs, overriding the job's `render.visibility`.
        #[arg(long, value_enum)]
        visibility: Option<VisibilityChoice>,
        /// Worker threads (default: all cores).
        #[arg(long)]
        threads: Option<usize>,
    },
    /// Check a job and its scenes without rendering.
    Validate { job: PathBuf },
    /// Write an Open Job Description template that renders the job's frames in chunks on a
    /// farm (`openjd run` runs it locally; AWS Deadline Cloud submits it), or measure what
    /// warming up parallel chunks buys (--measure-warmup).
    Farm {
        job: PathBuf,
        /// Frames per chunk.
        #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
        chunk_size: u32,
        /// Parallel chunks, each rendering N unwritten frames before its range.
        #[arg(
            long,
            value_name = "N",
            default_value_t = DEFAULT_WARMUP,
            conflicts_with = "chained",
            value_parser = warmup_frames()
        )]
        warmup: u32,
        /// Chunks run one after another, each resuming the previous chunk's last state: the
        /// frames of one render, byte for byte.
        #[arg(long)]
        chained: bool,
        /// Inclusive frame range `A-B`, overriding the job's `frames`.
        #[arg(long)]
        frames: Option<String>,
        /// The frames' output directory the template defaults to, overriding the job's.
        #[arg(long)]
        out: Option<PathBuf>,
        /// Write the template to FILE (default: standard output).
        #[arg(long, short = 'o', value_name = "FILE")]
        template: Option<PathBuf>,
        /// The anchorage executable the template runs (default: this one).
        #[arg(long, value_name = "PATH")]
        anchorage: Option<PathBuf>,
        /// Instead of a template: render the frames through, then every chunk seam again
        /// after each of these warm-ups (comma-separated frame counts), and print the seam
        /// error and the cost of each.
        #[arg(long, value_name = "N,N,..", conflicts_with_all = ["template", "chained"])]
        measure_warmup: Option<String>,
        /// Worker threads (default: all cores).
        #[arg(long)]
        threads: Option<usize>,
    },
    /// Render a job's frames, then render them again whenever the job or a file its scene
    /// reads changes, keeping the anchors' state where the change allows (until SIGINT or
    /// SIGTERM).
    Watch {
        job: PathBuf,
        /// Inclusive frame range `A-B` (or one frame `A`), overriding the job's `frames`.
        #[arg(long)]
        frames: Option<String>,
        /// Output directory, overriding the job's `output.directory`.
        #[arg(long)]
        out: Option<PathBuf>,
        /// Method, overriding the job's `method.name`.
        #[arg(long)]
        method: Option<String>,
        /// Worker threads (default: all cores).
        #[arg(long)]
        threads: Option<usize>,
        /// Also write a tone-mapped sRGB PNG per frame.
        #[arg(long)]
        preview: bool,
        /// Only the one line per re-render, no line per frame.
        #[arg(long, short)]
        quiet: bool,
        /// Most memory the frame states kept between re-renders may use, e.g. 4G or 512M
        /// (default: half the render's memory limit, 40 % of the machine's). Frames whose
        /// state does not fit are re-made from the frame before them
        #[arg(long)]
        state_memory: Option<String>,
    },
}

fn parse_frames(s: &str) -> Result<FrameRange, Error> {
    let bad = || Error::input("--frames", s, "expected A-B or A (integers, A <= B)");
    // The separator is the first '-' that follows a digit, so negative frames work: -5--2.
    let sep = s
        .char_indices()
        .skip(1)
        .find(|&(i, c)| c == '-' && s.as_bytes()[i - 1].is_ascii_digit());
    let (a, b) = match sep {
        Some((i, _)) => (&s[..i], &s[i + 1..]),
        None => (s, s),
    };
    let start: i32 = a.trim().parse().map_err(|_| bad())?;
    let end: i32 = b.trim().parse().map_err(|_| bad())?;
    if end < start {
        return Err(bad());
    }
    Ok(FrameRange { start, end })
}

/// Frames a parallel farm chunk renders before its range by default (README, Farm jobs:
/// the seam error this leaves, measured).
const DEFAULT_WARMUP: u32 = 0;

/// A warm-up's frame count: at most [`anchorage::job::MAX_FRAMES`], as a job's frames.
fn warmup_frames() -> clap::builder::RangedI64ValueParser<u32> {
    clap::value_parser!(u32).range(..=anchorage::job::MAX_FRAMES)
}

/// Most worker threads `--threads` may ask for: far more than any machine's cores, far fewer
/// than would exhaust its memory for stacks.
const MAX_THREADS: usize = 1024;

fn set_threads(threads: Option<usize>) -> Result<(), Error> {
    if let Some(n) = threads {
        if n == 0 || n > MAX_THREADS {
            return Err(Error::input(
                "--threads",
                n.to_string(),
                format!("must be 1..={MAX_THREADS}"),
            ));
        }
        rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build_global()
            .map_err(|e| Error::Render(e.to_string()))?;
    }
    Ok(())
}

fn parse_method(s: &str) -> Result<anchorage::job::Method, Error> {
    <anchorage::job::Method as clap::ValueEnum>::from_str(s, false).map_err(|_| {
        Error::input(
            "--method",
            s,
            "expected anchors, brute-force, precomputed, path-trace or direct",
        )
    })
}

/// A job wrapping a bare scene file, for `inspect SCENE.gltf`.
fn job_for_scene(path: &Path) -> Result<Job, Error> {
    let file =
        anchorage::job::JobFile::for_scene(PathBuf::from(path.file_name().unwrap_or_default()));
    Job::from_file(path, file, &Overrides::default())
}

fn run(cli: Cli) -> Result<(), Error> {
    match cli.command {
        Command::Render {
            job,
            frames,
            out,
            method,
            visibility,
            threads,
            preview,
            exposure,
            memory_limit,
            quiet,
            resume,
            warmup,
            state_out,
            state_every,
        } => {
            let overrides = Overrides {
                frames: frames.as_deref().map(parse_frames).transpose()?,
                out_dir: out,
                method: method.as_deref().map(parse_method).transpose()?,
                visibility,
                exposure,
            };
            set_threads(threads)?;
            let limit = memory_limit
                .as_deref()
                .map(anchorage::budget::Limit::parse)
                .transpose()?;
            let job = Job::load(&job, &overrides)?;
            let scene = job.load_scene()?;
            for w in scene.warnings() {
                eprintln!("anchorage: warning: {w}");
            }
            anchorage::budget::check_with_checkpoints(
                &job,
                &scene,
                limit,
                state_out.is_some() || resume.is_some(),
            )?;
            let opts = RenderOptions {
                preview,
                progress: if quiet {
                    Progress::Quiet
                } else {
                    Progress::Auto
                },
                state: StateOptions {
                    resume,
                    warmup,
                    out: state_out,
                    every: state_every,
                },
            };
            pipeline::render_job(&job, &scene, opts)?;
            Ok(())
        }
        Command::Compare {
            job,
            methods,
            presets,
            vary,
            reference,
            reference_preset,
            frames,
            out,
            visibility,
            threads,
        } => {
            set_threads(threads)?;
            let overrides = Overrides {
                frames: frames.as_deref().map(parse_frames).transpose()?,
                out_dir: out,
                method: None,
                visibility,
                exposure: None,
            };
            let job = Job::load(&job, &overrides)?;
            let flags = compare::plan::Flags {
                methods,
                presets,
                vary,
                reference,
                reference_preset,
            };
            let plan = compare::Plan::new(&flags, &job)?;
            let scene = job.load_scene()?;
            anchorage::budget::check(&job, &scene, None)?;
            anchorage::output::refuse_inputs(
                "--out",
                ["compare.json", "compare.png", "compare.svg"].map(|f| job.out_dir.join(f)),
            )?;
            anchorage::output::check_output_dir(&job.out_dir)?;
            let report = compare::run(&job, &scene, &plan)?;
            print!("{}", compare::table(&report));
            let [json, png, svg] = compare::write(&job.out_dir, &report)?;
            println!(
                "wrote {}, {} and {}",
                json.display(),
                png.display(),
                svg.display()
            );
            Ok(())
        }
        Command::Inspect { path } => {
            let is_job = path
                .extension()
                .is_some_and(|e| e.eq_ignore_ascii_case("json"));
            let job = if is_job {
                Job::load(&path, &Overrides::default())?
            } else {
                job_for_scene(&path)?
            };
            let scene = job.load_scene_layers()?;
            print!("{}", inspect::report(&job, &scene));
            Ok(())
        }
        Command::Farm {
            job,
            chunk_size,
            warmup,
            chained,
            frames,
            out,
            template,
            anchorage,
            measure_warmup,
            threads,
        } => {
            set_threads(threads)?;
            let overrides = Overrides {
                frames: frames.as_deref().map(parse_frames).transpose()?,
                out_dir: out,
                ..Overrides::default()
            };
            let job = Job::load(&job, &overrides)?;
            let scene = job.load_scene()?;
            if let Some(list) = measure_warmup {
                let warmups = list
                    .split(',')
                    .map(|v| {
                        v.trim()
                            .parse::<u32>()
                            .ok()
                            .filter(|&n| i64::from(n) <= anchorage::job::MAX_FRAMES)
                    })
                    .collect::<Option<Vec<u32>>>()
                    .ok_or_else(|| {
                        Error::input(
                            "--measure-warmup",
                            &list,
                            format!(
                                "expected frame counts N,N,.. of at most {}",
                                anchorage::job::MAX_FRAMES
                            ),
                        )
                    })?;
                anchorage::budget::check(&job, &scene, None)?;
                let rows = farm::measure_seams(&job, &scene, chunk_size, &warmups, |m| {
                    eprintln!("anchorage: {m}")
                })?;
                print!("{}", farm::seam_table(&rows));
                return Ok(());
            }
            let split = if chained {
                farm::Split::Chained
            } else {
                farm::Split::Warmup(warmup)
            };
            let exe = match anchorage {
                Some(p) => p,
                None => std::env::current_exe()
                    .map_err(|e| Error::Render(format!("cannot locate anchorage: {e}")))?,
            };
            let dir = match template.as_deref().and_then(Path::parent) {
                Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
                _ => PathBuf::from("."),
            };
            if let Some(path) = &template {
                anchorage::output::refuse_inputs("--template", [path])?;
            }
            let t = farm::template(&job, chunk_size, split, &exe, &dir)?;
            let text = serde_json::to_string_pretty(&t).expect("a JSON value serialises") + "\n";
            match template {
                Some(path) => anchorage::output::write_atomic(&path, |w| {
                    std::io::Write::write_all(w, text.as_bytes()).map_err(|e| e.to_string())
                })?,
                None => print!("{text}"),
            }
            Ok(())
        }
        Command::Watch {
            job,
            frames,
            out,
            method,
            threads,
            preview,
            quiet,
            state_memory,
        } => {
            set_threads(threads)?;
            let state_memory = state_memory
                .as_deref()
                .map(|s| {
                    anchorage::budget::Limit::parse_option("--state-memory", s).map(|l| l.bytes)
                })
                .transpose()?;
            let overrides = Overrides {
                frames: frames.as_deref().map(parse_frames).transpose()?,
                out_dir: out,
                method: method.as_deref().map(parse_method).transpose()?,
                visibility: None,
                exposure: None,
            };
            anchorage::watch::run(&anchorage::watch::Options {
                job,
                overrides,
                preview,
                quiet,
                state_memory,
            })
        }
        Command::Validate { job } => {
            let job = Job::load(&job, &Overrides::default())?;
            let scene = job.load_scene()?;
            for w in scene.warnings() {
                eprintln!("anchorage: warning: {w}");
            }
            anchorage::budget::check(&job, &scene, None)?;
            anchorage::output::check_output_dir_unmade(&job.out_dir)?;
            println!(
                "{}: ok: {} layer(s), frames {}..{}, {}x{}",
                job.path.display(),
                job.layers.len(),
                job.frames.start,
                job.frames.end,
                job.width,
                job.height
            );
            Ok(())
        }
    }
}

/// Names the input in the message a panic would print, and exits 1: a panic is a bug in
/// anchorage, never a crash the user has to decode.
fn install_panic_hook() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    std::panic::set_hook(Box::new(move |info| {
        let at = info
            .location()
            .map(|l| format!(" at {}:{}", l.file(), l.line()))
            .unwrap_or_default();
        let what = info
            .payload()
            .downcast_ref::<&str>()
            .map(|s| s.to_string())
            .or_else(|| info.payload().downcast_ref::<String>().cloned())
            .unwrap_or_default();
        eprintln!(
            "anchorage: internal error{at}: {what}\n  while running: anchorage {}\n  please \
             report it with the input files",
            args.join(" ")
        );
        std::process::exit(1);
    }));
}

/// The Vulkan probe loads the Wayland client library, which prints `error: XDG_RUNTIME_DIR is
/// invalid or not set` to stderr on machines without a session (render farms). anchorage
/// never opens a window: with no `WAYLAND_DISPLAY`, point it at a path that cannot exist,
/// which Wayland then fails to open without a word.
fn quiet_wayland() {
    let runtime_ok =
        std::env::var_os("XDG_RUNTIME_DIR").is_some_and(|d| Path::new(&d).is_absolute());
    if std::env::var_os("WAYLAND_DISPLAY").is_none() && !runtime_ok {
        // SAFETY: called first in `main`, before any other thread exists.
        unsafe { std::env::set_var("WAYLAND_DISPLAY", "/dev/null/anchorage-has-no-display") };
    }
}

fn main() -> ExitCode {
    quiet_wayland();
    install_panic_hook();
    let cli = Cli::parse();
    if matches!(
        cli.command,
        Command::Render { .. } | Command::Compare { .. } | Command::Watch { .. }
    ) && let Err(e) = anchorage::output::install_signal_cleanup()
    {
        eprintln!("anchorage: error: {e}");
        return ExitCode::from(e.exit_code() as u8);
    }
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("anchorage: error: {e}");
            ExitCode::from(e.exit_code() as u8)
        }
    }
}
