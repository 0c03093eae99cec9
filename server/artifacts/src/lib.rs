//! Run directories in object storage, so that a rollout run on one machine can be reviewed from any other.
//!
//! `--artifacts URL` names the store: a directory (`/srv/libero/artifacts` or `file:///srv/…`, e.g. a shared
//! NFS mount) or an S3-compatible bucket (`s3://bucket[/prefix]`; endpoint, region and credentials from the
//! standard `AWS_*` environment: `AWS_ENDPOINT_URL`, `AWS_REGION`, `AWS_ACCESS_KEY_ID`, `AWS_SECRET_ACCESS_KEY`,
//! `AWS_ALLOW_HTTP=true` for a plain-HTTP endpoint), never on a command line.
//!
//! Layout: `runs/<episode id>/…` holds an episode's run directory as the server wrote it (actions, result, stage
//! events, state record, observations, video); `batches/<batch>/rollouts/<rollout id>/…` the runner's files of a
//! rollout (harness manifest, logs, usage). Only regular files the caller selects are copied: links are never
//! followed, and what an agent created (its session home) is never selected.
use std::path::{Component, Path, PathBuf};
use std::sync::Arc;

use futures::TryStreamExt;
use object_store::aws::AmazonS3Builder;
use object_store::local::LocalFileSystem;
use object_store::path::Path as ObjectPath;
use object_store::prefix::PrefixStore;
use object_store::{ObjectStore, ObjectStoreExt, PutPayload, WriteMultipart};

/// The object written last by [`Artifacts::put_run`]: a prefix without it is an upload still going on or cut
/// short, and [`Artifacts::fetch_run`] does not take it.
pub const COMPLETE_MARKER: &str = "artifacts_complete.json";

/// Files above this size are uploaded in parts (S3's single PUT is capped, and a part stays in memory).
const MULTIPART_ABOVE_BYTES: u64 = 16 << 20;
/// At most this many files under one prefix are fetched (a run directory holds a few dozen).
const MAX_FILES: usize = 10_000;

#[derive(Debug, thiserror::Error)]
pub enum ArtifactError {
    #[error("artifact store URL {0:?}: expected a directory path, file:///PATH or s3://BUCKET[/PREFIX]")]
    BadUrl(String),
    #[error("{0:?} cannot name an artifact (letters, digits, '-', '_' and '.' only, not starting with '.', at most 128)")]
    BadName(String),
    #[error("artifact store {url}: {source}")]
    Store { url: String, source: object_store::Error },
    #[error("{}: {source}", path.display())]
    Io { path: PathBuf, source: std::io::Error },
    #[error("artifact {0:?} does not map to a file under the destination")]
    BadKey(String),
    #[error("more than {MAX_FILES} artifacts under {0}")]
    TooMany(String),
}

pub type Result<T> = std::result::Result<T, ArtifactError>;

/// What an upload copied.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Copied {
    pub files: u64,
    pub bytes: u64,
}

/// An artifact store.
#[derive(Clone)]
pub struct Artifacts {
    store: Arc<dyn ObjectStore>,
    url: String,
}

impl std::fmt::Debug for Artifacts {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Artifacts").field("url", &self.url).finish()
    }
}

/// Checks one path segment that comes from a caller (episode id, batch name, rollout id).
pub fn check_name(name: &str) -> Result<&str> {
    let ok = !name.is_empty()
        && name.len() <= 128
        && !name.starts_with('.')
        && name.bytes().all(|b| b.is_ascii_alphanumeric() || b"-_.".contains(&b));
    if ok { Ok(name) } else { Err(ArtifactError::BadName(name.to_owned())) }
}

/// Where an episode's run directory goes.
pub fn run_prefix(episode_id: &str) -> Result<String> {
    Ok(format!("runs/{}", check_name(episode_id)?))
}

/// Where the runner's files of one rollout go.
pub fn rollout_prefix(batch: &str, rollout_id: &str) -> Result<String> {
    Ok(format!("batches/{}/rollouts/{}", check_name(batch)?, check_name(rollout_id)?))
}

impl Artifacts {
    /// Opens the store `url` names; a directory is created when missing.
    pub fn open(url: &str) -> Result<Self> {
        let bad = || ArtifactError::BadUrl(url.to_owned());
        let store: Arc<dyn ObjectStore> = if let Some(rest) = url.strip_prefix("s3://") {
            let (bucket, prefix) = rest.split_once('/').unwrap_or((rest, ""));
            if bucket.is_empty() {
                return Err(bad());
            }
            let s3 = AmazonS3Builder::from_env()
                .with_bucket_name(bucket)
                .build()
                .map_err(|source| ArtifactError::Store { url: url.to_owned(), source })?;
            let prefix = prefix.trim_matches('/');
            if prefix.is_empty() { Arc::new(s3) } else { Arc::new(PrefixStore::new(s3, prefix)) }
        } else {
            let dir = PathBuf::from(url.strip_prefix("file://").unwrap_or(url));
            if !dir.is_absolute() || url.contains("://") && !url.starts_with("file://") {
                return Err(bad());
            }
            std::fs::create_dir_all(&dir).map_err(|source| ArtifactError::Io { path: dir.clone(), source })?;
            let local = LocalFileSystem::new_with_prefix(&dir).map_err(|source| ArtifactError::Store { url: url.to_owned(), source })?;
            Arc::new(local)
        };
        Ok(Self { store, url: url.to_owned() })
    }

    pub fn url(&self) -> &str {
        &self.url
    }

    fn err(&self, source: object_store::Error) -> ArtifactError {
        ArtifactError::Store { url: self.url.clone(), source }
    }

    /// Copies the regular files under `dir` that `select` accepts (by path relative to `dir`) to `prefix`,
    /// keeping their relative paths. Links and special files are skipped, never followed; a directory `select`
    /// refuses is not entered.
    pub async fn put_dir(&self, dir: &Path, prefix: &str, select: impl Fn(&Path) -> bool) -> Result<Copied> {
        let mut copied = Copied::default();
        let mut pending = vec![PathBuf::new()];
        while let Some(rel) = pending.pop() {
            let here = dir.join(&rel);
            let io = |source| ArtifactError::Io { path: here.clone(), source };
            let mut entries = tokio::fs::read_dir(&here).await.map_err(io)?;
            while let Some(entry) = entries.next_entry().await.map_err(io)? {
                let rel = rel.join(entry.file_name());
                if !select(&rel) {
                    continue;
                }
                let kind = entry.file_type().await.map_err(io)?;
                if kind.is_dir() {
                    pending.push(rel);
                } else if kind.is_file() {
                    let Some(key) = rel.to_str() else { continue };
                    copied.bytes += self.put_file(&entry.path(), &format!("{prefix}/{key}")).await?;
                    copied.files += 1;
                }
            }
        }
        Ok(copied)
    }

    async fn put_file(&self, path: &Path, key: &str) -> Result<u64> {
        let io = |source| ArtifactError::Io { path: path.to_path_buf(), source };
        let location = ObjectPath::parse(key).map_err(|e| self.err(e.into()))?;
        let size = tokio::fs::symlink_metadata(path).await.map_err(io)?.len();
        if size <= MULTIPART_ABOVE_BYTES {
            let bytes = tokio::fs::read(path).await.map_err(io)?;
            self.store.put(&location, PutPayload::from(bytes)).await.map_err(|e| self.err(e))?;
            return Ok(size);
        }
        use tokio::io::AsyncReadExt;
        let upload = self.store.put_multipart(&location).await.map_err(|e| self.err(e))?;
        let mut writer = WriteMultipart::new(upload);
        let mut file = tokio::fs::File::open(path).await.map_err(io)?;
        let mut buf = vec![0u8; 1 << 20];
        loop {
            let n = file.read(&mut buf).await.map_err(io)?;
            if n == 0 {
                break;
            }
            writer.write(&buf[..n]);
        }
        writer.finish().await.map_err(|e| self.err(e))?;
        Ok(size)
    }

    /// [`Artifacts::put_dir`], then the [`COMPLETE_MARKER`] (file count and bytes) once everything else is there.
    pub async fn put_run(&self, dir: &Path, prefix: &str, select: impl Fn(&Path) -> bool) -> Result<Copied> {
        let copied = self.put_dir(dir, prefix, |rel| rel != Path::new(COMPLETE_MARKER) && select(rel)).await?;
        let marker = format!("{{\"files\": {}, \"bytes\": {}}}", copied.files, copied.bytes);
        let location = ObjectPath::parse(format!("{prefix}/{COMPLETE_MARKER}")).map_err(|e| self.err(e.into()))?;
        self.store.put(&location, PutPayload::from(marker.into_bytes())).await.map_err(|e| self.err(e))?;
        Ok(copied)
    }

    /// [`Artifacts::fetch_dir`] of a prefix [`Artifacts::put_run`] completed; `None` when it is absent or its upload
    /// did not finish.
    pub async fn fetch_run(&self, prefix: &str, into: &Path) -> Result<Option<u64>> {
        let marker = ObjectPath::parse(format!("{prefix}/{COMPLETE_MARKER}")).map_err(|e| self.err(e.into()))?;
        match self.store.head(&marker).await {
            Ok(_) => Ok(Some(self.fetch_dir(prefix, into).await?)),
            Err(object_store::Error::NotFound { .. }) => Ok(None),
            Err(e) => Err(self.err(e)),
        }
    }

    /// The keys (relative to `prefix`) and sizes stored under `prefix`, sorted.
    pub async fn list(&self, prefix: &str) -> Result<Vec<(String, u64)>> {
        let root = ObjectPath::parse(prefix).map_err(|e| self.err(e.into()))?;
        let mut out = Vec::new();
        let mut stream = self.store.list(Some(&root));
        while let Some(meta) = stream.try_next().await.map_err(|e| self.err(e))? {
            if out.len() >= MAX_FILES {
                return Err(ArtifactError::TooMany(prefix.to_owned()));
            }
            let key = meta.location.as_ref().strip_prefix(root.as_ref()).unwrap_or(meta.location.as_ref()).trim_start_matches('/').to_owned();
            out.push((key, meta.size));
        }
        out.sort();
        Ok(out)
    }

    /// Fetches everything under `prefix` into the directory `into` (created), keeping relative paths; returns
    /// how many files. A key that would land outside `into` is refused.
    pub async fn fetch_dir(&self, prefix: &str, into: &Path) -> Result<u64> {
        let keys = self.list(prefix).await?;
        for (key, _) in &keys {
            let rel = Path::new(key);
            if key.is_empty() || !rel.components().all(|c| matches!(c, Component::Normal(_))) {
                return Err(ArtifactError::BadKey(key.clone()));
            }
            let dest = into.join(rel);
            let io = |source| ArtifactError::Io { path: dest.clone(), source };
            if let Some(parent) = dest.parent() {
                tokio::fs::create_dir_all(parent).await.map_err(io)?;
            }
            let location = ObjectPath::parse(format!("{prefix}/{key}")).map_err(|e| self.err(e.into()))?;
            let mut stream = self.store.get(&location).await.map_err(|e| self.err(e))?.into_stream();
            use tokio::io::AsyncWriteExt;
            let mut file = tokio::fs::File::create(&dest).await.map_err(io)?;
            while let Some(chunk) = stream.try_next().await.map_err(|e| self.err(e))? {
                file.write_all(&chunk).await.map_err(io)?;
            }
            file.sync_all().await.map_err(io)?;
        }
        Ok(keys.len() as u64)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_that_could_leave_their_prefix_are_refused() {
        assert_eq!(run_prefix("ep_20261125_abc").unwrap(), "runs/ep_20261125_abc");
        for bad in ["", "..", ".hidden", "a/b", "a b", "x\0", &"a".repeat(129)] {
            assert!(run_prefix(bad).is_err(), "{bad:?}");
            assert!(rollout_prefix("b", bad).is_err(), "{bad:?}");
        }
        assert!(Artifacts::open("relative/dir").is_err());
        assert!(Artifacts::open("gs://bucket").is_err());
        assert!(Artifacts::open("s3://").is_err());
    }

    /// A directory tree goes up selectively (links skipped, a refused directory not entered) and comes back whole,
    /// through the filesystem backend.
    #[tokio::test]
    async fn a_directory_goes_up_without_links_or_refused_parts_and_comes_back() {
        let tmp = tempfile::tempdir().unwrap();
        let src = tmp.path().join("run");
        std::fs::create_dir_all(src.join("observations/step_1")).unwrap();
        std::fs::create_dir_all(src.join("home")).unwrap();
        std::fs::write(src.join("result.json"), b"{\"success\": true}").unwrap();
        std::fs::write(src.join("observations/step_1/rgb.png"), vec![7u8; 3000]).unwrap();
        std::fs::write(src.join("home/secret"), b"agent-made").unwrap();
        std::os::unix::fs::symlink("/etc/passwd", src.join("link")).unwrap();
        let store = Artifacts::open(&format!("file://{}", tmp.path().join("bucket").display())).unwrap();
        let copied = store.put_dir(&src, "runs/ep1", |rel| !rel.starts_with("home")).await.unwrap();
        assert_eq!(copied, Copied { files: 2, bytes: 3000 + 17 });
        let keys: Vec<String> = store.list("runs/ep1").await.unwrap().into_iter().map(|(k, _)| k).collect();
        assert_eq!(keys, ["observations/step_1/rgb.png", "result.json"]);
        let back = tmp.path().join("back");
        assert_eq!(store.fetch_dir("runs/ep1", &back).await.unwrap(), 2);
        assert_eq!(std::fs::read(back.join("result.json")).unwrap(), b"{\"success\": true}");
        assert_eq!(std::fs::read(back.join("observations/step_1/rgb.png")).unwrap().len(), 3000);
        assert!(store.list("runs/none").await.unwrap().is_empty());
        assert_eq!(store.fetch_run("runs/ep1", &tmp.path().join("cut")).await.unwrap(), None, "no marker, no fetch");
        store.put_run(&src, "runs/ep3", |rel| !rel.starts_with("home")).await.unwrap();
        assert_eq!(store.fetch_run("runs/ep3", &tmp.path().join("whole")).await.unwrap(), Some(3));
        assert!(tmp.path().join("whole").join(COMPLETE_MARKER).is_file());
    }

    /// A file above the single-PUT size goes up in parts and comes back byte for byte.
    #[tokio::test]
    async fn a_large_file_goes_up_in_parts() {
        let tmp = tempfile::tempdir().unwrap();
        let src = tmp.path().join("run");
        std::fs::create_dir_all(&src).unwrap();
        let big: Vec<u8> = (0..(MULTIPART_ABOVE_BYTES as usize + 12345)).map(|i| (i % 251) as u8).collect();
        std::fs::write(src.join("video.mp4"), &big).unwrap();
        let store = Artifacts::open(tmp.path().join("bucket").to_str().unwrap()).unwrap();
        store.put_dir(&src, "runs/ep2", |_| true).await.unwrap();
        store.fetch_dir("runs/ep2", &tmp.path().join("back")).await.unwrap();
        assert!(std::fs::read(tmp.path().join("back/video.mp4")).unwrap() == big);
    }
}
