//! The Admin service's commands: ingest, list, retire, forget, stats, verify, repair and
//! compact.

use super::client::{call, Authed, Client};
use super::json::{distrusted, StatsJson, SurveyJson, Word};
use super::terrain::tile_crs;
use super::{
    printable, CompactArgs, Fail, ForgetArgs, IngestArgs, RepairArgs, RetireArgs, StatsArgs,
    SurveysArgs, VerifyArgs, WaitArgs,
};
use patchwork::engine::Engine;
use patchwork::paths::source_name;
use patchwork::serve::api;
use patchwork::serve::proto as pb;
use patchwork::serve::proto::admin_client::AdminClient;
use std::path::Path;
use std::sync::Arc;

pub async fn ingest(args: IngestArgs) -> Result<(), Fail> {
    let IngestArgs {
        files,
        accuracy,
        target,
    } = args;
    let mut c = Client::connect(&target).await?;
    // The bar counts bytes of files: a large file moves it through its phases while
    // the daemon reads, models, indexes and commits it.
    let sizes: Vec<u64> = files
        .iter()
        .map(|f| std::fs::metadata(f).map_or(1, |m| m.len().max(1)))
        .collect();
    let bar = indicatif::ProgressBar::new(sizes.iter().sum());
    bar.set_style(
        indicatif::ProgressStyle::with_template("{bar:30} {bytes}/{total_bytes} {elapsed} {msg}")
            .expect("template"),
    );
    let done = Arc::new(std::sync::atomic::AtomicU64::new(0));
    let watcher = watch_ingest(&c, bar.clone(), done.clone());
    // A hidden bar (no terminal) swallows its own println: print plainly then.
    let say = |line: String| {
        if bar.is_hidden() {
            println!("{line}");
        } else {
            bar.println(line);
        }
    };
    let mut failed = 0;
    for (f, size) in files.into_iter().zip(sizes) {
        let path = source_name(&f);
        if f.to_str().is_none() {
            // The wire carries text: the name cannot be sent as it is.
            failed += 1;
            say(format!(
                "failed    {}: the file name is not valid UTF-8: rename the file to ingest it",
                printable(&path)
            ));
            done.fetch_add(size, std::sync::atomic::Ordering::Relaxed);
            continue;
        }
        let req = pb::IngestRequest {
            paths: vec![path],
            accuracy_m: accuracy,
        };
        let r = req.clone();
        let reply = call!(&mut c, admin.ingest(req), move |e: &Engine| api::ingest(
            e, &r
        ))?;
        for r in reply.results {
            if r.outcome() == pb::Outcome::Failed {
                failed += 1;
                say(format!(
                    "failed    {}: {}",
                    printable(&r.source),
                    printable(&r.error)
                ));
            } else {
                say(format!(
                    "{:<9} {} {:016x} ({} samples, {:.2} s)",
                    r.outcome().word(),
                    printable(&r.source),
                    r.survey,
                    r.samples,
                    r.seconds
                ));
                for c in &r.conflicts {
                    say(format!(
                        "          conflicts with {}: up to {:.2} m apart, {:.2} m RMS",
                        c.survey, c.max_m, c.rms_m
                    ));
                }
            }
        }
        done.fetch_add(size, std::sync::atomic::Ordering::Relaxed);
        bar.set_position(done.load(std::sync::atomic::Ordering::Relaxed));
    }
    watcher.abort();
    bar.finish_and_clear();
    if failed > 0 {
        return Err(format!("{failed} file(s) failed").into());
    }
    Ok(())
}

pub async fn surveys(args: SurveysArgs) -> Result<(), Fail> {
    let SurveysArgs { json, target } = args;
    let mut c = Client::connect(&target).await?;
    let list = call!(
        &mut c,
        admin.list_surveys(pb::ListSurveysRequest {}),
        api::list_surveys
    )?;
    if json {
        let v: Vec<SurveyJson> = list.surveys.iter().map(SurveyJson::of).collect();
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        for s in &list.surveys {
            match s.status() {
                pb::SurveyStatus::Failed => println!(
                    "{:<16}  failed   {}  {}",
                    "-",
                    printable(&s.source),
                    printable(&s.error)
                ),
                pb::SurveyStatus::Deferred => println!(
                    "{:<16}  deferred {}  {}; read again once space is freed or it changes",
                    "-",
                    printable(&s.source),
                    printable(&s.error)
                ),
                pb::SurveyStatus::Skipped => println!(
                    "{:<16}  skipped  {}  {}",
                    "-",
                    printable(&s.source),
                    printable(&s.error)
                ),
                // Out of the terrain: what is wrong matters, not its claims.
                pb::SurveyStatus::Damaged => println!(
                    "{:<16}  damaged  {}  {}; ingest the file again or run `patchwork repair`",
                    s.id,
                    printable(&s.source),
                    printable(&s.error)
                ),
                st => {
                    // What most of it achieves beside what all of it does.
                    let claimed = if s.claimed_accuracy_m < s.accuracy_m {
                        format!(", claimed {:.3} m", s.claimed_accuracy_m)
                    } else {
                        String::new()
                    };
                    println!(
                            "{:<16}  {:<7}  {}  ε median {:.3} m, 90% {:.3} m, largest {:.3} m ({}{claimed})  {} samples  {} patches",
                            s.id,
                            st.word(),
                            printable(&s.source),
                            s.accuracy_median_m,
                            s.accuracy_p90_m,
                            s.accuracy_m,
                            s.accuracy_source().word(),
                            s.samples,
                            s.patches
                        );
                    if let Some(line) = about_line(s.about.as_ref()) {
                        println!("{:<16}  {}", "", printable(&line));
                    }
                    for c in &s.conflicts {
                        println!("{:<16}  {}", "", conflict_line(c));
                    }
                }
            }
        }
    }
    Ok(())
}

/// Waits for the daemon, then for each file to be a survey it serves. A file is looked for by
/// the name the daemon records it under (its absolute path), so `inbox/x.tif` names the file
/// dropped there.
pub async fn wait(args: WaitArgs) -> Result<(), Fail> {
    let WaitArgs {
        files,
        timeout,
        target,
    } = args;
    if target.data_dir.is_some() {
        return Err(
            "wait talks to a running daemon: a store opened with --data-dir takes \
                    files only through `patchwork ingest`"
                .into(),
        );
    }
    let until = std::time::Instant::now() + std::time::Duration::from_secs_f64(timeout.max(0.0));
    let pause = || tokio::time::sleep(std::time::Duration::from_millis(100));
    // A daemon just started may not listen yet.
    let mut c = loop {
        match Client::connect(&target).await {
            Ok(c) => break c,
            Err(e) if std::time::Instant::now() >= until => {
                return Err(format!("{e} (waited {timeout} s)").into())
            }
            Err(_) => pause().await,
        }
    };
    let mut waiting: Vec<(String, String)> = files
        .iter()
        .map(|f| (printable(&source_name(f)).into_owned(), source_name(f)))
        .collect();
    loop {
        let list = call!(
            &mut c,
            admin.list_surveys(pb::ListSurveysRequest {}),
            api::list_surveys
        )?;
        let mut still = Vec::new();
        for (shown, source) in waiting {
            let of: Vec<&pb::SurveyInfo> =
                list.surveys.iter().filter(|s| s.source == source).collect();
            if let Some(s) = of.iter().find(|s| s.status() == pb::SurveyStatus::Active) {
                println!("{shown}: active, survey {}", s.id);
            } else if let Some(s) = of.iter().find(|s| {
                matches!(
                    s.status(),
                    pb::SurveyStatus::Failed
                        | pb::SurveyStatus::Skipped
                        | pb::SurveyStatus::Damaged
                )
            }) {
                return Err(
                    format!("{shown}: {} ({})", s.status().word(), printable(&s.error)).into(),
                );
            } else {
                still.push((shown, source));
            }
        }
        waiting = still;
        if waiting.is_empty() {
            return Ok(());
        }
        if std::time::Instant::now() >= until {
            let names: Vec<&str> = waiting.iter().map(|(s, _)| s.as_str()).collect();
            return Err(format!(
                "after {timeout} s, not yet a survey: {} (is it in one of the daemon's inbox \
                 folders? `patchwork surveys` lists what it holds, deferred files with why)",
                names.join(", ")
            )
            .into());
        }
        pause().await;
    }
}

/// What a survey's sidecar says of it, on a line: title, acquisition, licence, attribution,
/// those it gives; None where it gives none.
fn about_line(a: Option<&pb::About>) -> Option<String> {
    let a = a?;
    let parts: Vec<String> = [
        (&a.title, ""),
        (&a.acquired, "acquired "),
        (&a.license, "licence "),
        (&a.attribution, "© "),
    ]
    .iter()
    .filter(|(v, _)| !v.is_empty())
    .map(|(v, label)| format!("{label}{v}"))
    .collect();
    (!parts.is_empty()).then(|| parts.join("  "))
}

pub async fn retire(args: RetireArgs) -> Result<(), Fail> {
    let RetireArgs {
        id_or_source,
        target,
    } = args;
    let mut c = Client::connect(&target).await?;
    let source = if Path::new(&id_or_source).exists() {
        source_name(Path::new(&id_or_source))
    } else {
        id_or_source
    };
    let req = pb::RetireRequest {
        id_or_source: source,
    };
    let r = req.clone();
    let reply = call!(&mut c, admin.retire(req), move |e: &Engine| api::retire(
        e, &r
    ))?;
    println!("retired {} ({} patches)", reply.id, reply.patches);
    Ok(())
}

pub async fn forget(args: ForgetArgs) -> Result<(), Fail> {
    let ForgetArgs { path, target } = args;
    let mut c = Client::connect(&target).await?;
    let source = source_name(&path);
    let req = pb::ForgetRequest {
        source: source.clone(),
    };
    let r = req.clone();
    call!(&mut c, admin.forget(req), move |e: &Engine| api::forget(
        e, &r
    ))?;
    println!("forgot the failure of {}", printable(&source));
    Ok(())
}

pub async fn stats(args: StatsArgs) -> Result<(), Fail> {
    let StatsArgs { json, target } = args;
    let mut c = Client::connect(&target).await?;
    let s = call!(&mut c, admin.stats(pb::StatsRequest {}), api::stats)?;
    if json {
        println!("{}", serde_json::to_string_pretty(&StatsJson::of(&s))?);
    } else {
        let crs = match tile_crs(&s.crs_key)? {
            Some(c) => c.label(),
            None => "none yet".into(),
        };
        let vertical = if s.vertical_crs.is_empty() {
            "none yet".to_string()
        } else {
            s.vertical_crs.clone()
        };
        if s.damaged > 0 {
            println!(
                    "damaged {} surveys, out of the terrain: `patchwork surveys` says why, `patchwork repair` drops them",
                    s.damaged
                );
        }
        println!("surveys {} active, {} retired, {} failed\npatches {} ({} active boxes, {} quadtree nodes)\nsamples {}\ndisk {} bytes\ncrs {crs}\nvertical crs {vertical}\nbackend {}\nblend {}",
                s.surveys, s.retired, s.failed, s.patches, s.active_boxes, s.quadtree_nodes, s.samples, s.disk_bytes, s.backend, s.blend);
        println!(
            "cache {} of {} bytes, {} hits, {} misses",
            s.cache_bytes, s.cache_capacity_bytes, s.cache_hits, s.cache_misses
        );
        if s.requests_limit > 0 {
            println!(
                "requests {} at work of at most {}, {} waiting, {} served",
                s.requests_running, s.requests_limit, s.requests_waiting, s.requests_served
            );
        }
        if !s.follows.is_empty() {
            println!(
                "replica of {}: at commit {} of {} published, {:.1} s behind",
                s.follows, s.commit, s.published_commit, s.lag_seconds
            );
        } else if s.commit > 0 {
            println!("commit {}", s.commit);
        }
        if !s.read_only.is_empty() {
            println!("read-only: {}", s.read_only);
        }
    }
    Ok(())
}

pub async fn verify(args: VerifyArgs) -> Result<(), Fail> {
    let VerifyArgs { target } = args;
    let mut c = Client::connect(&target).await?;
    // A long verification says how far it has got, from the daemon's stats, on stderr.
    let shown = match &c {
        Client::Remote { admin, .. } => Some(tokio::spawn(show_verify_progress((**admin).clone()))),
        Client::Local(_) => None,
    };
    let v = call!(&mut c, admin.verify(pb::VerifyRequest {}), api::verify);
    if let Some(task) = shown {
        task.abort();
        if std::io::IsTerminal::is_terminal(&std::io::stderr()) {
            eprint!("\r\x1b[K");
        }
    }
    let v = v?;
    for p in &v.problems {
        println!("problem: {p}");
    }
    if v.ok {
        println!("ok: {} surveys, {} patches", v.surveys, v.patches);
        Ok(())
    } else {
        Err(format!("{} problem(s) found", v.problems.len()).into())
    }
}

/// Prints where the daemon's verification stands, from its stats: from a second on, once a
/// second on a terminal (one line, rewritten), else a line every five seconds.
async fn show_verify_progress(mut admin: AdminClient<Authed>) {
    let terminal = std::io::IsTerminal::is_terminal(&std::io::stderr());
    let every = if terminal { 1 } else { 5 };
    let mut tick = tokio::time::interval(std::time::Duration::from_secs(every));
    tick.tick().await;
    loop {
        tick.tick().await;
        let Ok(s) = admin.stats(pb::StatsRequest {}).await else {
            continue;
        };
        let s = s.into_inner();
        if s.verify_step.is_empty() {
            continue;
        }
        let what = match s.verify_step.as_str() {
            "index" => "deriving the index again",
            _ => "checking surveys",
        };
        let line = format!(
            "verifying: {what}, {} of {} ({:.0} s)",
            s.verify_done, s.verify_total, s.verify_seconds
        );
        if terminal {
            eprint!("\r\x1b[K{line}");
        } else {
            eprintln!("{line}");
        }
    }
}

pub async fn repair(args: RepairArgs) -> Result<(), Fail> {
    let RepairArgs { target } = args;
    let mut c = Client::connect(&target).await?;
    let r = call!(&mut c, admin.repair(pb::RepairRequest {}), api::repair)?;
    for d in &r.dropped {
        let source = if d.source.is_empty() {
            "unreadable record".to_string()
        } else {
            printable(&d.source).to_string()
        };
        println!("dropped {} ({source}): {}", d.id, d.reason);
    }
    println!("{} damaged surveys dropped", r.dropped.len());
    Ok(())
}

pub async fn compact(args: CompactArgs) -> Result<(), Fail> {
    let CompactArgs { target } = args;
    let mut c = Client::connect(&target).await?;
    let spinner = indicatif::ProgressBar::new_spinner();
    spinner.set_message("compacting");
    spinner.enable_steady_tick(std::time::Duration::from_millis(120));
    let r = call!(&mut c, admin.compact(pb::CompactRequest {}), api::compact)?;
    spinner.finish_and_clear();
    println!(
        "compacted: {} → {} bytes, {} retired surveys removed",
        r.bytes_before, r.bytes_after, r.surveys_removed
    );
    Ok(())
}

/// Runs one request either way: over gRPC, or through the same dispatcher the daemon uses.
/// Shows the daemon's ingest under way on `bar` until aborted: its phase, and a position
/// within the file by phase (reading and modelling take most of an ingest, committing the
/// rest), on top of `done`, the bytes of files finished. Polls `stats` every 200 ms.
fn watch_ingest(
    c: &Client,
    bar: indicatif::ProgressBar,
    done: Arc<std::sync::atomic::AtomicU64>,
) -> tokio::task::JoinHandle<()> {
    let mut remote = match c {
        Client::Remote { admin, .. } => Some(admin.as_ref().clone()),
        Client::Local(_) => None,
    };
    let local = match c {
        Client::Local(e) => Some(e.clone()),
        Client::Remote { .. } => None,
    };
    tokio::spawn(async move {
        loop {
            tokio::time::sleep(std::time::Duration::from_millis(200)).await;
            let s = match (&mut remote, &local) {
                (Some(a), _) => match a.stats(pb::StatsRequest {}).await {
                    Ok(r) => r.into_inner(),
                    Err(_) => continue,
                },
                (None, Some(e)) => patchwork::serve::convert::stats(&e.stats()),
                (None, None) => return,
            };
            if s.ingesting_source.is_empty() {
                continue;
            }
            let share = match s.ingesting_phase() {
                pb::IngestPhase::Reading | pb::IngestPhase::Unspecified => 0.0,
                pb::IngestPhase::Modelling => 0.25,
                pb::IngestPhase::Indexing => 0.6,
                pb::IngestPhase::Committing => 0.8,
            };
            let base = done.load(std::sync::atomic::Ordering::Relaxed);
            bar.set_position(base + (share * s.ingesting_bytes as f64) as u64);
            let name = std::path::Path::new(&s.ingesting_source)
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default();
            bar.set_message(format!(
                "{} {} ({:.1} s)",
                s.ingesting_phase().word(),
                printable(&name),
                s.ingesting_seconds
            ));
        }
    })
}

/// A conflict as `patchwork surveys` says it.
fn conflict_line(c: &pb::Conflict) -> String {
    let why = if c.decided_by.is_empty() || c.decided_by == "undetermined" {
        let tie = if c.takes_tie {
            "this survey"
        } else {
            "the other"
        };
        format!("undetermined, the tie goes to {tie}")
    } else {
        format!(
            "by {} ({:.2}, confidence {:.2})",
            c.decided_by, c.statistic, c.confidence
        )
    };
    let whose = match distrusted(c) {
        pb::Distrusted::This => format!("this survey's claim is the false one, {why}"),
        pb::Distrusted::Other => format!("the other's claim is the false one, {why}"),
        _ => format!("either claim may be the false one: {why}"),
    };
    let shift = match &c.shift {
        Some(s) if !c.shift_determined => format!(
            "; the shift is undetermined ({:.1} m east, {:.1} m north fit no better than none)",
            s.east_m, s.north_m
        ),
        Some(s) => {
            // A turn, a scale or a tilt worth naming: past what a shift alone leaves.
            let turned = if s.turned_deg.abs() >= 0.01 {
                format!(", turned {:.2}°", s.turned_deg)
            } else {
                String::new()
            };
            let scaled = if (s.scale - 1.0).abs() >= 1e-4 {
                format!(", scaled {:.4}", s.scale)
            } else {
                String::new()
            };
            let tilted = if s.tilt_east_m_per_km.hypot(s.tilt_north_m_per_km) >= 0.01 {
                format!(
                    ", tilted {:.2} m/km east and {:.2} m/km north",
                    s.tilt_east_m_per_km, s.tilt_north_m_per_km
                )
            } else {
                String::new()
            };
            format!(
                "; it lies {:.1} m east, {:.1} m north and {:.2} m up of this one{turned}{scaled}{tilted}, {:.2} m RMS once moved back",
                s.east_m, s.north_m, s.up_m, s.rms_after_m
            )
        }
        None => String::new(),
    };
    let changes: String = c
        .changes
        .iter()
        .map(|r| {
            let who = match r.later.as_str() {
                "this" => "this survey saw it last and serves it",
                "other" => "the other saw it last and serves it",
                _ => "undated, so neither takes precedence",
            };
            format!(
                // Under the conflict's line, which starts 18 columns in.
                "\n                    changed ground: {:.0} m², {:.0} m³ gained and {:.0} m³ lost, up to \
                 {:.1} m; {who}",
                r.area_m2, r.gained_m3, r.lost_m3, r.most_m
            )
        })
        .collect();
    format!(
        "conflicts with {}: up to {:.2} m apart, {:.2} m RMS{shift}; {whose}{changes}",
        c.survey, c.max_m, c.rms_m
    )
}
