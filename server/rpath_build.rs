//! Shared build script: every package that links libmujoco into a binary or test gets an rpath to
//! the cached library, because cargo does not propagate link args from dependencies' build scripts.
fn main() {
    println!("cargo::rerun-if-env-changed=MUJOCO_DYNAMIC_LINK_DIR");
    if let Ok(dir) = std::env::var("MUJOCO_DYNAMIC_LINK_DIR") {
        let dir = std::fs::canonicalize(&dir).unwrap_or_else(|_| dir.clone().into());
        println!("cargo::rustc-link-arg=-Wl,-rpath,{}", dir.display());
    }
    println!("cargo::rustc-link-arg=-Wl,-rpath,$ORIGIN:$ORIGIN/lib");
}
