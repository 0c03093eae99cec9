//! A rollout's logs for operators: `/results/logs/{batch}/{rollout}` (`web/templates/rollout_logs.html`) shows
//! what the runner kept of one finished rollout in its batch directory (`rollouts/<id>/`): the agent's stdout and
//! stderr (scrubbed and bounded by the runner when the rollout ended), the harness manifest, the usage record, the
//! model-API gateway's records and the agent's transcript; `/results/logs/{batch}/{rollout}/{file}` serves one of
//! them as plain text.
//!
//! Only those fixed names are ever opened, and only the runner's own files: the agent's session home lies in the
//! same rollout directory when the batch runs without the resource cage, so every name below the batch directory
//! is opened relative to its parent's descriptor without following a symlink (`O_NOFOLLOW`, `O_DIRECTORY` for the
//! directories), never blocking on a FIFO (`O_NONBLOCK`), and a file is read only when `fstat` says it is a regular
//! file. The batch directory itself is the operator's (`<data>/batches/NAME`, `serve --batches`, a registered
//! batch's directory on this machine). Files are read from their end: the page shows the last
//! [`PAGE_TAIL_BYTES`], the raw route the last [`RAW_TAIL_BYTES`], each with a note of what was left out. A
//! rollout still running has no entry in `rollouts.jsonl` yet and no logs here: the runner scrubs its logs (keys,
//! tokens) when it ends.
use std::fs::File;
use std::io::{Read, Seek, SeekFrom};
use std::os::fd::{AsFd, OwnedFd};
use std::path::{Path, PathBuf};

use askama::Template;
use axum::Router;
use axum::extract::{Path as UrlPath, State};
use axum::http::header;
use axum::response::IntoResponse;
use axum::routing::get;
use libero_episode::dirfd;
use libero_report::batch::{LoadedBatch, RolloutRecord, agent_of, stderr_file, stdout_file};
use libero_server::{ApiError, ApiResult, App, AppState};
use rustix::fs::{Mode, OFlags};

use crate::common::page;
use crate::results::{self, Selection, percent_encode, plain_name};

/// The most of a file's end the rollout page shows inline.
pub const PAGE_TAIL_BYTES: u64 = 256 << 10;
/// The most of a file's end the raw route serves.
pub const RAW_TAIL_BYTES: u64 = 8 << 20;
/// How far into a cut file the first whole line is looked for (a cut starts at a line when one begins there).
const LINE_SEARCH_BYTES: usize = 64 << 10;

pub fn routes() -> Router<AppState> {
    Router::new()
        .route("/results/logs/{batch}/{rollout}", get(rollout_page))
        .route("/results/logs/{batch}/{rollout}/{file}", get(raw_file))
}

/// The files a rollout page offers, by the name its address uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LogFile {
    Stdout,
    Stderr,
    Manifest,
    Usage,
    Transcript,
    ModelApi,
}

impl LogFile {
    pub const ALL: [LogFile; 6] = [Self::Stdout, Self::Stderr, Self::Transcript, Self::Manifest, Self::Usage, Self::ModelApi];

    /// The address's name (`/results/logs/B/R/stdout`).
    pub fn slug(self) -> &'static str {
        match self {
            Self::Stdout => "stdout",
            Self::Stderr => "stderr",
            Self::Manifest => "harness_manifest",
            Self::Usage => "harness_usage",
            Self::Transcript => "transcript",
            Self::ModelApi => "model_api",
        }
    }

    pub fn from_slug(s: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|f| f.slug() == s)
    }

    fn title(self) -> &'static str {
        match self {
            Self::Stdout => "The agent's stdout",
            Self::Stderr => "The agent's stderr",
            Self::Manifest => "Harness manifest",
            Self::Usage => "Token usage",
            Self::Transcript => "Transcript (agent events)",
            Self::ModelApi => "Model-API gateway records",
        }
    }

    /// Where the runner writes it, relative to the rollout directory (directories, then the file's name), for a
    /// batch of `harness`; `None` when that harness leaves no such file name (an unknown harness's logs).
    pub fn relative(self, harness: Option<&str>) -> Option<Vec<String>> {
        Some(match self {
            Self::Stdout => vec![stdout_file(harness?)?],
            Self::Stderr => vec![stderr_file(harness?)?],
            Self::Manifest => vec!["harness_manifest.json".into()],
            Self::Usage => vec!["harness_usage.json".into()],
            Self::Transcript => vec![libero_records::agent_events::AGENT_EVENTS_FILE.into()],
            Self::ModelApi => vec!["sandbox".into(), "model_api.jsonl".into()],
        })
    }

    /// Why the file may be missing, for the page.
    fn absent_note(self) -> &'static str {
        match self {
            Self::ModelApi => "not written: the gateway runs only inside the sandbox",
            Self::Transcript => "not written",
            _ => "not written (the rollout may have ended before its agent started)",
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum LogError {
    #[error("not written")]
    Absent,
    /// A symlink, directory, FIFO or device where the runner writes a file: never opened or read.
    #[error("refused: {0} is not a regular file the runner wrote (a link or special file)")]
    NotRegular(String),
    #[error("cannot read {0}: {1}")]
    Io(String, std::io::Error),
}

/// The end of a file: at most the tail asked for, starting at a line when one begins near the cut.
#[derive(Debug)]
pub struct Tail {
    pub text: String,
    /// The file's size when it was read.
    pub size: u64,
    /// Bytes before the part shown.
    pub left_out: u64,
}

impl Tail {
    /// The note above a cut file (empty when nothing was left out).
    pub fn note(&self) -> String {
        if self.left_out == 0 {
            String::new()
        } else {
            format!(
                "the first {} of {} bytes are left out; this is the last {}",
                thousands(self.left_out),
                thousands(self.size),
                human_bytes(self.size - self.left_out)
            )
        }
    }
}

fn thousands(n: u64) -> String {
    let s = n.to_string();
    let mut out = String::with_capacity(s.len() + s.len() / 3);
    for (i, c) in s.chars().enumerate() {
        if i > 0 && (s.len() - i) % 3 == 0 {
            out.push(',');
        }
        out.push(c);
    }
    out
}

fn human_bytes(n: u64) -> String {
    match n {
        n if n >= 1 << 20 => format!("{:.1} MiB", n as f64 / f64::from(1u32 << 20)),
        n if n >= 1 << 10 => format!("{:.1} KiB", n as f64 / 1024.0),
        n => format!("{n} bytes"),
    }
}

const FILE_FLAGS: OFlags = OFlags::RDONLY.union(OFlags::NOFOLLOW).union(OFlags::NONBLOCK).union(OFlags::CLOEXEC).union(OFlags::NOCTTY);

fn io_err(what: &str) -> impl FnOnce(std::io::Error) -> LogError + '_ {
    move |e| match rustix::io::Errno::from_io_error(&e) {
        Some(rustix::io::Errno::NOENT) => LogError::Absent,
        Some(rustix::io::Errno::LOOP | rustix::io::Errno::NOTDIR | rustix::io::Errno::ISDIR) => LogError::NotRegular(what.to_owned()),
        _ => LogError::Io(what.to_owned(), e),
    }
}

/// Opens `relative` (directory names, then a file name) under `dir`, never following a symlink below `dir`, and
/// only when the last name is a regular file.
pub fn open_regular(dir: &Path, relative: &[String]) -> Result<File, LogError> {
    let (file_name, dirs) = relative.split_last().ok_or(LogError::Absent)?;
    let shown = relative.join("/");
    let mut fd: OwnedFd =
        rustix::fs::open(dir, OFlags::RDONLY | OFlags::DIRECTORY | OFlags::CLOEXEC, Mode::empty()).map_err(|e| io_err(&shown)(e.into()))?;
    for name in dirs {
        fd = dirfd::open_dir_at(fd.as_fd(), name).map_err(io_err(&shown))?;
    }
    let file = rustix::fs::openat(fd.as_fd(), file_name.as_str(), FILE_FLAGS, Mode::empty()).map_err(|e| io_err(&shown)(e.into()))?;
    let stat = rustix::fs::fstat(&file).map_err(|e| LogError::Io(shown.clone(), e.into()))?;
    if rustix::fs::FileType::from_raw_mode(stat.st_mode) != rustix::fs::FileType::RegularFile {
        return Err(LogError::NotRegular(shown));
    }
    Ok(File::from(file))
}

/// The last `max` bytes of `file` (fewer when it is smaller), as text (invalid UTF-8 replaced); a cut one starts
/// after the first line break within [`LINE_SEARCH_BYTES`] of the cut.
pub fn read_tail(mut file: File, max: u64) -> std::io::Result<Tail> {
    let size = file.metadata()?.len();
    let start = size.saturating_sub(max);
    file.seek(SeekFrom::Start(start))?;
    let mut bytes = Vec::with_capacity(usize::try_from(size - start).unwrap_or(0));
    file.take(max).read_to_end(&mut bytes)?;
    let mut skip = 0;
    if start > 0
        && let Some(nl) = bytes.iter().take(LINE_SEARCH_BYTES).position(|b| *b == b'\n')
    {
        skip = nl + 1;
    }
    Ok(Tail { text: String::from_utf8_lossy(&bytes[skip..]).into_owned(), size, left_out: start + skip as u64 })
}

/// A rollout of a batch directory: the batch's files and its record.
struct Rollout {
    batch: LoadedBatch,
    record: RolloutRecord,
}

impl Rollout {
    fn dir(&self) -> PathBuf {
        self.batch.dir.join("rollouts").join(&self.record.rollout_id)
    }

    fn harness(&self) -> Option<&str> {
        self.batch.batch.harness_setting()
    }
}

/// The finished rollout `rollout` of batch `batch`, or the answer saying why there is none.
async fn find(app: &App, batch: &str, rollout: &str) -> ApiResult<Rollout> {
    if !plain_name(batch) || !plain_name(rollout) {
        return Err(ApiError::not_found("no such batch or rollout"));
    }
    let (_, mut batches) = results::selected(app, &Selection { batches: vec![batch.to_owned()], reps: None }).await?;
    let b = batches.pop().ok_or_else(|| ApiError::not_found(format!("no batch {batch:?}")))?;
    let Some(record) = b.records.iter().find(|r| r.rollout_id == rollout).cloned() else {
        return Err(ApiError::not_found(format!(
            "batch {batch} has no finished rollout {rollout:?}: a running rollout's logs show here once it has ended (the runner scrubs them then)"
        )));
    };
    let found = Rollout { batch: b, record };
    let dir = found.batch.dir.clone();
    if !tokio::fs::metadata(dir.join("rollouts")).await.is_ok_and(|m| m.is_dir()) {
        return Err(ApiError::not_found(format!(
            "batch {batch}'s directory {} is not on this machine (its runner or workers keep its rollout logs)",
            dir.display()
        )));
    }
    Ok(found)
}

/// The file's tail, where the transcript lives: the rollout directory's copy (a server elsewhere), else the
/// episode's run directory, where the runner appends it when it can (the batch's or this server's); `true` when it
/// came from there.
async fn tail_of(app: &App, r: &Rollout, file: LogFile, max: u64) -> Result<(Tail, bool), LogError> {
    let relative = file.relative(r.harness()).ok_or(LogError::Absent)?;
    let dir = r.dir();
    let rel = relative.clone();
    let in_rollout = blocking(move || open_regular(&dir, &rel).and_then(|f| read_tail(f, max).map_err(|e| LogError::Io(rel.join("/"), e)))).await;
    match (file, in_rollout, r.record.episode_id.as_deref()) {
        (LogFile::Transcript, Err(LogError::Absent), Some(episode)) => {
            let run = crate::rows::stored_row(app, episode).await.map_err(|_| LogError::Absent)?.episode.run_dir;
            blocking(move || open_regular(&run, &relative).and_then(|f| read_tail(f, max).map_err(|e| LogError::Io(relative.join("/"), e))))
                .await
                .map(|t| (t, true))
        }
        (_, result, _) => result.map(|t| (t, false)),
    }
}

async fn blocking<T: Send + 'static>(f: impl FnOnce() -> Result<T, LogError> + Send + 'static) -> Result<T, LogError> {
    tokio::task::spawn_blocking(f).await.unwrap_or_else(|e| Err(LogError::Io("read thread".into(), std::io::Error::other(e.to_string()))))
}

/// One file's section of the page.
struct FileView {
    slug: &'static str,
    title: &'static str,
    /// Where it is in the rollout directory.
    name: String,
    href: String,
    size: String,
    /// What was left out, or why there is nothing.
    note: String,
    text: String,
    present: bool,
}

#[derive(Template)]
#[template(path = "rollout_logs.html")]
struct RolloutPage {
    batch: String,
    batch_href: String,
    rollout: String,
    task: String,
    task_href: String,
    facts: Vec<(String, String)>,
    outcome: String,
    review: String,
    files: Vec<FileView>,
    page_tail: String,
    raw_tail: String,
}

async fn rollout_page(State(app): State<AppState>, UrlPath((batch, rollout)): UrlPath<(String, String)>) -> ApiResult {
    let r = find(&app, &batch, &rollout).await?;
    let mut files = Vec::new();
    for f in LogFile::ALL {
        let mut name = f.relative(r.harness()).map(|p| p.join("/")).unwrap_or_else(|| "?".into());
        let href = format!("/results/logs/{}/{}/{}", percent_encode(&batch), percent_encode(&rollout), f.slug());
        let (present, size, note, text) = match tail_of(&app, &r, f, PAGE_TAIL_BYTES).await {
            Ok((t, from_run)) => {
                if from_run {
                    name = format!("{name} (in the episode's run directory)");
                }
                let note = if t.size == 0 { "empty".to_owned() } else { t.note() };
                (true, format!("{} bytes", thousands(t.size)), note, t.text)
            }
            Err(LogError::Absent) => (false, String::new(), f.absent_note().to_owned(), String::new()),
            Err(e) => (false, String::new(), e.to_string(), String::new()),
        };
        files.push(FileView { slug: f.slug(), title: f.title(), name, href, size, note, text, present });
    }
    let rec = &r.record;
    let mut facts = vec![
        ("repetition".to_owned(), rec.repetition.to_string()),
        ("level".to_owned(), rec.level.to_string()),
        ("demonstration".to_owned(), rec.demo.as_str().to_owned()),
        ("stages".to_owned(), format!("{}/{}", rec.completed_stages.map_or("?".into(), |c| c.to_string()), rec.stage_count)),
        ("agent".to_owned(), agent_of(&r.batch)),
        ("agent exit code".to_owned(), rec.agent_exit_code.map_or("–".into(), |c| c.to_string())),
        ("harness time".to_owned(), rec.harness_elapsed_s.map_or("–".into(), |s| format!("{s:.1} s"))),
    ];
    if let Some(why) = rec.reason() {
        facts.push(("reason".to_owned(), why));
    }
    if let Some(w) = &rec.worker {
        facts.push(("worker".to_owned(), w.clone()));
    }
    let (task_href, _) = crate::task_page::task_link(&rec.task);
    Ok(page(RolloutPage {
        batch_href: format!("/results?batch={}", percent_encode(&batch)),
        batch,
        rollout,
        task: rec.task.clone(),
        task_href,
        facts,
        outcome: rec.outcome.as_str().to_owned(),
        review: rec.episode_id.as_ref().map(|id| format!("/episodes/{id}/review")).unwrap_or_default(),
        files,
        page_tail: human_bytes(PAGE_TAIL_BYTES),
        raw_tail: human_bytes(RAW_TAIL_BYTES),
    }))
}

/// The last [`RAW_TAIL_BYTES`] of one file as plain text (never rendered by the browser as a page), with a first
/// line saying what was left out when the file is longer.
async fn raw_file(State(app): State<AppState>, UrlPath((batch, rollout, file)): UrlPath<(String, String, String)>) -> ApiResult {
    let f = LogFile::from_slug(&file).ok_or_else(|| {
        let names: Vec<&str> = LogFile::ALL.iter().map(|f| f.slug()).collect();
        ApiError::not_found(format!("a rollout's logs are {}, not {file:?}", names.join(", ")))
    })?;
    let r = find(&app, &batch, &rollout).await?;
    let tail = match tail_of(&app, &r, f, RAW_TAIL_BYTES).await {
        Ok((t, _)) => t,
        Err(LogError::Absent) => return Err(ApiError::not_found(format!("rollout {rollout}: {} {}", f.title().to_lowercase(), f.absent_note()))),
        Err(e @ LogError::NotRegular(_)) => return Err(ApiError::forbidden(e.to_string())),
        Err(e) => return Err(ApiError::internal(e.to_string())),
    };
    let note = tail.note();
    let body = if note.is_empty() { tail.text } else { format!("[libero-agent: {note}]\n{}", tail.text) };
    Ok((
        [
            (header::CONTENT_TYPE, "text/plain; charset=utf-8"),
            (header::X_CONTENT_TYPE_OPTIONS, "nosniff"),
            (header::CONTENT_SECURITY_POLICY, "sandbox"),
            (header::CACHE_CONTROL, "no-store"),
        ],
        body,
    )
        .into_response())
}

#[cfg(test)]
mod tests {
    use std::os::unix::fs::symlink;

    use super::*;

    fn rel(parts: &[&str]) -> Vec<String> {
        parts.iter().map(|s| (*s).to_owned()).collect()
    }

    #[test]
    fn a_long_log_is_served_from_its_end_starting_at_a_line_with_a_note() {
        let dir = tempfile::tempdir().unwrap();
        let lines: String = (0..20_000).map(|i| format!("line {i:05}\n")).collect();
        std::fs::write(dir.path().join("log"), &lines).unwrap();
        let t = read_tail(open_regular(dir.path(), &rel(&["log"])).unwrap(), 1000).unwrap();
        assert_eq!(t.size, lines.len() as u64);
        assert!(t.text.starts_with("line ") && t.text.ends_with("line 19999\n"), "{}", &t.text[..20]);
        assert!(t.text.len() <= 1000 && t.text.len() > 980, "{}", t.text.len());
        assert_eq!(t.left_out + t.text.len() as u64, t.size);
        assert!(t.note().contains(&format!("of {} bytes are left out", thousands(t.size))), "{}", t.note());
        let whole = read_tail(open_regular(dir.path(), &rel(&["log"])).unwrap(), 1 << 30).unwrap();
        assert_eq!((whole.text.as_str(), whole.left_out, whole.note().as_str()), (lines.as_str(), 0, ""));
    }

    #[test]
    fn links_fifos_and_directories_where_a_log_belongs_are_refused_unopened() {
        let dir = tempfile::tempdir().unwrap();
        let secret = dir.path().join("secret");
        std::fs::write(&secret, "operator token").unwrap();
        let rollout = dir.path().join("rollouts/w1");
        std::fs::create_dir_all(&rollout).unwrap();
        symlink(&secret, rollout.join("command_stdout.log")).unwrap();
        assert!(std::process::Command::new("mkfifo").arg(rollout.join("command_stderr.log")).status().unwrap().success());
        std::fs::create_dir(rollout.join("harness_manifest.json")).unwrap();
        // a linked directory on the way: the gateway's directory, and a whole rollout
        std::fs::create_dir(dir.path().join("elsewhere")).unwrap();
        std::fs::write(dir.path().join("elsewhere/model_api.jsonl"), "secret").unwrap();
        symlink(dir.path().join("elsewhere"), rollout.join("sandbox")).unwrap();
        symlink(&rollout, dir.path().join("rollouts/w2")).unwrap();
        for (path, what) in [
            (rel(&["rollouts", "w1", "command_stdout.log"]), "a symlink to a file"),
            (rel(&["rollouts", "w1", "command_stderr.log"]), "a FIFO (and the read never blocks)"),
            (rel(&["rollouts", "w1", "harness_manifest.json"]), "a directory"),
            (rel(&["rollouts", "w1", "sandbox", "model_api.jsonl"]), "a linked directory on the way"),
            (rel(&["rollouts", "w2", "harness_usage.json"]), "a linked rollout directory"),
        ] {
            assert!(matches!(open_regular(dir.path(), &path), Err(LogError::NotRegular(_))), "{what} must be refused");
        }
        assert!(matches!(open_regular(dir.path(), &rel(&["rollouts", "w1", "harness_usage.json"])), Err(LogError::Absent)));
        std::fs::write(rollout.join("harness_usage.json"), "{}").unwrap();
        assert_eq!(read_tail(open_regular(dir.path(), &rel(&["rollouts", "w1", "harness_usage.json"])).unwrap(), 10).unwrap().text, "{}");
    }

    #[test]
    fn only_plain_names_and_known_files_reach_the_filesystem() {
        for bad in ["", "..", ".hidden", "a/b", "a b", "w1%2F..", &"x".repeat(161)] {
            assert!(!plain_name(bad), "{bad:?}");
        }
        assert!(plain_name("w1_t28_level3") && plain_name("batch-2026.01"));
        assert_eq!(LogFile::from_slug("home"), None);
        assert_eq!(LogFile::from_slug("stdout"), Some(LogFile::Stdout));
        assert_eq!(LogFile::Stdout.relative(Some("codex")), Some(rel(&["codex_stdout.jsonl"])));
        assert_eq!(LogFile::Stderr.relative(Some("command")), Some(rel(&["command_stderr.log"])));
        assert_eq!(LogFile::Stdout.relative(None), None);
        assert_eq!((LogFile::Stdout.relative(Some("../x")), LogFile::Stderr.relative(Some("../x"))), (None, None), "an unknown harness names no file");
        for f in LogFile::ALL {
            assert!(!f.relative(Some("command")).unwrap().iter().any(|p| p == "home" || p.contains('/')), "{f:?}");
        }
    }
}
