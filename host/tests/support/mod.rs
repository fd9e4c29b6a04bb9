//! Shared by the integration tests: where the repository is, and the Rust
//! guest components, built once per test process from guest-components/rust.

#![allow(dead_code, clippy::panic)]

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

/// The repository root.
pub fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().map_or_else(|| PathBuf::from(".."), Path::to_path_buf)
}

/// The folder holding the built guest components (`NAME.wasm`), building
/// them first if this process has not yet done so.
pub fn guest_dir() -> PathBuf {
    static BUILT: OnceLock<Result<PathBuf, String>> = OnceLock::new();
    let built = BUILT.get_or_init(|| {
        let dir = repo_root().join("guest-components/rust");
        let cargo = std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into());
        let output = Command::new(cargo)
            .args(["build", "--release", "--quiet"])
            .current_dir(&dir)
            .env_remove("CARGO_TARGET_DIR")
            .output()
            .map_err(|e| format!("cannot run cargo to build the guests: {e}"))?;
        if !output.status.success() {
            return Err(format!("building the guests failed:\n{}", String::from_utf8_lossy(&output.stderr)));
        }
        Ok(dir.join("target/wasm32-wasip2/release"))
    });
    match built {
        Ok(dir) => dir.clone(),
        Err(why) => panic!("{why}"),
    }
}

/// The built guest `name` (crate name with `-` as `_`).
pub fn guest(name: &str) -> PathBuf {
    guest_dir().join(format!("{}.wasm", name.replace('-', "_")))
}

/// A compile cache shared by the tests of this checkout.
pub fn cache_dir() -> PathBuf {
    repo_root().join("target/test-component-cache")
}
