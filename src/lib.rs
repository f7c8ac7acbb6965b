//! Test kit for the multi-process tests in `tests/`: runs `scripts/run_swarm.sh` as a user
//! would, under a watchdog, and checks that nothing of the run is left behind.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};

/// The repository root.
pub fn repo_root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// Directory of the built binaries (`target/debug` beside the test executable).
pub fn bin_dir() -> Result<PathBuf> {
    let exe = std::env::current_exe()?;
    // target/<profile>/deps/<test> -> target/<profile>
    let dir = exe
        .parent()
        .and_then(Path::parent)
        .context("cannot locate the target directory")?
        .to_path_buf();
    for name in ["formation-sim", "formation-agent", "formation-critic"] {
        if !dir.join(name).is_file() {
            bail!(
                "{} is missing: build the binaries first (scripts/test.sh does: cargo build --bins)",
                dir.join(name).display()
            );
        }
    }
    Ok(dir)
}

/// A fresh, empty directory for one test's run.
pub fn scratch_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("formation-test-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

/// What a finished launcher run printed and left.
#[derive(Debug)]
pub struct RunOutcome {
    /// Exit code of the launcher (None when killed by the watchdog).
    pub status: Option<i32>,
    /// Everything it printed.
    pub output: String,
    /// The run id it announced.
    pub run_id: Option<String>,
    /// The run directory.
    pub run_dir: PathBuf,
}

impl RunOutcome {
    /// `summary.json` of the run.
    pub fn summary(&self) -> Result<serde_json::Value> {
        let path = self.run_dir.join("summary.json");
        let text = std::fs::read_to_string(&path).with_context(|| format!("no {}", path.display()))?;
        Ok(serde_json::from_str(&text)?)
    }
}

/// Runs `scripts/run_swarm.sh` with `args` (the run directory is added), killing the whole
/// process group if it takes longer than `watchdog`.
pub fn run_swarm(args: &[&str], run_dir: &Path, watchdog: Duration) -> Result<RunOutcome> {
    run_swarm_with(args, run_dir, watchdog, |_| {})
}

/// As [`run_swarm`], calling `during(pid)` once with the launcher's pid right after it starts.
pub fn run_swarm_with(
    args: &[&str],
    run_dir: &Path,
    watchdog: Duration,
    during: impl FnOnce(u32),
) -> Result<RunOutcome> {
    use std::os::unix::process::CommandExt;
    let log = run_dir.with_extension("log");
    std::fs::create_dir_all(run_dir.parent().unwrap_or(Path::new("/tmp")))?;
    let log_file = std::fs::File::create(&log)?;
    let mut child = Command::new(repo_root().join("scripts/run_swarm.sh"))
        .args(args)
        .arg("--run-dir")
        .arg(run_dir)
        .env("FORMATION_BIN_DIR", bin_dir()?)
        .stdin(Stdio::null())
        .stdout(log_file.try_clone()?)
        .stderr(log_file)
        .process_group(0)
        .spawn()
        .context("cannot start scripts/run_swarm.sh")?;
    during(child.id());
    let started = Instant::now();
    let status = loop {
        if let Some(status) = child.try_wait()? {
            break status.code();
        }
        if started.elapsed() > watchdog {
            // SAFETY: kill(2) on the process group we created.
            unsafe { libc::kill(-(child.id() as i32), libc::SIGKILL) };
            let _ = child.wait();
            break None;
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let output = std::fs::read_to_string(&log).unwrap_or_default();
    let run_id = output
        .lines()
        .find_map(|l| l.strip_prefix("run ").and_then(|rest| rest.split(':').next()))
        .map(str::to_string);
    if let (None, Some(id)) = (status, &run_id) {
        // The watchdog killed the launcher before its own clean-up: do it here so a failed
        // test leaves nothing behind (the test still fails on the missing status).
        if let Ok(identity) = formation_ipc::services::RunIdentity::new(id) {
            identity.remove_leftovers();
        }
    }
    Ok(RunOutcome {
        status,
        output,
        run_id,
        run_dir: run_dir.to_path_buf(),
    })
}

/// Waits (up to a minute) until the launcher's `log` has a line `find` extracts a value from.
pub fn announced<T>(log: &Path, what: &str, find: impl Fn(&str) -> Option<T>) -> T {
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let text = std::fs::read_to_string(log).unwrap_or_default();
        if let Some(value) = text.lines().find_map(&find) {
            return value;
        }
        assert!(Instant::now() < deadline, "no {what} announced:\n{text}");
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// Waits until the launcher has announced its run id in `log`, then returns it.
pub fn run_id_of(log: &Path) -> String {
    announced(log, "run id", |line| {
        line.strip_prefix("run ")
            .and_then(|rest| rest.split(':').next())
            .map(str::to_string)
    })
}

/// Pid of the process of run `run_id` whose command line contains `needle`.
pub fn pid_of(run_id: &str, needle: &str) -> Option<u32> {
    processes_of_run(run_id).into_iter().find(|pid| {
        std::fs::read(format!("/proc/{pid}/cmdline"))
            .map(|c| String::from_utf8_lossy(&c).replace('\0', " ").contains(needle))
            .unwrap_or(false)
    })
}

/// Files of run `run_id` still in `/dev/shm`.
pub fn shm_leftovers(run_id: &str) -> Vec<String> {
    let prefix = format!("fc_{run_id}_");
    std::fs::read_dir("/dev/shm")
        .map(|entries| {
            entries
                .flatten()
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .filter(|name| name.starts_with(&prefix))
                .collect()
        })
        .unwrap_or_default()
}

/// Processes whose command line mentions `run_id` (or any other text of it, such as the run
/// directory): children that outlived their run, or the processes of a run in progress.
pub fn processes_of_run(run_id: &str) -> Vec<u32> {
    let Ok(entries) = std::fs::read_dir("/proc") else {
        return Vec::new();
    };
    entries
        .flatten()
        .filter_map(|entry| {
            let pid: u32 = entry.file_name().to_str()?.parse().ok()?;
            let cmdline = std::fs::read(entry.path().join("cmdline")).ok()?;
            let text = String::from_utf8_lossy(&cmdline).replace('\0', " ");
            text.contains(run_id).then_some(pid)
        })
        .collect()
}

/// Asserts that a finished run left no process, no shared memory and no iceoryx2 root path.
pub fn assert_clean(outcome: &RunOutcome) {
    let run_id = outcome.run_id.as_deref().expect("the launcher announces its run id");
    assert!(
        shm_leftovers(run_id).is_empty(),
        "shared memory left: {:?}",
        shm_leftovers(run_id)
    );
    assert!(
        processes_of_run(run_id).is_empty(),
        "processes left: {:?}",
        processes_of_run(run_id)
    );
    let root = std::env::temp_dir().join("formation-iox2").join(run_id);
    assert!(!root.exists(), "iceoryx2 root path left: {}", root.display());
}
