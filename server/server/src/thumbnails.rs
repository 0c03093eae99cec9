//! Task thumbnails: the settled initial head- and wrist-camera views of a task (`T14`, or a runnable pool entry
//! `suite/task_id`), rendered through the same world set-up as an episode (placement, init state, settle) at seed
//! 100, init row 0, level 1.
//!
//! They are cached under `<data>/thumbnails/<scene hash>-{head,wrist}.png`, where the hash covers everything
//! that decides the scene: the BDDL file's bytes, the init-state file's bytes, the catalog's start settings
//! (placement seed, init row, settle steps, poses) and the asset roots. So a cache entry survives restarts,
//! a changed scene gets a fresh one, and pool entries that run on a release task's scene share its files.
//!
//! A server with a console renders them ahead at start ([`Thumbnails::render_ahead`]), in background threads
//! at the lowest CPU priority that also wait while any episode is open, so benchmark episodes and the
//! server's answers never queue behind them. A page asking for one not rendered yet renders it on demand
//! ([`Thumbnails::get`]): one at a time, in the order asked (a page's cards top to bottom), and a request whose
//! page has gone (the browser closed its connection, so its handler was dropped) leaves the queue before its
//! render starts, so the next page never waits behind the thumbnails of pages nobody is looking at. Pages come
//! first: the background pass starts no scene while a page's request waits or renders, and a request for a scene
//! being rendered right now (by the pass or for another page) waits for that render outside the queue.
use std::collections::HashMap;
use std::fs;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use libero_episode::Level;
use libero_episode::task::resolve_task;
use libero_episode::world::{LiberoWorld, WorldSpec};
use serde::Serialize;
use sha2::{Digest, Sha256};

use crate::episodes::Episodes;

/// Bumped whenever how a thumbnail is made changes (seed, row, level, image format): every old entry is stale.
const SCHEME: &str = "libero-agent thumbnails v2: seed 100, init row 0, level 1, settled start, frame 0";
/// The seed every thumbnail's world is set up with (the teleop page's default seed too).
const SEED: u64 = 100;
/// Longest task id accepted (`vlabench_tube_precision/12` and the like).
const MAX_ID_LEN: usize = 80;
/// How long a background render waits for open episodes to end before it looks again.
const EPISODE_POLL: Duration = Duration::from_secs(2);
/// How long a background render waits for the pages' renders before it looks again: short, so the pass goes on
/// soon after a page has what it asked for.
const ON_DEMAND_POLL: Duration = Duration::from_millis(250);

/// Which camera's view.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Camera {
    /// `agentview`.
    Head,
    /// `robot0_eye_in_hand`.
    Wrist,
}

impl Camera {
    /// `head` / `wrist` (the `?camera=` value and the file suffix).
    pub fn parse(s: Option<&str>) -> Option<Self> {
        match s.unwrap_or("head") {
            "head" => Some(Self::Head),
            "wrist" => Some(Self::Wrist),
            _ => None,
        }
    }

    fn suffix(self) -> &'static str {
        match self {
            Self::Head => "head",
            Self::Wrist => "wrist",
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum ThumbnailError {
    /// Not a release task or runnable pool entry (the page answers 404).
    #[error("{0}")]
    NoSuchTask(String),
    #[error("assets are missing; run `python3 scripts/setup.py`")]
    NoAssets,
    #[error("cannot render the thumbnail of {task}: {cause}")]
    Render { task: String, cause: String },
    #[error("thumbnail cache {path}: {cause}")]
    Io { path: String, cause: std::io::Error },
}

impl ThumbnailError {
    fn io(path: &Path) -> impl FnOnce(std::io::Error) -> Self + '_ {
        move |cause| Self::Io { path: path.display().to_string(), cause }
    }
}

/// What the cache did since the server started (`GET /api/thumbnails`).
#[derive(Debug, Default, Serialize)]
pub struct ThumbnailStats {
    /// Scenes rendered (both cameras each).
    pub rendered: u64,
    /// Scenes asked for (ahead or by a page) whose files were on disk already.
    pub reused: u64,
    pub failed: u64,
    /// Tasks the background pass has still to look at.
    pub ahead_pending: u64,
    /// Whether the background pass has run through its list.
    pub ahead_done: bool,
    /// Page requests waiting for their turn to render now.
    pub on_demand_waiting: u64,
    /// Page renders running now (0 or 1).
    pub on_demand_rendering: u64,
    /// Page requests that went away while they waited, whose render therefore never started.
    pub on_demand_cancelled: u64,
}

/// The thumbnail cache of one data directory.
pub struct Thumbnails {
    episodes: Arc<Episodes>,
    dir: PathBuf,
    /// One lock per scene hash: a page asking for a scene the background pass is rendering waits for that
    /// render instead of starting a second one.
    scenes: Mutex<HashMap<String, Arc<Mutex<()>>>>,
    /// Renders asked for by pages run one at a time, so a page of thumbnails does not build thirty worlds at once;
    /// the semaphore is fair, so they run in the order asked, and a request dropped while it waits leaves the queue.
    on_demand: Arc<tokio::sync::Semaphore>,
    on_demand_waiting: AtomicU64,
    on_demand_rendering: AtomicU64,
    on_demand_cancelled: AtomicU64,
    rendered: AtomicU64,
    reused: AtomicU64,
    failed: AtomicU64,
    ahead_pending: AtomicU64,
    ahead_running: AtomicU64,
}

impl Thumbnails {
    pub fn new(episodes: Arc<Episodes>) -> Self {
        let dir = episodes.lifecycle().data_dir().join("thumbnails");
        Self {
            episodes,
            dir,
            scenes: Mutex::new(HashMap::new()),
            on_demand: Arc::new(tokio::sync::Semaphore::new(1)),
            on_demand_waiting: AtomicU64::new(0),
            on_demand_rendering: AtomicU64::new(0),
            on_demand_cancelled: AtomicU64::new(0),
            rendered: AtomicU64::new(0),
            reused: AtomicU64::new(0),
            failed: AtomicU64::new(0),
            ahead_pending: AtomicU64::new(0),
            ahead_running: AtomicU64::new(0),
        }
    }

    pub fn stats(&self) -> ThumbnailStats {
        ThumbnailStats {
            rendered: self.rendered.load(Ordering::Relaxed),
            reused: self.reused.load(Ordering::Relaxed),
            failed: self.failed.load(Ordering::Relaxed),
            ahead_pending: self.ahead_pending.load(Ordering::Relaxed),
            ahead_done: self.ahead_running.load(Ordering::Relaxed) == 0,
            on_demand_waiting: self.on_demand_waiting.load(Ordering::Relaxed),
            on_demand_rendering: self.on_demand_rendering.load(Ordering::Relaxed),
            on_demand_cancelled: self.on_demand_cancelled.load(Ordering::Relaxed),
        }
    }

    /// The cached PNG of `camera` for task `id`, rendered now (seconds) if it is not on disk yet: after the renders
    /// other pages asked for first. Dropping the future while it waits for its turn cancels the render; once started,
    /// a render completes (its files serve the next page that asks).
    pub async fn get(self: &Arc<Self>, id: String, camera: Camera) -> Result<PathBuf, ThumbnailError> {
        let me = self.clone();
        let (id, hash, task, path) = blocking(move || {
            let (hash, task) = me.scene(&id)?;
            let path = me.file(&hash, camera);
            Ok((id, hash, task, path))
        })
        .await?;
        if path.is_file() {
            return Ok(path);
        }
        // The same scene being rendered now (for another page, or by the pass): wait for that render, out of the
        // queue, instead of waiting for a turn to find the files there.
        if self.wait_for_render_in_flight(&hash).await && path.is_file() {
            self.reused.fetch_add(1, Ordering::Relaxed);
            return Ok(path);
        }
        let permit = {
            let waiting = Waiting::new(self);
            let permit = self.on_demand.clone().acquire_owned().await;
            waiting.served();
            permit.map_err(|e| ThumbnailError::Render { task: id.clone(), cause: e.to_string() })?
        };
        let me = self.clone();
        blocking(move || {
            let _one_page_render = permit;
            me.on_demand_rendering.fetch_add(1, Ordering::Relaxed);
            let done = me.ensure(&hash, &id, task);
            me.on_demand_rendering.fetch_sub(1, Ordering::Relaxed);
            done.map(|()| path)
        })
        .await
    }

    /// Waits for a render of scene `hash` in progress, if one is; whether there was one.
    async fn wait_for_render_in_flight(&self, hash: &str) -> bool {
        let lock = self.scenes.lock().unwrap_or_else(|p| p.into_inner()).get(hash).cloned();
        let Some(lock) = lock else { return false };
        if lock.try_lock().is_ok() {
            return false;
        }
        let waited = tokio::task::spawn_blocking(move || drop(lock.lock().unwrap_or_else(|p| p.into_inner())));
        waited.await.is_ok()
    }

    /// Whether a page is waiting for a render or has one running: the background pass then holds back.
    fn pages_waiting(&self) -> bool {
        self.on_demand_waiting.load(Ordering::Relaxed) + self.on_demand_rendering.load(Ordering::Relaxed) > 0
    }

    /// The scene hash of `id` and its resolved task.
    fn scene(&self, id: &str) -> Result<(String, libero_episode::task::TaskSource), ThumbnailError> {
        let id = checked_id(id)?;
        let paths = self.episodes.lifecycle().asset_paths().ok_or(ThumbnailError::NoAssets)?;
        let task = resolve_task(id, paths).map_err(|e| ThumbnailError::NoSuchTask(e.to_string()))?;
        Ok((scene_hash(&task, paths)?, task))
    }

    fn file(&self, hash: &str, camera: Camera) -> PathBuf {
        self.dir.join(format!("{hash}-{}.png", camera.suffix()))
    }

    /// Renders both cameras of scene `hash` unless both files are there; counts what it did.
    fn ensure(&self, hash: &str, id: &str, task: libero_episode::task::TaskSource) -> Result<(), ThumbnailError> {
        let lock = {
            let mut scenes = self.scenes.lock().unwrap_or_else(|p| p.into_inner());
            scenes.entry(hash.to_owned()).or_default().clone()
        };
        let _this_scene = lock.lock().unwrap_or_else(|p| p.into_inner());
        let (head, wrist) = (self.file(hash, Camera::Head), self.file(hash, Camera::Wrist));
        if head.is_file() && wrist.is_file() {
            self.reused.fetch_add(1, Ordering::Relaxed);
            return Ok(());
        }
        // Released after every render tried, not after a cached scene: a pass over cached thumbnails (each
        // restart) would otherwise empty MuJoCo's asset cache under the episodes 240 times for nothing.
        let rendered = self.render(id, task, &head, &wrist);
        release_scene();
        match rendered {
            Ok(()) => {
                self.rendered.fetch_add(1, Ordering::Relaxed);
                Ok(())
            }
            Err(e) => {
                self.failed.fetch_add(1, Ordering::Relaxed);
                Err(e)
            }
        }
    }

    /// Renders scene `task` on a GPU device of its own, closed with the world: the episodes' shared device never
    /// holds a thumbnail's pipelines, uploads or per-frame buffers (about 200 MB on a software renderer, kept for
    /// the server's lifetime once opened), and opening one costs tens of milliseconds against seconds of scene
    /// set-up. On the pass's thread the device's own threads inherit its lowest priority.
    fn render(&self, id: &str, task: libero_episode::task::TaskSource, head: &Path, wrist: &Path) -> Result<(), ThumbnailError> {
        let failed = |cause: String| ThumbnailError::Render { task: id.to_owned(), cause };
        let paths = self.episodes.lifecycle().asset_paths().ok_or(ThumbnailError::NoAssets)?.clone();
        let spec = WorldSpec { task, level: Level::L1, seed: SEED, init_index: 0, paths };
        let renderer = libero_render::Renderer::new().map_err(|e| failed(format!("cannot open a GPU for rendering: {e}")))?;
        let mut world = LiberoWorld::new(&spec, renderer).map_err(|e| failed(e.to_string()))?;
        libero_episode::World::start(&mut world).map_err(|e| failed(e.to_string()))?;
        let frame = libero_episode::World::frame(&mut world, 0).map_err(|e| failed(e.to_string()))?;
        fs::create_dir_all(&self.dir).map_err(ThumbnailError::io(&self.dir))?;
        for (image, path) in [(&frame.wrist.image, wrist), (&frame.head.image, head)] {
            // written aside and renamed: a reader never sees half a PNG, and the head file (the one the Tasks
            // page shows) appears last, once the scene is complete
            let partial = path.with_extension("png.partial");
            libero_episode::observation::write_png(&partial, image.width, image.height, 3, &image.rgb)
                .map_err(ThumbnailError::io(&partial))?;
            fs::rename(&partial, path).map_err(ThumbnailError::io(path))?;
        }
        Ok(())
    }

    /// Renders every task of `ids` that is not cached yet, `concurrency` at a time, in background threads at the
    /// lowest CPU priority that wait while any episode is open. Returns at once.
    pub fn render_ahead(self: &Arc<Self>, ids: Vec<String>, concurrency: usize) {
        if ids.is_empty() {
            return;
        }
        self.ahead_pending.store(ids.len() as u64, Ordering::Relaxed);
        let queue = Arc::new(Mutex::new(ids.into_iter()));
        let workers = concurrency.max(1);
        self.ahead_running.store(workers as u64, Ordering::Relaxed);
        for n in 0..workers {
            let (me, queue) = (self.clone(), queue.clone());
            let spawned = std::thread::Builder::new().name(format!("thumbnails-{n}")).spawn(move || me.ahead_worker(&queue));
            if let Err(e) = spawned {
                tracing::warn!("cannot start a thumbnail thread: {e}");
                self.ahead_running.fetch_sub(1, Ordering::Relaxed);
            }
        }
    }

    fn ahead_worker(&self, queue: &Mutex<std::vec::IntoIter<String>>) {
        lowest_priority();
        // Each scene opens a device of its own: a machine that has none says so once, not once per scene.
        if let Err(e) = libero_render::Renderer::new() {
            tracing::warn!("thumbnails are not rendered ahead: cannot open a GPU for rendering: {e}");
            self.ahead_pending.store(0, Ordering::Relaxed);
            self.ahead_running.fetch_sub(1, Ordering::Relaxed);
            return;
        }
        loop {
            let next = queue.lock().unwrap_or_else(|p| p.into_inner()).next();
            let Some(id) = next else { break };
            loop {
                if self.episodes.lifecycle().count() > 0 {
                    std::thread::sleep(EPISODE_POLL);
                } else if self.pages_waiting() {
                    std::thread::sleep(ON_DEMAND_POLL);
                } else {
                    break;
                }
            }
            let done = self.scene(&id).and_then(|(hash, task)| self.ensure(&hash, &id, task));
            if let Err(e) = done {
                tracing::warn!("thumbnail of {id}: {e}");
            }
            self.ahead_pending.fetch_sub(1, Ordering::Relaxed);
        }
        self.ahead_running.fetch_sub(1, Ordering::Relaxed);
    }

}

/// After a render: hands back what its scene held, as an ended episode does. The world and its device went with
/// [`Thumbnails::render`] (model, upload, simulation, pipelines), but MuJoCo's compiler keeps the meshes and
/// textures it decoded in its process-wide asset cache (up to 500 MB, filled by scenes no episode may ever open), a
/// base model another scene's read from stays until [`libero_sim::shared_model::release_unused`], and the freed
/// pages in the allocator's arenas until trimmed. Episodes compile from the asset files again afterwards (their
/// scenes' compiled models are shared while they live, whatever this cache holds).
fn release_scene() {
    libero_sim::mujoco_rs::prelude::MjCache::current().clear();
    libero_sim::shared_model::release_unused();
    libero_episode::memory::return_freed_memory();
}

/// A page request in the on-demand queue: counted while it waits, and counted as cancelled if it is dropped there.
struct Waiting<'a> {
    thumbnails: &'a Thumbnails,
    served: bool,
}

impl<'a> Waiting<'a> {
    fn new(thumbnails: &'a Thumbnails) -> Self {
        thumbnails.on_demand_waiting.fetch_add(1, Ordering::Relaxed);
        Self { thumbnails, served: false }
    }

    fn served(mut self) {
        self.served = true;
    }
}

impl Drop for Waiting<'_> {
    fn drop(&mut self) {
        self.thumbnails.on_demand_waiting.fetch_sub(1, Ordering::Relaxed);
        if !self.served {
            self.thumbnails.on_demand_cancelled.fetch_add(1, Ordering::Relaxed);
        }
    }
}

/// `f` on tokio's blocking pool (file reads, hashing, world set-up and rendering).
async fn blocking<T: Send + 'static>(
    f: impl FnOnce() -> Result<T, ThumbnailError> + Send + 'static,
) -> Result<T, ThumbnailError> {
    tokio::task::spawn_blocking(f)
        .await
        .unwrap_or_else(|e| Err(ThumbnailError::Render { task: String::new(), cause: format!("render thread: {e}") }))
}

/// The tasks `--thumbnails-ahead` names: `off`, or a task selection (`libero_tasks::selector`: `release,all` for
/// every implemented release task, then every runnable pool entry; suites, groups, task ids). A task named on its
/// own that does not run is refused; the members of a set that do not run are left out.
pub fn ahead_ids(selection: &str) -> Result<Vec<String>, String> {
    let selection = selection.trim();
    if selection == "off" || selection.is_empty() {
        return Ok(Vec::new());
    }
    let selection: libero_tasks::Selection = selection.parse().map_err(|e: libero_tasks::SelectionError| e.to_string())?;
    let catalog = libero_tasks::Catalog::discover().map_err(|e| e.to_string())?;
    let pool = libero_tasks::Pool::discover().map_err(|e| e.to_string())?;
    let picks = selection.runnable(catalog.tasks(), &pool).map_err(|e| e.to_string())?;
    let ids = picks.iter().map(|p| p.member.id()).collect();
    Ok(ids)
}

/// A task id as the routes give it: `T14` or `suite/task_id`, short and of plain characters.
fn checked_id(id: &str) -> Result<&str, ThumbnailError> {
    let plain = |s: &str| !s.is_empty() && s.chars().all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-');
    let ok = id.len() <= MAX_ID_LEN
        && match id.split_once('/') {
            Some((suite, task)) => plain(suite) && plain(task),
            None => plain(id),
        };
    if ok { Ok(id) } else { Err(ThumbnailError::NoSuchTask(format!("bad task id {id:?}"))) }
}

/// SHA-256 over what decides the rendered scene (first 20 hex digits): [`SCHEME`], the start settings the task
/// resolves to (its BDDL and init-state files by content, not by path; never the instruction or task name), and
/// the asset roots.
fn scene_hash(task: &libero_episode::task::TaskSource, paths: &libero_sim::AssetPaths) -> Result<String, ThumbnailError> {
    let mut h = Sha256::new();
    h.update(SCHEME.as_bytes());
    for file in std::iter::once(&task.bddl).chain(task.init_states.as_ref()) {
        let bytes = fs::read(file).map_err(ThumbnailError::io(file))?;
        h.update((bytes.len() as u64).to_le_bytes());
        h.update(&bytes);
    }
    // the start settings (placement seed, init row, settle steps, poses, layout); the checker is part of the
    // suite record, so a changed checker also renews the files, which is harmless
    let start = serde_json::json!({"suite": task.suite, "layout": task.layout, "init": task.init_states.is_some()});
    h.update(start.to_string().as_bytes());
    for root in [&paths.robosuite_assets, &paths.libero_assets, &paths.libero_root, &paths.project_assets] {
        h.update(root.to_string_lossy().as_bytes());
        h.update([0]);
    }
    let digest = h.finalize();
    Ok(digest.iter().take(10).map(|b| format!("{b:02x}")).collect())
}

/// This thread at nice 19 (Linux: the nice value is per thread).
fn lowest_priority() {
    // SAFETY: setpriority on the calling thread (`who` 0) with a constant; no memory is passed.
    let rc = unsafe { libc::setpriority(libc::PRIO_PROCESS, 0, 19) };
    if rc != 0 {
        tracing::debug!("cannot lower the thumbnail thread's priority: {}", std::io::Error::last_os_error());
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn task_ids_with_path_tricks_or_odd_characters_are_refused() {
        for bad in ["", "../etc", "T14/../x", "a/b/c", "T 14", "libero_90/", "/35", &"x".repeat(81)] {
            assert!(checked_id(bad).is_err(), "{bad:?} must be refused");
        }
        for good in ["T14", "libero_90/35", "vlabench_tube_precision/1"] {
            assert!(checked_id(good).is_ok(), "{good:?}");
        }
    }

    #[test]
    fn camera_names_are_head_by_default_and_nothing_else_but_wrist() {
        assert_eq!(Camera::parse(None), Some(Camera::Head));
        assert_eq!(Camera::parse(Some("wrist")), Some(Camera::Wrist));
        assert_eq!(Camera::parse(Some("depth")), None);
    }

    /// The background pass lets go of every scene it rendered: once it is done, the episodes' GPU device was never
    /// opened (each scene rendered on a device of its own, closed with it), and the process's shared models and
    /// MuJoCo's compiler cache are back where they were before it. A pass that kept a scene (its world, its model,
    /// a base model another read from, its device, its decoded assets) leaves it counted here.
    #[test]
    fn the_background_pass_leaves_no_model_or_upload_of_its_scenes_behind() {
        let _alone = crate::PROCESS_WIDE_TEST_LOCK.lock().unwrap_or_else(|p| p.into_inner());
        let dir = tempfile::tempdir().unwrap();
        let episodes = Arc::new(Episodes::new(dir.path().join("data"), "http://127.0.0.1:9".into()).unwrap());
        let cache = libero_sim::mujoco_rs::prelude::MjCache::current();
        let (models, cached) = (libero_sim::shared_model::alive(), cache.size());
        let thumbnails = Arc::new(Thumbnails::new(episodes.clone()));
        thumbnails.render_ahead(vec!["T14".into(), "libero_90/35".into()], 1);
        let started = std::time::Instant::now();
        while !thumbnails.stats().ahead_done {
            assert!(started.elapsed() < Duration::from_secs(900), "the pass did not end: {:?}", thumbnails.stats());
            std::thread::sleep(Duration::from_millis(200));
        }
        let stats = thumbnails.stats();
        assert_eq!((stats.rendered, stats.failed), (2, 0), "{stats:?}");
        assert!(!episodes.lifecycle().renderer_is_open(), "the pass opened the episodes' shared GPU device and left it open");
        assert_eq!(libero_sim::shared_model::alive(), models, "models of rendered scenes are still alive");
        assert_eq!(libero_sim::shared_model::compiled_scenes_alive(), 0);
        // (the pass empties the whole cache after each scene, so it may end below where it began)
        assert!(cache.size() <= cached, "MuJoCo's compiler still caches the rendered scenes' assets: {} > {cached} bytes", cache.size());
    }

    #[test]
    fn ahead_selection_takes_suites_and_ids_once_each_and_refuses_unknown_words() {
        let ids = ahead_ids("T14, release,libero_90/35").unwrap();
        assert_eq!(ids.first().map(String::as_str), Some("T14"));
        assert_eq!(ids.iter().filter(|i| *i == "T14").count(), 1);
        assert!(ids.contains(&"libero_90/35".to_owned()));
        assert!(ahead_ids("off").unwrap().is_empty());
        assert!(ahead_ids("everything").is_err());
    }
}
