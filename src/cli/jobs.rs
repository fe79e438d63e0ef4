//! The farm's client commands: submit, jobs, status, watch, cancel, fetch, workers.

use super::outln;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{Context, Result, bail};
use clap::Args;
use tessera_proto::{JobSpec, pb};
use tokio_stream::StreamExt as _;
use tracer_core::adaptive::AdaptiveMode;

use super::farm_common::{CoordinatorUrl, JobClient, connect, rpc, runtime};
use super::output::{Format, Progress, job_json, print_json, worker_json};
use super::render::{AdaptiveArgs, ModelArgs, OverrideArgs};

/// Exit codes of `tessera watch` and `tessera submit --wait`.
pub const EXIT_DONE: u8 = 0;
pub const EXIT_FAILED: u8 = 3;
pub const EXIT_CANCELLED: u8 = 4;
/// `watch` (or `submit --wait`) stopped by Ctrl-C: the job goes on.
pub const EXIT_INTERRUPTED: u8 = 130;

/// An inclusive frame range, written `A..B` (or `A..=B`, or one frame `N`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Frames {
    pub first: u32,
    pub last: u32,
}

impl std::str::FromStr for Frames {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        let num = |t: &str| {
            t.trim().parse::<u32>().map_err(|_| {
                // `1-5` (or `1:5`, `1..=5` typed `1...5`) means a range:
                // say how to write one.
                match t.split_once(['-', ':']) {
                    Some((a, b))
                        if a.trim().parse::<u32>().is_ok() && b.trim().parse::<u32>().is_ok() =>
                    {
                        format!(
                            "{t:?} is not a frame number; write a range as {}..{}",
                            a.trim(),
                            b.trim()
                        )
                    }
                    _ => format!(
                        "{t:?} is not a frame number (write one frame as N, a range as A..B)"
                    ),
                }
            })
        };
        let (first, last) = match s.split_once("..") {
            Some((a, b)) => (num(a)?, num(b.strip_prefix('=').unwrap_or(b))?),
            None => (num(s)?, num(s)?),
        };
        if first > last {
            return Err(format!("frame range {s} is empty (first frame after last)"));
        }
        Ok(Frames { first, last })
    }
}

#[derive(Args, Debug)]
pub struct SubmitArgs {
    /// Scene file (TOML; see docs/scene-format.md), or a model file
    /// rendered as a scene: .gltf, .glb, .obj, .obj.gz (sent with the
    /// scene `tessera render` makes of it, so the farm renders the same)
    pub scene: PathBuf,
    #[command(flatten)]
    pub model: ModelArgs,
    /// Frames to render, inclusive: `1..5` renders frames 1 to 5 (each
    /// with its camera keyframe pose, docs/scene-format.md), `3` frame 3 alone [default: frame 0]
    #[arg(long)]
    pub frames: Option<Frames>,
    #[command(flatten)]
    pub overrides: OverrideArgs,
    #[command(flatten)]
    pub adaptive: AdaptiveArgs,
    /// Higher priorities are rendered first (any i32; jobs of equal
    /// priority in the order submitted)
    #[arg(long, default_value_t = 0, allow_negative_numbers = true)]
    pub priority: i32,
    /// Job name [default: the scene's file stem]
    #[arg(long)]
    pub name: Option<String>,
    /// Tile side in pixels, 8..=4096: the smallest piece of a frame a
    /// worker leases (fast workers take several at once) [default: the coordinator's, 64]
    #[arg(long, allow_negative_numbers = true, value_parser = clap::value_parser!(u32).range(8..=4096))]
    pub tile_size: Option<u32>,
    /// Samples per pixel in one work unit, 1..=65536 (more than the job's
    /// samples means all of them) [default: the coordinator's, 64]
    #[arg(long, allow_negative_numbers = true, value_parser = clap::value_parser!(u32).range(1..=65536))]
    pub samples_per_unit: Option<u32>,
    /// Failed attempts of one unit before the job fails, at least 1 [default: the coordinator's, 3]
    #[arg(long, allow_negative_numbers = true, value_parser = clap::value_parser!(u32).range(1..))]
    pub max_attempts: Option<u32>,
    /// Lease the job's units only to workers with this label, repeatable:
    /// KEY=VALUE (the label equals VALUE: `pool=night`, `backend=gpu`) or
    /// KEY>=N (the label is a number of at least N: `gpu_memory_gb>=40`).
    /// A job no connected worker meets says so in `status` and `watch`
    #[arg(long = "require", value_name = "REQUIREMENT", value_parser = requirement_parser)]
    pub require: Vec<String>,
    /// Run the job after job JOB is done, repeatable: it stays `waiting`
    /// (no unit leased) until every named job is done, and fails, naming
    /// it, if one fails or is cancelled. An unknown JOB is refused
    #[arg(long = "after", value_name = "JOB")]
    pub after: Vec<String>,
    /// When the job ends (done, failed, cancelled), the coordinator POSTs
    /// its JSON (as `status --json` prints it) to this http:// URL, signed
    /// with its --notify-secret-file (`X-Tessera-Signature: sha256=HEX`)
    /// and retried with back-off; repeatable
    #[arg(long = "on-done", value_name = "URL")]
    pub on_done: Vec<String>,
    /// Units of this job a worker may report failed before it is kept
    /// from the job (its blocklist, shown by `status`); 0: never
    /// [default: the coordinator's --blocklist-after, 3]
    #[arg(long, value_name = "N")]
    pub blocklist_after: Option<u32>,
    /// Seconds a worker blocklisted from this job is kept from it, then
    /// forgiven [default: the coordinator's --blocklist-seconds, 1800]
    #[arg(long, value_name = "SECONDS")]
    pub blocklist_forgive: Option<f64>,
    /// Wait for the job to finish (progress on stderr); the exit code is then
    /// the job's outcome (0 done, 3 failed, 4 cancelled). At the end it
    /// prints the `tessera fetch` command that downloads the frames here
    #[arg(long)]
    pub wait: bool,
    /// Wait as --wait does, then download the finished frames into DIR
    /// (as `tessera fetch JOB -o DIR`; frame files already there are
    /// refused unless --force)
    #[arg(long, value_name = "DIR")]
    pub fetch: Option<PathBuf>,
    /// With --fetch: overwrite frame files that already exist in DIR
    #[arg(long, requires = "fetch")]
    pub force: bool,
    /// Send files the scene references from outside its folder (absolute
    /// paths, or `..` above it) too; without it such a scene is refused
    #[arg(long)]
    pub allow_outside: bool,
    #[command(flatten)]
    pub format: Format,
    #[command(flatten)]
    pub coordinator: CoordinatorUrl,
}

/// `--require`: checked here with the coordinator's own parser, sent as typed.
fn requirement_parser(s: &str) -> Result<String, String> {
    tessera_proto::placement::Requirement::parse(s)
        .map(|_| s.to_string())
        .map_err(|e| e.to_string())
}

pub fn submit(args: SubmitArgs) -> Result<ExitCode> {
    // Validated here first, through the loaders `tessera render` uses: a
    // bad scene fails before anything is uploaded.
    let bundle = super::bundle::gather(
        &args.scene,
        &args.model.options(&args.scene, &args.overrides),
        args.allow_outside,
    )?;
    let frames = args.frames.unwrap_or(Frames { first: 0, last: 0 });
    // What the job asks for, in its one shape; the coordinator checks it
    // against the scene. Its files go beside it in the message.
    let job = JobSpec {
        name: args.name.clone().unwrap_or_default(),
        // The path as typed, so errors read exactly as `tessera render`'s.
        scene_name: args.scene.display().to_string(),
        overrides: (&args.overrides).into(),
        adaptive: (&args.adaptive).into(),
        first_frame: frames.first,
        last_frame: frames.last,
        priority: args.priority,
        tile_size: args.tile_size,
        samples_per_unit: args.samples_per_unit,
        max_attempts: args.max_attempts,
        requirements: args.require.clone(),
        after: args.after.clone(),
        on_done: args.on_done.clone(),
        blocklist_after: args.blocklist_after,
        blocklist_seconds: args.blocklist_forgive,
    };
    let spec = pb::JobSpec {
        scene: bundle.scene,
        ..job.into()
    };
    runtime()?.block_on(async move {
        let mut client = connect(&args.coordinator).await?;
        let mut spec = spec;
        spec.files = super::bundle::upload(&mut client, &bundle.files)
            .await?
            .into_iter()
            .collect();
        let id = client
            .submit_job(pb::SubmitJobRequest { spec: Some(spec) })
            .await
            .map_err(rpc)?
            .into_inner()
            .job_id;
        if args.format.json {
            print_json(&serde_json::json!({ "job_id": id }));
        } else {
            outln!("{id}");
        }
        if args.wait || args.fetch.is_some() {
            // In place before the first event is shown: a Ctrl-C from then
            // on is this watch's to handle.
            let interrupt = interrupt_signal()?;
            let code = watch_job(
                &mut client,
                &id,
                args.format,
                &args.coordinator,
                args.fetch.as_deref(),
                interrupt,
            )
            .await?;
            if let Some(dir) = &args.fetch
                && code == ExitCode::from(EXIT_DONE)
            {
                return fetch_frames(&mut client, &id, dir, args.force, args.format).await;
            }
            return Ok(code);
        }
        Ok(ExitCode::SUCCESS)
    })
}

#[derive(Args, Debug)]
pub struct JobArg {
    /// Job id (as printed by `tessera submit`)
    pub job: String,
    #[command(flatten)]
    pub format: Format,
    #[command(flatten)]
    pub coordinator: CoordinatorUrl,
}

#[derive(Args, Debug)]
pub struct ListArgs {
    #[command(flatten)]
    pub format: Format,
    #[command(flatten)]
    pub coordinator: CoordinatorUrl,
}

#[derive(Args, Debug)]
pub struct FetchArgs {
    /// Job id
    pub job: String,
    /// Directory to write the frames into
    #[arg(short, long)]
    pub output: PathBuf,
    /// Overwrite frame files that already exist in the directory (without
    /// it, fetch refuses before writing anything)
    #[arg(long)]
    pub force: bool,
    #[command(flatten)]
    pub format: Format,
    #[command(flatten)]
    pub coordinator: CoordinatorUrl,
}

/// A name from the coordinator as it may be printed on a terminal: control
/// characters (escape sequences, newlines) escaped.
pub fn printable(s: &str) -> String {
    s.chars()
        .flat_map(|c| {
            if c.is_control() {
                c.escape_default().collect::<Vec<_>>()
            } else {
                vec![c]
            }
        })
        .collect()
}

pub fn delete(args: JobArg) -> Result<ExitCode> {
    runtime()?.block_on(async move {
        let mut client = connect(&args.coordinator).await?;
        client
            .delete_job(pb::DeleteJobRequest {
                job_id: args.job.clone(),
            })
            .await
            .map_err(rpc)?;
        if args.format.json {
            print_json(&serde_json::json!({ "job_id": args.job, "deleted": true }));
        } else {
            outln!("deleted {}", args.job);
        }
        Ok(ExitCode::SUCCESS)
    })
}

/// Whether a job in this state is over.
fn ended(state: i32) -> bool {
    [
        pb::JobState::Done,
        pb::JobState::Failed,
        pb::JobState::Cancelled,
    ]
    .iter()
    .any(|&s| s as i32 == state)
}

pub use tessera_coordinator::status_json::state_name;

/// The job's progress as the coordinator defines it for every view
/// (sample-weighted), in percent.
fn percent(j: &pb::JobStatus) -> f64 {
    100.0 * j.progress
}

pub fn jobs(args: ListArgs) -> Result<ExitCode> {
    runtime()?.block_on(async move {
        let mut client = connect(&args.coordinator).await?;
        let jobs = client
            .list_jobs(pb::ListJobsRequest {})
            .await
            .map_err(rpc)?
            .into_inner()
            .jobs;
        if args.format.json {
            print_json(&jobs.iter().map(job_json).collect());
            return Ok(ExitCode::SUCCESS);
        }
        outln!(
            "{:<12} {:<10} {:>6} {:>4} {:>11} {:>9}  NAME",
            "ID",
            "STATE",
            "DONE",
            "PRI",
            "SIZE",
            "FRAMES"
        );
        for j in jobs {
            let s = j.settings.unwrap_or_default();
            outln!(
                "{:<12} {:<10} {:>5.1}% {:>4} {:>11} {:>9}  {}",
                j.job_id,
                state_name(j.state),
                percent(&j),
                j.priority,
                format!("{}x{}x{}", s.width, s.height, s.samples),
                format!("{}..{}", j.first_frame, j.last_frame),
                printable(&j.name)
            );
        }
        Ok(ExitCode::SUCCESS)
    })
}

pub fn status(args: JobArg) -> Result<ExitCode> {
    runtime()?.block_on(async move {
        let mut client = connect(&args.coordinator).await?;
        let j = get_job(&mut client, &args.job).await?;
        if args.format.json {
            print_json(&job_json(&j));
            return Ok(ExitCode::SUCCESS);
        }
        // A job that waits for workers that are not there says so (not
        // one that waits for other jobs: no worker could take it yet).
        let no_workers = !ended(j.state)
            && j.state != pb::JobState::Waiting as i32
            && client
                .list_workers(pb::ListWorkersRequest {})
                .await
                .map_err(rpc)?
                .into_inner()
                .workers
                .is_empty();
        let s = j.settings.unwrap_or_default();
        let rays = j.rays.unwrap_or_default();
        outln!("job:       {} ({})", j.job_id, printable(&j.name));
        if no_workers {
            outln!(
                "state:     {} (no workers connected: the job waits for one; start `tessera worker --coordinator URL`)",
                state_name(j.state)
            );
        } else {
            outln!("state:     {}", state_name(j.state));
        }
        outln!(
            "progress:  {:.1}% of the pixel-samples ({} of {} units)",
            percent(&j),
            j.units_done,
            j.units_total
        );
        outln!(
            "image:     {}x{}, {} samples, depth {}, frames {}..{}",
            s.width,
            s.height,
            s.samples,
            s.max_depth,
            j.first_frame,
            j.last_frame
        );
        outln!(
            "units:     tile {} px, {} samples per unit",
            j.tile_size,
            j.samples_per_unit
        );
        if !j.requirements.is_empty() {
            outln!("requires:  {}", j.requirements.join(", "));
        }
        if !j.after.is_empty() {
            outln!("after:     {}", j.after.join(", "));
        }
        if !j.waiting_for.is_empty() {
            outln!(
                "waiting:   for job(s) {} to be done (--after)",
                j.waiting_for.join(", ")
            );
        }
        if !j.unrunnable.is_empty() {
            outln!("waiting:   {}", j.unrunnable);
        }
        if !j.failure_classes.is_empty() {
            let mut by_class: Vec<_> = j.failure_classes.iter().collect();
            by_class.sort();
            outln!(
                "failures:  {} (units reported failed by workers, by class); blocklist after {} of them, forgiven after {} s",
                by_class
                    .iter()
                    .map(|(k, n)| format!("{k} {n}"))
                    .collect::<Vec<_>>()
                    .join(", "),
                j.blocklist_after,
                j.blocklist_seconds
            );
        }
        for b in &j.blocklisted {
            let left = (b.until_unix_ms - now_unix_ms()).max(0) / 1000;
            outln!(
                "blocklist: worker {} ({}) failed {} unit(s); kept from this job for {}m{:02}s more",
                b.name,
                b.worker_id,
                b.failures,
                left / 60,
                left % 60
            );
        }
        outln!(
            "rays:      {} ({:.2} Mrays/s)",
            rays.primary + rays.shadow + rays.reflection + rays.refraction,
            j.rays_per_second / 1e6
        );
        if let Some(a) = &j.adaptive {
            let settings = tracer_core::adaptive::AdaptiveSettings {
                target_error: a.target_error,
                relative_error: a.relative_error,
                min_samples: a.min_samples,
                max_samples: a.max_samples,
                mode: adaptive_mode(a),
            };
            let (mode, blocks, error) = match settings.mode {
                AdaptiveMode::Image => ("image mode, ", "settled", "estimated image RMSE"),
                AdaptiveMode::Pixel => ("", "converged", "estimated RMS error"),
            };
            outln!(
                "adaptive:  {mode}{} ({}..{} spp): {:.1}% of blocks {blocks}, {error} {:.2e}, {} of {} expected pixel-samples",
                settings.describe_target(),
                a.min_samples,
                a.max_samples,
                100.0 * a.converged_share,
                a.estimated_error,
                j.samples_done,
                j.samples_total
            );
        }
        if !ended(j.state) {
            if j.eta_seconds >= 0.0 {
                outln!("eta:       {:.0} s", j.eta_seconds);
            } else {
                outln!("eta:       unknown (no recent progress to measure)");
            }
        }
        outln!(
            "results:   {} accepted, {} rejected, {} late, {} duplicate",
            j.units_accepted,
            j.results_rejected,
            j.results_late,
            j.results_duplicate
        );
        // Only a job with a finished frame has anything to fetch.
        let written = j.frames.iter().filter(|f| !f.output.is_empty()).count();
        if written > 0 {
            outln!(
                "output:    {} on the coordinator's host; download with: {}",
                j.output_dir,
                fetch_command(&j.job_id, &args.coordinator)
            );
        } else if ended(j.state) {
            outln!(
                "output:    none: the job ended ({}) before any frame was finished; nothing to fetch",
                state_name(j.state)
            );
        } else {
            outln!(
                "output:    {} on the coordinator's host (nothing to fetch until a frame is finished)",
                j.output_dir
            );
        }
        for f in &j.frames {
            let done = if f.output.is_empty() {
                format!("{:.0}%", 100.0 * f.progress)
            } else {
                f.output.clone()
            };
            outln!("  frame {:>5}: {done}", f.frame);
        }
        if !j.error.is_empty() {
            outln!("error:     {}", j.error);
        }
        Ok(ExitCode::SUCCESS)
    })
}

/// Frames a page of `GetJob` asks for.
const FRAME_PAGE: u32 = 10_000;

/// The job with every frame, asked for in pages: one status of a long
/// animation is no larger than a page (a coordinator of an earlier
/// release answers the first request with every frame).
async fn get_job(client: &mut JobClient, id: &str) -> Result<pb::JobStatus> {
    let mut job: Option<pb::JobStatus> = None;
    let mut token = String::new();
    loop {
        let mut page = client
            .get_job(pb::GetJobRequest {
                job_id: id.to_string(),
                frame_limit: FRAME_PAGE,
                frame_page_token: token,
            })
            .await
            .map_err(rpc)?
            .into_inner();
        token = std::mem::take(&mut page.next_frame_page_token);
        match &mut job {
            None => job = Some(page),
            Some(j) => merge_frames(&mut j.frames, page.frames),
        }
        if token.is_empty() {
            return Ok(job.expect("a page"));
        }
    }
}

/// Merges frames (a page, a watch's changes) into `frames`, kept in frame
/// order. A frame's units only grow and its output stays once set, so
/// whichever of two reports is newer wins.
fn merge_frames(frames: &mut Vec<pb::FrameStatus>, changed: Vec<pb::FrameStatus>) {
    for f in changed {
        match frames.binary_search_by_key(&f.frame, |g| g.frame) {
            Ok(i) => {
                let g = &mut frames[i];
                g.units_done = g.units_done.max(f.units_done);
                g.units_total = f.units_total;
                if !f.output.is_empty() {
                    g.output = f.output;
                }
            }
            Err(i) => frames.insert(i, f),
        }
    }
}

/// A watched job as the events so far tell it: a delta's fields over the
/// last, its frames merged in; an event of a coordinator of an earlier
/// release (no deltas) replaces it. Keepalives change nothing (None).
fn apply_event(cur: &mut Option<pb::JobStatus>, mut ev: pb::JobStatus) -> Option<bool> {
    if ev.keepalive {
        return None;
    }
    let first = cur.is_none();
    if ev.delta
        && let Some(c) = cur.as_mut()
    {
        let mut frames = std::mem::take(&mut c.frames);
        merge_frames(&mut frames, std::mem::take(&mut ev.frames));
        ev.frames = frames;
    }
    *cur = Some(ev);
    Some(first)
}

pub fn watch(args: JobArg) -> Result<ExitCode> {
    runtime()?.block_on(async move {
        // From the start: a Ctrl-C while still connecting stops only the
        // watch too, and says so.
        let mut interrupt = interrupt_signal()?;
        let mut client = tokio::select! {
            c = connect(&args.coordinator) => c?,
            _ = &mut interrupt => {
                return Ok(stopped_watching(&args.job, &args.coordinator));
            }
        };
        watch_job(
            &mut client,
            &args.job,
            args.format,
            &args.coordinator,
            None,
            interrupt,
        )
        .await
    })
}

/// Ctrl-C stopped a watch: says that the job goes on, and how to watch or
/// cancel it; [`EXIT_INTERRUPTED`].
fn stopped_watching(id: &str, coordinator: &CoordinatorUrl) -> ExitCode {
    eprintln!(
        "stopped watching; job {id} keeps running on the coordinator. Watch it again with: {}; cancel it with: {}",
        client_command("watch", &shell_word(id), coordinator),
        client_command("cancel", &shell_word(id), coordinator)
    );
    ExitCode::from(EXIT_INTERRUPTED)
}

/// The progress line of a watched job.
fn show_progress(progress: &Progress, j: &pb::JobStatus, no_workers: bool) {
    let eta = if j.eta_seconds >= 0.0 && j.state == pb::JobState::Running as i32 {
        format!(" eta {:.0} s", j.eta_seconds)
    } else {
        String::new()
    };
    let workers = if !j.waiting_for.is_empty() {
        " (waiting for the jobs it runs after)"
    } else if no_workers {
        " (no workers)"
    } else if !j.unrunnable.is_empty() {
        " (no worker meets its requirements)"
    } else {
        ""
    };
    let adaptive = j.adaptive.as_ref().map_or(String::new(), |a| {
        let (blocks, error) = match adaptive_mode(a) {
            AdaptiveMode::Image => ("settled", "est. image RMSE"),
            AdaptiveMode::Pixel => ("converged", "est. error"),
        };
        format!(
            " {blocks} {:.1}% {error} {:.2e}",
            100.0 * a.converged_share,
            a.estimated_error
        )
    });
    progress.set(
        (percent(j) * 10.0) as u64,
        &format!(
            "{}{workers} {:.1} Mrays/s{adaptive}{eta}",
            state_name(j.state),
            j.rays_per_second / 1e6
        ),
    );
}

/// How often `watch` asks whether any worker is connected.
const WORKER_CHECK_EVERY: std::time::Duration = std::time::Duration::from_secs(5);

/// Shows progress until the job ends; the exit code is its outcome
/// ([`EXIT_DONE`], [`EXIT_FAILED`], [`EXIT_CANCELLED`]), or
/// [`EXIT_INTERRUPTED`] on Ctrl-C (the job goes on). With `--json`, every
/// event is a JSON line on stdout instead. `fetch_to`: the frames will be
/// fetched into that folder next (so no fetch command is suggested).
async fn watch_job(
    client: &mut JobClient,
    id: &str,
    format: Format,
    coordinator: &CoordinatorUrl,
    fetch_to: Option<&Path>,
    mut interrupt: Interrupt,
) -> Result<ExitCode> {
    let request = client.watch_job(pb::WatchJobRequest {
        job_id: id.to_string(),
        // Changes, not the whole job each time (a long animation's
        // frames are most of it).
        deltas: true,
    });
    let mut stream = tokio::select! {
        s = request => s.map_err(rpc)?.into_inner(),
        _ = &mut interrupt => return Ok(stopped_watching(id, coordinator)),
    };
    let progress = Progress::new(&format!("job {id}"), 1000, format.json);
    let mut last: Option<pb::JobStatus> = None;
    let mut workers_check = tokio::time::interval(WORKER_CHECK_EVERY);
    let mut no_workers = false;
    let mut unrunnable = String::new();
    loop {
        let ev = tokio::select! {
            ev = stream.next() => ev,
            _ = &mut interrupt => {
                // Only this watch stops: say so, and how to go on.
                progress.abandon();
                return Ok(stopped_watching(id, coordinator));
            }
            _ = workers_check.tick() => {
                // A job waits silently for workers that are not there:
                // say so (once each time the farm empties).
                let ended = last.as_ref().is_some_and(|j| ended(j.state));
                if !ended && let Ok(ws) = client.list_workers(pb::ListWorkersRequest {}).await {
                    let none = ws.into_inner().workers.is_empty();
                    if none && !no_workers {
                        progress.note(&format!(
                            "job {id}: no workers are connected to the coordinator; the job waits for one (start `tessera worker --coordinator URL`)"
                        ));
                    }
                    no_workers = none;
                }
                // No events while the job does not change: the plain
                // progress line (and its "(no workers)") still comes.
                if !format.json && let Some(j) = &last {
                    show_progress(&progress, j, no_workers);
                }
                continue;
            }
        };
        let Some(ev) = ev else { break };
        let Some(first) = apply_event(&mut last, ev.map_err(rpc)?) else {
            continue; // a keepalive
        };
        if format.json && first && last.as_ref().is_some_and(|j| j.delta) {
            // Deltas start without frames: `--json` prints whole jobs.
            let all = get_job(client, id).await?;
            if let Some(j) = last.as_mut() {
                merge_frames(&mut j.frames, all.frames);
            }
        }
        let j = last.as_ref().expect("an event applied");
        // A job no connected worker can run says why (once each time).
        if j.unrunnable != unrunnable {
            if !j.unrunnable.is_empty() {
                progress.note(&format!("job {id}: {}", j.unrunnable));
            }
            unrunnable = j.unrunnable.clone();
        }
        if format.json {
            print_json(&job_json(j));
        } else {
            show_progress(&progress, j, no_workers);
        }
    }
    progress.finish();
    let Some(j) = last else {
        bail!("the coordinator ended the watch of {id} without any event")
    };
    match pb::JobState::try_from(j.state).unwrap_or(pb::JobState::Unspecified) {
        pb::JobState::Done => {
            // The output folder is on the coordinator's host (and relative
            // to its directory): what to run here is the fetch.
            match fetch_to {
                Some(dir) => eprintln!(
                    "job {id} done: {} frame(s); fetching them into {}",
                    j.last_frame - j.first_frame + 1,
                    dir.display()
                ),
                None => eprintln!(
                    "job {id} done: {} frame(s); download them with: {}",
                    j.last_frame - j.first_frame + 1,
                    fetch_command(id, coordinator)
                ),
            }
            Ok(ExitCode::from(EXIT_DONE))
        }
        pb::JobState::Failed => {
            eprintln!("job {id} failed: {}", j.error);
            Ok(ExitCode::from(EXIT_FAILED))
        }
        pb::JobState::Cancelled => {
            eprintln!("job {id} cancelled");
            Ok(ExitCode::from(EXIT_CANCELLED))
        }
        _ => bail!(
            "the watch of {id} ended while the job is {}",
            state_name(j.state)
        ),
    }
}

/// A Ctrl-C to wait for (see [`interrupt_signal`]).
type Interrupt = std::pin::Pin<Box<dyn std::future::Future<Output = ()> + Send>>;

/// Resolves on Ctrl-C (SIGINT); the handler is installed when this returns.
fn interrupt_signal() -> Result<Interrupt> {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{SignalKind, signal};
        let mut s = signal(SignalKind::interrupt()).context("cannot handle Ctrl-C")?;
        Ok(Box::pin(async move {
            s.recv().await;
        }))
    }
    #[cfg(not(unix))]
    Ok(Box::pin(async {
        let _ = tokio::signal::ctrl_c().await;
    }))
}

pub fn cancel(args: JobArg) -> Result<ExitCode> {
    runtime()?.block_on(async move {
        let mut client = connect(&args.coordinator).await?;
        let j = client
            .cancel_job(pb::CancelJobRequest { job_id: args.job })
            .await
            .map_err(rpc)?
            .into_inner();
        if args.format.json {
            print_json(&job_json(&j));
        } else {
            eprintln!("job {} is {}", j.job_id, state_name(j.state));
        }
        Ok(ExitCode::SUCCESS)
    })
}

/// The command that downloads job `id`'s frames into a folder named after
/// it, with the coordinator flags this command was given (quoted for a
/// POSIX shell where needed).
pub fn fetch_command(id: &str, c: &CoordinatorUrl) -> String {
    client_command(
        "fetch",
        &format!("{} -o {}", shell_word(id), shell_word(id)),
        c,
    )
}

/// `tessera VERB WORDS` (WORDS already quoted) with the coordinator flags
/// this command was given (quoted for a POSIX shell where needed).
pub fn client_command(verb: &str, words: &str, c: &CoordinatorUrl) -> String {
    let mut cmd = format!("tessera {verb} {words}");
    if c.url != super::farm_common::DEFAULT_COORDINATOR {
        cmd += &format!(" --coordinator {}", shell_word(&c.url));
    }
    if let Some(ca) = &c.ca {
        cmd += &format!(" --ca {}", shell_word(&ca.display().to_string()));
    }
    if let Some(t) = &c.token_file {
        cmd += &format!(" --token-file {}", shell_word(&t.display().to_string()));
    }
    cmd
}

/// `s` as one word of a POSIX shell command line.
fn shell_word(s: &str) -> String {
    let plain = !s.is_empty()
        && s.chars()
            .all(|c| c.is_ascii_alphanumeric() || "-_./:=@%+,".contains(c));
    if plain {
        s.to_string()
    } else {
        format!("'{}'", s.replace('\'', r"'\''"))
    }
}

pub fn fetch(args: FetchArgs) -> Result<ExitCode> {
    runtime()?.block_on(async move {
        let mut client = connect(&args.coordinator).await?;
        fetch_frames(
            &mut client,
            &args.job,
            &args.output,
            args.force,
            args.format,
        )
        .await
    })
}

/// Downloads job `id`'s finished frames into `dir`; fails (creating
/// nothing) when none is finished, or when a frame file is already there
/// and not `force`; exits 1 after fetching what there is of a cancelled
/// or failed job. `--json`: one object naming the files written.
async fn fetch_frames(
    client: &mut JobClient,
    id: &str,
    dir: &Path,
    force: bool,
    format: Format,
) -> Result<ExitCode> {
    // Ask first: an unknown job, or one with no finished frame, leaves
    // nothing behind (no empty output folder).
    let j = get_job(client, id).await?;
    let written = j.frames.iter().filter(|f| !f.output.is_empty()).count();
    let total = j.frames.len();
    let ended_early =
        j.state == pb::JobState::Cancelled as i32 || j.state == pb::JobState::Failed as i32;
    if written == 0 {
        bail!(
            "job {} is {}{}: no frame is finished, nothing to fetch",
            j.job_id,
            state_name(j.state),
            if j.error.is_empty() {
                String::new()
            } else {
                format!(" ({})", j.error)
            }
        );
    }
    // Refused before anything is written: a second fetch into the same
    // folder (or frames of another job of the same names) would otherwise
    // replace files silently.
    if !force
        && let Some(f) = j
            .frames
            .iter()
            .filter(|f| !f.output.is_empty())
            .map(|f| dir.join(&f.output))
            .find(|p| p.exists())
    {
        bail!(
            "{} already exists; fetch refuses to overwrite frame files: pass --force to replace them, or fetch into another folder",
            f.display()
        );
    }
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let mut stream = client
        .fetch_results(pb::FetchResultsRequest {
            job_id: id.to_string(),
        })
        .await
        .map_err(rpc)?
        .into_inner();
    let mut files = Vec::new();
    while let Some(img) = stream.next().await {
        let img = img.map_err(rpc)?;
        // Only a plain file name from the coordinator: never a path elsewhere.
        let name = Path::new(&img.file_name)
            .file_name()
            .filter(|n| n.to_str() == Some(img.file_name.as_str()));
        let Some(name) = name else {
            bail!(
                "the coordinator sent an unsafe file name {:?}",
                img.file_name
            )
        };
        let path = dir.join(name);
        std::fs::write(&path, &img.data)
            .with_context(|| format!("cannot write {}", path.display()))?;
        files.push(img.file_name);
    }
    // Where the client can use it: absolute, on this machine.
    let out = std::path::absolute(dir).unwrap_or(dir.to_path_buf());
    if format.json {
        print_json(&serde_json::json!({
            "job_id": id,
            "state": state_name(j.state),
            "dir": out,
            "files": files,
            "frames_total": total,
        }));
    }
    eprintln!(
        "fetched {} of {total} frame(s) of {id} into {}",
        files.len(),
        out.display()
    );
    if ended_early {
        eprintln!(
            "error: job {} is {}: the other frames will not be rendered",
            j.job_id,
            state_name(j.state)
        );
        return Ok(ExitCode::FAILURE);
    }
    Ok(ExitCode::SUCCESS)
}

pub fn workers(args: ListArgs) -> Result<ExitCode> {
    runtime()?.block_on(async move {
        let mut client = connect(&args.coordinator).await?;
        let ws = client
            .list_workers(pb::ListWorkersRequest {})
            .await
            .map_err(rpc)?
            .into_inner()
            .workers;
        if args.format.json {
            print_json(&ws.iter().map(worker_json).collect());
            return Ok(ExitCode::SUCCESS);
        }
        outln!(
            "{:<20} {:<20} {:<12} {:<7} {:>7} {:>6} {:>8} {:>12} {:>9}  {}",
            "ID",
            "NAME",
            "HOST",
            "BACKEND",
            "THREADS",
            "LEASES",
            "UNITS",
            "MSAMPLES/S",
            "MRAYS/S",
            "LABELS"
        );
        for w in ws {
            let c = w.capabilities.unwrap_or_default();
            let backend = super::output::backend_name(c.backend);
            // Machine ids are 32 hex digits; 12 tell a farm's hosts apart.
            let host: String = printable(&c.host_id).chars().take(12).collect();
            // Backend and cores are columns already.
            let mut labels: Vec<String> = c
                .labels
                .iter()
                .filter(|(k, _)| !matches!(k.as_str(), "backend" | "cores"))
                .map(|(k, v)| printable(&format!("{k}={v}")))
                .collect();
            labels.sort();
            outln!(
                "{:<20} {:<20} {:<12} {:<7} {:>7} {:>6} {:>8} {:>12.2} {:>9.2}  {}",
                w.worker_id,
                if w.quarantined_until_unix_ms > 0 {
                    format!("{} (quarantined)", printable(&w.name))
                } else {
                    printable(&w.name)
                },
                if host.is_empty() { "-" } else { &host },
                backend,
                c.threads,
                w.leases,
                w.units_done,
                w.samples_per_second / 1e6,
                w.rays_per_second / 1e6,
                labels.join(",")
            );
        }
        Ok(ExitCode::SUCCESS)
    })
}

/// This machine's clock, unix ms (for times the coordinator sends).
fn now_unix_ms() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as i64)
}

/// What an adaptive job's target bounds, as its status says (a
/// coordinator of an earlier release says nothing: per pixel).
fn adaptive_mode(a: &pb::AdaptiveStatus) -> AdaptiveMode {
    tessera_proto::convert::adaptive_mode_from_pb(a.mode).unwrap_or_default()
}
