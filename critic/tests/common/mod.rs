//! Helpers the critic crate's test files share.

use std::path::PathBuf;

/// A fresh directory under the system's temp dir, unique to this process and moment, named
/// after `tool`.
pub fn tempdir(tool: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!(
        "{tool}-test-{}-{}",
        std::process::id(),
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .expect("clock")
            .as_nanos()
    ));
    std::fs::create_dir_all(&dir).expect("temp dir");
    dir
}
